"""``recal accuracy --model MODEL.json --data MEAS.csv [--target NAME] [--out R.json]``

Accuracy figures of measurements in the manner of ISO 9283 (calibration.metrics, formulas in
docs/accuracy.md). Each row's command is where the model puts its target at the row's joint
readings; rows that repeat one commanded configuration (the same ``pose_id``, or ``pose``, label;
without one, the same joint readings within ``--joint-tol``) form a pose. Per pose: the pose
accuracy AP (and its components) and, when it was measured at least twice, the pose
repeatability RP = l̄ + 3·S_l; overall: AP and RP mean and max over the poses, and the statistics
of every measurement's position error. Full-pose rows add the orientation figures.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np

DEFAULT_JOINT_TOL = 0.05  # degrees (or mm for prismatic joints)


def add_parser(s) -> None:
    s.add_argument(
        "--model",
        required=True,
        help="model file (recal.model/1) or a library robot name; its world "
        "frame must be the instrument's (an identified model's is)",
    )
    s.add_argument(
        "--data",
        required=True,
        help="measurement CSV (docs/contracts.md §3); repeated configurations give the repeatability",
    )
    s.add_argument("--target", help="the target measured by rows that name none (default the tool origin)")
    s.add_argument("--out", help="JSON report to write (every figure, per pose and overall)")
    s.add_argument(
        "--joint-tol",
        type=float,
        help="rows without a pose_id are the same pose when every joint "
        "reading agrees within this, model angle unit (length unit for prismatic joints); default "
        "0.05 degrees (0.05 mm)",
    )


def _labels(args, model, data, table):
    """Pose label (N,) of each row and how the rows were grouped."""
    from calibration.metrics import group_configurations
    from service.files import InputError

    column = next((c for c in ("pose_id", "pose") if table.has(c)), None)
    if column is not None:
        labels = table.strings(column)
        for r, v in enumerate(labels):
            if v is None:
                raise InputError(
                    args.data,
                    f"expected a pose label (the file has a {column!r} column, so every row needs one)",
                    row=r + 1,
                    line=table.lines[r],
                    column=column,
                )
        return np.array(labels, dtype=object), f"by the {column!r} column"
    u = model.units
    if args.joint_tol is not None:
        tol = args.joint_tol
        tol_si = np.array([tol * (u.angle_rad if j.revolute else u.length_m) for j in model.joints])
        said = f"{tol:g} {u.angle}" + ("" if all(j.revolute for j in model.joints) else f" ({tol:g} {u.length})")
    else:
        tol_si = np.array(
            [math.radians(DEFAULT_JOINT_TOL) if j.revolute else DEFAULT_JOINT_TOL * 1e-3 for j in model.joints]
        )
        said = f"{DEFAULT_JOINT_TOL:g} deg" + (
            "" if all(j.revolute for j in model.joints) else f" ({DEFAULT_JOINT_TOL:g} mm)"
        )
    ids = group_configurations(data.q, tol_si)
    return np.array([str(k + 1) for k in ids], dtype=object), f"by joint readings within {said}"


def _commands(model, data, target):
    """Where the model puts each row's target (N, 3), and the tool orientations (N, 3, 3) when every
    row carries a measured one (else None)."""
    from calibration.kinematics import fk
    from calibration.transforms import quat_to_matrix

    names = np.array([t if t is not None else target for t in data.target], dtype=object)
    T = fk(model, data.q, data.payload)  # a compliant model sags under each row's payload
    p_tool = np.stack([model.target(t) for t in names])
    p_cmd = np.einsum("nij,nj->ni", T[:, :3, :3], p_tool) + T[:, :3, 3]
    rmap = _residual_map(model)
    inside = None
    if rmap is not None:  # where the model's residual correction applies, it corrects the commanded
        corr, inside = rmap.evaluate(data.q, p_tool)  # position (a transmission's: at each row's point)
        p_cmd = p_cmd + corr
    full = data.quat is not None and bool(np.all(data.has_orientation))
    R = (T[:, :3, :3], quat_to_matrix(data.quat)) if full else (None, None)
    return names, p_cmd, R, inside


def _residual_map(model):
    from calibration.residual_map import ResidualMapError, from_model
    from service.cli import Fail

    try:
        return from_model(model)
    except ResidualMapError as exc:
        raise Fail(f"model field {exc.field!r}: {str(exc).split(': ', 1)[-1]}") from None


def _f(x, digits=6):
    x = float(x)
    return None if not math.isfinite(x) else float(f"{x:.{digits}g}")


def run(args) -> int:
    from calibration.metrics import error_statistics, pose_statistics
    from service.cli import Fail, progress
    from service.files import InputError, check_output, load_model, read_measurements, read_table, write_atomic

    if args.out:
        check_output(args.out)
    if args.joint_tol is not None and not (args.joint_tol > 0 and math.isfinite(args.joint_tol)):
        raise Fail(f"--joint-tol: expected a positive number, got {args.joint_tol}")
    model = load_model(args.model)
    if args.target is not None and args.target not in model.targets:
        known = f"one of {', '.join(sorted(model.targets))}" if model.targets else "a target, but the model has none"
        raise InputError(
            args.model, f"field 'targets': no target {args.target!r} (asked for by --target); expected {known}"
        )
    progress(f"reading {args.data} ...")
    data = read_measurements(args.data, model)
    progress(f"accuracy of {len(data)} rows ...")
    labels, grouping = _labels(args, model, data, read_table(args.data))
    names, p_cmd, (R_cmd, R_meas), inside = _commands(model, data, args.target)
    # a pose is a commanded configuration and the target measured there
    keys: dict[tuple, int] = {}
    pose = np.array([keys.setdefault((lab, t), len(keys)) for lab, t in zip(labels, names)])
    st = pose_statistics(p_cmd, data.p_world, pose, R_cmd=R_cmd, R_meas=R_meas)
    err = error_statistics(p_cmd, data.p_world, R_cmd=R_cmd, R_meas=R_meas)
    report = _report(args, model, data, grouping, list(keys), pose, st, err)
    report["frame"] = _frame_check(p_cmd, data.p_world, model)
    if inside is not None:
        # rows outside the correction's region are judged by the geometric model alone: counted, said
        report["outside_mapped_region"] = int(np.count_nonzero(~np.asarray(inside, dtype=bool)))
    if args.out:
        write_atomic(args.out, json.dumps(report, indent=1) + "\n")
    _print(report, args.out)
    if report.get("outside_mapped_region"):
        sys.stdout.flush()
        print(
            f"note: {report['outside_mapped_region']} of {len(data)} rows lie outside the region the model's residual "
            "correction was fitted in: there the geometric model alone was judged",
            file=sys.stderr,
        )
    if report["frame"] is not None:  # after the figures it explains, the last line a user reads
        sys.stdout.flush()
        print(f"warning: {report['frame']['warning']}", file=sys.stderr)
    return 0


# The errors are "mostly where the robot stands" when a rigid transform between the model's world
# and the instrument's takes away this share of them, and they are larger than any robot's error
# (an unregistered base puts them at the robot's distance from the tracker: metres).
FRAME_RATIO = 5.0
FRAME_RMS_M = 0.01


def _frame_check(p_cmd, p_meas, model) -> dict | None:
    """A one-line warning (and its figures) when the model's world is not the instrument's: a
    nominal or library model's world is the robot's own base frame, and its "errors" against a
    tracker's measurements are then the tracker-to-robot transform (about 1.8 m), not the robot's.
    None when the frames agree (or too few distinct points to tell)."""
    from calibration.registration import kabsch

    points = np.unique(np.round(p_cmd, 6), axis=0)
    if len(points) < 3 or np.linalg.matrix_rank(points - points.mean(axis=0), tol=1e-6) < 2:
        return None
    raw_rms = float(np.sqrt(np.mean(np.sum((p_meas - p_cmd) ** 2, axis=1))))
    T = kabsch(p_cmd, p_meas)
    moved = p_cmd @ T[:3, :3].T + T[:3, 3]
    fit_rms = float(np.sqrt(np.mean(np.sum((p_meas - moved) ** 2, axis=1))))
    if raw_rms < FRAME_RMS_M or raw_rms < FRAME_RATIO * fit_rms:
        return None
    L, lu = model.units.length_m, model.units.length
    own = "" if np.any(np.asarray(model.base) != 0) else " (its base is the robot's own frame)"
    return {
        "rms": _f(raw_rms / L),
        "rms_after_rigid_fit": _f(fit_rms / L),
        "warning": (
            f"{model.name}'s base is not registered to the instrument{own}: the errors (RMS {raw_rms / L:.4g} {lu}) "
            f"are mostly where the robot stands (a rigid transform leaves RMS {fit_rms / L:.4g} {lu}); "
            f"check an identified model (recal identify), whose world is the instrument's"
        ),
    }


def _report(args, model, data, grouping, keys, pose, st, err) -> dict:
    u = model.units
    L, A = u.length_m, u.angle_rad
    repeated = st.n >= 2
    per_pose = []
    for k, (label, target) in enumerate(keys):
        entry = {
            "pose": label,
            "target": target,
            "n": int(st.n[k]),
            "rows": [int(r) for r in data.row[pose == k]],
            "command": [_f(v / L, 9) for v in st.command_m[k]],
            "barycentre": [_f(v / L, 9) for v in st.barycentre_m[k]],
            "AP": _f(st.AP_m[k] / L),
            "AP_xyz": [_f(v / L) for v in st.AP_xyz_m[k]],
            "l_mean": _f(st.l_mean_m[k] / L) if repeated[k] else None,
            "S_l": _f(st.S_l_m[k] / L),
            "three_S_l": _f(3.0 * st.S_l_m[k] / L),
            "RP": _f(st.RP_m[k] / L),
        }
        if st.AP_abc_rad is not None:
            entry["AP_abc"] = [_f(v / A) for v in st.AP_abc_rad[k]]
            entry["RP_abc"] = [_f(v / A) for v in st.RP_abc_rad[k]]
        per_pose.append(entry)
    rp = st.RP_m[repeated]
    overall = {
        "poses": len(keys),
        "repeated_poses": int(repeated.sum()),
        "AP": {"mean": _f(st.AP_m.mean() / L), "max": _f(st.AP_m.max() / L)},
        "RP": {"mean": _f(rp.mean() / L), "max": _f(rp.max() / L)} if rp.size else None,
    }
    if st.AP_abc_rad is not None:
        overall["AP_abc_max"] = [_f(v / A) for v in np.abs(st.AP_abc_rad).max(axis=0)]
        overall["RP_abc_max"] = [_f(v / A) for v in st.RP_abc_rad[repeated].max(axis=0)] if rp.size else None
    errors = {
        "n": err.n,
        "mean": _f(err.mean_m / L),
        "std": _f(err.std_m / L),
        "three_sigma": _f(err.three_sigma_m / L),
        "mean_plus_3sigma": _f(err.mean_plus_3sigma_m / L),
        "rms": _f(err.rms_m / L),
        "p95": _f(err.p95_m / L),
        "max": _f(err.max_m / L),
        "bias_xyz": [_f(v / L) for v in err.bias_xyz_m],
    }
    if err.errors_rad is not None:
        errors["angle"] = {
            "mean": _f(err.mean_rad / A),
            "three_sigma": _f(err.three_sigma_rad / A),
            "mean_plus_3sigma": _f(err.mean_plus_3sigma_rad / A),
            "max": _f(err.max_rad / A),
        }
    single = len(keys) - int(repeated.sum())
    note = None
    if not rp.size:
        note = (
            "every pose was measured once: these are accuracy figures only; the repeatability RP needs each "
            "configuration measured at least twice (ISO 9283: 30 times)"
        )
    elif single:
        note = f"{single} of {len(keys)} poses were measured once: they have an AP but no RP"
    return {
        "format": "recal.accuracy-report/1",
        "model": model.name,
        "data": str(args.data),
        "units": {"length": u.length, "angle": u.angle},
        "grouping": grouping,
        "measurements": int(len(data)),
        "per_pose": per_pose,
        "overall": overall,
        "errors": errors,
        "note": note,
    }


def _num(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def _print(rep: dict, out: str | None) -> None:
    """The summary on stdout; the per-pose figures are in the ``--out`` report."""
    lu, au = rep["units"]["length"], rep["units"]["angle"]
    o, e = rep["overall"], rep["errors"]
    print(
        f"ISO 9283 pose accuracy (AP) and repeatability (RP) of {rep['model']} on {rep['data']}: "
        f"{rep['measurements']} measurements of {o['poses']} poses (grouped {rep['grouping']}); {lu}, {au}"
    )
    line = f"overall: AP mean {_num(o['AP']['mean'])}, max {_num(o['AP']['max'])} {lu}"
    if o["RP"] is not None:
        line += (
            f"; RP mean {_num(o['RP']['mean'])}, max {_num(o['RP']['max'])} {lu} "
            f"({o['repeated_poses']} poses measured more than once)"
        )
    if "AP_abc_max" in o:
        line += f"; orientation AP_a, AP_b, AP_c max {', '.join(map(_num, o['AP_abc_max']))} {au}"
    print(line)
    line = (
        f"position error of the {e['n']} measurements: mean {_num(e['mean'])}, 3σ {_num(e['three_sigma'])}, "
        f"mean + 3σ {_num(e['mean_plus_3sigma'])}, RMS {_num(e['rms'])}, p95 {_num(e['p95'])}, "
        f"max {_num(e['max'])} {lu}"
    )
    if "angle" in e:
        line += f"; orientation error mean {_num(e['angle']['mean'])}, max {_num(e['angle']['max'])} {au}"
    print(line)
    if rep["note"]:
        print(f"note: {rep['note']}")
    if out:
        print(f"per-pose figures (AP, RP and their components, each pose's rows): {out}")
    else:
        print("per-pose figures (AP, RP and their components, each pose's rows): give --out R.json")
