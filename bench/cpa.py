"""Circle-point analysis benchmark (``python bench/cpa.py [--trials 20]``).

1. Hold-out accuracy of the model CPA writes: a UR10e whose every link is perturbed (0.5 mm,
   0.05°, 0.1° offsets), the tracker somewhere in the cell, the reflector mounted 2.6 mm off
   its nominal place; 24 points a joint over 200° with 0.02 mm noise (per axis); the reflector
   predicted at 200 random configurations. The geometric circle fit (Recal's) against the
   book's plain plane-plus-circle (Kåsa only); for scale, the registered nominal model and a
   pose identification (50 random configurations, same noise) started from the CPA model.
2. Axis errors against arc span and noise: direction error (deg) and position error (mm,
   distance of the fitted centre from the true axis), RMS over the six joints and the trials.

Prints Markdown (the tables of docs/benchmarks.md, section "Circle-point analysis").
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from calibration import robots
from calibration.cpa import axis_lines, circle_point_analysis, simulate_sweeps
from calibration.identify import identify
from calibration.kinematics import target_positions
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.transforms import matrix_to_pose

SIGNATURE = np.deg2rad([10.0, -80.0, 70.0, -60.0, 45.0, 20.0])
SPANS_DEG = (30, 60, 90, 180, 270)
NOISES_MM = (0.005, 0.02, 0.1)


def cell(seed: int):
    rng = np.random.default_rng(seed)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.06, 0.04, 0.09])})
    truth = dataclasses.replace(
        perturbed(nominal, rng),
        base=np.array([1.8, -0.6, 0.3, 0.002, -0.004, np.deg2rad(130.0)]),
        targets={"smr": np.array([0.0608, 0.0388, 0.0912])},
    )
    return nominal, truth, rng


def holdout(model, truth, q) -> np.ndarray:
    return np.linalg.norm(target_positions(model, q, "smr") - target_positions(truth, q, "smr"), axis=1)


def accuracy(trials: int):
    rows = {"geometric": [], "kasa": [], "nominal": [], "identified": []}
    times = []
    for seed in range(trials):
        nominal, truth, rng = cell(seed)
        sw = simulate_sweeps(truth, SIGNATURE, rng, sigma_m=20e-6, target="smr", points=24)
        q = random_configurations(nominal, 200, rng)
        for method in ("geometric", "kasa"):
            t0 = time.perf_counter()
            res = circle_point_analysis(nominal, sw, method=method)
            if method == "geometric":
                times.append(time.perf_counter() - t0)
                start = res.model
            e = holdout(res.model, truth, q)
            rows[method].append((np.sqrt(np.mean(e**2)), e.max()))
        data = simulate_measurements(truth, random_configurations(nominal, 50, rng), rng, targets=("smr",))
        e = holdout(identify(start, data).model, truth, q)
        rows["identified"].append((np.sqrt(np.mean(e**2)), e.max()))
        reg = dataclasses.replace(nominal, base=matrix_to_pose(res.T_world_base))
        e = holdout(reg, truth, q)
        rows["nominal"].append((np.sqrt(np.mean(e**2)), e.max()))
    return {k: np.array(v) * 1e3 for k, v in rows.items()}, np.array(times)


def axis_errors(trials: int):
    out = {}
    for span in SPANS_DEG:
        for noise in NOISES_MM:
            acc = {"geometric": ([], []), "kasa": ([], [])}
            for seed in range(trials):
                _, truth, rng = cell(1000 + seed)
                nominal = dataclasses.replace(robots.nominal("ur10e"), targets=truth.targets)
                sw = simulate_sweeps(
                    truth, SIGNATURE, rng, sigma_m=noise * 1e-3, target="smr", points=24, span_rad=np.deg2rad(span)
                )
                S, R = (a[0] for a in axis_lines(truth, SIGNATURE))
                for method in acc:
                    res = circle_point_analysis(nominal, sw, method=method)
                    ang = np.arctan2(np.linalg.norm(np.cross(S, res.directions), axis=1), np.sum(S * res.directions, 1))
                    dist = np.linalg.norm(np.cross(res.points - R, S), axis=1)
                    acc[method][0].extend(np.rad2deg(ang))
                    acc[method][1].extend(dist * 1e3)
            out[span, noise] = {
                m: (float(np.sqrt(np.mean(np.square(a)))), float(np.sqrt(np.mean(np.square(d)))))
                for m, (a, d) in acc.items()
            }
    return out


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import scipy

    return (
        f"{cpu}, {os.cpu_count()} cores; Python {platform.python_version()}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}; {platform.system()} {platform.release()}"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20, help="simulated robots per figure (default 20)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    acc, times = accuracy(args.trials)
    table = axis_errors(max(args.trials // 2, 1))
    elapsed = time.perf_counter() - t0

    print(f"Machine: {machine()}. Whole benchmark: {elapsed:.1f} s (`python bench/cpa.py --trials {args.trials}`).\n")
    print(
        f"Hold-out accuracy, UR10e, 24 points a joint over 200°, 0.02 mm noise, 200 random configurations, "
        f"{args.trials} simulated robots (mm; median and worst over the robots):\n"
    )
    print("| model | RMS (median) | RMS (worst) | max (median) | max (worst) |")
    print("|---|---|---|---|---|")
    names = {
        "geometric": "CPA, geometric circle fit (Recal)",
        "kasa": "CPA, plane + Kåsa circle only (book)",
        "nominal": "nominal model, registered",
        "identified": "pose identification from the CPA model (50 more points)",
    }
    for k in ("geometric", "kasa", "nominal", "identified"):
        a = acc[k]
        print(
            f"| {names[k]} | {np.median(a[:, 0]):.4f} | {a[:, 0].max():.4f} | {np.median(a[:, 1]):.4f} | "
            f"{a[:, 1].max():.4f} |"
        )
    ratio = acc["geometric"][:, 0] / acc["kasa"][:, 0]
    print(
        f"\nRMS ratio geometric / Kåsa, per robot: median {np.median(ratio):.3f}, worst {ratio.max():.3f}. "
        f"One CPA (6 joints, 144 points): median {np.median(times) * 1e3:.1f} ms.\n"
    )
    print(
        f"Axis errors against arc span and noise ({max(args.trials // 2, 1)} robots, RMS over the 6 joints; "
        f"direction in degrees / position in mm; geometric fit, Kåsa-only fit in brackets):\n"
    )
    print("| arc | " + " | ".join(f"σ = {s} mm" for s in NOISES_MM) + " |")
    print("|---|" + "---|" * len(NOISES_MM))
    for span in SPANS_DEG:
        cells = []
        for noise in NOISES_MM:
            g, k = table[span, noise]["geometric"], table[span, noise]["kasa"]
            cells.append(f"{g[0]:.2g}° / {g[1]:.2g} ({k[0]:.2g}° / {k[1]:.2g})")
        print(f"| {span}° | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
