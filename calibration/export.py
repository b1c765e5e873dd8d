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
from .transforms import homogeneous, matrix_to_pose, pose_to_matrix, rot

FORMATS = ("urdf", "dh-csv", "dh-md")


def export_warnings(model: KinematicModel, fmt: str = "urdf") -> list[str]:
    """What the export ``fmt`` cannot represent of ``model`` (empty when the export is exact)."""
    out = []
    if fmt == "urdf":
        if model.coupling is not None:
            out.append("the joint coupling matrix is not representable in URDF (a URDF joint position is the reading)")
        for j in model.joints:
            if model.coupling is None and j.gain != 1.0:
                out.append(f"joint {j.name}: gain {j.gain:.9g} is not representable in URDF (URDF assumes gain 1)")
    for j in model.joints:
        if j.harmonic is not None:
            out.append(f"joint {j.name}: the gear-eccentricity harmonic is not representable in {fmt}")
    if model.compliance is not None:
        out.append(f"{'URDF' if fmt == 'urdf' else fmt} cannot carry joint compliance under gravity: "
                   "the rigid part of the model is written")
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


def _num(v: float) -> str:
    v = float(v)
    if abs(v) < 1e-15:
        return "0"
    return repr(v)


def _origin(parent: ET.Element, T: np.ndarray) -> None:
    p = matrix_to_pose(T)
    ET.SubElement(parent, "origin", xyz=" ".join(_num(v) for v in p[:3]), rpy=" ".join(_num(v) for v in p[3:]))


def to_urdf(model: KinematicModel, *, name: str | None = None, effort: float = 0.0, velocity: float = 0.0,
            prefix: str = "") -> str:
    """The model as a URDF document (kinematics only: links without inertia or geometry).

    Links: ``world`` -> ``base_link`` -> ``<joint>_link`` ... -> ``flange`` -> ``tool`` ->
    ``target_<name>``; every name is prefixed with ``prefix``. ``effort`` and ``velocity`` go into
    each ``<limit>`` (the model does not know them; URDF requires the attributes)."""
    robot = ET.Element("robot", name=name or model.name or "robot")
    robot.append(ET.Comment(f" generated by recal from model {model.name!r} ({model.convention}); "
                            "metres and radians; joint origins carry the calibrated values "))
    for w in export_warnings(model, "urdf"):
        robot.append(ET.Comment(f" warning: {w} "))
    limits = {j.name: (j.lower, j.upper) for j in model.joints}

    def link(n: str) -> str:
        ET.SubElement(robot, "link", name=prefix + n)
        return prefix + n

    def joint(n: str, jtype: str, parent: str, child: str, T: np.ndarray, axis: np.ndarray | None = None,
              limit: tuple[float, float] | None = None) -> None:
        e = ET.SubElement(robot, "joint", name=prefix + n, type=jtype)
        _origin(e, T)
        ET.SubElement(e, "parent", link=parent)
        ET.SubElement(e, "child", link=child)
        if axis is not None:
            ET.SubElement(e, "axis", xyz=" ".join(_num(v) for v in axis))
        if limit is not None:
            ET.SubElement(e, "limit", lower=_num(limit[0]), upper=_num(limit[1]), effort=_num(effort),
                          velocity=_num(velocity))

    parent = link("world")
    for jname, jtype, T, axis in joint_origins(model):
        if jname == "base":
            child = link("base_link")
            joint("base_joint", "fixed", parent, child, T)
        elif jname == "flange":
            child = link("flange")
            joint("flange_joint", "fixed", parent, child, T)
        else:
            child = link(f"{jname}_link")
            joint(jname, jtype, parent, child, T, axis, limits[jname])
        parent = child
    tool = link("tool")
    joint("tool_joint", "fixed", parent, tool, pose_to_matrix(model.tool))
    for tname, p in model.targets.items():
        child = link(f"target_{tname}")
        joint(f"target_{tname}_joint", "fixed", tool, child, homogeneous(np.eye(3), p))
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


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
    return {"convention": model.convention, "kind": m.convention, "header": header, "rows": rows, "frames": frames,
            "units": {"length": model.units.length, "angle": model.units.angle}}


_KIND_TEXT = {
    "dh": "standard Denavit-Hartenberg: A_i = Rz(theta + q)·Tz(d)·Tx(a)·Rx(alpha); "
          "Hayati links (beta given): Rz(theta + q)·Tx(a)·Rx(alpha)·Ry(beta)",
    "mdh": "modified DH (Craig): A_i = Rx(alpha)·Tx(a)·Rz(theta + q)·Tz(d), alpha and a of the preceding link",
}


def to_dh_csv(model: KinematicModel) -> str:
    """The DH table as CSV (model units); base, tool and targets as ``#`` comment lines first."""
    t = dh_table(model)
    u = t["units"]
    lines = [f"# recal DH table of model {model.name!r}: {_KIND_TEXT[t['kind']]}",
             f"# convention: {t['kind']}",
             f"# units: length {u['length']}, angle {u['angle']}; "
             "poses are x, y, z, rx, ry, rz = Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx)"]
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
    unit = {"theta": u["angle"], "alpha": u["angle"], "beta": u["angle"], "d": u["length"], "a": u["length"],
            "x": u["length"], "y": u["length"], "z": u["length"], "rx": u["angle"], "ry": u["angle"], "rz": u["angle"]}
    out = [f"# Kinematic model `{model.name or 'robot'}`", "",
           f"Convention: {_KIND_TEXT[t['kind']]}.", "",
           f"Units: length {u['length']}, angle {u['angle']}. Joint limits are in the units of the joint's reading.",
           ""]
    for w in export_warnings(model, "dh-md"):
        out.append(f"> Warning: {w}.")
        out.append("")
    head = [f"{h} ({unit[h]})" if h in unit else h for h in t["header"]]
    out.append("| " + " | ".join(head) + " |")
    out.append("|" + "|".join("---" for _ in head) + "|")
    for row in t["rows"]:
        out.append("| " + " | ".join(v if isinstance(v, str) else _fmt(v) for v in row) + " |")
    out += ["", "Fixed frames (poses are x, y, z, rx, ry, rz = Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx); targets are "
            "points in the tool frame):", "", "| frame | values |", "|---|---|"]
    for fname, vals in t["frames"]:
        out.append(f"| {fname} | " + ", ".join(_fmt(v) for v in vals) + " |")
    return "\n".join(out) + "\n"


def export(model: KinematicModel, fmt: str, **kw) -> str:
    """``fmt`` one of :data:`FORMATS`."""
    if fmt == "urdf":
        return to_urdf(model, **kw)
    if fmt == "dh-csv":
        return to_dh_csv(model)
    if fmt == "dh-md":
        return to_dh_markdown(model)
    raise ValueError(f"`fmt` must be one of {', '.join(FORMATS)}; got {fmt!r}")
