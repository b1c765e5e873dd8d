"""Compensating a parsed RAPID, KRL or TP program (:class:`.base.Program`) with an identified
model, for a controller that knows only the nominal one (docs/compensation.md §7).

Pose targets: the pose the program means is ``X = B · T_work · P`` in the nominal model's world
(``B`` its base: the robot's base frame), with the program's tool; the nominal controller's joint
solution in the target's written configuration is found (:func:`calibration.vendors.configured_ik`);
the target is corrected by :func:`calibration.compensation.compensate_targets` (Algorithm B) from
that solution, so the compensated joints keep its branch and turns; the configuration of the
result, in the brand's terms, is compared with the written one (``branch_change`` where it
differs; the configuration numbers are never rewritten). A target the nominal model cannot reach
in its written configuration is left as written and flagged ``unreachable``.

Joint targets: the pose the nominal robot reached there, reached by the identified robot
(:func:`calibration.compensation.compensate_joints`).

Tools: the program's tool ``t`` is taken on the nominal model's flange (its tool replaced by
``t``) and on the identified model as ``T_tool_identified · T_tool_nominal⁻¹ · t`` (the
identified correction of the flange and tool kept).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from calibration import vendors
from calibration.compensation import (
    FLAG_BIT,
    compensate_joints,
    compensate_targets,
    compensate_through_correction,
    concatenate,
    source_poses,
    take,
)
from calibration.kinematics import fk
from calibration.transforms import invert, matrix_to_pose, pose_to_matrix

from .base import Program, Target, motion_order, written


def decode(brand: str, config: tuple | None):
    """A written configuration as (front, up, codes (6,)) for
    :func:`calibration.vendors.configured_ik` (``None``, or NaN in ``codes``, where the target does
    not state that part)."""
    if config is None:
        return None, None, None
    if brand == "abb":
        cf1, cf4, cf6, cfx = config
        return not (cfx & 4), not (cfx & 2), np.array([cf1, 0, 0, cf4, cfx & 1, cf6])
    if brand == "kuka":
        S, T = config
        front = None if S is None else not (S & 1)
        up = None if S is None else bool(S & 2)
        if T is None:
            return front, up, None
        codes = np.array([(T >> i) & 1 for i in range(6)], dtype=float)
        # A5's code holds T bit 4 and S bit 2 (sin A5 < 0): not stated without S
        codes[4] = float("nan") if S is None else codes[4] + 2 * ((S >> 2) & 1)
        return front, up, codes
    if brand == "fanuc":
        # the turn numbers count J1, J4 and J6 (docs/compensation.md §7: not J4, J5, J6)
        flip, up, front, t1, t4, t6 = config
        return bool(front), bool(up), np.array([2 * t1, 0, 0, 2 * t4, flip, 2 * t6])
    raise ValueError(brand)


def configuration(brand: str, model, q: np.ndarray) -> list[tuple]:
    """The configurations (brand terms) of readings ``q`` (N, 6)."""
    if brand == "abb":
        return [tuple(int(v) for v in row) for row in vendors.abb_confdata(model, q)]
    if brand == "kuka":
        return [tuple(int(v) for v in row) for row in vendors.kuka_status_turn(model, q)]
    return [tuple(int(v) for v in row) for row in vendors.fanuc_config(model, q)]


def same(brand: str, written_config: tuple, found: tuple) -> bool:
    if brand == "kuka":
        # only S bits 0-2 choose the solution (bit 4 marks a point taught on an absolutely
        # accurate robot, bit 3 is unused): the others are kept as written, not compared
        mask = (7, 63)
        return all(w is None or (w & m) == f for w, f, m in zip(written_config, found, mask))
    return tuple(written_config) == tuple(found)


def show(brand: str, config: tuple | None):
    """A configuration as the brand writes it (for the report)."""
    if config is None:
        return None
    if brand == "fanuc":
        flip, up, front, t1, t4, t6 = config
        return f"{'F' if flip else 'N'} {'U' if up else 'D'} {'T' if front else 'B'}, {t1}, {t4}, {t6}"
    if brand == "kuka":
        return {"S": config[0], "T": config[1]}
    return list(config)


def _with_tool(model, T_tool: np.ndarray, nominal):
    """``model`` with the program's tool (see the module docstring)."""
    if model is nominal:
        return dataclasses.replace(model, tool=matrix_to_pose(T_tool))
    corr = pose_to_matrix(model.tool) @ invert(pose_to_matrix(nominal.tool))
    return dataclasses.replace(model, tool=matrix_to_pose(corr @ T_tool))


def _f(x, digits=12):
    x = float(x)
    return None if not np.isfinite(x) else float(f"{x:.{digits}g}")


def compensate_program(prog: Program, model, nominal, taught, M: np.ndarray, calibrated, kw: dict, correction=None):
    """The compensated files (bytes, one per file of ``prog``), the
    :class:`~calibration.compensation.CompensatedPoints` of every target in program order, and the
    report's leading fields per target (JSON text ending in a comma). ``correction``: the model's
    residual correction (``calibration.residual_map.from_model``) or None; targets are compensated
    through it (:func:`calibration.compensation.compensate_through_correction`), each tool's at
    that tool's point."""
    B = pose_to_matrix(nominal.base)
    groups: dict[bytes, list[int]] = {}  # the targets of each tool
    for i, t in enumerate(prog.targets):
        groups.setdefault(np.round(t.T_tool, 12).tobytes(), []).append(i)
    ref = np.zeros(6)
    ref[1:] = vendors.REFERENCE[prog.brand]
    q_all, found_all = controller_solutions(prog, nominal, B, ref)
    out = _Compensated()
    for idx in groups.values():
        T_tool = prog.targets[idx[0]].T_tool
        nom = _with_tool(nominal, T_tool, nominal)
        ide = _with_tool(model, T_tool, nominal)
        tau = _with_tool(taught, T_tool, nominal) if taught is not None else None
        through = _through(correction, _tool_point(model, ide))
        poses = [i for i in idx if prog.targets[i].kind == "pose"]
        joints = [i for i in idx if prog.targets[i].kind == "joints"]
        if poses:
            ts = [prog.targets[i] for i in poses]
            X_nom = np.array([B @ t.T_work @ t.P for t in ts])
            q_nom, found = q_all[poses], found_all[poses]
            X_d = np.linalg.inv(M) @ X_nom if tau is None else fk(tau, q_nom)
            cp = through(
                lambda X, ide=ide, nom=nom, q_nom=q_nom: compensate_targets(
                    ide, nom, X, q_nom, T_nominal_world=M, keep_branch=True, calibrated_range=calibrated, **kw
                ),
                X_d,
            )
            out.parts.append(_pose_targets_rewritten(prog, ts, nom, cp, found, B, out))
        if joints:
            ts = [prog.targets[i] for i in joints]
            Q = np.array([t.q for t in ts])
            cj = through(
                lambda X, ide=ide, Q=Q: compensate_joints(ide, X, Q, calibrated_range=calibrated, **kw),
                source_poses(Q, tau, nom, M),
            )
            for k, t in enumerate(ts):
                texts = [written(n, v, "deg") for n, v in zip(t.joints, np.degrees(cj.q[k]))]
                out.edits += list(zip(t.joints, texts))
                out.add(t, _head(prog, t, [n.text for n in t.joints], texts, None))
            out.parts.append(cj)
    comp = concatenate(out.parts)
    perm = sorted(range(len(out.order)), key=lambda k: out.order[k])
    comp = take(comp, np.array(perm, dtype=int))
    heads = [out.heads[k] for k in perm]
    return prog.rewrite(out.edits), comp, heads


def _tool_point(model, ide) -> np.ndarray:
    """The program tool's point (3,) m in ``model``'s tool frame (``ide``: the model with the
    program's tool): where a residual correction with a physical model (the joint transmission)
    is evaluated. A smooth map or trees correct the point they were measured at, whatever this is
    (the compensation report's notes say so)."""
    return (invert(pose_to_matrix(model.tool)) @ pose_to_matrix(ide.tool))[:3, 3]


def _through(correction, p_tool: np.ndarray):
    """``through(run, X)``: ``run(X)``, through ``correction`` where there is one."""
    if correction is None:
        return lambda run, X: run(X)
    return lambda run, X: compensate_through_correction(run, X, correction, p_tool)


@dataclasses.dataclass
class _Compensated:
    """What :func:`compensate_program` gathers, tool group by tool group."""

    parts: list = dataclasses.field(default_factory=list)  # Compensations, one per group and kind
    order: list = dataclasses.field(default_factory=list)  # (file, line) of each target, as compensated
    heads: list = dataclasses.field(default_factory=list)  # the report's leading fields of each target
    edits: list = dataclasses.field(default_factory=list)  # (number written, its new text)

    def add(self, t: Target, head: str) -> None:
        self.heads.append(head)
        self.order.append((t.file, t.line))


def _pose_targets_rewritten(prog: Program, ts: list[Target], nom, cp, found: np.ndarray, B: np.ndarray, out):
    """The pose targets ``ts`` compensated (``cp``) flagged where the solution's configuration
    differs from the written one or the nominal controller had none (``found``); their new
    numbers into ``out`` (a target not found is left as written)."""
    brand = prog.brand
    sol = configuration(brand, nom, cp.q)
    changed = np.array(
        [t.config is not None and not t.config_off and not same(brand, t.config, s) for t, s in zip(ts, sol)]
    )
    flags = (
        cp.flags
        | np.where(changed, FLAG_BIT["branch_change"], 0)
        | np.where(~found, FLAG_BIT["unreachable"] | FLAG_BIT["branch_change"], 0)
    )
    cp = dataclasses.replace(cp, flags=flags, converged=cp.converged & found)
    P_new = np.linalg.inv(np.array([B @ t.T_work for t in ts])) @ cp.T_command
    for k, t in enumerate(ts):
        texts = _pose_texts(t, P_new[k])
        if found[k]:
            out.edits += list(zip(t.position + t.orientation, texts))
        config = {"written": show(brand, t.config), "solution": show(brand, sol[k])}
        out.add(t, _head(prog, t, [n.text for n in t.position + t.orientation], texts if found[k] else None, config))
    return cp


def _pose_texts(t: Target, P_new: np.ndarray) -> list[str]:
    """The texts of pose target ``t``'s numbers for its new pose ``P_new`` (4, 4) in its work
    object: position in mm, orientation in the target's own terms (quaternion, KUKA A,B,C or
    Fanuc W,P,R, nearest the written angles)."""
    new_pos = P_new[:3, 3] * 1e3
    orig_rot = np.array([n.value for n in t.orientation])
    if t.rotation == "quat":
        new_rot, unit = vendors.quat_near(P_new[:3, :3], orig_rot)[0], "quat"
    elif t.rotation == "kuka_abc":
        new_rot = np.degrees(vendors.matrix_to_kuka_abc(P_new[:3, :3], np.radians(orig_rot))[0])
        unit = "deg"
    else:
        new_rot = np.degrees(vendors.matrix_to_fanuc_wpr(P_new[:3, :3], np.radians(orig_rot))[0])
        unit = "deg"
    return [written(n, v, "mm") for n, v in zip(t.position, new_pos)] + [
        written(n, v, unit) for n, v in zip(t.orientation, new_rot)
    ]


# Moves whose path is Cartesian (KRL, RAPID, TP, URScript names): the arm cannot change its
# configuration on the way, so a target without configuration data keeps the start's.
LINEAR_MOVES = {
    "lin",
    "circ",
    "slin",
    "scirc",
    "spl",
    "movel",
    "movec",
    "movep",
    "movelsync",
    "movecsync",
    "searchl",
    "searchc",
    "triggl",
    "triggc",
    "arcl",
    "arcc",
    "arclstart",
    "arclend",
    "arccstart",
    "arccend",
    "l",
    "c",
    "a",
}


def is_linear(move: str) -> bool:
    return move.lower() in LINEAR_MOVES


def controller_solutions(prog: Program, nominal, B: np.ndarray, ref: np.ndarray):
    """The nominal controller's joints (N, 6) for every pose target of ``prog`` (rows of joint
    targets unused) and whether it has them (N,).

    A target with configuration data: the solution in that configuration, turns nearest the
    brand's reference (:func:`calibration.vendors.configured_ik`). A target without (a KRL POS or
    FRAME without S and T; a RAPID target whose move runs under ``ConfL\\Off``/``ConfJ\\Off``)
    takes what the controller takes, moving from the previous target in the program's motions (:func:`~.base.motion_order`): a linear or circular move keeps the
    start configuration (the same side of axis 1, elbow and wrist), turns nearest the start; a
    joint move the solution nearest the axes where it starts. Where a linear move's target has no
    solution in the start configuration, it is not found (the controller stops there)."""
    brand = prog.brand
    N = len(prog.targets)
    q_all, found_all = np.zeros((N, 6)), np.ones(N, dtype=bool)
    nan = float("nan")
    groups: dict[bytes, list[int]] = {}
    for i, t in enumerate(prog.targets):
        if t.kind == "pose":
            groups.setdefault(np.round(t.T_tool, 12).tobytes(), []).append(i)
    stated = set()
    for idx in groups.values():
        nom = _with_tool(nominal, prog.targets[idx[0]].T_tool, nominal)
        # a configuration the controller does not monitor (RAPID ConfL\Off) chooses nothing
        dec = {i: decode(brand, None if prog.targets[i].config_off else prog.targets[i].config) for i in idx}
        rows = [i for i in idx if any(v is not None for v in dec[i])]
        if not rows:
            continue
        X = np.array([B @ prog.targets[i].T_work @ prog.targets[i].P for i in rows])
        fr = np.array([nan if dec[i][0] is None else float(dec[i][0]) for i in rows])
        up = np.array([nan if dec[i][1] is None else float(dec[i][1]) for i in rows])
        codes = np.array([np.full(6, nan) if dec[i][2] is None else dec[i][2].astype(float) for i in rows])
        q_all[rows], found_all[rows] = vendors.configured_ik(nom, X, brand, fr, up, codes, ref)
        stated.update(rows)
    prev = ref
    for i in sorted(range(N), key=lambda k: motion_order(prog.targets[k])):
        t = prog.targets[i]
        if t.kind == "joints":
            prev = t.q
            continue
        if i not in stated:
            nom = _with_tool(nominal, t.T_tool, nominal)
            X = (B @ t.T_work @ t.P)[None]
            if is_linear(t.move):
                f, u = vendors.arm_flags(nom, prev[None], brand)
                # the wrist keeps its side too: axis 5 cannot pass zero on a Cartesian path
                codes = np.full((1, 6), nan)
                codes[0, 4] = vendors.joint_codes(prev[None], brand)[0, 4]
                q, ok = vendors.configured_ik(nom, X, brand, f.astype(float), u.astype(float), codes, prev[None])
            else:
                q, ok = vendors.configured_ik(nom, X, brand, np.array([nan]), np.array([nan]), None, prev[None])
            q_all[i], found_all[i] = q[0], ok[0]
        prev = q_all[i]
    return q_all, found_all


def _head(prog: Program, t: Target, original, compensated, config) -> str:
    head = {
        "file": prog.paths[t.file],
        "line": t.line,
        "move": t.move,
        "kind": t.kind,
        "variable": t.name,
        "frames": t.frames,
        "original": original,
        "compensated": compensated,
    }
    if config is not None:
        head["configuration"] = config
    return json.dumps(head)[1:-1] + ","
