"""``recal identify --model NOMINAL.json --data MEAS.csv --out MODEL.json [--report R.json] [--validate VAL.csv]``

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
    s.add_argument("--data", required=True, help="measurement CSV (contracts §3)")
    s.add_argument("--out", required=True, help="identified model file to write")
    s.add_argument("--report", help="JSON report to write")
    s.add_argument("--validate", help="hold-out measurement CSV to test the identified model on")
    s.add_argument("--sigma", type=float, help="instrument standard uncertainty per axis, in the model's length "
                   "unit, for rows without a sigma column (default 0.02 mm)")
    s.add_argument("--sigma-angle", type=float, help="orientation uncertainty of full-pose rows, model angle unit")
    s.add_argument("--loss", default="linear", choices=["linear", "huber", "soft_l1", "cauchy"],
                   help="robust loss against bad rows (default linear)")
    s.add_argument("--f-scale", type=float, default=3.0, help="robust loss scale, in sigmas (default 3)")
    s.add_argument("--register", default="auto", choices=["auto", "always", "never"],
                   help="start from a rigid registration of the base (default auto: when it fits better)")
    s.add_argument("--gains", action="store_true", help="also identify joint gains")
    s.add_argument("--fix", action="append", metavar="NAME", help="keep a parameter fixed (repeatable; prefix* allowed)")


def run(args) -> int:

    from calibration.identify import identify
    from calibration.report import consistency_text, identification_block, identification_report, summary_line
    from calibration.uncertainty import validate
    from service.cli import Fail
    from service.files import check_output, load_model, read_measurements, save_model, write_atomic

    t0 = time.perf_counter()
    for path in (args.out, args.report):  # before any work: a run never ends unable to write
        if path:
            check_output(path)
    model = load_model(args.model)
    data = read_measurements(args.data, model)
    holdout = read_measurements(args.validate, model) if args.validate else None
    L = model.units.length_m
    if args.sigma is not None and not args.sigma > 0:
        raise Fail(f"--sigma: expected a positive number, got {args.sigma}")
    if args.sigma_angle is not None and not args.sigma_angle > 0:
        raise Fail(f"--sigma-angle: expected a positive number, got {args.sigma_angle}")
    try:
        result = identify(
            model, data,
            sigma_m=args.sigma * L if args.sigma is not None else 20e-6,
            sigma_rad=args.sigma_angle * model.units.angle_rad if args.sigma_angle is not None else None,
            loss=args.loss, f_scale=args.f_scale, register=args.register, gains=args.gains,
            fixed=tuple(args.fix or ()),
        )
    except (ValueError, KeyError) as exc:
        raise Fail(f"{args.data}: {exc}") from None
    validation = validate(result, holdout) if holdout is not None else None
    report = identification_report(result, model.units, data_rows=data.row, validation=validation)
    report["elapsed_s"] = round(time.perf_counter() - t0, 3)
    if args.report:
        write_atomic(args.report, json.dumps(report, indent=2) + "\n")
    # the block keeps what `recal compensate` needs later: the nominal model the controller
    # knows, and the joint ranges the data covered (its "calibrated region")
    block = identification_block(result, model.units, nominal=model, q=data.q)
    save_model(args.out, result.model, {"identification": block})
    line = summary_line(result, model.units, len(data), validation)
    print(line)
    if result.outliers:
        rows = ", ".join(str(int(data.row[i])) for i in result.outliers[:10])
        print(f"warning: {len(result.outliers)} rows look like outliers (rows {rows}); see the report", file=sys.stderr)
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not result.success:
        return 1
    if result.consistency is not None and not result.consistency["consistent"]:
        # the model and the report are written: a nightly job sees the status, a person the report
        print(f"recal identify: {consistency_text(result, model.units)}", file=sys.stderr)
        return 3
    return 0
