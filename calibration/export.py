"""Exports of a (calibrated) model for other tools: URDF, and DH tables as CSV and Markdown.

Pure: a model in, text out. Nothing here reads or writes files.

URDF (for ROS users). Each joint's ``<origin>`` carries the exact constant transform from the
previous joint's moving frame to this joint's motion frame, read off the model's kinematic
program (:func:`calibration.kinematics.program`): the elementary transforms between two joint
motions, the joint's own constant offset (``theta``, or ``d`` of a prismatic joint) included,
multiplied out. That is exact for ``dh``, Hayati ``dh`` (``beta``), ``mdh`` and ``poe`` alike,
with no convention-specific formulas; the joint then rotates about (or slides along) its local
z axis. The base (world -> robot base), the flange (after the last joint: the rest of the last
link, and ``home`` for ``poe``), the tool and every target are fixed joints. URDF is always in
metres and radians, and a URDF joint position is the reading itself: joint gains other than 1,
a coupling matrix and gear-eccentricity harmonics cannot be written in URDF (see
:func:`export_warnings`).

DH tables, in the model's units. ``dh`` and ``mdh`` models are written as they are (``beta`` for
Hayati links); a ``poe`` model is converted to ``dh`` first with
:func:`calibration.conventions.poe_to_dh` (exact: common normals of consecutive joint axes, Hayati
links where they are parallel). Base, tool and targets come with the table.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from .conventions import poe_to_dh
from .kinematics import Op, program
from .model import KinematicModel
from .robots import is_ur, nominal
from .robots import names as library_names
from .transforms import homogeneous, invert, matrix_to_pose, pose_to_matrix, rot

FORMATS = ("urdf", "ur-calibration", "dh-csv", "dh-md")


def export_warnings(model: KinematicModel, fmt: str = "urdf") -> list[str]:
    """What the export ``fmt`` cannot represent of ``model`` (empty when the export is exact)."""
    out = []
    if fmt in ("urdf", "ur-calibration"):
        what = "URDF" if fmt == "urdf" else "the UR calibration YAML"
        if model.coupling is not None:
            out.append(
                f"the joint coupling matrix is not representable in {what} (a joint position there is the reading)"
            )
        for j in model.joints:
            if model.coupling is None and j.gain != 1.0:
                out.append(f"joint {j.name}: gain {j.gain:.9g} is not representable in {what} (it assumes gain 1)")
    for j in model.joints:
        if j.harmonic is not None:
            out.append(f"joint {j.name}: the gear-eccentricity harmonic is not representable in {fmt}")
    if model.compliance is not None:
        out.append(
            f"{'URDF' if fmt == 'urdf' else fmt} cannot carry joint compliance under gravity: "
            "the rigid part of the model is written"
        )
    return out


# --------------------------------------------------------------------------- URDF


def _elementary(op: Op) -> np.ndarray:
    """The constant part of a rot/trans op (its offset) as a 4x4 transform."""
    if op.kind == "rot":
        return homogeneous(rot(op.axis, op.const), np.zeros(3))
    t = np.zeros(3)
    t[op.axis] = op.const
    return homogeneous(np.eye(3), t)


def joint_origins(model: KinematicModel) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """The chain as fixed and moving joints: ``(name, type, T_parent_joint (4, 4) SI, axis (3,))``
    in order: ``base`` (fixed), each joint (``revolute``/``prismatic``), ``flange`` (fixed). At
    reading q the chain is ``T_base · Π (T_i · Motion_i(q_i)) · T_flange`` (gain 1, no coupling)."""
    ops = program(model)
    tool_at = len(ops) - 2  # the program ends with fixed(tool), mark(tool)
    assert ops[tool_at].kind == "fixed" and ops[-1].key == "tool"
    out: list[tuple[str, str, np.ndarray, np.ndarray]] = []
    T = np.eye(4)
    for op in ops[:tool_at]:
        if op.kind == "fixed":
            T = T @ op.T
        elif op.kind == "mark":
            if op.key == "base":
                out.append(("base", "fixed", T, np.zeros(3)))
                T = np.eye(4)
        else:
            T = T @ _elementary(op)
            if op.joint is not None:
                j = model.joints[op.joint]
                axis = np.zeros(3)
                axis[op.axis] = 1.0
                out.append((j.name, "revolute" if op.kind == "rot" else "prismatic", T, axis))
                T = np.eye(4)
    out.append(("flange", "fixed", T, np.zeros(3)))
    return out


def joint_origins_ros(model: KinematicModel) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """:func:`joint_origins` with each link frame moved to where ROS descriptions put it: the shift
    along joint i's axis that starts the next origin (a DH link's ``d``) moved before joint i+1's
    origin into joint i's, and the flange transform's shift along and turn about the last axis into
    the last joint's. Both commute with the joint's motion, so the chain is the same; the origins
    are then UR's calibration layout (``shoulder`` = ``Rz(theta1)·Tz(d1)``, ``upper_arm`` =
    ``Tx(a1)·Rx(alpha1)·Rz(theta2)·Tz(d2)`` ...)."""
    out = [list(o) for o in joint_origins(model)]
    moving = [o for o in out if o[1] != "fixed"]
    for cur, nxt in zip(moving, moving[1:] + [out[-1]]):
        T_next = nxt[2]
        if nxt is out[-1]:  # flange: Rz(phi)·Tz(dz) commutes with the last joint
            x = T_next[:3, 0]
            phi = float(np.arctan2(x[1], x[0])) if np.hypot(x[0], x[1]) > 1e-12 else 0.0
            S = homogeneous(rot(2, phi), np.array([0.0, 0.0, T_next[2, 3]]))
        else:
            S = homogeneous(np.eye(3), np.array([0.0, 0.0, T_next[2, 3]]))
        cur[2] = cur[2] @ S
        nxt[2] = invert(S) @ T_next
    return [tuple(o) for o in out]


def _num(v: float) -> str:
    v = float(v)
    if abs(v) < 1e-15:
        return "0"
    return repr(v)


def _origin(parent: ET.Element, T: np.ndarray) -> None:
    p = matrix_to_pose(T)
    ET.SubElement(parent, "origin", xyz=" ".join(_num(v) for v in p[:3]), rpy=" ".join(_num(v) for v in p[3:]))


NAMINGS = ("auto", "ur", "ros", "recal")
UR_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
UR_LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
# Fixed frames of UR's ur_description: base_link is REP-103 aligned (x forward), the controller's
# base frame (and the DH frame 0) is base_link turned by pi about z; tool0 is the controller's
# flange frame, and ``flange`` is tool0 with x pointing out (flange -> tool0: rpy pi/2 0 pi/2).
_RZ_PI = pose_to_matrix(np.array([0, 0, 0, 0, 0, np.pi]))
_UR_FLANGE_TOOL0 = pose_to_matrix(np.array([0, 0, 0, np.pi / 2, 0, np.pi / 2]))
# ROS-Industrial (kuka_experimental, abb_experimental): flange -> tool0 is rpy 0 pi/2 0, so
# tool0's z (out of the flange) is the flange's x.
_ROS_FLANGE_TOOL0 = pose_to_matrix(np.array([0, 0, 0, 0, np.pi / 2, 0]))


def naming(model: KinematicModel, names: str = "auto") -> str:
    """The URDF naming a model gets: ``auto`` is ``ur`` for a Universal Robots arm of the library
    (by the model's name, six revolute joints) and ``ros`` for every other model."""
    if names not in NAMINGS:
        raise ValueError(f"`names` must be one of {', '.join(NAMINGS)}; got {names!r}")
    if names != "auto":
        if names == "ur" and (model.n_joints != 6 or not all(j.revolute for j in model.joints)):
            raise ValueError("UR names need six revolute joints")
        return names
    return "ur" if is_ur(model.name) and model.n_joints == 6 and all(j.revolute for j in model.joints) else "ros"


def joint_limits_for_export(
    model: KinematicModel, *, velocity: float | None = None, effort: float | None = None
) -> list[tuple[float, float]]:
    """``(velocity, effort)`` of each joint for a URDF ``<limit>``: ``velocity``/``effort`` when given
    (every joint), else the model's, else those of the library robot the model is named after
    (``kr16-identified`` -> ``kr16``). Raises ``ValueError`` naming the joint when neither is known:
    a URDF limit of 0 stops every ROS planner."""
    lib = None
    head = model.name.lower()
    for suffix in ("-nominal", "-identified", "-true", "-controller"):
        head = head.removesuffix(suffix)
    if head in library_names():
        cand = nominal(head)
        if cand.n_joints == model.n_joints:
            lib = cand.joints
    out = []
    for i, j in enumerate(model.joints):
        vals = []
        for key, given, flag in (("velocity", velocity, "--velocity"), ("effort", effort, "--effort")):
            v = given if given is not None else getattr(j, key)
            if v is None and lib is not None:
                v = getattr(lib[i], key)
            if v is None:
                raise ValueError(
                    f"joint {j.name!r} has no {key} limit (the model and the library do not give one); give {flag}"
                )
            if not v > 0:
                raise ValueError(f"{flag}: expected a positive number, got {v!r}")
            vals.append(float(v))
        out.append((vals[0], vals[1]))
    return out


def to_urdf(
    model: KinematicModel,
    *,
    name: str | None = None,
    effort: float | None = None,
    velocity: float | None = None,
    prefix: str = "",
    names: str = "auto",
) -> str:
    """The model as a URDF document (kinematics only: links without inertia or geometry).

    ``names`` (see :func:`naming`):

    - ``ur``: UR's names (ur_description): ``world`` -> ``base_link`` -> ``base_link_inertia`` ->
      ``shoulder_link`` (``shoulder_pan_joint``) ... ``wrist_3_link`` (``wrist_3_joint``) ->
      ``flange`` -> ``tool0`` (the model's flange) -> ``tcp`` (the model's tool) ->
      ``target_<name>``; ``base_link`` -> ``base`` (the controller's base frame).
    - ``ros``: ROS-Industrial's: ``world`` -> ``base_link`` -> ``link_1`` ... ``link_n`` (joints keep
      the model's names) -> ``flange`` -> ``tool0`` (the model's flange) -> ``tcp`` ->
      ``target_<name>``; ``base_link`` -> ``base``.
    - ``recal``: ``world`` -> ``base_link`` -> ``<joint>_link`` ... -> ``flange`` (the model's
      flange) -> ``tool`` -> ``target_<name>``.

    Every name is prefixed with ``prefix``. ``<limit>`` carries the joint's velocity and effort
    (:func:`joint_limits_for_export`)."""
    scheme = naming(model, names)
    rates = joint_limits_for_export(model, velocity=velocity, effort=effort)
    robot = ET.Element("robot", name=name or model.name or "robot")
    robot.append(
        ET.Comment(
            f" generated by recal from model {model.name!r} ({model.convention}); "
            f"{scheme} names; metres and radians; joint origins carry the calibrated values "
        )
    )
    for w in export_warnings(model, "urdf"):
        robot.append(ET.Comment(f" warning: {w} "))
    limits = {j.name: (j.lower, j.upper, *r) for j, r in zip(model.joints, rates)}

    def link(n: str) -> str:
        ET.SubElement(robot, "link", name=prefix + n)
        return prefix + n

    def joint(
        n: str,
        jtype: str,
        parent: str,
        child: str,
        T: np.ndarray,
        axis: np.ndarray | None = None,
        limit: tuple[float, float, float, float] | None = None,
    ) -> None:
        e = ET.SubElement(robot, "joint", name=prefix + n, type=jtype)
        _origin(e, T)
        ET.SubElement(e, "parent", link=parent)
        ET.SubElement(e, "child", link=child)
        if axis is not None:
            ET.SubElement(e, "axis", xyz=" ".join(_num(v) for v in axis))
        if limit is not None:
            ET.SubElement(
                e, "limit", lower=_num(limit[0]), upper=_num(limit[1]), effort=_num(limit[3]), velocity=_num(limit[2])
            )

    world = link("world")
    k = 0
    for jname, jtype, T, axis in joint_origins(model) if scheme == "recal" else joint_origins_ros(model):
        if jname == "base":
            if scheme == "ur":
                base_link = link("base_link")
                joint("base_joint", "fixed", world, base_link, T @ _RZ_PI)
                joint("base_link-base_fixed_joint", "fixed", base_link, link("base"), _RZ_PI)
                parent = link("base_link_inertia")
                joint("base_link-base_link_inertia", "fixed", base_link, parent, _RZ_PI)
            elif scheme == "ros":
                parent = link("base_link")
                joint("base_joint", "fixed", world, parent, T)
                joint("base_link-base", "fixed", parent, link("base"), np.eye(4))
            else:
                parent = link("base_link")
                joint("base_joint", "fixed", world, parent, T)
        elif jname == "flange":
            if scheme == "recal":
                parent_flange = link("flange")
                joint("flange_joint", "fixed", parent, parent_flange, T)
                tool = link("tool")
                joint("tool_joint", "fixed", parent_flange, tool, pose_to_matrix(model.tool))
            else:
                F = _UR_FLANGE_TOOL0 if scheme == "ur" else _ROS_FLANGE_TOOL0
                flange, tool0 = link("flange"), link("tool0")
                last = parent.removeprefix(prefix)
                joint("wrist_3-flange" if scheme == "ur" else f"{last}-flange", "fixed", parent, flange, T @ invert(F))
                joint("flange-tool0", "fixed", flange, tool0, F)
                tool = link("tcp")
                joint("tool0-tcp", "fixed", tool0, tool, pose_to_matrix(model.tool))
        else:
            if scheme == "ur":
                jn, child = UR_JOINTS[k], link(UR_LINKS[k])
            elif scheme == "ros":
                jn, child = jname, link(f"link_{k + 1}")
            else:
                jn, child = jname, link(f"{jname}_link")
            joint(jn, jtype, parent, child, T, axis, limits[jname])
            parent = child
            k += 1
    for tname, p in model.targets.items():
        child = link(f"target_{tname}")
        joint(f"target_{tname}_joint", "fixed", tool, child, homogeneous(np.eye(3), p))
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


# --------------------------------------------------------------------------- UR calibration YAML

UR_SEGMENTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")


def ur_calibration(model: KinematicModel) -> tuple[dict, np.ndarray]:
    """The six joint origins of a 6-revolute-joint model in the layout of UR's calibration YAML
    (ur_calibration writes it, ur_description reads it as the ``<origin>`` of shoulder_pan_joint
    ... wrist_3_joint): ``{segment: (x, y, z, roll, pitch, yaw)}`` in m and rad, and the
    remainder ``T_tool0_flange`` (4, 4).

    ur_description's chain is ``base_link_inertia · Π origin_i · Rz(q_i)`` and ``tool0`` is the
    wrist_3 link, so the model's flange is ``T_base · chain(q) · T_tool0_flange`` with the
    base_link_inertia frame at the model's base. The part of the model's flange transform that is
    a shift along and a turn about joint 6's axis commutes with joint 6 and goes into ``wrist_3``;
    the rest (zero for a DH robot like a UR controller's model) cannot be held by the YAML and
    is returned (a TCP offset).

    roll, pitch, yaw are what ur_description needs: URDF's ``Rz(yaw)·Ry(pitch)·Rx(roll)``.
    (ur_calibration computes them with Eigen's ``eulerAngles(0, 1, 2)``, i.e. ``Rx·Ry·Rz``; the two
    agree for the nominal tables' pure x rotations, not for a calibrated chain's.)
    """
    if model.n_joints != 6 or not all(j.revolute for j in model.joints):
        raise ValueError("the UR calibration format needs six revolute joints")
    origins = joint_origins_ros(model)
    segs = {
        seg: tuple(float(v) for v in matrix_to_pose(T))
        for seg, (_, _, T, _) in zip(UR_SEGMENTS, [o for o in origins if o[1] == "revolute"])
    }
    return segs, origins[-1][2]


def to_ur_calibration(model: KinematicModel) -> str:
    """UR's calibration YAML (``kinematics:`` shoulder ... wrist_3 with x, y, z, roll, pitch, yaw
    and ``hash``), as ur_robot_driver's ``kinematics_params_file`` reads it (see
    :func:`ur_calibration`). ``hash`` is ``calib_`` and a number derived from the values: the driver
    compares it to the hash the controller computes from its own factory calibration, so it warns
    that the file is not the controller's (which it is not: it describes the measured robot)."""
    import hashlib

    segs, remainder = ur_calibration(model)
    lines = [
        f"# UR calibration of model {model.name!r}, written by recal (ur_calibration layout; metres, radians;",
        "# roll, pitch, yaw as URDF rpy: Rz(yaw)·Ry(pitch)·Rx(roll), as ur_description reads them)",
    ]
    rest = matrix_to_pose(remainder)
    if np.any(np.abs(rest) > 1e-12):
        lines.append(
            "# tool0 -> model flange (not representable here; set it as a TCP offset): "
            + ", ".join(_num(v) for v in rest)
        )
    for w in export_warnings(model, "ur-calibration"):
        lines.append(f"# warning: {w}")
    lines.append("kinematics:")
    body = []
    for seg in UR_SEGMENTS:
        body.append(f"  {seg}:")
        for key, v in zip(("x", "y", "z", "roll", "pitch", "yaw"), segs[seg]):
            body.append(f"    {key}: {_num(0.0 if abs(v) < 1e-15 else v)}")
    digest = hashlib.sha256("\n".join(body).encode()).digest()
    lines += body + [f"  hash: calib_{int.from_bytes(digest[:8], 'big') >> 1}"]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- DH tables


def _fmt(v: float, digits: int = 10) -> str:
    v = float(v)
    if abs(v) < 1e-12:
        v = 0.0
    return f"{v:.{digits}g}"


def dh_table(model: KinematicModel) -> dict:
    """The model's table in its own units: ``{"convention", "kind", "header", "rows", "frames",
    "units"}``.

    ``kind`` is ``"dh"`` or ``"mdh"``; a ``poe`` model is converted to ``dh`` first
    (:func:`calibration.conventions.poe_to_dh`, exact, Hayati links where consecutive axes are
    parallel). ``rows`` are the joints' link parameters, gains (when not all 1) and limits;
    ``frames`` lists the fixed poses (``base``, ``tool``), the targets and the rows of a coupling
    matrix as ``(name, values)``."""
    L, A = model.units.length_m, model.units.angle_rad
    m = poe_to_dh(model) if model.convention == "poe" else model

    def pose_units(p):
        return [v / L for v in p[:3]] + [v / A for v in p[3:]]

    frames: list[tuple[str, list[float]]] = [("base", pose_units(m.base)), ("tool", pose_units(m.tool))]
    for tname, p in m.targets.items():
        frames.append((f"target {tname}", [v / L for v in p]))
    if m.coupling is not None:  # readings -> joint variables, before theta is added
        frames += [(f"coupling row {i + 1}", list(row)) for i, row in enumerate(m.coupling)]
    hayati = any(j.hayati for j in m.joints)
    header = ["joint", "type", "theta", "d", "a", "alpha"] + (["beta"] if hayati else [])
    rows: list[list] = []
    for j in m.joints:
        row = [j.name, j.type, j.theta / A, j.d / L, j.a / L, j.alpha / A]
        if hayati:
            row.append(j.beta / A if j.hayati else "")
        rows.append(row)
    if m.coupling is None and any(j.gain != 1.0 for j in m.joints):
        header.append("gain")
        for row, j in zip(rows, m.joints):
            row.append(j.gain)
    header += ["lower", "upper"]
    for row, j in zip(rows, m.joints):
        s = A if j.revolute else L
        row += [j.lower / s, j.upper / s]
    return {
        "convention": model.convention,
        "kind": m.convention,
        "header": header,
        "rows": rows,
        "frames": frames,
        "units": {"length": model.units.length, "angle": model.units.angle},
    }


_KIND_TEXT = {
    "dh": "standard Denavit-Hartenberg: A_i = Rz(theta + q)·Tz(d)·Tx(a)·Rx(alpha); "
    "Hayati links (beta given): Rz(theta + q)·Tx(a)·Rx(alpha)·Ry(beta)",
    "mdh": "modified DH (Craig): A_i = Rx(alpha)·Tx(a)·Rz(theta + q)·Tz(d), alpha and a of the preceding link",
}


def to_dh_csv(model: KinematicModel) -> str:
    """The DH table as CSV (model units); base, tool and targets as ``#`` comment lines first."""
    t = dh_table(model)
    u = t["units"]
    lines = [
        f"# recal DH table of model {model.name!r}: {_KIND_TEXT[t['kind']]}",
        f"# convention: {t['kind']}",
        f"# units: length {u['length']}, angle {u['angle']}; "
        "poses are x, y, z, rx, ry, rz = Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx)",
    ]
    for w in export_warnings(model, "dh-csv"):
        lines.append(f"# warning: {w}")
    for fname, vals in t["frames"]:
        lines.append(f"# {fname}: " + ", ".join(_fmt(v) for v in vals))
    lines.append(",".join(t["header"]))
    for row in t["rows"]:
        lines.append(",".join(v if isinstance(v, str) else _fmt(v) for v in row))
    return "\n".join(lines) + "\n"


def to_dh_markdown(model: KinematicModel) -> str:
    """The DH table as a Markdown document (model units), with base, tool and targets."""
    t = dh_table(model)
    u = t["units"]
    unit = {
        "theta": u["angle"],
        "alpha": u["angle"],
        "beta": u["angle"],
        "d": u["length"],
        "a": u["length"],
        "x": u["length"],
        "y": u["length"],
        "z": u["length"],
        "rx": u["angle"],
        "ry": u["angle"],
        "rz": u["angle"],
    }
    out = [
        f"# Kinematic model `{model.name or 'robot'}`",
        "",
        f"Convention: {_KIND_TEXT[t['kind']]}.",
        "",
        f"Units: length {u['length']}, angle {u['angle']}. Joint limits are in the units of the joint's reading.",
        "",
    ]
    for w in export_warnings(model, "dh-md"):
        out.append(f"> Warning: {w}.")
        out.append("")
    head = [f"{h} ({unit[h]})" if h in unit else h for h in t["header"]]
    out.append("| " + " | ".join(head) + " |")
    out.append("|" + "|".join("---" for _ in head) + "|")
    for row in t["rows"]:
        out.append("| " + " | ".join(v if isinstance(v, str) else _fmt(v) for v in row) + " |")
    out += [
        "",
        "Fixed frames (poses are x, y, z, rx, ry, rz = Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx); targets are "
        "points in the tool frame):",
        "",
        "| frame | values |",
        "|---|---|",
    ]
    for fname, vals in t["frames"]:
        out.append(f"| {fname} | " + ", ".join(_fmt(v) for v in vals) + " |")
    return "\n".join(out) + "\n"


def export(model: KinematicModel, fmt: str, **kw) -> str:
    """``fmt`` one of :data:`FORMATS`."""
    if fmt == "urdf":
        return to_urdf(model, **kw)
    if fmt == "ur-calibration":
        return to_ur_calibration(model)
    if fmt == "dh-csv":
        return to_dh_csv(model)
    if fmt == "dh-md":
        return to_dh_markdown(model)
    raise ValueError(f"`fmt` must be one of {', '.join(FORMATS)}; got {fmt!r}")
