"""``recal cpa --model NOMINAL.json --data CPA.csv --out MODEL.json [--report R.json]``

Circle-point analysis (book §4.6, ``docs/cpa.md``): the joint axes from single-joint sweeps
(contracts §4: a measurement CSV plus a 1-based ``joint`` column), then a model that
``recal predict`` and ``recal identify`` accept (a good starting point for pose identification).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from calibration.report import cpa_report


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="nominal model file (recal.model/1) or a library robot name")
    s.add_argument(
        "--data", required=True, help="circle-point CSV (docs/contracts.md §4): measurements plus a `joint` column"
    )
    s.add_argument("--out", required=True, help="model file to write")
    s.add_argument("--report", help="JSON report to write (per-joint fits and diagnostics)")
    s.add_argument(
        "--convention",
        choices=["dh", "poe"],
        help="convention of the written model (default: poe for a poe nominal model, else dh)",
    )
    s.add_argument(
        "--method",
        default="geometric",
        choices=["geometric", "kasa"],
        help="circle fit: geometric least squares (default) or the algebraic Kåsa fit alone",
    )
    s.add_argument(
        "--sigma",
        type=float,
        help="instrument standard uncertainty per axis, in the model's length "
        "unit, for the small-radius warnings (default: estimated from the residuals)",
    )
    s.add_argument(
        "--min-arc", type=float, help="warn for arcs under this, in the model's angle unit (default: half a circle)"
    )


def read_sweeps(path: str | os.PathLike, model):
    """A circle-point CSV (contracts §4) for ``model``: :class:`calibration.cpa.Sweeps` in SI
    and the parsed table (for the file line of each row). Bad input raises ``InputError``."""
    from calibration.cpa import Sweeps
    from service.files import InputError, read_measurements, read_table

    table = read_table(path)
    if not table.has("joint"):
        raise InputError(
            path,
            f"missing required column 'joint' (the swept joint, 1..{model.n_joints}; "
            f"header has: {', '.join(table.header)})",
        )
    data = read_measurements(path, model)
    raw = table.numbers("joint")
    joint = np.empty(len(raw), dtype=int)
    for r, x in enumerate(raw):
        if x != math.floor(x) or not 1 <= x <= model.n_joints:
            cell = table.rows[r][table.index["joint"]].strip()
            raise InputError(
                path,
                f"expected a joint number 1..{model.n_joints}, got {cell!r}",
                row=r + 1,
                line=table.lines[r],
                column="joint",
            )
        joint[r] = int(x) - 1
    return Sweeps(q=data.q, p_world=data.p_world, joint=joint, target=data.target, row=data.row), table


def run(args) -> int:
    from calibration.cpa import SweepError, circle_point_analysis
    from service.cli import Fail, progress
    from service.files import InputError, load_model, save_model, write_atomic

    t0 = time.perf_counter()
    model = load_model(args.model)
    progress(f"reading {args.data} ...")
    sweeps, table = read_sweeps(args.data, model)
    progress(f"circle-point analysis of {len(sweeps)} sweeps ...")
    L, A = model.units.length_m, model.units.angle_rad
    if args.sigma is not None and not args.sigma > 0:
        raise Fail(f"--sigma: expected a positive number, got {args.sigma}")
    if args.min_arc is not None and not args.min_arc >= 0:
        raise Fail(f"--min-arc: expected a non-negative angle, got {args.min_arc}")
    kw = {}
    if args.min_arc is not None:
        kw["min_arc_rad"] = args.min_arc * A
    try:
        result = circle_point_analysis(
            model,
            sweeps,
            method=args.method,
            convention=args.convention,
            sigma_m=args.sigma * L if args.sigma is not None else None,
            **kw,
        )
    except SweepError as exc:
        line = None
        if exc.row is not None and 1 <= exc.row <= len(table.lines):
            line = table.lines[exc.row - 1]
        raise InputError(args.data, str(exc), row=exc.row, line=line, column=exc.column) from None
    except ValueError as exc:
        raise InputError(args.data, str(exc)) from None
    rep = cpa_report(result, model, sweeps)
    rep["elapsed_s"] = round(time.perf_counter() - t0, 3)
    if args.report:
        write_atomic(args.report, json.dumps(rep, indent=2) + "\n")
    block = {
        k: rep[k]
        for k in ("success", "message", "rows", "signature", "registration", "target_changes", "warnings", "notes")
    }
    block["axes"] = [{"joint": e["joint"], "swept": e["swept"], **e["axis"]} for e in rep["joints"]]
    save_model(args.out, result.model, {"cpa": block})
    worst = max((a.out_of_plane_rms_m for a in result.axes if a is not None), default=float("nan"))
    print(
        f"circle-point analysis: {result.message}; worst out-of-plane RMS {worst / L:.4g} {model.units.length}; "
        f"wrote a {result.model.convention} model to {args.out}"
    )
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0 if result.success else 1
