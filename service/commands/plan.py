"""``recal plan --model NOMINAL.json --count K --out POSES.csv [--candidates CAND.csv] [--target NAME]``

Chooses the K configurations to measure for the best identification (calibration.planning), from
the candidates' ``q1..qN`` rows, or from configurations drawn within the joint limits (and the
instrument's volume and line of sight, when given). Writes ``q1..qN`` (model units) in a short
measurement order, prints the predicted accuracy, and with ``--accuracy`` finds how many poses a
wanted accuracy needs instead of taking ``--count``.
"""

from __future__ import annotations

import json
import math
import time


def add_parser(s) -> None:
    _add_choice_options(s)
    _add_volume_and_sight_options(s)
    _add_accuracy_options(s)


def _add_choice_options(s) -> None:
    """What to plan: the model, how many poses, among which candidates, by which criterion."""
    s.add_argument("--model", required=True, help="nominal model file (recal.model/1) or a library robot name")
    s.add_argument("--count", type=int, help="number of poses to choose (with --accuracy: the most allowed)")
    s.add_argument("--out", required=True, help="CSV of the chosen configurations to write (q1..qN)")
    s.add_argument("--candidates", help="CSV with q1..qN: choose among these rows (default: draw candidates)")
    s.add_argument(
        "--target",
        action="append",
        metavar="NAME",
        help="the model's target that is measured (repeatable; default the tool origin)",
    )
    s.add_argument(
        "--criterion",
        default="D",
        choices=["D", "I", "O1", "O3", "O4", "condition"],
        help="D (log det, default), I (least mean predicted position error over the evaluation "
        "configurations: 4-5 %% better on average, 3-7 times slower), O1 (Borm-Menq), "
        "O3 (min singular value), O4 (noise amplification) or condition (condition number)",
    )
    s.add_argument(
        "--sigma", type=float, help="instrument standard uncertainty per axis, model length unit (default 0.02 mm)"
    )
    s.add_argument("--seed", type=int, default=0, help="seed for drawn candidates and evaluation configurations")
    s.add_argument(
        "--candidates-count", type=int, default=2000, help="candidates to draw without --candidates (default 2000)"
    )


def _add_volume_and_sight_options(s) -> None:
    """Where the instrument can measure: its volume, and the line of sight from it to the target."""
    s.add_argument(
        "--volume-box",
        type=float,
        nargs=6,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="the instrument's measuring volume, a box in the world frame (model length unit)",
    )
    s.add_argument(
        "--volume-sphere",
        type=float,
        nargs="+",
        metavar="V",
        help="the measuring volume as a sphere: X Y Z RADIUS [MIN_RADIUS] (world frame, model length unit)",
    )
    s.add_argument(
        "--instrument",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="instrument position in the world frame, for the line-of-sight tests (default 0 0 0)",
    )
    s.add_argument(
        "--normal",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        default=[0.0, 0.0, 1.0],
        help="direction the target faces, tool frame (default 0 0 1)",
    )
    s.add_argument(
        "--cone",
        type=float,
        help="acceptance half-angle of the target (model angle unit): the target must face the instrument within it",
    )
    s.add_argument(
        "--clearance",
        type=float,
        help="the beam must pass at least this far from the robot's links (model length unit)",
    )
    s.add_argument(
        "--near-target",
        type=float,
        help="beam length before the target not tested for clearance (model length unit; default 100 mm)",
    )


def _add_accuracy_options(s) -> None:
    """Where the accuracy is predicted, what accuracy is wanted, and what else the plan is for."""
    s.add_argument(
        "--evaluation",
        help="CSV with q1..qN where the predicted accuracy is evaluated (default: random configurations)",
    )
    s.add_argument("--evaluation-count", type=int, default=300, help="random evaluation configurations (default 300)")
    s.add_argument(
        "--accuracy",
        type=float,
        help="wanted accuracy (model length unit): choose the fewest poses predicted to reach it",
    )
    s.add_argument(
        "--statistic",
        default="rms",
        choices=["rms", "p95"],
        help="which predicted figure --accuracy applies to (default rms)",
    )
    s.add_argument("--gains", action="store_true", help="plan for identifying joint gains too")
    s.add_argument("--fix", action="append", metavar="NAME", help="a parameter kept fixed (repeatable; prefix*)")
    s.add_argument("--report", help="JSON report to write")
    s.add_argument(
        "--compliance",
        choices=["gravity"],
        help="plan for joint compliance under gravity too (configurations that excite the gravity torques "
        "of the joints that carry the arm; a model with a compliance section plans for it anyway)",
    )


def _positive(name: str, v, allow_zero: bool = False) -> None:
    from service.cli import Fail

    if v is None:
        return
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise Fail(f"{name}: expected a {'non-negative' if allow_zero else 'positive'} number, got {v}")


def run(args) -> int:
    import numpy as np

    from calibration import planning

    t0 = time.perf_counter()
    model, targets = _model_and_targets(args)
    _check_numbers(args)
    volume, sight = _volume_and_sight(args, model)
    rng = np.random.default_rng(args.seed)
    cand, rows = _candidates(args, model, targets, volume, sight, rng)
    options = _plan_options(args, model, targets, volume, rng)
    result, curve = _choose(args, model, cand, options)

    # what the plan leaves undetermined, and how many more poses, or which kind, would determine it (issue 27)
    short = planning.shortfall(model, cand, len(result.indices), options) if _undetermined(result) else None
    report = _report(result, curve, model, len(cand), args, time.perf_counter() - t0)
    report["shortfall"] = None if short is None else short.as_dict()
    if args.report:
        from service.files import write_atomic

        write_atomic(args.report, json.dumps(report, indent=2) + "\n")
    _refuse_unreached(args, model, result, curve)
    n_poses = _write_poses(args, model, result, rows, options.sigma_m)
    _print_summary(args, model, result, curve, len(cand), n_poses, short)
    return 0


def _model_and_targets(args):
    """The nominal model (with a default compliance section when --compliance asks for one) and
    the targets measured, each known to the model (None: the tool origin)."""
    from service.cli import Fail
    from service.files import load_model

    model = load_model(args.model)
    if args.compliance and model.compliance is None:
        from calibration.compliance import default_section, with_section

        model = with_section(model, default_section(model))
    targets = tuple(args.target) if args.target else (None,)
    for t in targets:
        if t is not None and t not in model.targets:
            known = ", ".join(sorted(model.targets)) or "none"
            raise Fail(f"{args.model}: unknown target {t!r} (the model has: {known})")
    return model, targets


def _check_numbers(args) -> None:
    """Refuse counts, uncertainties and angles that cannot be meant, before any work."""
    from service.cli import Fail

    if args.count is None and args.accuracy is None:
        raise Fail("give --count K (or --accuracy A to find how many poses are needed)")
    if args.count is not None and args.count < 1:
        raise Fail(f"--count: expected a positive number of poses, got {args.count}")
    for name, v in (("--sigma", args.sigma), ("--accuracy", args.accuracy), ("--cone", args.cone)):
        _positive(name, v)
    _positive("--clearance", args.clearance, allow_zero=True)
    _positive("--near-target", args.near_target, allow_zero=True)
    if args.candidates_count < 1 or args.evaluation_count < 1:
        raise Fail("--candidates-count and --evaluation-count must be positive")
    if args.volume_box is not None and args.volume_sphere is not None:
        raise Fail("give --volume-box or --volume-sphere, not both")


def _volume_and_sight(args, model):
    """The instrument's measuring volume and line of sight (SI units, world frame), or None each
    when not given."""
    import numpy as np

    from calibration import planning
    from service.cli import Fail

    L, A = model.units.length_m, model.units.angle_rad
    volume = None
    try:
        if args.volume_box is not None:
            b = np.array(args.volume_box) * L
            volume = planning.Volume.box(b[:3], b[3:])
        elif args.volume_sphere is not None:
            if len(args.volume_sphere) not in (4, 5):
                raise Fail("--volume-sphere: expected X Y Z RADIUS [MIN_RADIUS]")
            v = np.array(args.volume_sphere) * L
            volume = planning.Volume.sphere(v[:3], v[3], v[4] if len(v) == 5 else 0.0)
        sight = None
        if args.cone is not None or args.clearance is not None:
            sight = planning.LineOfSight(
                instrument_m=np.array(args.instrument or [0, 0, 0]) * L,
                normal_tool=np.array(args.normal),
                cone_rad=None if args.cone is None else args.cone * A,
                clearance_m=None if args.clearance is None else args.clearance * L,
                near_target_m=0.1 if args.near_target is None else args.near_target * L,
            )
    except ValueError as exc:
        raise Fail(f"volume / line of sight: {exc}") from None
    return volume, sight


def _candidates(args, model, targets, volume, sight, rng):
    """The candidate configurations (SI joint units) and their 1-based rows in --candidates (or
    in the drawn set): the file's rows that the volume and line of sight allow, or drawn ones."""
    import numpy as np

    from calibration import planning
    from service.cli import Fail, progress
    from service.files import read_joints, read_table

    if args.candidates:
        table = read_table(args.candidates)
        cand = read_joints(args.candidates, model, table)
        rows = np.arange(1, len(cand) + 1)
        if volume is not None or sight is not None:
            ok = planning.feasible(model, cand, targets=targets, volume=volume, sight=sight)
            if not ok.any():
                raise Fail(
                    f"{args.candidates}: no candidate puts the target(s) inside the volume and in sight "
                    "of the instrument"
                )
            cand, rows = cand[ok], rows[ok]
        return cand, rows
    progress(f"drawing {args.candidates_count} candidate configurations ...")
    try:
        cand = planning.generate_candidates(
            model, args.candidates_count, rng, targets=targets, volume=volume, sight=sight
        )
    except ValueError as exc:
        raise Fail(str(exc)) from None
    return cand, np.arange(1, len(cand) + 1)


def _plan_options(args, model, targets, volume, rng):
    from calibration import planning
    from calibration.identification import INSTRUMENT_SIGMA_M
    from service.files import read_joints

    evaluation = read_joints(args.evaluation, model) if args.evaluation else None
    L = model.units.length_m
    return planning.PlanOptions(
        targets=targets,
        criterion=args.criterion,
        sigma_m=args.sigma * L if args.sigma is not None else INSTRUMENT_SIGMA_M,
        evaluation=evaluation,
        n_evaluation=args.evaluation_count,
        volume=volume,
        rng=rng,
        gains=args.gains,
        fixed=tuple(args.fix or ()),
    )


def _choose(args, model, cand, options):
    """The plan of --count poses, or with --accuracy the fewest predicted to reach it: (plan,
    accuracy curve or None)."""
    from calibration import planning
    from service.cli import Fail, progress

    progress(f"planning among {len(cand)} candidates ...")
    try:
        if args.accuracy is not None:
            acc = planning.poses_for_accuracy(
                model,
                cand,
                args.accuracy * model.units.length_m,
                statistic=args.statistic,
                k_max=args.count,
                options=options,
            )
            return acc.plan, acc
        return planning.plan(model, cand, args.count, options), None
    except (ValueError, KeyError) as exc:
        raise Fail(f"{args.candidates or 'candidates'}: {exc.args[0] if isinstance(exc, KeyError) else exc}") from None


def _refuse_unreached(args, model, result, curve) -> None:
    """With --accuracy: fail when even the most poses allowed are predicted to miss it."""
    from service.cli import Fail

    if curve is None or curve.success:
        return
    L, unit = model.units.length_m, model.units.length
    raise Fail(
        f"even {len(result.indices)} poses are predicted to give a {args.statistic} error of "
        f"{(result.predicted_rms_m if args.statistic == 'rms' else result.predicted_p95_m) / L:.4g} {unit}, "
        f"above the {args.accuracy:g} {unit} wanted: allow more poses (--count), more candidates, "
        "or use a better instrument"
    )


def _write_poses(args, model, result, rows, sigma_m: float) -> int:
    """Write the chosen configurations (model units) to --out in measurement order, each with its
    candidate row; returns how many."""
    import numpy as np

    from calibration import planning
    from service.files import format_csv, write_atomic

    L, A, unit = model.units.length_m, model.units.angle_rad, model.units.length
    order = planning.measurement_order(result.q)
    q_out = result.q[order] / np.array([A if j.revolute else L for j in model.joints])
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["candidate"]
    text = (
        f"# recal plan: {len(order)} poses, criterion {result.criterion}, predicted RMS "
        f"{result.predicted_rms_m / L:.4g} {unit} (sigma {sigma_m / L:.4g} {unit})\n"
        + format_csv(header, [list(map(float, qr)) + [int(rows[result.indices[k]])] for qr, k in zip(q_out, order)])
    )
    write_atomic(args.out, text)
    return len(order)


def _print_summary(args, model, result, curve, n_candidates: int, n_poses: int, short) -> None:
    import sys

    L, unit = model.units.length_m, model.units.length
    lead = (
        f"{n_poses} poses are needed for a predicted {args.statistic} error of at most {args.accuracy:g} {unit}"
        if curve is not None
        else f"planned {n_poses} poses"
    )
    # the I criterion's value is the predicted RMS printed next
    crit = result.criterion if result.criterion == "I" else f"{result.criterion} = {result.value:.6g}"
    print(
        f"{lead} (from {n_candidates} candidates, criterion {crit}): predicted "
        f"accuracy over {len(result.evaluation_q)} configurations RMS {result.predicted_rms_m / L:.4g} {unit}, "
        f"95th percentile {result.predicted_p95_m / L:.4g} {unit}, max {result.predicted_max_m / L:.4g} {unit}; "
        f"{len(result.params)} parameters identifiable, {len(result.unidentifiable)} not"
    )
    if short is not None:
        print(f"not determined: {short.message}")
    if not result.success:
        print(f"warning: {result.message}", file=sys.stderr)


def _undetermined(result) -> bool:
    """Whether a plan leaves a parameter undetermined: one poses of its kind never determine, or
    too few poses for the ones they can."""
    return bool(result.unidentifiable) or not result.success


def _report(result, curve, model, n_candidates: int, args, elapsed_s: float) -> dict:
    L, A = model.units.length_m, model.units.angle_rad

    def f(x, digits=9):
        x = float(x)
        return None if not math.isfinite(x) else float(f"{x:.{digits}g}")

    def unit(kind):
        return (
            (model.units.length, L) if kind == "length" else (model.units.angle, A) if kind == "angle" else ("1", 1.0)
        )

    rep = {
        "poses": len(result.indices),
        "candidates": n_candidates,
        "criterion": result.criterion,
        "value": f(result.value / (L if result.criterion == "I" else 1.0)),  # I: the predicted RMS, length unit
        "greedy_value": f(result.greedy_value / (L if result.criterion == "I" else 1.0)),
        "log_det": f(result.log_det),
        "swaps": result.swaps,
        "observability": {k: f(v) for k, v in result.observability.items()},
        "units": {"length": model.units.length, "angle": model.units.angle},
        "sigma": f(result.sigma_m / L),
        "targets": [t or "" for t in result.targets],
        "predicted": {
            "rms": f(result.predicted_rms_m / L),
            "p95": f(result.predicted_p95_m / L),
            "max": f(result.predicted_max_m / L),
            "configurations": len(result.evaluation_q),
        },
        "parameters": [
            {"name": p.name, "unit": unit(p.kind)[0], "predicted_std_error": f(s / unit(p.kind)[1])}
            for p, s in zip(result.params, result.std_errors)
        ],
        "unidentifiable": [{"name": d.name, "reason": d.reason} for d in result.unidentifiable],
        "success": result.success,
        "message": result.message,
        "seed": args.seed,
        "elapsed_s": round(elapsed_s, 3),
    }
    if curve is not None:
        rep["accuracy"] = {
            "wanted": f(curve.accuracy_m / L),
            "statistic": curve.statistic,
            "count": curve.count,
            "success": curve.success,
            "greedy_curve": [{"poses": int(k), "predicted": f(v / L)} for k, v in zip(curve.counts, curve.predicted_m)],
        }
    return rep
