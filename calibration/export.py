"""Exports of a (calibrated) model for other tools: URDF, and DH tables as CSV and Markdown.

Pure: a model in, text out. Nothing here reads or writes files.

URDF (for ROS users). Each joint's ``<origin>`` carries the exact constant transform from the
previous joint's moving frame to this joint's motion frame, read off the model's kinematic
program (:func:`calibration.kinematics.program`): the elementary transforms between two joint
motions, the joint's own constant offset (``theta``, or ``d`` of a prismatic joint) included,
multiplied out. That is exact for ``dh``, Hayati ``dh`` (``beta``), ``mdh`` and ``poe`` alike,
with no convention-specific formulas; the joint then rotates about (or slides along) its local
z axis. The flange (after the last joint: the rest of the last link, and ``home`` for ``poe``),
the tool and every target are fixed joints; the base (instrument frame -> robot base) is one too
with ``world=True``, and otherwise a comment: the URDF is rooted at ``base_link``, as ROS
descriptions are. URDF is always in
metres and radians, and a URDF joint position is the reading itself: joint gains other than 1,
a coupling matrix (but for a mimic joint's, :func:`mimic_rows`, written as ``<mimic>``) and
gear-eccentricity harmonics cannot be written in URDF (see :func:`export_warnings`).

DH tables, in the model's units. ``dh`` and ``mdh`` models are written as they are (``beta`` for
Hayati links); a ``poe`` model is converted to ``dh`` first with
:func:`calibration.conventions.poe_to_dh` (exact: common normals of consecutive joint axes, Hayati
links where they are parallel). Base, tool and targets come with the table.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from .conventions import poe_to_dh
from .kinematics import Op, program
from .model import KinematicModel
from .robots import is_ur, nominal
from .robots import names as library_names
from .transforms import homogeneous, invert, matrix_to_pose, pose_to_matrix, rot

FORMATS = ("urdf", "ur-calibration", "dh-csv", "dh-md")


def export_warnings(
    model: KinematicModel, fmt: str = "urdf", *, effort: float | None = None, world: bool = False
) -> list[str]:
    """What the export ``fmt`` cannot represent of ``model`` (empty when the export is exact); for
    ``urdf`` (with the options :func:`to_urdf` was given) also the joints whose effort limit is a
    placeholder and a base left out of a robot-only URDF."""
    out = []
    if fmt == "urdf":
        out += _urdf_notes(model, effort=effort, world=world)
    if fmt in ("urdf", "ur-calibration"):
        what = "URDF" if fmt == "urdf" else "the UR calibration YAML"
        if model.coupling is not None and (fmt != "urdf" or mimic_rows(model) is None):
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


def mimic_rows(model: KinematicModel) -> dict[int, tuple[int, float]] | None:
    """``{joint i: (lead joint k, multiplier)}`` when the model's coupling is URDF's ``<mimic>``:
    each row either the joint's own reading, or a multiple of one other joint's reading that is
    itself read as it is (what ``recal model --from-urdf`` makes of a mimic joint on the chain);
    ``None`` for any other coupling (the Fanuc J2/J3 sum, gains) or none."""
    if model.coupling is None:
        return None
    C = np.asarray(model.coupling)
    n = len(C)
    plain = [bool(np.array_equal(C[i], np.eye(n)[i])) for i in range(n)]
    out = {}
    for i in range(n):
        if plain[i]:
            continue
        nz = np.flatnonzero(C[i])
        if C[i, i] != 0.0 or len(nz) != 1 or not plain[nz[0]]:
            return None
        out[i] = (int(nz[0]), float(C[i, nz[0]]))
    return out or None


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
            assert op.T is not None  # a fixed op carries its transform
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
    out: list[list[Any]] = [list(o) for o in joint_origins(model)]
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
    return [(name, kind, T, axis) for name, kind, T, axis in out]


def ur_match(model: KinematicModel, tol_m: float = 0.02) -> tuple[str, np.ndarray] | None:
    """``(library UR name, T_bli_base)`` when ``model`` (six revolute joints) moves as a Universal
    Robots arm of the library, whatever its name or convention: its flange positions at eight
    configurations (base and tool left out) are those of the library UR within ``tol_m`` in the
    controller's base frame (``base_link_inertia``: ``T_bli_base`` identity) or in ``base_link``
    (REP-103, the model imported from a URDF's ``base_link``: ``T_bli_base = Rz(pi)``). A
    calibrated arm differs from its type by millimetres, UR types from each other by decimetres.
    ``None`` for any other arm."""
    import dataclasses

    from .kinematics import fk

    if model.n_joints != 6 or not all(j.revolute for j in model.joints):
        return None
    q = np.random.default_rng(26).uniform(-1.5, 1.5, (8, 6))
    bare = dataclasses.replace(model, base=np.zeros(6), tool=np.zeros(6), compliance=None)
    p_model = fk(bare, q)[:, :3, 3]
    best = None
    for name in library_names():
        if not is_ur(name):
            continue
        p_ur = fk(nominal(name), q)[:, :3, 3]  # in the controller's base frame
        for F in (np.eye(4), _RZ_PI):
            err = float(np.max(np.linalg.norm(p_model @ F[:3, :3].T + F[:3, 3] - p_ur, axis=1)))
            if err < tol_m and (best is None or err < best[0]):
                best = (err, name, F)
    return None if best is None else (best[1], best[2])


def ur_joint_origins(model: KinematicModel) -> tuple[list[np.ndarray], np.ndarray, str | None]:
    """``(origins, T_tool0_flange, matched)``: the six joint origins of a six-revolute-joint model
    as ur_description composes them, from ``base_link_inertia`` (``T = Π origin_i · Rz(q_i)``,
    ``tool0`` the wrist_3 link), the rest to the model's flange, and the library UR it matched.

    - The first origin starts in the controller's base frame: a model whose base is
      ``base_link`` (:func:`ur_match`) gets ``Rz(pi)`` in front of it.
    - Each link frame is the one UR's description has, up to the calibration, so that the link's
      meshes sit where they belong: a frame is turned about its joint's axis (the turn moves
      from origin i into origin i+1; it commutes with the joint, so the chain is the same) until
      its x axis is UR's nominal frame's. A ``dh`` (or ``mdh``) frame's x is a common normal and
      is only turned over (by pi, where ``poe_to_dh`` chose ``a >= 0`` and UR's table has
      ``a < 0``), so a controller's DH deltas stay where ur_calibration puts them; a ``poe``
      frame's x means nothing and is turned onto UR's x axis (projected on the link's plane).
    Without a match the model's base frame is taken as the controller's and frames are kept."""
    origins = joint_origins_ros(model)
    joints = [o[2] for o in origins if o[1] == "revolute"]
    remainder = origins[-1][2]
    match = ur_match(model)
    if match is None:
        return joints, remainder, None
    name, F = match
    joints[0] = F @ joints[0]
    ref = [o[2] for o in joint_origins_ros(nominal(name)) if o[1] == "revolute"]
    L, L_ref = np.eye(4), np.eye(4)
    for i in range(5):  # wrist_3's frame is the model's flange (tool0): never turned
        L, L_ref = L @ joints[i], L_ref @ ref[i]
        x_ref = L[:3, :3].T @ L_ref[:3, 0]  # UR's x axis in the model's link frame
        phi = float(np.arctan2(x_ref[1], x_ref[0]))
        if model.convention != "poe":  # DH frames' x is a common normal: keep it, up to its sign
            phi = np.pi if abs(phi) > np.pi / 2 else 0.0
        if phi != 0.0:
            joints[i] = joints[i] @ homogeneous(rot(2, phi), np.zeros(3))
            joints[i + 1] = homogeneous(rot(2, -phi), np.zeros(3)) @ joints[i + 1]
            L = L @ homogeneous(rot(2, phi), np.zeros(3))
    return joints, remainder, name


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
    """The URDF naming a model gets: ``auto`` is ``ur`` for a model that moves as a Universal
    Robots arm of the library (:func:`ur_match`: by its kinematics, whatever its name, e.g. a
    calibrated ``demo-ur10e-calibrated``) and ``ros`` for every other model."""
    if names not in NAMINGS:
        raise ValueError(f"`names` must be one of {', '.join(NAMINGS)}; got {names!r}")
    if names != "auto":
        if names == "ur" and (model.n_joints != 6 or not all(j.revolute for j in model.joints)):
            raise ValueError("UR names need six revolute joints")
        return names
    return "ur" if ur_match(model) is not None else "ros"


def ros_joint_names(model: KinematicModel) -> list[str]:
    """ROS-Industrial joint names: the model's where they are a description's (``joint_a1``,
    ``joint_1_s``, ``fr3_joint1`` ...), ``joint_1`` ... ``joint_n`` where they are Recal's generic
    ``j1`` ... ``jn``."""
    generic = [f"j{i + 1}" for i in range(model.n_joints)]
    if [j.name for j in model.joints] == generic:
        return [f"joint_{i + 1}" for i in range(model.n_joints)]
    return [j.name for j in model.joints]


# The effort limit written for a library arm whose public description publishes none (ROS-Industrial's
# KUKA, ABB and Fanuc descriptions write effort="0"). URDF needs a positive figure; MoveIt and
# position-controlled drivers do not use it. Large, so that a simulator does not clamp the arm
# with it; each use is said in the file and on stderr.
EFFORT_PLACEHOLDER = 1.0e4


def _library_joints(model: KinematicModel):
    """The library robot's joints a model is, by its name (``kr16-identified`` -> ``kr16``) or, for
    a UR, by its kinematics; ``None`` when it is none."""
    head = model.name.lower()
    for suffix in ("-nominal", "-identified", "-true", "-controller", "-ur-calibration"):
        head = head.removesuffix(suffix)
    if head not in library_names():
        match = ur_match(model)
        if match is None:
            return None
        head = match[0]
    cand = nominal(head)
    return cand.joints if cand.n_joints == model.n_joints else None


def joint_limits_for_export(
    model: KinematicModel, *, velocity: float | None = None, effort: float | None = None
) -> list[tuple[float, float]]:
    """``(velocity, effort)`` of each joint for a URDF ``<limit>``: ``velocity``/``effort`` when given
    (every joint), else the model's, else those of the library robot the model is
    (:func:`_library_joints`); a library arm whose description publishes no effort gets
    :data:`EFFORT_PLACEHOLDER` (said by :func:`export_warnings`). Raises ``ValueError`` naming the
    joint when a limit is still unknown: a URDF velocity limit of 0 stops every ROS planner."""
    lib = _library_joints(model)
    out = []
    for i, j in enumerate(model.joints):
        vals = []
        for key, given, flag in (("velocity", velocity, "--velocity"), ("effort", effort, "--effort")):
            v = given if given is not None else getattr(j, key)
            if v is None and lib is not None:
                v = getattr(lib[i], key)
                if v is None and key == "effort":
                    v = EFFORT_PLACEHOLDER
            if v is None:
                raise ValueError(
                    f"joint {j.name!r} has no {key} limit (the model and the library do not give one); give {flag}"
                )
            if not v > 0:
                raise ValueError(f"{flag}: expected a positive number, got {v!r}")
            vals.append(float(v))
        out.append((vals[0], vals[1]))
    return out


def _urdf_notes(model: KinematicModel, *, effort: float | None, world: bool) -> list[str]:
    out = []
    if effort is None:
        lib = _library_joints(model)
        unknown = [j.name for i, j in enumerate(model.joints) if j.effort is None and lib and lib[i].effort is None]
        if unknown:
            out.append(
                f"joint(s) {', '.join(unknown)}: effort limit not published for this arm; written as a placeholder "
                f"{EFFORT_PLACEHOLDER:g} (MoveIt does not use it; give --effort for the real figure)"
            )
    if not world and np.any(np.abs(model.base) > 1e-15):
        out.append(
            "the model's base (instrument frame -> robot base) is not in the robot-only URDF; "
            "--world adds it as a 'world' link"
        )
    return out


def _comment_safe(text: str) -> str:
    """``text`` for an XML comment, which may not hold ``--``: ``--effort`` -> ``the effort option``."""
    return re.sub(r"--(\w+)", r"the \1 option", text).replace("--", "-")


def to_urdf(
    model: KinematicModel,
    *,
    name: str | None = None,
    effort: float | None = None,
    velocity: float | None = None,
    prefix: str = "",
    names: str = "auto",
    world: bool = False,
) -> str:
    """The model as a URDF document (kinematics only: links without inertia or geometry), a
    robot-only description rooted at ``base_link``, as ROS descriptions are (a MoveIt
    configuration adds its own ``world`` joint). ``world=True`` adds a ``world`` link (the
    instrument's frame) and the model's ``base`` as the fixed joint ``world`` -> ``base_link``.

    ``names`` (see :func:`naming`):

    - ``ur``: UR's names (ur_description): ``base_link`` -> ``base_link_inertia`` ->
      ``shoulder_link`` (``shoulder_pan_joint``) ... ``wrist_3_link`` (``wrist_3_joint``) ->
      ``flange`` -> ``tool0`` (the model's flange) -> ``tcp`` (the model's tool) ->
      ``target_<name>``; ``base_link`` -> ``base`` (the controller's base frame). The joint
      origins are :func:`ur_joint_origins`' (those of the UR calibration YAML).
    - ``ros``: ROS-Industrial's: ``base_link`` -> ``link_1`` ... ``link_n`` (joints:
      :func:`ros_joint_names`) -> ``flange`` -> ``tool0`` (the model's flange) -> ``tcp`` ->
      ``target_<name>``; ``base_link`` -> ``base``.
    - ``recal``: ``base_link`` -> ``<joint>_link`` ... -> ``flange`` (the model's flange) ->
      ``tool`` -> ``target_<name>``.

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
    for warning in export_warnings(model, "urdf", effort=effort, world=world):
        robot.append(ET.Comment(f" warning: {_comment_safe(warning)} "))
    limits, urdf_names, mimics = _urdf_joint_names(model, scheme, rates)
    w = _UrdfWriter(robot, prefix)
    origins, T_base_base_link = _urdf_origins(model, scheme)
    base_link = w.link("base_link")
    T_world_base = origins[0][2]
    if world:
        w.joint("base_joint", "fixed", w.link("world"), base_link, T_world_base @ T_base_base_link)
    elif np.any(np.abs(model.base) > 1e-15):
        p = matrix_to_pose(T_world_base @ T_base_base_link)
        robot.append(
            ET.Comment(
                " the model's base: instrument frame -> base_link, xyz "
                + " ".join(_num(v) for v in p[:3])
                + " rpy "
                + " ".join(_num(v) for v in p[3:])
                + " (recal export's world option adds it as a 'world' link) "
            )
        )
    parent = base_link
    if scheme == "ur":
        w.joint("base_link-base_fixed_joint", "fixed", base_link, w.link("base"), _RZ_PI)
        parent = w.link("base_link_inertia")
        w.joint("base_link-base_link_inertia", "fixed", base_link, parent, _RZ_PI)
    elif scheme == "ros":
        w.joint("base_link-base", "fixed", base_link, w.link("base"), np.eye(4))
    tool = _urdf_chain(w, model, scheme, parent, origins, urdf_names, limits, mimics)
    for tname, p in model.targets.items():
        child = w.link(f"target_{tname}")
        w.joint(f"target_{tname}_joint", "fixed", tool, child, homogeneous(np.eye(3), p))
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def _urdf_origins(model: KinematicModel, scheme: str) -> tuple[list[list[Any]], np.ndarray]:
    """The joint origins ``[name, type, T (4, 4), axis]`` of the chain in ``scheme``'s frames
    (``ur``: those of the UR calibration YAML, :func:`ur_joint_origins`, the remainder on the
    flange), and the transform (4, 4) from the model's base frame to ``base_link`` (``ur``: through
    ``base_link_inertia`` and UR's half turn about z; else the identity)."""
    origins: list[list[Any]] = [
        list(o) for o in (joint_origins(model) if scheme == "recal" else joint_origins_ros(model))
    ]
    T_base_base_link = np.eye(4)  # the model's base frame -> base_link
    if scheme == "ur":
        ur_joints, remainder, matched = ur_joint_origins(model)
        for o, T in zip([o for o in origins if o[1] != "fixed"], ur_joints):
            o[2] = T
        origins[-1][2] = remainder
        match = ur_match(model) if matched else None  # ur_joint_origins matched it: not None then
        F = match[1] if match is not None else np.eye(4)  # base_link_inertia <- model base
        T_base_base_link = invert(F) @ _RZ_PI
    return origins, T_base_base_link


def _urdf_chain(
    w: _UrdfWriter,
    model: KinematicModel,
    scheme: str,
    parent: str,
    origins: list[list[Any]],
    urdf_names: dict,
    limits: dict,
    mimics: dict,
) -> str:
    """The chain's links and joints from ``parent`` (the joints after the base origin in
    ``origins``, each link named by ``scheme``), ending with the flange and tool frames
    (:func:`_urdf_flange`); returns the tool link, where the targets hang."""
    k = 0
    for jname, jtype, T, axis in origins[1:]:
        if jname == "flange":
            tool = _urdf_flange(w, model, scheme, parent, T)
        else:
            if scheme == "ur":
                child = w.link(UR_LINKS[k])
            elif scheme == "ros":
                child = w.link(f"link_{k + 1}")
            else:
                child = w.link(f"{jname}_link")
            w.joint(urdf_names[jname], jtype, parent, child, T, axis, limits[jname], mimics.get(jname))
            parent = child
            k += 1
    return tool


class _UrdfWriter:
    """The links and joints of a URDF document being written (every name prefixed)."""

    def __init__(self, robot: ET.Element, prefix: str):
        self.robot, self.prefix = robot, prefix

    def link(self, n: str) -> str:
        ET.SubElement(self.robot, "link", name=self.prefix + n)
        return self.prefix + n

    def joint(
        self,
        n: str,
        jtype: str,
        parent: str,
        child: str,
        T: np.ndarray,
        axis: np.ndarray | None = None,
        limit: tuple[float, float, float, float] | None = None,
        mimic: tuple[str, float] | None = None,
    ) -> None:
        e = ET.SubElement(self.robot, "joint", name=self.prefix + n, type=jtype)
        _origin(e, T)
        ET.SubElement(e, "parent", link=parent)
        ET.SubElement(e, "child", link=child)
        if axis is not None:
            ET.SubElement(e, "axis", xyz=" ".join(_num(v) for v in axis))
        if limit is not None:
            ET.SubElement(
                e, "limit", lower=_num(limit[0]), upper=_num(limit[1]), effort=_num(limit[3]), velocity=_num(limit[2])
            )
        if mimic is not None:
            ET.SubElement(e, "mimic", joint=self.prefix + mimic[0], multiplier=_num(mimic[1]), offset="0")


def _urdf_joint_names(model: KinematicModel, scheme: str, rates) -> tuple[dict, dict, dict]:
    """Per joint of ``model``: its limits (lower, upper, velocity, effort), its URDF name in
    ``scheme``, and for a mimic joint (the joint it follows, the multiplier)."""
    limits = {j.name: (j.lower, j.upper, *r) for j, r in zip(model.joints, rates)}
    ros_names = dict(zip((j.name for j in model.joints), ros_joint_names(model)))
    urdf_names = {
        j.name: UR_JOINTS[k] if scheme == "ur" else ros_names[j.name] if scheme == "ros" else j.name
        for k, j in enumerate(model.joints)
    }
    # a mimic joint: its variable is a multiple of another's reading (its offset is in its origin)
    mimics = {
        model.joints[i].name: (urdf_names[model.joints[k].name], m) for i, (k, m) in (mimic_rows(model) or {}).items()
    }

    return limits, urdf_names, mimics


def _urdf_flange(w: _UrdfWriter, model: KinematicModel, scheme: str, parent: str, T: np.ndarray) -> str:
    """The flange, the tool and (``ur``, ``ros``) ``tool0`` after the last joint's link
    ``parent``, ``T`` the flange's origin; returns the tool's link."""
    prefix = w.prefix
    if scheme == "recal":
        parent_flange = w.link("flange")
        w.joint("flange_joint", "fixed", parent, parent_flange, T)
        tool = w.link("tool")
        w.joint("tool_joint", "fixed", parent_flange, tool, pose_to_matrix(model.tool))
    else:
        Ft = _UR_FLANGE_TOOL0 if scheme == "ur" else _ROS_FLANGE_TOOL0
        flange, tool0 = w.link("flange"), w.link("tool0")
        last = parent.removeprefix(prefix)
        w.joint("wrist_3-flange" if scheme == "ur" else f"{last}-flange", "fixed", parent, flange, T @ invert(Ft))
        w.joint("flange-tool0", "fixed", flange, tool0, Ft)
        tool = w.link("tcp")
        w.joint("tool0-tcp", "fixed", tool0, tool, pose_to_matrix(model.tool))
    return tool


# --------------------------------------------------------------------------- UR calibration YAML

UR_SEGMENTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")


def ur_calibration(model: KinematicModel) -> tuple[dict, np.ndarray]:
    """The six joint origins of a 6-revolute-joint model in the layout of UR's calibration YAML
    (ur_calibration writes it, ur_description reads it as the ``<origin>`` of shoulder_pan_joint
    ... wrist_3_joint): ``{segment: (x, y, z, roll, pitch, yaw)}`` in m and rad, and the
    remainder ``T_tool0_flange`` (4, 4) (see :func:`ur_joint_origins`).

    ur_description's chain is ``base_link_inertia · Π origin_i · Rz(q_i)`` and ``tool0`` is the
    wrist_3 link, so the model's flange is ``T_bli · chain(q) · T_tool0_flange``. The part of the
    model's flange transform that is a shift along and a turn about joint 6's axis commutes with
    joint 6 and goes into ``wrist_3``; the rest (zero for a DH robot like a UR controller's model)
    cannot be held by the YAML and is returned (a TCP offset).

    roll, pitch, yaw are what ur_description needs: URDF's ``Rz(yaw)·Ry(pitch)·Rx(roll)``.
    (ur_calibration computes them with Eigen's ``eulerAngles(0, 1, 2)``, i.e. ``Rx·Ry·Rz``; the two
    agree for the nominal tables' pure x rotations, not for a calibrated chain's.)
    """
    if model.n_joints != 6 or not all(j.revolute for j in model.joints):
        raise ValueError("the UR calibration format needs six revolute joints")
    joints, remainder, _ = ur_joint_origins(model)
    segs = {seg: tuple(float(v) for v in matrix_to_pose(T)) for seg, T in zip(UR_SEGMENTS, joints)}
    return segs, remainder


def _hash_bytes(data: bytes, seed: int = 0xC70F6907) -> int:
    """libstdc++'s ``std::_Hash_bytes`` (64-bit MurmurHash2 variant, libsupc++/hash_bytes.cc),
    which ``std::hash<std::string>`` calls with ``seed`` 0xc70f6907."""
    mask = (1 << 64) - 1
    mul = (0xC6A4A793 << 32) + 0x5BD1E995

    def shift_mix(v: int) -> int:
        return v ^ (v >> 47)

    n = len(data)
    h = (seed ^ (n * mul)) & mask
    aligned = n & ~7
    for i in range(0, aligned, 8):
        word = int.from_bytes(data[i : i + 8], "little")
        h = ((h ^ ((shift_mix((word * mul) & mask) * mul) & mask)) * mul) & mask
    if n & 7:
        h = ((h ^ int.from_bytes(data[aligned:], "little")) * mul) & mask
    h = (shift_mix(h) * mul) & mask
    return shift_mix(h)


def _cpp_stream(v: float) -> str:
    """A double as ``std::ostream << v`` writes it by default (``%g``, 6 significant digits)."""
    return f"{v:.6g}"


def ur_hash(dh: list[tuple[float, ...]]) -> str:
    """UR's calibration hash of a DH table ``[(theta, d, a, alpha)]`` (m, rad), as the driver's
    client library computes it from the controller's kinematics (``KinematicsInfo::toHash``):
    ``std::hash<std::string>`` of theta, d, a, alpha of each joint streamed one after the other."""
    text = "".join("".join(_cpp_stream(v) for v in row) for row in dh)
    return f"calib_{_hash_bytes(text.encode())}"


def _ur_dh_of_segments(joints: list[np.ndarray]) -> list[tuple[float, ...]] | None:
    """The DH table (theta, d, a, alpha per joint) that gives these six origins in UR's layout
    (``shoulder = Rz(theta1)·Tz(d1)``, ``origin_i = Tx(a_{i-1})·Rx(alpha_{i-1})·Rz(theta_i)·Tz(d_i)``,
    ``a6 = alpha6 = 0``), or ``None`` where an origin is not of that form (a ``poe`` model's tilts)."""
    rows = []  # (theta_i, d_i, (a_{i-1}, alpha_{i-1}))
    for T in joints:
        R, p = T[:3, :3], T[:3, 3]
        theta = float(np.arctan2(-R[0, 1], R[0, 0]))
        alpha = float(np.arctan2(-R[1, 2], R[2, 2]))
        a = float(p[0])
        d = float(-np.sin(alpha) * p[1] + np.cos(alpha) * p[2])
        again = homogeneous(rot(0, alpha) @ rot(2, theta), np.array([a, -np.sin(alpha) * d, np.cos(alpha) * d]))
        if not np.allclose(again, T, atol=1e-12):
            return None
        rows.append((theta, d, (a, alpha)))
    if rows[0][2] != (0.0, 0.0):  # the shoulder has no a, alpha before it
        return None
    following = [r[2] for r in rows[1:]] + [(0.0, 0.0)]
    out = [(theta, d, a, alpha) for (theta, d, _), (a, alpha) in zip(rows, following)]
    return [tuple(0.0 if abs(v) < 1e-15 else v for v in row) for row in out]


def to_ur_calibration(model: KinematicModel) -> str:
    """UR's calibration YAML (``kinematics:`` shoulder ... wrist_3 with x, y, z, roll, pitch, yaw
    and ``hash``), as ur_robot_driver's ``kinematics_params_file`` reads it (see
    :func:`ur_calibration`). ``hash`` is UR's (:func:`ur_hash`) of the model's DH table in UR's
    layout, so a nominal export carries the hash of UR's default file; a model the layout cannot
    hold as a DH table gets the same hash of the written values (the driver warns either way
    when the controller's own calibration differs, which for a measured robot it does)."""
    if model.n_joints != 6 or not all(j.revolute for j in model.joints):
        raise ValueError("the UR calibration format needs six revolute joints")
    joints, remainder, matched = ur_joint_origins(model)
    segs = {seg: tuple(float(v) for v in matrix_to_pose(T)) for seg, T in zip(UR_SEGMENTS, joints)}
    lines = [
        f"# UR calibration of model {model.name!r}, written by recal (ur_calibration layout; metres, radians;",
        "# roll, pitch, yaw as URDF rpy: Rz(yaw)·Ry(pitch)·Rx(roll), as ur_description reads them)",
    ]
    if matched is None:
        lines.append(
            "# warning: the model does not move as a library UR arm; its base frame is taken as the "
            "controller's (base_link_inertia)"
        )
    rest = matrix_to_pose(remainder)
    if np.any(np.abs(rest) > 1e-12):
        lines.append(
            "# tool0 -> model flange (not representable here; set it as a TCP offset): "
            + ", ".join(_num(v) for v in rest)
        )
    for w in export_warnings(model, "ur-calibration"):
        lines.append(f"# warning: {w}")
    lines.append("kinematics:")
    values = []
    for seg in UR_SEGMENTS:
        lines.append(f"  {seg}:")
        for key, v in zip(("x", "y", "z", "roll", "pitch", "yaw"), segs[seg]):
            v = 0.0 if abs(v) < 1e-15 else v
            values.append(v)
            lines.append(f"    {key}: {_num(v)}")
    dh = _ur_dh_of_segments(joints)
    lines.append(f"  hash: {ur_hash(dh if dh is not None else [tuple(values[i : i + 4]) for i in range(0, 36, 4)])}")
    return "\n".join(lines) + "\n"


UR_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


def parse_ur_calibration_yaml(text: str) -> dict:
    """The nested mappings of a UR calibration YAML as yaml-cpp writes them (``kinematics:``, two-space
    indented ``segment:`` blocks of ``key: number`` lines, ``hash: calib_...``; ``#`` comments):
    ``{"kinematics": {"shoulder": {"x": 0.0, ...}, ..., "hash": "calib_..."}}``. Values that read
    as numbers are floats. Raises ``ValueError`` naming the line for anything outside that
    subset of YAML (lists, flow style, tabs, an indentation that is not a mapping's)."""
    root: dict = {}
    stack: list[tuple[int, dict]] = [(-1, root)]
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split(" #")[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        if "\t" in raw[: len(raw) - len(raw.lstrip())]:
            raise ValueError(f"line {no}: tab in the indentation")
        indent = len(line) - len(line.lstrip())
        key, sep, value = line.strip().partition(":")
        if not sep or not key or key.startswith(("-", "{", "[")):
            raise ValueError(f"line {no}: expected 'key: value' or 'key:', got {line.strip()!r}")
        key = key.strip().strip("'\"")
        while indent <= stack[-1][0]:
            stack.pop()
        parent = stack[-1][1]
        value = value.strip()
        if not value:
            child: dict = {}
            parent[key] = child
            stack.append((indent, child))
            continue
        if value.startswith(("[", "{", "&", "*", "|", ">")):
            raise ValueError(f"line {no}: {key}: expected a plain value, got {value!r}")
        value = value.strip("'\"")
        try:
            parent[key] = float(value)
        except ValueError:
            parent[key] = value
    return root


def model_from_ur_calibration(doc: dict, robot: str, *, name: str | None = None) -> KinematicModel:
    """The model a UR calibration YAML (``doc``: the file as parsed, ``{"kinematics": {...}}``)
    describes for the library UR ``robot``, read as ur_description reads it: segment i is the
    ``<origin xyz rpy>`` of joint i (``rpy`` URDF's ``Rz(yaw)·Ry(pitch)·Rx(roll)``), after which the
    joint turns about its z axis; the chain starts at ``base_link_inertia`` (the controller's base
    frame, the library UR's base) and ends at ``tool0`` (the wrist_3 link, the model's flange).
    Joint names, limits, speeds and torques are the library robot's. Raises ``ValueError`` naming
    the field at fault (``kinematics.forearm.yaw``)."""
    from .urdf import ChainJoint, chain_to_model, origin

    if not is_ur(robot) or robot.lower() not in library_names():
        raise ValueError(
            f"--robot: expected a library UR arm ({', '.join(n for n in library_names() if is_ur(n))}), got {robot!r}"
        )
    lib = nominal(robot.lower())
    kin = doc.get("kinematics") if isinstance(doc, dict) else None
    if not isinstance(kin, dict):
        raise ValueError("kinematics: expected a mapping with shoulder, upper_arm, forearm, wrist_1, wrist_2, wrist_3")
    chain, parent = [], "base_link_inertia"
    for seg, j in zip(UR_SEGMENTS, lib.joints):
        s = kin.get(seg)
        if not isinstance(s, dict):
            raise ValueError(f"kinematics.{seg}: missing (expected x, y, z, roll, pitch, yaw)")
        vals = []
        for key in UR_KEYS:
            v = s.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise ValueError(f"kinematics.{seg}.{key}: expected a number, got {v!r}")
            vals.append(float(v))
        child = f"{seg}_link"
        T = origin(vals[:3], vals[3:])
        chain.append(
            ChainJoint(
                j.name, "revolute", parent, child, T, np.array([0.0, 0.0, 1.0]), j.lower, j.upper, j.velocity, j.effort
            )
        )
        parent = child
    units = lib.units
    return chain_to_model(name or f"{robot.lower()}-ur-calibration", chain, convention="auto", units=units)


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
            row.append(j.beta / A if j.beta is not None else "")  # j.hayati
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
