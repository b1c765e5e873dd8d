"""Serial chains of URDF robot descriptions, as Recal models. Pure: URDF text in, a model out.

A URDF (the ROS robot description format) is a tree of links joined by joints. Each joint has
an ``<origin xyz rpy>`` (the joint frame in its parent link's frame, ``rpy`` meaning
``Rz(yaw)·Ry(pitch)·Rx(roll)``, as Recal's poses), an ``<axis>`` in the joint frame (default
``1 0 0``) and, for ``revolute`` and ``prismatic`` joints, a ``<limit>``. The link frame of the
child is the joint frame moved by the joint: a rotation about, or a translation along, the axis.

:func:`model_from_urdf` takes the chain from a base link to a tip link, folds the fixed joints
into their neighbours and writes each moving joint as a ``poe`` joint (its axis and a point on it
in the base link's frame, at zero joint positions), which is exact for any URDF; the flange
(``home``) is the tip link's frame at zero. :func:`calibration.conventions.poe_to_dh` then gives
the ``dh`` form (exact as well). A joint position of the URDF is the model's joint reading.

The library (:mod:`calibration.robots`) builds its arms from the same chain description
(:class:`ChainJoint`), so a library arm and its URDF import are one code path.
"""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any

import numpy as np

from .conventions import poe_to_dh
from .errors import RecalError
from .model import Joint, KinematicModel, Units
from .transforms import homogeneous, matrix_to_pose, pose_to_matrix, rot, rpy_to_matrix

MOVING = ("revolute", "continuous", "prismatic")
MM_DEG = Units("mm", "deg")  # what models read from a URDF are written in


class UrdfError(RecalError, ValueError):
    """A URDF that is not a serial chain Recal can model. The message names the element at fault
    (``joint 'j4'``, ``link 'tool0'``) and what was expected."""


@dataclass(frozen=True, eq=False)
class ChainJoint:
    """One URDF joint: ``T_parent_joint`` (4, 4) SI from ``<origin>``, ``axis`` (3,) unit vector in
    the joint frame; limits (rad or m) and published velocity (rad/s or m/s) and effort (N·m or N),
    ``None`` where the URDF gives none."""

    name: str
    type: str
    parent: str
    child: str
    T_parent_joint: np.ndarray
    axis: np.ndarray
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    effort: float | None = None
    mimic: tuple[str, float, float] | None = None  # (leading joint, multiplier, offset): q = m·q_lead + offset


def origin(xyz=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The transform (4, 4) of a URDF ``<origin xyz rpy>``."""
    return homogeneous(rpy_to_matrix(np.asarray(rpy, dtype=float)), np.asarray(xyz, dtype=float))


# --------------------------------------------------------------------------- parsing


def _floats(text: str | None, n: int, what: str, default) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=float)
    try:
        v = [float(x) for x in text.split()]
    except ValueError:
        v = []
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise UrdfError(f"{what}: expected {n} numbers, got {text!r}")
    return np.array(v)


def _attr_float(e: ET.Element, key: str, what: str) -> float | None:
    text = e.get(key)
    if text is None:
        return None
    try:
        v = float(text)
    except ValueError:
        raise UrdfError(f"{what}: {key}={text!r} is not a number") from None
    if not math.isfinite(v):
        raise UrdfError(f"{what}: {key}={text!r} is not a finite number")
    return v


def parse_urdf(text: str) -> tuple[str, list[str], list[ChainJoint]]:
    """``(robot name, link names, joints)`` of a URDF document. Joints of every type are returned
    (``floating`` and ``planar`` too: whether they matter depends on the chain asked for)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise UrdfError(f"not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise UrdfError(f"the root element is <{root.tag}>; expected <robot>")
    links: list[str] = []
    for e in root.findall("link"):
        link_name = e.get("name")
        if not link_name:
            raise UrdfError("a <link> has no name")
        links.append(link_name)
    joints = []
    for e in root.findall("joint"):
        name = e.get("name")
        what = f"joint {name!r}"
        if not name:
            raise UrdfError("a <joint> has no name")
        jtype = e.get("type")
        if jtype not in MOVING + ("fixed", "floating", "planar"):
            raise UrdfError(f"{what}: unknown type {jtype!r}")
        ends: dict[str, str] = {}
        for tag in ("parent", "child"):
            c = e.find(tag)
            link = None if c is None else c.get("link")
            if not link:
                raise UrdfError(f"{what}: missing <{tag} link=...>")
            if link not in links:
                raise UrdfError(f"{what}: {tag} link {link!r} is not a <link> of the robot")
            ends[tag] = link
        o = e.find("origin")
        xyz = _floats(None if o is None else o.get("xyz"), 3, f"{what} <origin xyz>", [0, 0, 0])
        rpy = _floats(None if o is None else o.get("rpy"), 3, f"{what} <origin rpy>", [0, 0, 0])
        a = e.find("axis")
        axis = _floats(None if a is None else a.get("xyz"), 3, f"{what} <axis xyz>", [1, 0, 0])
        if jtype in MOVING and not np.linalg.norm(axis) > 0:
            raise UrdfError(f"{what}: <axis xyz> must not be zero")
        lim = e.find("limit")
        lower = upper = velocity = effort = None
        if lim is not None:
            lw = f"{what} <limit>"
            lower, upper = _attr_float(lim, "lower", lw), _attr_float(lim, "upper", lw)
            velocity, effort = _attr_float(lim, "velocity", lw), _attr_float(lim, "effort", lw)
        if jtype == "continuous":  # URDF: a continuous joint has no position limits
            lower = upper = None
        if lower is not None and upper is not None and not lower < upper:
            lower = upper = None  # URDF's "no limits" spelling (lower = upper = 0)
        mimic = None
        m = e.find("mimic")
        if m is not None and jtype in MOVING:
            lead = m.get("joint")
            if not lead:
                raise UrdfError(f"{what} <mimic>: missing joint=...")
            mult = _attr_float(m, "multiplier", f"{what} <mimic>")
            off = _attr_float(m, "offset", f"{what} <mimic>")
            mimic = (lead, 1.0 if mult is None else mult, 0.0 if off is None else off)
        joints.append(
            ChainJoint(
                name,
                jtype,
                ends["parent"],
                ends["child"],
                origin(xyz, rpy),
                axis / (np.linalg.norm(axis) or 1.0),
                lower,
                upper,
                velocity if velocity and velocity > 0 else None,
                effort if effort and effort > 0 else None,
                mimic,
            )
        )
    names = {j.name for j in joints}
    for j in joints:
        if j.mimic is not None and j.mimic[0] not in names:
            raise UrdfError(f"joint {j.name!r} <mimic>: joint {j.mimic[0]!r} is not a <joint> of the robot")
    return root.get("name") or "robot", links, joints


def serial_chain(
    links: list[str], joints: list[ChainJoint], base: str | None = None, tip: str | None = None
) -> list[ChainJoint]:
    """The joints from link ``base`` (default: the root link) to link ``tip`` (default: the only
    leaf below ``base``), in order."""
    by_child: dict[str, ChainJoint] = {}
    children: dict[str, list[ChainJoint]] = {n: [] for n in links}
    for j in joints:
        if j.child in by_child:
            raise UrdfError(f"link {j.child!r} is the child of two joints ({by_child[j.child].name!r}, {j.name!r})")
        by_child[j.child] = j
        children[j.parent].append(j)
    if base is None:
        roots = [n for n in links if n not in by_child]
        if len(roots) != 1:
            raise UrdfError(
                f"the robot has {len(roots)} root links ({', '.join(roots) or 'none'}); expected one (give --base LINK)"
            )
        base = roots[0]
    elif base not in children:
        raise UrdfError(f"link {base!r} (the base) is not a <link> of the robot")
    if tip is None:
        tip = _default_tip(children, base)
    elif tip not in children:
        raise UrdfError(f"link {tip!r} (the tip) is not a <link> of the robot")
    path = []
    link = tip
    while link != base:
        if link not in by_child:
            raise UrdfError(f"link {tip!r} (the tip) is not below link {base!r} (the base)")
        path.append(by_child[link])
        link = by_child[link].parent
    path.reverse()
    for j in path:
        if j.type in ("floating", "planar"):
            raise UrdfError(
                f"joint {j.name!r}: type {j.type!r} is not a single-axis joint; Recal models revolute, "
                "continuous, prismatic and fixed joints"
            )
    if not any(j.type in MOVING for j in path):
        raise UrdfError(f"no moving joint between link {base!r} and link {tip!r}")
    return path


def _default_tip(children: dict[str, list[ChainJoint]], base: str) -> str:
    """The tip when none is given: down from ``base``, into the only branch that holds a joint
    that moves on its own (a ROS-Industrial ``base_link`` -> ``base`` frame, Recal's own export's
    ``base``, a balancing cylinder whose joints are mimics are not), then
    along fixed joints while the way is single; where it forks into fixed-only branches (an
    exported URDF's tool frame with its ``target_*`` frames) the tip is the fork. Two branches
    that move on their own are refused: the tip must be given."""
    link = base
    while children[link]:
        moving = [j for j in children[link] if _moves_below(children, j)]
        if len(moving) > 1:
            leaves = sorted(_leaves(children, link))
            raise UrdfError(
                f"link {link!r} branches ({', '.join(repr(j.name) for j in moving)} lead to moving joints; "
                f"leaves {', '.join(leaves)}): give --tip LINK"
            )
        if moving:
            link = moving[0].child
        elif len(children[link]) == 1:
            link = children[link][0].child
        else:
            break
    return link


def _moves_below(children: dict[str, list[ChainJoint]], j: ChainJoint) -> bool:
    """Whether joint ``j`` or one below it moves on its own (not as a mimic of another joint)."""
    own = j.type in MOVING and j.mimic is None
    return own or any(_moves_below(children, c) for c in children[j.child])


def _leaves(children: dict, link: str) -> list[str]:
    if not children[link]:
        return [link]
    return [leaf for j in children[link] for leaf in _leaves(children, j.child)]


# --------------------------------------------------------------------------- chain -> model


def chain_to_poe(name: str, chain: list[ChainJoint], *, units: Units = MM_DEG) -> KinematicModel:
    """The ``poe`` model of a serial chain (book eq. 2.72-2.75): each moving joint's axis and
    origin in the first link's frame at zero joint positions, the last link's frame as ``home``.
    Exact for any chain. Joints without limits get the model's defaults.

    A ``<mimic>`` joint on the chain (``q = multiplier·q_lead + offset``, ``q_lead`` a moving joint
    of the chain) becomes a row of the model's ``coupling``: its variable is ``multiplier`` times
    the lead's reading (its own reading is not used), ``offset`` its ``theta`` (``d`` for a
    prismatic joint)."""
    T = np.eye(4)
    joints = []
    moving = [cj.name for cj in chain if cj.type != "fixed"]
    for cj in chain:
        T = T @ cj.T_parent_joint
        if cj.type == "fixed":
            continue
        rev = cj.type != "prismatic"
        kw: dict[str, Any] = {}  # the limits, where the URDF has them (else Joint's own)
        if cj.lower is not None and cj.upper is not None:
            kw = {"lower": cj.lower, "upper": cj.upper}
        elif not rev:
            kw = {"lower": -10.0, "upper": 10.0}
        offset = 0.0 if cj.mimic is None else cj.mimic[2]
        joints.append(
            Joint(
                name=cj.name,
                type="revolute" if rev else "prismatic",
                axis=T[:3, :3] @ cj.axis,
                point=T[:3, 3].copy(),
                theta=offset if rev else 0.0,
                d=0.0 if rev else offset,
                velocity=cj.velocity,
                effort=cj.effort,
                **kw,
            )
        )
    coupling = _mimic_coupling(chain, moving)
    return KinematicModel(
        name=name, convention="poe", joints=tuple(joints), home=matrix_to_pose(T), units=units, coupling=coupling
    )


def _mimic_coupling(chain: list[ChainJoint], moving: list[str]) -> np.ndarray | None:
    """The coupling matrix of the chain's mimic joints (``None`` without any)."""
    mimics = [(cj, cj.mimic) for cj in chain if cj.type != "fixed" and cj.mimic is not None]
    if not mimics:
        return None
    C = np.eye(len(moving))
    for cj, (lead, mult, _) in mimics:
        if lead not in moving:
            raise UrdfError(
                f"joint {cj.name!r} <mimic>: it follows joint {lead!r}, which is not a moving joint of the chain; "
                "its position cannot be read from the model's joints"
            )
        if next(c for c in chain if c.name == lead).mimic is not None:
            raise UrdfError(f"joint {cj.name!r} <mimic>: joint {lead!r} is itself a mimic joint")
        i = moving.index(cj.name)
        C[i, i] = 0.0
        C[i, moving.index(lead)] = mult
    return C


def chain_to_model(
    name: str, chain: list[ChainJoint], *, convention: str = "auto", units: Units = MM_DEG
) -> KinematicModel:
    """The model of a serial chain, exact in every ``convention``:

    - ``poe``: :func:`chain_to_poe`;
    - ``dh``: the ``poe`` model converted with :func:`calibration.conventions.poe_to_dh` (common
      normals, Hayati's form where consecutive axes are parallel), the tip frame folded into the
      last link where it can be; what the DH links cannot hold is in ``base`` and ``tool``;
    - ``auto``: ``dh`` when the DH chain starts on the base link and ends on the tip link
      (``base`` and ``tool`` zero), else ``poe``. Then the base link is the model's robot base and
      the tip link its flange, so that a user's ``base`` (world -> robot) and ``tool`` (the TCP)
      mean what they say.
    """
    if convention not in ("auto", "dh", "poe"):
        raise ValueError(f"`convention` must be auto, dh or poe; got {convention!r}")
    poe = chain_to_poe(name, chain, units=units)
    if convention == "poe":
        return poe
    dh = poe_to_dh(poe)
    folded = _flange_into_last_link(dh)
    if convention == "dh":
        return dh if folded is None else folded
    exact = folded is not None and np.allclose(folded.base, 0.0, atol=1e-12)
    return folded if folded is not None and exact else poe


def _flange_into_last_link(model: KinematicModel) -> KinematicModel | None:
    """``model`` (``dh``, last link with ``a = alpha = 0`` as :func:`poe_to_dh` writes it) with its
    tool folded into the last link, or ``None`` when the tool is not of the form
    ``Rz(phi)·Tz(d)·Tx(a)·Rx(alpha)`` (tip frame's x axis not perpendicular to the last joint's
    axis, or its origin off the plane of that x axis and the joint axis)."""
    last = model.joints[-1]
    if last.hayati or last.a != 0.0 or last.alpha != 0.0:
        return None
    T = pose_to_matrix(model.tool)
    R, p = T[:3, :3], T[:3, 3]
    if abs(R[2, 0]) > 1e-12:
        return None
    phi = math.atan2(R[1, 0], R[0, 0])
    M = rot(2, -phi) @ R
    alpha = math.atan2(M[2, 1], M[1, 1])
    x = np.array([math.cos(phi), math.sin(phi), 0.0])
    a = float(p @ x)
    if not (np.allclose(M, rot(0, alpha), atol=1e-12) and np.allclose(p, a * x + [0, 0, p[2]], atol=1e-12)):
        return None
    joints = model.joints[:-1] + (dataclasses.replace(last, theta=last.theta + phi, d=last.d + p[2], a=a, alpha=alpha),)
    return dataclasses.replace(model, joints=joints, tool=np.zeros(6))


def model_from_urdf(
    text: str,
    *,
    base: str | None = None,
    tip: str | None = None,
    convention: str = "auto",
    units: Units = MM_DEG,
    name: str | None = None,
) -> KinematicModel:
    """The model of :func:`import_urdf`, without its notes."""
    return import_urdf(text, base=base, tip=tip, convention=convention, units=units, name=name)[0]


def import_urdf(
    text: str,
    *,
    base: str | None = None,
    tip: str | None = None,
    convention: str = "auto",
    units: Units = MM_DEG,
    name: str | None = None,
) -> tuple[KinematicModel, list[str]]:
    """``(model, notes)``: the model whose forward kinematics is the URDF chain's from link
    ``base`` to link ``tip`` (defaults: the root link, and :func:`_default_tip`) in
    ``convention`` (see :func:`chain_to_model`), and one note per joint of the tree that is not
    on the chain and so is ignored, as ROS's own chain solvers (KDL, MoveIt's groups) ignore it:
    a gripper's fingers, a balancing cylinder's mimic joints, a camera's floating or planar
    joint. Fixed leaves ``target_<name>`` under the tip link (Recal's own URDF export writes
    them) become the model's targets.

    Raises :class:`UrdfError` naming the element at fault: a fork of moving branches without
    ``tip``, a link that does not exist, a ``floating`` or ``planar`` joint on the chain, a mimic
    joint on the chain that follows a joint off it, a malformed number."""
    robot, links, joints = parse_urdf(text)
    chain = serial_chain(links, joints, base, tip)
    tip_link = chain[-1].child
    targets = {
        j.child.removeprefix("target_"): j.T_parent_joint[:3, 3].copy()
        for j in joints
        if j.parent == tip_link and j.type == "fixed" and j.child.startswith("target_") and _is_leaf(joints, j.child)
    }
    model = chain_to_model(name or robot, chain, convention=convention, units=units)
    if targets:
        model = dataclasses.replace(model, targets=targets)
    return model, off_chain_notes(joints, chain, set(targets))


def _is_leaf(joints: list[ChainJoint], link: str) -> bool:
    return not any(j.parent == link for j in joints)


def off_chain_notes(
    joints: list[ChainJoint], chain: list[ChainJoint], targets: set[str] | frozenset[str] = frozenset()
) -> list[str]:
    """One line per non-fixed joint not on ``chain`` (ignored), and one for the fixed ones."""
    on = {j.name for j in chain}
    out, fixed = [], []
    for j in joints:
        if j.name in on:
            continue
        if j.type == "fixed":
            if j.child.removeprefix("target_") not in targets or not j.child.startswith("target_"):
                fixed.append(j.child)
            continue
        kind = j.type if j.mimic is None else f"{j.type}, mimic of {j.mimic[0]!r}"
        out.append(f"joint {j.name!r} ({kind}) is not on the chain {chain[0].parent} -> {chain[-1].child}: ignored")
    if fixed:
        shown = ", ".join(repr(n) for n in fixed[:4]) + (", ..." if len(fixed) > 4 else "")
        out.append(f"{len(fixed)} fixed frame(s) off the chain ({shown}): ignored")
    return out
