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


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="nominal model file (recal.model/1) or a library robot name")
    s.add_argument("--data", required=True, help="circle-point CSV (contracts §4): measurements plus a `joint` column")
    s.add_argument("--out", required=True, help="model file to write")
    s.add_argument("--report", help="JSON report to write (per-joint fits and diagnostics)")
    s.add_argument("--convention", choices=["dh", "poe"],
                   help="convention of the written model (default: poe for a poe nominal model, else dh)")
    s.add_argument("--method", default="geometric", choices=["geometric", "kasa"],
                   help="circle fit: geometric least squares (default) or the algebraic Kåsa fit alone")
    s.add_argument("--sigma", type=float, help="instrument standard uncertainty per axis, in the model's length "
                   "unit, for the small-radius warnings (default: estimated from the residuals)")
    s.add_argument("--min-arc", type=float, help="warn for arcs under this, in the model's angle unit "
                   "(default: half a circle)")


def read_sweeps(path: str | os.PathLike, model):
    """A circle-point CSV (contracts §4) for ``model``: :class:`calibration.cpa.Sweeps` in SI
    and the parsed table (for the file line of each row). Bad input raises ``InputError``."""
    from calibration.cpa import Sweeps
    from service.files import InputError, read_measurements, read_table

    table = read_table(path)
    if not table.has("joint"):
        raise InputError(path, f"missing required column 'joint' (the swept joint, 1..{model.n_joints}; "
                               f"header has: {', '.join(table.header)})")
    data = read_measurements(path, model)
    raw = table.numbers("joint")
    joint = np.empty(len(raw), dtype=int)
    for r, x in enumerate(raw):
        if x != math.floor(x) or not 1 <= x <= model.n_joints:
            cell = table.rows[r][table.index["joint"]].strip()
            raise InputError(path, f"expected a joint number 1..{model.n_joints}, got {cell!r}",
                             row=r + 1, line=table.lines[r], column="joint")
        joint[r] = int(x) - 1
    return Sweeps(q=data.q, p_world=data.p_world, joint=joint, target=data.target, row=data.row), table


def _f(x, digits: int = 9):
    x = float(x)
    return None if not math.isfinite(x) else float(f"{x:.{digits}g}")


def _vec(v, scale: float = 1.0) -> list:
    return [_f(x / scale) for x in np.asarray(v, dtype=float)]


def _plain(key: str) -> str:
    """A setting's name without its SI suffix (the report is in the model's units)."""
    return {"held_tol_rad": "held_tol_angle", "held_tol_m": "held_tol_length"}.get(
        key, key.removesuffix("_rad").removesuffix("_m"))


def _setting(key: str, value, L: float, A: float):
    """A setting in the model's units (``*_rad`` angles, ``*_m`` lengths)."""
    if value is None or isinstance(value, (str, int)):
        return value
    return _f(value / A) if key.endswith("_rad") else _f(value / L) if key.endswith("_m") else _f(value)


def report(result, nominal, sweeps) -> dict:
    """The CPA report, JSON-ready, in the nominal model's units."""
    from calibration.transforms import matrix_to_pose

    u = nominal.units
    L, A = u.length_m, u.angle_rad
    joints = []
    for j, jt in enumerate(nominal.joints):
        axis = result.axes[j]
        rows = sweeps.row[sweeps.joint == j]
        entry = {"joint": j + 1, "name": jt.name, "type": jt.type, "swept": axis is not None,
                 "axis": {"direction": _vec(result.directions[j]), "point": _vec(result.points[j], L)},
                 "from_nominal": {"tilt": _f(result.nominal_tilt_rad[j] / A),
                                  "offset": _f(result.nominal_offset_m[j] / L) if jt.revolute else None}}
        if axis is not None:
            entry["rows"] = [int(rows[0]), int(rows[-1])]
            entry["targets"] = [t for t in result.fits[j]]
            fits = []
            for t, f in result.fits[j].items():
                fits.append({
                    "target": t, "points": f.n_points, "method": f.method,
                    "radius": _f(f.radius_m / L), "arc": _f(f.arc_rad / A), "travel": _f(f.travel_m / L),
                    "out_of_plane_rms": _f(f.out_of_plane_rms_m / L), "circle_rms": _f(f.circle_rms_m / L),
                    "noise": _f(f.noise_m / L), "direction_std": _f(f.direction_std_rad / A),
                    "position_std": _f(f.point_std_m / L), "scale": _f(f.scale),
                    "axis": {"direction": _vec(f.direction), "point": _vec(f.point, L)},
                    "warnings": list(f.warnings),
                })
            entry["fits"] = fits
        joints.append(entry)
    base = matrix_to_pose(result.T_world_base)
    return {
        "success": result.success,
        "message": result.message,
        "units": {"length": u.length, "angle": u.angle},
        "convention": result.model.convention,
        "rows": len(sweeps),
        "signature": {"q": [_f(v / (A if jt.revolute else L)) for v, jt in zip(result.signature_q, nominal.joints)]},
        "joints": joints,
        "registration": {"base": _vec(np.concatenate([base[:3] / L, base[3:] / A])),
                         "rms": _f(result.registration_rms_m / L),
                         "method": "rigid point registration of the nominal model onto the sweeps (Kabsch)"},
        "target_changes": {("tool" if t is None else t): _vec(d, L) for t, d in result.target_changes.items()},
        "warnings": list(result.warnings),
        "notes": list(result.notes),
        "settings": {_plain(k): _setting(k, v, L, A) for k, v in result.settings.items()},
    }


def run(args) -> int:
    from calibration.cpa import SweepError, circle_point_analysis
    from service.cli import Fail
    from service.files import InputError, load_model, save_model, write_atomic

    t0 = time.perf_counter()
    model = load_model(args.model)
    sweeps, table = read_sweeps(args.data, model)
    L, A = model.units.length_m, model.units.angle_rad
    if args.sigma is not None and not args.sigma > 0:
        raise Fail(f"--sigma: expected a positive number, got {args.sigma}")
    if args.min_arc is not None and not args.min_arc >= 0:
        raise Fail(f"--min-arc: expected a non-negative angle, got {args.min_arc}")
    kw = {}
    if args.min_arc is not None:
        kw["min_arc_rad"] = args.min_arc * A
    try:
        result = circle_point_analysis(model, sweeps, method=args.method, convention=args.convention,
                                       sigma_m=args.sigma * L if args.sigma is not None else None, **kw)
    except SweepError as exc:
        line = None
        if exc.row is not None and 1 <= exc.row <= len(table.lines):
            line = table.lines[exc.row - 1]
        raise InputError(args.data, str(exc), row=exc.row, line=line, column=exc.column) from None
    except ValueError as exc:
        raise InputError(args.data, str(exc)) from None
    rep = report(result, model, sweeps)
    rep["elapsed_s"] = round(time.perf_counter() - t0, 3)
    if args.report:
        write_atomic(args.report, json.dumps(rep, indent=2) + "\n")
    block = {k: rep[k] for k in ("success", "message", "rows", "signature", "registration", "target_changes",
                                 "warnings", "notes")}
    block["axes"] = [{"joint": e["joint"], "swept": e["swept"], **e["axis"]} for e in rep["joints"]]
    save_model(args.out, result.model, {"cpa": block})
    worst = max((a.out_of_plane_rms_m for a in result.axes if a is not None), default=float("nan"))
    print(f"circle-point analysis: {result.message}; worst out-of-plane RMS {worst / L:.4g} {model.units.length}; "
          f"wrote a {result.model.convention} model to {args.out}")
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0 if result.success else 1
