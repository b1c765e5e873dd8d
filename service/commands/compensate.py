"""``recal compensate --model MODEL.json --task TASK.csv --out OUT.csv [--mode joints|targets] [--nominal NOMINAL.json]``

Compensated task files (contracts §5), from an identified model:

- task CSV, ``joints`` mode: ``q1..qN`` replaced by the commands that bring the identified robot
  to each row's pose (rows with only joints: to the pose those joints gave the robot they were
  taught or planned on);
- task CSV, ``targets`` mode: ``x..qz`` replaced by the targets a controller that knows only the
  nominal model must be sent (in the nominal model's world frame: for a library robot, its base
  frame);
- URScript program (``.script``/``.urscript``): pose targets rewritten for the nominal controller,
  joint targets rewritten as joint commands, every other byte kept; lines that cannot be
  interpreted are reported (stderr and ``--report``), not guessed.

The nominal model is ``--nominal`` or the one the identified model records
(``identification.controller``, a UR cell's controller model, written by the service; else
``identification.nominal``, written by ``recal identify``); in joints mode without one, rows
without joints start from the identified model's own inverse kinematics. Robots without a
closed-form inverse use the numerical one (``calibration.ik.numerical_ik``: from the row's joints
or ``--qnear``, the previous row's solution, seeds over the joint limits). See
docs/compensation.md.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

import numpy as np

CHUNK = 25_000


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="identified model (recal.model/1)")
    s.add_argument("--task", required=True, help="task CSV (contracts §5) or URScript program (.script, .urscript)")
    s.add_argument("--out", required=True, help="compensated task file to write")
    s.add_argument("--mode", choices=["joints", "targets"], default="joints",
                   help="CSV: replace q1..qN (joints, default) or x..qz for a nominal controller (targets)")
    s.add_argument("--nominal", help="the nominal model the controller uses (default: the one the identified model "
                   "records)")
    s.add_argument("--taught-on", metavar="MODEL", help="identified model of the robot the task's joint vectors were "
                   "taught on, same world frame (default: they were planned on the nominal model)")
    s.add_argument("--report", help="per-point report to write (JSON)")
    s.add_argument("--calibration-data", metavar="MEAS.csv", help="the identification measurements: their joint "
                   "ranges are the calibrated region (default: the ranges the identified model records)")
    s.add_argument("--qnear", help="comma-separated joints (model units) that choose the branch of rows without "
                   "q1..qN (default: all zero): the solution nearest it is taken, as UR's get_inverse_kin does; "
                   "for robots without a closed form it is also where the numerical inverse kinematics starts")
    s.add_argument("--tolerance", type=float, help="position residual to reach, model length unit (default 1e-9 m)")
    s.add_argument("--singular-tol", type=float, default=0.02, help="near_singular below this smallest "
                   "dimensionless singular value of the Jacobian (default 0.02)")
    s.add_argument("--max-correction", type=float, help="branch_change above this joint correction, model angle "
                   "unit (default 5 degrees)")


# ----------------------------------------------------------------------------- models


def _models(args):
    from calibration.model import ModelFormatError, model_from_dict
    from service.cli import Fail
    from service.files import load_model

    model = load_model(args.model)
    nominal = None
    if args.nominal:
        nominal = load_model(args.nominal)
    else:
        # a UR cell's calibration records its controller's own model (issue 16): that, not the
        # published table, is what the controller computes with
        ident = model.metadata.get("identification") or {}
        key = "controller" if ident.get("controller") is not None else "nominal"
        doc = ident.get(key)
        if doc is not None:
            try:
                nominal = model_from_dict(doc)
            except ModelFormatError as exc:
                raise Fail(f"{args.model}: field 'identification.{key}.{exc.field}': "
                           f"{str(exc).split(': ', 1)[-1]}") from None
    taught = load_model(args.taught_on) if args.taught_on else None
    for m, what in ((nominal, args.nominal or "identification.nominal"), (taught, args.taught_on)):
        if m is not None and m.n_joints != model.n_joints:
            raise Fail(f"{what}: has {m.n_joints} joints, the identified model {model.n_joints}")
    return model, nominal, taught


def _calibrated_range(args, model):
    """(n, 2) joint ranges of the calibration data, SI, or None."""
    from service.cli import Fail
    from service.files import read_joints

    if args.calibration_data:
        q = read_joints(args.calibration_data, model)
        return np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
    ranges = (model.metadata.get("identification") or {}).get("joint_ranges")
    if ranges is None:
        return None
    scale = np.array([model.units.angle_rad if j.revolute else model.units.length_m for j in model.joints])
    try:
        r = np.asarray(ranges, dtype=float).reshape(model.n_joints, 2)
    except (TypeError, ValueError):
        raise Fail(f"{args.model}: field 'identification.joint_ranges': expected {model.n_joints} pairs "
                   f"[lower, upper]") from None
    return r * scale[:, None]


def _frame(model, nominal, calibrated):
    """``T_nominal_world`` and the RMS of the fit (m): where the nominal model's world (the
    controller's base frame) sits, fitted over configurations of the calibrated region (or of the
    joint limits, within ±180°)."""
    from calibration.compensation import frame_map
    from calibration.kinematics import fk
    from calibration.simulate import random_configurations

    rng = np.random.default_rng(0)
    q = random_configurations(model, 256, rng, limits=calibrated)
    M = frame_map(model, nominal, q)
    p_id = fk(model, q)[:, :3, 3]
    p_nom = fk(nominal, q)[:, :3, 3]
    rms = float(np.sqrt(np.mean(np.sum((p_id @ M[:3, :3].T + M[:3, 3] - p_nom) ** 2, axis=1))))
    return M, rms


def _settings(args, model):
    from service.cli import Fail

    u = model.units
    kw = {"singular_tol": args.singular_tol}
    if args.tolerance is not None:
        if not args.tolerance > 0:
            raise Fail(f"--tolerance: expected a positive number, got {args.tolerance}")
        kw["position_tol_m"] = args.tolerance * u.length_m
        kw["rotation_tol_rad"] = args.tolerance * u.length_m  # per metre of reach
    if args.max_correction is not None:
        if not args.max_correction > 0:
            raise Fail(f"--max-correction: expected a positive number, got {args.max_correction}")
        kw["max_correction_rad"] = args.max_correction * u.angle_rad
    qnear = np.zeros(model.n_joints)
    if args.qnear:
        try:
            vals = [float(v) for v in args.qnear.split(",")]
        except ValueError:
            raise Fail(f"--qnear: expected {model.n_joints} comma-separated numbers, got {args.qnear!r}") from None
        if len(vals) != model.n_joints:
            raise Fail(f"--qnear: expected {model.n_joints} numbers, got {len(vals)}")
        qnear = np.array([v * (u.angle_rad if j.revolute else u.length_m) for v, j in zip(vals, model.joints)])
    return kw, qnear


# ----------------------------------------------------------------------------- running


def _concat(parts):
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    out = {}
    for f in dataclasses.fields(first):
        v = getattr(first, f.name)
        out[f.name] = np.concatenate([getattr(p, f.name) for p in parts]) if isinstance(v, np.ndarray) else v
    from calibration.compensation import _message

    out["message"] = _message(out["converged"], out["flags"])
    return dataclasses.replace(first, **out)


def _take(comp, idx):
    """The points ``idx`` of a compensation result, in that order."""
    return dataclasses.replace(comp, **{f.name: getattr(comp, f.name)[idx] for f in dataclasses.fields(comp)
                                        if isinstance(getattr(comp, f.name), np.ndarray)})


def _chunked(N, fn, t0):
    """Run ``fn(slice)`` over chunks of the task, with a progress line once it takes > 2 s."""
    from service.cli import progress

    parts = []
    for start in range(0, N, CHUNK):
        parts.append(fn(slice(start, min(start + CHUNK, N))))
        if time.perf_counter() - t0 > 2.0 and start + CHUNK < N:
            progress(f"recal compensate: {start + CHUNK} of {N} points")
    return _concat(parts)


def _source_poses(q, taught, nominal, M):
    """World poses (N, 4, 4) the joint vectors ``q`` gave the robot they were taught or planned on."""
    from calibration.kinematics import fk

    if taught is not None:
        return fk(taught, q)
    return np.linalg.inv(M) @ fk(nominal, q)


def _csv(args, model, nominal, taught, calibrated, kw, qnear, t0):
    from calibration.compensation import compensate_joints, compensate_targets, flag_names, nominal_solution
    from service.cli import Fail, progress
    from service.taskfiles import format_task, read_task

    task = read_task(args.task, model)
    N = len(task)
    M, fit_rms = _frame(model, nominal, calibrated) if nominal is not None else (np.eye(4), None)
    only_q = task.has_q & ~task.has_pose
    if np.any(only_q) and taught is None and nominal is None:
        r = int(np.nonzero(only_q)[0][0])
        raise Fail(f"{args.task}: row {r + 1} (line {task.table.lines[r]}) has only joints: give --nominal (they were "
                   f"planned on it) or --taught-on MODEL (the robot they were taught on)")
    X = task.T_world_tool.copy()
    if np.any(only_q):
        X[only_q] = _source_poses(task.q[only_q], taught, nominal, M)
    q_near = np.where(task.has_q[:, None], np.nan_to_num(task.q), qnear)
    if args.mode == "targets":
        if nominal is None:
            raise Fail(f"{args.model}: targets mode needs the nominal model the controller uses: give --nominal "
                       f"NOMINAL.json (this model does not record the one it was identified from)")

        def run(sl):
            return compensate_targets(model, nominal, X[sl], q_near[sl], T_nominal_world=M,
                                      keep_branch=task.has_q[sl], calibrated_range=calibrated, **kw)
    else:
        # the correction starts from the nominal controller's solution; without a nominal model,
        # from the identified model's own inverse kinematics (numerical: calibration.ik.numerical_ik)
        start = nominal if nominal is not None else model

        def run(sl):
            q0 = q_near[sl].copy()
            reachable = np.ones(len(q0), dtype=bool)
            changed = np.zeros(len(q0), dtype=bool)
            rows = task.has_pose[sl]
            if np.any(rows):
                sol = nominal_solution(start, M @ X[sl][rows], q_near[sl][rows], keep_branch=task.has_q[sl][rows])
                q0[rows], reachable[rows] = sol.q, sol.reachable
                if sol.branch_changed is not None:
                    changed[rows] = sol.branch_changed
            return compensate_joints(model, X[sl], q0, reachable=reachable, branch_changed=changed,
                                     calibrated_range=calibrated, **kw)

    comp = _chunked(N, run, t0)
    if time.perf_counter() - t0 > 2.0:
        progress(f"recal compensate: {N} points compensated; writing {args.out}")
    names = {int(b): ";".join(flag_names(b)) for b in np.unique(comp.flags)}
    flags = [names[int(b)] for b in comp.flags]
    text = format_task(task, model, args.mode, comp.q, comp.T_command, comp.converged, comp.residual_m, flags)
    prefixes = [f'"row":{i + 1},"line":{line},' for i, line in enumerate(task.table.lines)]
    return text, comp, prefixes, [], M, fit_rms


def _g(x: float) -> str:
    """A float as JSON text, 9 significant digits (``null`` if not finite)."""
    return f"{x:.9g}" if np.isfinite(x) else "null"


def _point_lines(comp, model, prefixes: list[str]) -> list[str]:
    """One compact JSON object per point (``prefixes[i]``: its leading fields, JSON text ending
    in a comma), in the model's units. Written directly: a 100,000-point report in about a
    second, where ``json.dumps`` of dicts takes several."""
    import json as _json

    from calibration.compensation import flag_names

    u = model.units
    scales = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    res, ang = comp.residual_m / u.length_m, comp.residual_rad / u.angle_rad
    corr = comp.correction / scales
    names = {int(b): _json.dumps(flag_names(b)) for b in np.unique(comp.flags)}
    return ["{" + prefixes[i]
            + f'"converged":{"true" if comp.converged[i] else "false"},"iterations":{int(comp.iterations[i])},'
            + f'"residual":{_g(res[i])},"residual_angle":{_g(ang[i])},'
            + '"correction":[' + ",".join(_g(c) for c in corr[i]) + "],"
            + f'"sigma_min":{_g(comp.sigma_min[i])},"flags":{names[int(comp.flags[i])]}' + "}"
            for i in range(len(comp))]


def _f(x, digits=9):
    x = float(x)
    return None if not np.isfinite(x) else float(f"{x:.{digits}g}")


def _script(args, model, nominal, taught, calibrated, kw, qnear, t0):
    from calibration.compensation import compensate_joints, compensate_targets, nominal_solution
    from calibration.kinematics import fk
    from calibration.transforms import pose_to_matrix
    from service.cli import Fail
    from service.taskfiles import matrix_to_pose_ur, parse_urscript, pose_to_matrix_ur

    script = parse_urscript(args.task, model.n_joints)
    if not script.targets:
        _no_targets(args, model, script)
    if nominal is None:
        raise Fail(f"{args.model}: a URScript program needs the nominal model its controller uses: give --nominal "
                   f"NOMINAL.json (this model does not record the one it was identified from)")
    M, fit_rms = _frame(model, nominal, calibrated)
    B = pose_to_matrix(nominal.base)
    n = model.n_joints
    # program order: pose targets without qnear take the branch nearest the previous target (what
    # the controller's get_inverse_kin does from the robot's current joints)
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
    replacements, literals, prefixes, order = {}, {}, [], []
    comps = []
    if pose_t:
        P = np.array([t.pose.values for t in pose_t])
        X_nom = B @ pose_to_matrix_ur(P)
        seeds = np.array(pose_seed)
        X_d = np.linalg.inv(M) @ X_nom if taught is None else fk(taught, seeds)
        cp = compensate_targets(model, nominal, X_d, seeds, T_nominal_world=M, keep_branch=True,
                                calibrated_range=calibrated, **kw)
        P_new = matrix_to_pose_ur(np.linalg.inv(B) @ cp.T_command, like=P)
        for i, t in enumerate(pose_t):
            replacements[id(t.pose)], literals[id(t.pose)] = P_new[i], t.pose
            if t.joints is not None:
                replacements[id(t.joints)], literals[id(t.joints)] = cp.q[i], t.joints
            head = {"line": t.line, "move": t.move, "kind": "pose", "variable": t.pose.name,
                    "qnear_variable": t.joints.name if t.joints is not None else None,
                    "original": [float(v) for v in P[i]], "compensated": [_f(v, 12) for v in P_new[i]]}
            order.append(t.line)
            prefixes.append(json.dumps(head)[1:-1] + ",")
        comps.append(cp)
    if joint_t:
        Q = np.array([t.joints.values for t in joint_t]).reshape(-1, n)
        cj = compensate_joints(model, _source_poses(Q, taught, nominal, M), Q, calibrated_range=calibrated, **kw)
        for i, t in enumerate(joint_t):
            replacements[id(t.joints)], literals[id(t.joints)] = cj.q[i], t.joints
            head = {"line": t.line, "move": t.move, "kind": "joints", "variable": t.joints.name,
                    "original": [float(v) for v in Q[i]], "compensated": [_f(v, 12) for v in cj.q[i]]}
            order.append(t.line)
            prefixes.append(json.dumps(head)[1:-1] + ",")
        comps.append(cj)
    comp = _concat(comps) if len(comps) > 1 else comps[0]
    # report the targets in program order
    perm = np.argsort(order, kind="stable")
    comp = _take(comp, perm)
    prefixes = [prefixes[k] for k in perm]
    skipped = [{"line": u.line, "text": u.text, "reason": u.reason} for u in script.uninterpreted]
    return script.rewrite(replacements, literals), comp, prefixes, skipped, M, fit_rms


def _no_targets(args, model, script) -> None:
    """A program without a single target to compensate is bad input. The message names the lines
    left alone and why the first was; with ``--report`` the report is still written and lists
    each with its text and reason (and no points), so that the hint can be followed. ``--out`` is
    not written."""
    from service.files import InputError, write_atomic

    skipped = script.uninterpreted
    if not skipped:
        raise InputError(args.task, "no movej/movel/movep/movec call found; expected a URScript program with move "
                                    "targets to compensate")
    first = skipped[0]
    lines = ", ".join(str(k.line) for k in skipped[:10])
    if len(skipped) > 10:
        lines += f" and {len(skipped) - 10} more"
    message = (f"no movej/movel/movep/movec target could be interpreted: {len(skipped)} line(s) left alone (line "
               f"{lines}), the first because {first.reason}")
    where = ("the report lists each with its text and reason" if args.report
             else "--report R.json lists each with its text and reason")
    if args.report:
        u = model.units
        report = {"format": "recal.compensation-report/1", "task": str(args.task), "model": model.name,
                  "mode": "script", "units": {"length": u.length, "angle": u.angle}, "error": message,
                  "summary": {"points": 0, "converged": 0},
                  "uninterpreted": [{"line": k.line, "text": k.text, "reason": k.reason} for k in skipped],
                  "points": []}
        write_atomic(args.report, json.dumps(report, indent=1) + "\n")
    raise InputError(args.task, f"{message}; {where}", line=first.line)


def _notes(model) -> list[str]:
    """What the user of the compensated file must know about the model it came from: a tool
    orientation the calibration data could not determine (position-only data) stays the nominal
    one, so orientations are compensated only as far as the identified joints go."""
    held = [u["name"] for u in (model.metadata.get("identification") or {}).get("unidentifiable", [])
            if u.get("category") == "tool_orientation"]
    if not held:
        return []
    return [f"the calibration did not determine the tool orientation ({', '.join(held)}: position-only "
            f"data); the compensated orientations keep the nominal tool frame's, positions are compensated fully"]


def run(args) -> int:
    from calibration.transforms import matrix_to_pose
    from service.files import check_output, write_atomic
    from service.taskfiles import is_script

    t0 = time.perf_counter()
    for path in (args.out, args.report):  # before any work: a run never ends unable to write
        if path:
            check_output(path)
    model, nominal, taught = _models(args)
    calibrated = _calibrated_range(args, model)
    kw, qnear = _settings(args, model)
    script = is_script(args.task)
    handler = _script if script else _csv
    output, comp, prefixes, skipped, M, fit_rms = handler(args, model, nominal, taught, calibrated, kw, qnear, t0)
    u = model.units
    L = u.length_m
    counts = {name: comp.count(name) for name in
              ("joint_limit", "near_singular", "outside_calibrated_region", "no_convergence", "branch_change",
               "unreachable")}
    summary = {
        "points": len(comp), "converged": int(np.count_nonzero(comp.converged)),
        "residual_max": _f(comp.residual_m.max(initial=0.0) / L),
        "residual_angle_max": _f(comp.residual_rad.max(initial=0.0) / u.angle_rad),
        "correction_max": _f(np.abs(comp.correction).max(initial=0.0) / u.angle_rad),
        "flags": counts,
        "notes": _notes(model),
    }
    if args.report:
        pose = matrix_to_pose(M)
        report = {
            "format": "recal.compensation-report/1",
            "task": str(args.task), "model": model.name, "nominal": nominal.name if nominal is not None else None,
            "mode": "script" if script else args.mode,
            "units": {"length": u.length, "angle": u.angle},
            "frame": {"T_nominal_world": [_f(v / L) for v in pose[:3]] + [_f(v / u.angle_rad) for v in pose[3:]],
                      "fit_rms": _f(fit_rms / L) if fit_rms is not None else None},
            "calibrated_region": None if calibrated is None else [
                [_f(v / (u.angle_rad if j.revolute else L)) for v in r] for r, j in zip(calibrated, model.joints)],
            "summary": summary, "uninterpreted": skipped,
            "elapsed_s": round(time.perf_counter() - t0, 3),
        }
        head = json.dumps(report, indent=1)
        lines = _point_lines(comp, model, prefixes)
        write_atomic(args.report, head[:-2] + ',\n "points": [\n  ' + ",\n  ".join(lines) + "\n ]\n}\n")
    write_atomic(args.out, output)
    for s in skipped:
        print(f"warning: {args.task}, line {s['line']}: not compensated ({s['reason']}): {s['text']}", file=sys.stderr)
    for note in summary["notes"]:
        print(f"note: {note}", file=sys.stderr)
    flagged = ", ".join(f"{k} {v}" for k, v in counts.items() if v)
    print(f"compensated {len(comp)} points ({'URScript' if script else args.mode + ' mode'}): "
          f"{summary['converged']} converged, residual max {summary['residual_max']:.3g} {u.length}"
          + (f"; flagged: {flagged}" if flagged else "") + f"; wrote {args.out}")
    return 0
