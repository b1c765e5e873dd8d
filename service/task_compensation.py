"""Use case: compensate a task file (a task CSV or a robot program) with an identified model.

``recal compensate`` (service/commands/compensate.py) and the service's compensation routes
(service/stored_compensation.py) both call :func:`compensate_task`; neither calls the other. It reads the
task (and a KRL program's .dat) from ``CompensationRequest.task``, compensates every target
(``calibration.compensation``), and returns the compensated files' texts and the per-point
report, writing nothing. Formats: task CSV (contracts §5, ``service.taskfiles``) and the programs
of ``service.programs`` (URScript, ABB RAPID, KUKA KRL, Fanuc TP); docs/compensation.md.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from calibration.compensation import (
    FLAG_BIT,
    CompensatedPoints,
    compensate_joints,
    compensate_targets,
    compensate_through_correction,
    concatenate,
    flag_names,
    nominal_solution,
    nominal_world_frame,
    source_poses,
    take,
)
from calibration.errors import RecalError
from calibration.kinematics import fk
from calibration.model import KinematicModel
from calibration.residual_map import ResidualMapError, from_model
from calibration.transforms import matrix_to_pose, pose_to_matrix

from . import programs
from .files import InputError
from .programs import urscript
from .programs.frames import Frames
from .programs.retarget import compensate_program
from .taskfiles import format_task, matrix_to_pose_ur, pose_to_matrix_ur, read_task

CHUNK = 25_000
FLAG_COUNTS = (
    "joint_limit",
    "near_singular",
    "outside_calibrated_region",
    "no_convergence",
    "branch_change",
    "unreachable",
)


class CompensationInputError(RecalError, ValueError):
    """The task cannot be compensated as asked (one line, for the user)."""


class NoTargetsError(InputError):
    """A program without a single target to compensate; ``report`` (or None) lists the lines left
    alone and why, for the caller to write where the user asked for a report."""

    def __init__(self, path, message, *, line=None, report: dict | None = None):
        super().__init__(path, message, line=line)
        self.report = report


@dataclass(frozen=True, eq=False)
class CompensationRequest:
    """What to compensate and how. ``task``: the task file's path (a KRL program's .dat beside
    it); ``out``: the output's path (names the companion outputs, nothing is written);
    ``model_label``: how messages name the identified model (its file); ``fmt``: ``csv``,
    ``urscript`` or a brand of ``service.programs``; ``mode``: ``joints`` or ``targets`` (CSV);
    ``nominal``: the model the controller uses; ``taught``: the identified model of the robot the
    task's joints were taught on; ``calibrated``: (n, 2) SI joint ranges of the calibration;
    ``settings``: keyword arguments of the compensation functions (tolerances); ``qnear``: (n,)
    SI joints choosing the branch of rows without joints; ``frames``: KRL/TP tool and base
    frames; ``report``: the caller will write a report (messages say so)."""

    task: str
    out: str
    model_label: str
    fmt: str = "csv"
    mode: str = "joints"
    nominal: KinematicModel | None = None
    taught: KinematicModel | None = None
    calibrated: np.ndarray | None = None
    settings: dict = field(default_factory=dict)
    qnear: np.ndarray | None = None
    frames: Frames | None = None
    report: bool = False


@dataclass(frozen=True, eq=False)
class CompensationResult:
    """The compensated files ``outputs`` (``[(path, text)]``, the task's first), every target's
    :class:`~calibration.compensation.CompensatedPoints` in file order, the report's leading fields
    per point (``prefixes``, JSON text), the lines left alone (``skipped``), the nominal world
    frame ``T_nominal_world`` and its fit RMS (m), the ``summary`` and the report document
    without its points (``report_head``)."""

    outputs: list
    comp: CompensatedPoints
    prefixes: list
    skipped: list
    T_nominal_world: np.ndarray
    fit_rms_m: float | None
    summary: dict
    report_head: dict
    model: KinematicModel

    def report_text(self) -> str:
        """The whole report as JSON text (points written directly: fast for 100,000 points)."""
        head = json.dumps(self.report_head, indent=1)
        lines = _point_lines(self.comp, self.model, self.prefixes)
        return head[:-2] + ',\n "points": [\n  ' + ",\n  ".join(lines) + "\n ]\n}\n"

    def report(self) -> dict:
        """The whole report as a document."""
        return json.loads(self.report_text())

    def shortfall(self) -> str | None:
        """What was asked but not done, in one line (``None`` when every target was compensated):
        how many targets were left as written (unreachable in their configuration) or did not
        converge, and where (the report's rows: file and line, or row)."""
        bad = np.flatnonzero(~self.comp.converged)
        if len(bad) == 0:
            return None
        unreachable = (self.comp.flags[bad] & FLAG_BIT["unreachable"]) != 0
        parts = []
        if unreachable.any():
            kept = ", left as written" if self.report_head.get("mode") in programs.BRAND else ""
            parts.append(f"{int(unreachable.sum())} unreachable{kept}")
        if (~unreachable).any():
            worst = self.comp.residual_m[bad[~unreachable]].max(initial=0.0) / self.model.units.length_m
            parts.append(
                f"{int((~unreachable).sum())} not converged (residual up to {worst:.3g} {self.model.units.length})"
            )
        where = [_where(self.prefixes[k]) if k < len(self.prefixes) else f"point {k + 1}" for k in bad[:10]]
        more = f" and {len(bad) - 10} more" if len(bad) > 10 else ""
        return (
            f"{len(bad)} of {len(self.comp)} targets not compensated ({'; '.join(parts)}): " + ", ".join(where) + more
        )


def _where(prefix: str) -> str:
    """A report row's place, from its leading fields: ``file, line L (NAME)`` or ``row R``."""
    try:
        head = json.loads("{" + prefix.rstrip().rstrip(",") + "}")
    except ValueError:
        return "?"
    if "row" in head:
        return f"row {head['row']}"
    place = f"{Path(str(head.get('file', ''))).name}, line {head.get('line')}".lstrip(", ")
    return place + (f" ({head['variable']})" if head.get("variable") else "")


def residual_map_of(model: KinematicModel):
    """The model's residual map (``calibration.residual_map``), or None."""
    try:
        return from_model(model)
    except ResidualMapError as exc:
        raise CompensationInputError(f"field {exc.field!r}: {str(exc).split(': ', 1)[-1]}") from None


def calibrated_range_of(model: KinematicModel) -> np.ndarray | None:
    """(n, 2) SI joint ranges the identified model records (``identification.joint_ranges``), or
    None."""
    ranges = (model.metadata.get("identification") or {}).get("joint_ranges")
    if ranges is None:
        return None
    scale = np.array([model.units.angle_rad if j.revolute else model.units.length_m for j in model.joints])
    try:
        r = np.asarray(ranges, dtype=float).reshape(model.n_joints, 2)
    except (TypeError, ValueError):
        raise CompensationInputError(
            f"field 'identification.joint_ranges': expected {model.n_joints} pairs [lower, upper]"
        ) from None
    return r * scale[:, None]


def compensate_task(
    model: KinematicModel, req: CompensationRequest, *, progress: Callable[[str], None] | None = None
) -> CompensationResult:
    """Compensate the task ``req`` names with the identified ``model``; see the module docstring.
    Raises ``InputError`` (the file, row or line at fault) or :class:`CompensationInputError`."""
    t0 = time.perf_counter()
    if req.qnear is None:
        req = dataclasses.replace(req, qnear=np.zeros(model.n_joints))
    handler = _script if req.fmt == "urscript" else _program if req.fmt in programs.BRAND else _csv
    output, comp, prefixes, skipped, M, fit_rms, *more_notes = handler(req, model, t0, progress)
    u = model.units
    L = u.length_m
    counts = {name: comp.count(name) for name in FLAG_COUNTS}
    if comp.count("outside_mapped_region"):  # only a model with a residual map sets it
        counts["outside_mapped_region"] = comp.count("outside_mapped_region")
    summary = {
        "points": len(comp),
        "converged": int(np.count_nonzero(comp.converged)),
        # targets left as written (unreachable) or not converged: `recal compensate` exits 3
        "not_compensated": int(np.count_nonzero(~comp.converged)),
        "residual_max": _f(comp.residual_m.max(initial=0.0) / L),
        "residual_angle_max": _f(comp.residual_rad.max(initial=0.0) / u.angle_rad),
        "correction_max": _f(np.abs(comp.correction).max(initial=0.0) / u.angle_rad),
        "flags": counts,
        "notes": notes_for(model) + [note for notes in more_notes for note in notes],
    }
    pose = matrix_to_pose(M)
    script = req.fmt != "csv"
    head = {
        "format": "recal.compensation-report/1",
        "task": str(req.task),
        "model": model.name,
        "nominal": req.nominal.name if req.nominal is not None else None,
        "mode": ("script" if req.fmt == "urscript" else req.fmt) if script else req.mode,
        "units": {"length": u.length, "angle": u.angle},
        # the payload a compliant model sagged under (kg, centre of gravity in the tool frame in the
        # length unit): the task's (--payload, the service's ?payload=) or the model's own; None for
        # a rigid model, which has no use for one
        "payload": None
        if model.compliance is None or model.compliance.payload is None
        else [_f(model.compliance.payload[0])] + [_f(v / L) for v in model.compliance.payload[1:]],
        "frame": {
            "T_nominal_world": [_f(v / L) for v in pose[:3]] + [_f(v / u.angle_rad) for v in pose[3:]],
            "fit_rms": _f(fit_rms / L) if fit_rms is not None else None,
        },
        "calibrated_region": None
        if req.calibrated is None
        else [[_f(v / (u.angle_rad if j.revolute else L)) for v in r] for r, j in zip(req.calibrated, model.joints)],
        "summary": summary,
        "uninterpreted": skipped,
        "elapsed_s": round(time.perf_counter() - t0, 3),
    }
    outputs = output if isinstance(output, list) else [(req.out, output)]
    return CompensationResult(
        outputs=outputs,
        comp=comp,
        prefixes=prefixes,
        skipped=skipped,
        T_nominal_world=M,
        fit_rms_m=fit_rms,
        summary=summary,
        report_head=head,
        model=model,
    )


def _chunked(N, fn, t0, progress):
    """Run ``fn(slice)`` over chunks of the task, with a progress line once it takes > 2 s."""
    parts = []
    for start in range(0, N, CHUNK):
        parts.append(fn(slice(start, min(start + CHUNK, N))))
        if progress is not None and time.perf_counter() - t0 > 2.0 and start + CHUNK < N:
            progress(f"recal compensate: {start + CHUNK} of {N} points")
    return concatenate(parts)


def _csv(req: CompensationRequest, model: KinematicModel, t0: float, progress):
    task = read_task(req.task, model)
    M, fit_rms, X = _csv_goals(req, model, task)
    run = _csv_runner(req, model, task, M)
    comp = _compensate_with_map(model, run, X, len(task), t0, progress)
    names = {int(b): ";".join(flag_names(b)) for b in np.unique(comp.flags)}
    flags = [names[int(b)] for b in comp.flags]
    text = format_task(task, model, req.mode, comp.q, comp.T_command, comp.converged, comp.residual_m, flags)
    prefixes = [f'"row":{i + 1},"line":{line},' for i, line in enumerate(task.table.lines)]
    return text, comp, prefixes, [], M, fit_rms


def _csv_goals(req: CompensationRequest, model: KinematicModel, task):
    """The nominal model's world frame in the identified one's (identity without a nominal), the
    fit's RMS (or None), and each row's goal pose in the world frame: its own pose, or for a row
    with only joints the pose they gave the robot they were taught (or planned) on."""
    nominal, taught = req.nominal, req.taught
    M, fit_rms = nominal_world_frame(model, nominal, req.calibrated) if nominal is not None else (np.eye(4), None)
    only_q = task.has_q & ~task.has_pose
    if np.any(only_q) and taught is None and nominal is None:
        r = int(np.nonzero(only_q)[0][0])
        raise CompensationInputError(
            f"{req.task}: row {r + 1} (line {task.table.lines[r]}) has only joints: give --nominal (they were "
            f"planned on it) or --taught-on MODEL (the robot they were taught on)"
        )
    X = task.T_world_tool.copy()
    if np.any(only_q):
        X[only_q] = source_poses(task.q[only_q], taught, nominal, M)
    return M, fit_rms, X


def _csv_runner(
    req: CompensationRequest, model: KinematicModel, task, M: np.ndarray
) -> Callable[[np.ndarray, slice], CompensatedPoints]:
    """``run(X, rows)``: compensate the task's ``rows`` aiming at goal poses ``X`` (all rows',
    world frame; ``M``: the nominal world frame in it), as the request's mode asks: targets for
    the nominal controller, or joint commands."""
    nominal, calibrated, kw = req.nominal, req.calibrated, req.settings
    q_near = np.where(task.has_q[:, None], np.nan_to_num(task.q), req.qnear)
    if req.mode == "targets":
        if nominal is None:
            raise CompensationInputError(
                f"{req.model_label}: targets mode needs the nominal model the controller uses: give --nominal "
                f"NOMINAL.json (this model does not record the one it was identified from)"
            )

        def run_targets(X, sl):
            return compensate_targets(
                model,
                nominal,
                X[sl],
                q_near[sl],
                T_nominal_world=M,
                keep_branch=task.has_q[sl],
                calibrated_range=calibrated,
                **kw,
            )

        return run_targets
    # the correction starts from the nominal controller's solution; without a nominal model,
    # from the identified model's own inverse kinematics (numerical: calibration.ik.numerical_ik)
    start = nominal if nominal is not None else model

    def run_joints(X, sl):
        q0 = q_near[sl].copy()
        reachable = np.ones(len(q0), dtype=bool)
        changed = np.zeros(len(q0), dtype=bool)
        rows = task.has_pose[sl]
        if np.any(rows):
            sol = nominal_solution(start, M @ X[sl][rows], q_near[sl][rows], keep_branch=task.has_q[sl][rows])
            q0[rows], reachable[rows] = sol.q, sol.reachable
            if sol.branch_changed is not None:
                changed[rows] = sol.branch_changed
        return compensate_joints(
            model, X[sl], q0, reachable=reachable, branch_changed=changed, calibrated_range=calibrated, **kw
        )

    return run_joints


def _through_correction(model: KinematicModel, run, X: np.ndarray) -> CompensatedPoints:
    """``run(X)``, through the model's residual correction where it has one."""
    rmap = residual_map_of(model)
    return run(X) if rmap is None else compensate_through_correction(run, X, rmap)


def _compensate_with_map(model: KinematicModel, run, X: np.ndarray, N: int, t0: float, progress) -> CompensatedPoints:
    """``run`` over all ``N`` rows aiming at ``X``, in chunks; with a residual correction in the
    model, through it (:func:`calibration.compensation.compensate_through_correction`)."""
    rmap = residual_map_of(model)
    if rmap is None:
        return _chunked(N, partial(run, X), t0, progress)
    return compensate_through_correction(lambda X_aim: _chunked(N, partial(run, X_aim), t0, progress), X, rmap)


def _g(x: float) -> str:
    """A float as JSON text, 9 significant digits (``null`` if not finite)."""
    return f"{x:.9g}" if np.isfinite(x) else "null"


def _point_lines(comp, model, prefixes: list[str]) -> list[str]:
    """One compact JSON object per point (``prefixes[i]``: its leading fields, JSON text ending
    in a comma), in the model's units. Written directly: a 100,000-point report in about a
    second, where ``json.dumps`` of dicts takes several."""
    u = model.units
    scales = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    res, ang = comp.residual_m / u.length_m, comp.residual_rad / u.angle_rad
    corr = comp.correction / scales
    names = {int(b): json.dumps(flag_names(b)) for b in np.unique(comp.flags)}
    return [
        "{"
        + prefixes[i]
        + f'"converged":{"true" if comp.converged[i] else "false"},"iterations":{int(comp.iterations[i])},'
        + f'"residual":{_g(res[i])},"residual_angle":{_g(ang[i])},'
        + '"correction":['
        + ",".join(_g(c) for c in corr[i])
        + "],"
        + f'"sigma_min":{_g(comp.sigma_min[i])},"flags":{names[int(comp.flags[i])]}'
        + "}"
        for i in range(len(comp))
    ]


def _f(x, digits=9):
    x = float(x)
    return None if not np.isfinite(x) else float(f"{x:.{digits}g}")


def _needs_nominal(req: CompensationRequest, what: str) -> None:
    """A program's targets are for its controller, which computes with the nominal model: refuse
    ``what`` without one."""
    if req.nominal is None:
        raise CompensationInputError(
            f"{req.model_label}: {what} needs the nominal model its controller uses: give --nominal "
            f"NOMINAL.json (this model does not record the one it was identified from)"
        )


def _script(req: CompensationRequest, model: KinematicModel, t0: float, progress):
    nominal = req.nominal
    script = urscript.parse(req.task, n_joints=model.n_joints)
    if not script.targets:
        _no_targets(req, model, script)
    _needs_nominal(req, "a URScript program")
    M, fit_rms = nominal_world_frame(model, nominal, req.calibrated)
    B = pose_to_matrix(nominal.base)
    pose_t, pose_seed, joint_t = _script_targets(script, nominal, B, req.qnear)
    replacements: dict = {}
    literals: dict = {}
    heads: list[tuple[int, str]] = []  # (line, the point's leading report fields)
    comps = []
    if pose_t:
        comps.append(_script_pose_targets(req, model, M, B, pose_t, pose_seed, replacements, literals, heads))
    if joint_t:
        comps.append(_script_joint_targets(req, model, M, joint_t, replacements, literals, heads))
    comp = concatenate(comps) if len(comps) > 1 else comps[0]
    # report the targets in program order
    perm = np.argsort([line for line, _ in heads], kind="stable")
    comp = take(comp, perm)
    prefixes = [heads[k][1] for k in perm]
    skipped = [
        {"line": u.line, "text": u.text, "reason": u.reason}
        for u in script.uninterpreted
        if not (u.tcp is not None and tcp_is_tool(u.tcp, model))
    ]
    return script.rewrite(replacements, literals), comp, prefixes, skipped, M, fit_rms


def _script_targets(script, nominal: KinematicModel, B: np.ndarray, qnear):
    """The program's pose targets with the nominal controller's joints for each (the seed of
    their compensation), and its joint targets. In program order: pose targets without qnear take
    the branch nearest the previous target (what the controller's get_inverse_kin does from the
    robot's current joints)."""
    prev = qnear
    pose_t, pose_seed, joint_t = [], [], []
    for t in script.targets:
        if t.pose is not None:
            X_nom = B @ pose_to_matrix_ur(t.pose.values)
            seed, keep = (t.joints.values, True) if t.joints is not None else (prev, False)
            sol = nominal_solution(nominal, X_nom, seed, keep_branch=keep)
            prev = sol.q[0]
            pose_t.append(t)
            pose_seed.append(sol.q[0])
        else:
            prev = t.joints.values
            joint_t.append(t)
    return pose_t, pose_seed, joint_t


def _script_pose_targets(req, model, M, B, pose_t, pose_seed, replacements, literals, heads) -> CompensatedPoints:
    """Compensate the pose targets for the nominal controller (base frame ``B``): each literal's
    replacement (and its qnear's) into ``replacements``/``literals``, its report head into ``heads``."""
    nominal, taught = req.nominal, req.taught
    P = np.array([t.pose.values for t in pose_t])
    X_nom = B @ pose_to_matrix_ur(P)
    seeds = np.array(pose_seed)
    X_d = np.linalg.inv(M) @ X_nom if taught is None else fk(taught, seeds)
    cp = _through_correction(
        model,
        lambda X: compensate_targets(
            model,
            nominal,
            X,
            seeds,
            T_nominal_world=M,
            keep_branch=True,
            calibrated_range=req.calibrated,
            **req.settings,
        ),
        X_d,
    )
    P_new = matrix_to_pose_ur(np.linalg.inv(B) @ cp.T_command, like=P)
    for i, t in enumerate(pose_t):
        replacements[id(t.pose)], literals[id(t.pose)] = P_new[i], t.pose
        if t.joints is not None:
            replacements[id(t.joints)], literals[id(t.joints)] = cp.q[i], t.joints
        head = {
            "line": t.line,
            "move": t.move,
            "kind": "pose",
            "variable": t.pose.name,
            "qnear_variable": t.joints.name if t.joints is not None else None,
            "original": [float(v) for v in P[i]],
            "compensated": [_f(v, 12) for v in P_new[i]],
        }
        heads.append((t.line, json.dumps(head)[1:-1] + ","))
    return cp


def _script_joint_targets(req, model, M, joint_t, replacements, literals, heads) -> CompensatedPoints:
    """Compensate the joint targets as joint commands, as :func:`_script_pose_targets` does."""
    Q = np.array([t.joints.values for t in joint_t]).reshape(-1, model.n_joints)
    cj = _through_correction(
        model,
        lambda X: compensate_joints(model, X, Q, calibrated_range=req.calibrated, **req.settings),
        source_poses(Q, req.taught, req.nominal, M),
    )
    for i, t in enumerate(joint_t):
        replacements[id(t.joints)], literals[id(t.joints)] = cj.q[i], t.joints
        head = {
            "line": t.line,
            "move": t.move,
            "kind": "joints",
            "variable": t.joints.name,
            "original": [float(v) for v in Q[i]],
            "compensated": [_f(v, 12) for v in cj.q[i]],
        }
        heads.append((t.line, json.dumps(head)[1:-1] + ","))
    return cj


# How close a set_tcp must be to the model's tool to count as it: the digits a program gives a TCP
# (1 µm, 10 µrad: a few µm at the tool point), far below the 0.01 mm a target must reach.
TCP_SAME_M, TCP_SAME_RAD = 1e-6, 1e-5


def tcp_is_tool(tcp_ur: np.ndarray, model: KinematicModel) -> bool:
    """Whether a URScript ``set_tcp`` pose (m, rotation vector) is the model's tool: the targets,
    compensated for that tool, are then right under it, and the line needs no flag (issue 27)."""
    T_set, T_tool = pose_to_matrix_ur(tcp_ur), pose_to_matrix(model.tool)
    dR = T_set[:3, :3].T @ T_tool[:3, :3]
    angle = float(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(np.linalg.norm(T_set[:3, 3] - T_tool[:3, 3]) <= TCP_SAME_M and angle <= TCP_SAME_RAD)


def _program(req: CompensationRequest, model: KinematicModel, t0: float, progress):
    """RAPID, KRL or TP (``service.programs``)."""
    nominal, taught, calibrated, kw = req.nominal, req.taught, req.calibrated, req.settings
    prog = programs.parse(req.fmt, req.task, n_joints=model.n_joints, frames=req.frames)
    if not prog.targets:
        _no_targets(req, model, prog)
    _needs_nominal(req, "a robot program")
    M, fit_rms = nominal_world_frame(model, nominal, calibrated)
    outputs, comp, prefixes = compensate_program(
        prog, model, nominal, taught, M, calibrated, kw, correction=residual_map_of(model)
    )
    skipped = [
        {"line": u.line, "text": u.text, "reason": u.reason} | ({"file": prog.paths[u.file]} if u.file else {})
        for u in prog.uninterpreted
    ]
    paths = [req.out] + [companion_path(req.out, p) for p in prog.paths[1:]]
    return list(zip(paths, outputs)), comp, prefixes, skipped, M, fit_rms, _tool_notes(prog, model, nominal)


def _tool_notes(prog, model: KinematicModel, nominal: KinematicModel) -> list[str]:
    """A note where the model's residual correction is a smooth map or trees (they correct the
    point they were measured at, the model's tool) and some target uses another tool: that
    target gets the correction of the measured point, the part a rotation error would add at its
    own tool not modelled (the joint transmission, a physical model, is evaluated at each tool)."""
    family = (model.metadata.get("residual_map") or {}).get("family")
    if residual_map_of(model) is None or family == "transmission":
        return []
    T_tool = pose_to_matrix(nominal.tool)
    other = [t for t in prog.targets if not np.allclose(t.T_tool, T_tool, atol=1e-9)]
    if not other:
        return []
    lines = ", ".join(str(t.line) for t in other[:5]) + (" ..." if len(other) > 5 else "")
    name = {"trees": "boosted trees"}.get(family, "smooth map")
    return [
        f"the residual correction ({name}) corrects the point it was measured at, the model's tool: "
        f"{len(other)} target(s) with another tool (line {lines}) get that point's correction"
    ]


def companion_path(out: str, path: str) -> str:
    """Where a program's second file (KRL's .dat) goes: beside ``out``, with ``out``'s stem."""
    return str(Path(out).with_suffix(Path(path).suffix))


def _no_targets(req: CompensationRequest, model: KinematicModel, script) -> None:
    """A program without a single target to compensate is bad input. The message names the lines
    left alone and why the first was; with ``--report`` the report is still written and lists
    each with its text and reason (and no points), so that the hint can be followed. ``--out`` is
    not written."""
    skipped = script.uninterpreted
    if not skipped:
        if hasattr(script, "brand"):
            raise NoTargetsError(req.task, "no move target found; expected a program with move targets to compensate")
        raise InputError(
            req.task,
            "no movej/movel/movep/movec call found; expected a URScript program with move targets to compensate",
        )
    first = skipped[0]
    lines = ", ".join(str(k.line) for k in skipped[:10])
    if len(skipped) > 10:
        lines += f" and {len(skipped) - 10} more"
    what = "move" if hasattr(script, "brand") else "movej/movel/movep/movec"
    message = (
        f"no {what} target could be interpreted: {len(skipped)} line(s) left alone (line "
        f"{lines}), the first because {first.reason}"
    )
    where = (
        "the report lists each with its text and reason"
        if req.report
        else "--report R.json lists each with its text and reason"
    )
    report = None
    if req.report:
        u = model.units
        report = {
            "format": "recal.compensation-report/1",
            "task": str(req.task),
            "model": model.name,
            "mode": "script",
            "units": {"length": u.length, "angle": u.angle},
            "error": message,
            "summary": {"points": 0, "converged": 0, "not_compensated": 0},
            "uninterpreted": [{"line": k.line, "text": k.text, "reason": k.reason} for k in skipped],
            "points": [],
        }
    raise NoTargetsError(req.task, f"{message}; {where}", line=first.line, report=report)


def notes_for(model: KinematicModel) -> list[str]:
    """What the user of the compensated file must know about the model it came from: a tool
    orientation the calibration data could not determine (position-only data) stays the nominal
    one, so orientations are compensated only as far as the identified joints go."""
    held = [
        u["name"]
        for u in (model.metadata.get("identification") or {}).get("unidentifiable", [])
        if u.get("category") == "tool_orientation"
    ]
    if not held:
        return []
    return [
        f"the calibration did not determine the tool orientation ({', '.join(held)}: position-only "
        f"data); the compensated orientations keep the nominal tool frame's, positions are compensated fully"
    ]
