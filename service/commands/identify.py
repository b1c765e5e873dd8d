"""``recal identify --model NOMINAL.json --data MEAS.csv --out MODEL.json [--report R.json] [--validate VAL.csv]
[--compliance gravity|auto] [--residual-map auto]``

Exit status: 0 identified; 1 the solver did not converge; 2 bad input, or too few rows to check
the fit (the message says how many are needed; nothing written); 3 the model and the report are
written, but the residuals are not consistent with the stated uncertainty (the model does not
explain the data: a chi-squared test, docs/formats.md §4).
"""

from __future__ import annotations

import json
import sys
import time


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="nominal model file (recal.model/1) or a library robot name")
    s.add_argument("--data", required=True, help="measurement CSV (docs/contracts.md §3)")
    s.add_argument("--out", required=True, help="identified model file to write")
    s.add_argument("--report", help="JSON report to write")
    s.add_argument("--validate", help="hold-out measurement CSV to test the identified model on")
    s.add_argument(
        "--sigma",
        type=float,
        help="instrument standard uncertainty per axis, in the model's length "
        "unit, for rows without a sigma column (default 0.02 mm)",
    )
    s.add_argument("--sigma-angle", type=float, help="orientation uncertainty of full-pose rows, model angle unit")
    s.add_argument(
        "--loss",
        default="linear",
        choices=["linear", "huber", "soft_l1", "cauchy"],
        help="robust loss against bad rows (default linear)",
    )
    s.add_argument("--f-scale", type=float, default=3.0, help="robust loss scale, in sigmas (default 3)")
    s.add_argument(
        "--register",
        default="auto",
        choices=["auto", "always", "never"],
        help="start from a rigid registration of the base (default auto: when it fits better)",
    )
    s.add_argument("--gains", action="store_true", help="also identify joint gains")
    s.add_argument(
        "--fix", action="append", metavar="NAME", help="keep a parameter fixed (repeatable; prefix* allowed)"
    )
    s.add_argument(
        "--compliance",
        choices=["gravity", "auto"],
        help="add joint compliance under gravity (level 3): 'gravity' always, 'auto' only for the joints "
        "where 5-fold cross-validation on the data shows a gain (the figures are reported either way)",
    )
    s.add_argument(
        "--compliance-joints",
        metavar="J2,J3",
        help="the joints that may deflect (default: the revolute ones among the first three whose axis "
        "is not along gravity)",
    )
    s.add_argument("--gravity", metavar="X,Y,Z", help="gravity's direction in the robot base frame (default 0,0,-1)")
    s.add_argument(
        "--residual-map",
        choices=["auto"],
        help="add a correction of what the model leaves, as a function of the joints: the family (a smooth "
        "map, book §5.4; joint transmission errors; boosted trees) with the least error by 5-fold nested "
        "cross-validation, where it shows a gain; applied only inside the measured region (docs/residual.md)",
    )


def run(args) -> int:
    from calibration.identify import identify
    from calibration.report import identification_block
    from calibration.uncertainty import validate
    from service.cli import Fail, progress
    from service.files import save_model

    t0 = time.perf_counter()
    model, data, holdout = _inputs(args, t0)
    kw = _identify_options(args, model)
    try:
        start, compliance = _with_compliance(args, model, data, kw)
        result = identify(start, data, **kw)
    except (ValueError, KeyError) as exc:
        raise Fail(f"{args.data}: {exc}") from None
    progress(f"identified in {time.perf_counter() - t0:.1f} s ({result.iterations} iterations)")
    if holdout is not None:
        progress(f"validating on {len(holdout)} hold-out rows ...")
    validation = validate(result, holdout) if holdout is not None else None
    try:  # the map's cross-validation identifies on each fold's share of the rows (NotEnoughData)
        rmap_doc, rmap_line = (
            _residual_map(args, model, start, data, holdout, result, kw) if args.residual_map else (None, None)
        )
    except (ValueError, KeyError) as exc:
        raise Fail(f"{args.data}: --residual-map: {exc}") from None
    report = _write_report(args, result, model, data, validation, compliance, rmap_line, t0)
    # the block keeps what `recal compensate` needs later: the nominal model the controller
    # knows, and the joint ranges the data covered (its "calibrated region")
    block = identification_block(result, model.units, nominal=model, q=data.q, report=report)
    save_model(args.out, result.model, {"identification": block, **({"residual_map": rmap_doc} if rmap_doc else {})})
    _print_summary(result, model, data, validation, compliance, rmap_line)
    return _exit_status(result, model)


def _inputs(args, t0: float):
    """The nominal model, the measurements and the hold-out ones (or None), once the outputs are
    known to be writable (a run never ends unable to write)."""
    from service.cli import progress
    from service.files import check_output, load_model, read_measurements

    for path in (args.out, args.report):  # before any work: a run never ends unable to write
        if path:
            check_output(path)
    model = load_model(args.model)
    progress(f"reading {args.data} ...")
    data = read_measurements(args.data, model)
    holdout = read_measurements(args.validate, model) if args.validate else None
    progress(f"read {len(data)} rows in {time.perf_counter() - t0:.1f} s; identifying ...")
    return model, data, holdout


def _identify_options(args, model) -> dict:
    """:func:`calibration.identify.identify`'s keywords from the flags (SI units)."""
    from calibration.identification import INSTRUMENT_SIGMA_M
    from service.cli import Fail

    L = model.units.length_m
    if args.sigma is not None and not args.sigma > 0:
        raise Fail(f"--sigma: expected a positive number, got {args.sigma}")
    if args.sigma_angle is not None and not args.sigma_angle > 0:
        raise Fail(f"--sigma-angle: expected a positive number, got {args.sigma_angle}")
    return dict(
        sigma_m=args.sigma * L if args.sigma is not None else INSTRUMENT_SIGMA_M,
        sigma_rad=args.sigma_angle * model.units.angle_rad if args.sigma_angle is not None else None,
        loss=args.loss,
        f_scale=args.f_scale,
        register=args.register,
        gains=args.gains,
        fixed=tuple(args.fix or ()),
    )


def _write_report(args, result, model, data, validation, compliance, rmap_line, t0: float) -> dict:
    """The identification report (with the compliance and residual-map entries), written to
    --report when given."""
    from calibration.report import identification_report
    from service.files import write_atomic

    report = identification_report(result, model.units, data_rows=data.row, validation=validation)
    if compliance is not None:
        report["compliance"] = compliance
    if rmap_line is not None:
        report["residual_map"] = rmap_line[1]
    report["elapsed_s"] = round(time.perf_counter() - t0, 3)
    if args.report:
        write_atomic(args.report, json.dumps(report, indent=2) + "\n")
    return report


def _print_summary(result, model, data, validation, compliance, rmap_line) -> None:
    """The summary line, the compliance and residual-map verdicts on stdout; outliers and the
    identification's warnings on stderr."""
    from calibration.report import summary_line

    u = model.units.length
    print(summary_line(result, model.units, len(data), validation))
    if compliance is not None and "cross_validation" in compliance:
        cv = compliance["cross_validation"]
        verdict = (
            f"compliance of {', '.join(compliance['joints'])} added"
            if compliance["joints"]
            else "no gain: the model stays rigid"
        )
        print(
            f"compliance ({cv['folds']}-fold cross-validation): RMS rigid {cv['rms_rigid']:.4g} {u}, "
            f"compliant {cv['rms_compliant']:.4g} {u}; {verdict}"
        )
    if rmap_line is not None:
        print(rmap_line[0])
    if result.outliers:
        rows = ", ".join(str(int(data.row[i])) for i in result.outliers[:10])
        print(f"warning: {len(result.outliers)} rows look like outliers (rows {rows}); see the report", file=sys.stderr)
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)


def _exit_status(result, model) -> int:
    """1 not converged; 3 the residuals inconsistent with the stated uncertainty; else 0."""
    from calibration.report import consistency_text

    if not result.success:
        return 1
    if result.consistency is not None and not result.consistency["consistent"]:
        # the model and the report are written: a nightly job sees the status, a person the report
        print(f"recal identify: {consistency_text(result, model.units)}", file=sys.stderr)
        return 3
    return 0


def _with_compliance(args, model, data, kw):
    """The model identification starts from under ``--compliance`` (a section with every term 0,
    or the model's own), and the report's ``compliance`` entry (None without the flag)."""
    from calibration import compliance as comp
    from calibration import compliance_fit
    from service.cli import Fail

    if args.compliance is None:
        if args.compliance_joints or args.gravity:
            raise Fail("--compliance-joints and --gravity need --compliance gravity or auto")
        return model, None
    names = [j.name for j in model.joints]
    joints = None
    if args.compliance_joints:
        joints = tuple(j.strip() for j in args.compliance_joints.split(",") if j.strip())
        for j in joints:
            if j not in names:
                raise Fail(f"--compliance-joints: no joint {j!r}; expected names from {', '.join(names)}")
            if not model.joints[names.index(j)].revolute:
                raise Fail(f"--compliance-joints: joint {j!r} is prismatic; expected revolute joints")
    gravity = (0.0, 0.0, -1.0)
    if args.gravity:
        try:
            gravity = tuple(float(v) for v in args.gravity.split(","))
        except ValueError:
            gravity = ()
        if len(gravity) != 3 or not any(gravity):
            raise Fail(f"--gravity: expected three numbers X,Y,Z not all zero, got {args.gravity!r}")
    if model.compliance is not None and joints is None and not args.gravity:
        candidates = model.compliance
    else:
        candidates = comp.default_section(model, gravity=gravity, joints=joints)
    L = model.units.length_m
    entry = {"mode": args.compliance}
    if args.compliance == "gravity":
        start = comp.with_section(model, candidates)
    else:
        cv = compliance_fit.choose_compliance(model, data, candidates=candidates, identify_kw=kw)
        start = comp.with_section(model, cv.section)
        entry["cross_validation"] = {
            "folds": cv.folds,
            "min_gain": compliance_fit.MIN_CV_GAIN,
            "rms_rigid": cv.rms_rigid_m / L,
            "rms_compliant": cv.rms_compliant_m / L,
            "candidates": list(candidates.joints),
            "tried": [{"joints": list(j), "rms": r / L} for j, r in cv.tried],
        }
    section = start.compliance
    entry["joints"] = [] if section is None else list(section.joints)
    entry["lumps"] = [] if section is None else list(section.lumps)
    entry["gravity"] = list(candidates.gravity)
    return start, entry


def _residual_map(args, model, start, data, holdout, result, kw):
    """``--residual-map auto``: nested cross-validation among no correction, the smooth map, the
    joint transmission and boosted trees (calibration.residual_choice, issue 28). Returns the
    chosen correction's file section (None when none is kept) and the line to print with the
    report's figures (model units)."""
    import numpy as np

    from calibration import residual_choice as rc
    from calibration import residual_map as rm

    L = model.units.length_m
    u = model.units.length
    choice = rc.choose_correction(start, data, identify_kw=kw, final=result.model)
    fig = choice.figures
    figures = choice.report(model)
    fams = ", ".join(f"{f} {v['rms_m'] / L:.4g}" for f, v in fig["families"].items())
    fams += "".join(f", {f} not tried ({why})" for f, why in fig.get("not_tried", {}).items())
    line = f"residual map ({fig['folds']}-fold nested cross-validation, RMS {u}): {fams}; "
    if choice.correction is None:
        line += f"no gain of {100 * fig['min_gain']:.0f} % or more: left out"
        return None, (line, figures)
    line += f"kept {choice.family} ({100 * fig['gain']:.0f} % lower than without)"
    if holdout is not None:
        r = rm.residuals(result.model, holdout)
        p_tool = np.array([result.model.target(t) for t in holdout.target])
        corr, inside = choice.correction.evaluate(holdout.q, p_tool)
        after = float(np.sqrt(np.mean(np.sum((r - corr) ** 2, axis=1))))
        coverage = _corrected_coverage(model, result, choice.section(model), holdout, kw)
        figures["validation"] = {
            "rms_with_map": after / L,
            "inside_share": float(np.mean(inside)),
            "coverage_95": coverage,
        }
        line += f"; hold-out RMS with it {after / L:.4g} {u} ({100 * np.mean(inside):.0f}% of it inside its region"
        line += ")" if coverage is None else f", {100 * coverage:.1f} % of those within their 95 % bound)"
    return choice.section(model), (line, figures)


def _corrected_coverage(model, result, section: dict, holdout, kw: dict) -> float | None:
    """The share of the hold-out rows inside the correction's region whose error lies within the
    95 % bound the stored model will give there (``calibration.uncertainty.stored_position_bound``,
    the one bound every verb uses) plus the instrument's stated noise: honest bounds cover about
    95 % (issue 28). None when no hold-out row is inside."""
    import dataclasses

    import numpy as np

    from calibration.jacobian import predict
    from calibration.report import identification_block
    from calibration.residual_map import from_model
    from calibration.uncertainty import chi2_quantile, stored_position_bound

    meta = {"identification": identification_block(result, model.units), "residual_map": section}
    stored = dataclasses.replace(result.model, units=model.units, metadata=meta)
    sigma = np.where(np.isfinite(holdout.sigma) & (holdout.sigma > 0), holdout.sigma, kw["sigma_m"])
    d2 = np.full(len(holdout), np.nan)
    for t in {None if x is None else str(x) for x in holdout.target}:
        rows = np.array([(None if x is None else str(x)) == t for x in holdout.target])
        q = holdout.q[rows]
        C, inside = stored_position_bound(stored, q, t)
        p_tool = np.tile(stored.target(t), (len(q), 1))
        corr, _ = from_model(stored).evaluate(q, p_tool)
        e = holdout.p_world[rows] - predict(stored, q, p_tool).p_world - corr
        C = C + (sigma[rows] ** 2)[:, None, None] * np.eye(3)
        d = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
        d2[np.flatnonzero(rows)] = np.where(inside if inside is not None else True, d, np.nan)
    keep = np.isfinite(d2)
    return float(np.mean(d2[keep] <= chi2_quantile(0.95, 3))) if keep.any() else None
