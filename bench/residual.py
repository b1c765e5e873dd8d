"""Benchmark of the residual correction's families and their choice (issue 28).

A simulated UR10e-class arm with a random 6-DOF error in every link, an unknown base and
harmonic-drive transmission errors in every joint (``calibration.simulate.harmonic_drive_errors``),
measured at the reflector on N random configurations within ±60° of a working configuration,
tracker noise 0.01 mm per axis. For each N, in the same run:

- the nested cross-validation of ``--residual-map auto`` (``choose_correction``): each family's
  cross-validated RMS, the family kept, its learning curve, and its time; the baseline in the
  same run: the smooth map alone (``choose_residual_map``, what ``--residual-map auto`` did before);
- on 1,000 fresh configurations of the region, against the noise-free truth: the error the
  geometric model leaves and what each family fitted to all N leaves of it.

Run: ``python bench/residual.py`` (a few minutes); ``--poses 500 2000`` for other sizes.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # many small BLAS calls: threads only slow them down

import numpy as np

from calibration import residual_choice as RC
from calibration.identify import identify
from calibration.jacobian import predict
from calibration.robots import nominal
from calibration.simulate import (
    harmonic_drive_errors,
    perturbed,
    random_configurations,
    simulate_measurements,
)

CENTRE = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
REGION = np.stack([CENTRE - np.deg2rad(60), CENTRE + np.deg2rad(60)], axis=1)
SIGMA_M = 10e-6


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def run(n_poses: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3)
    tx = harmonic_drive_errors(nom, rng)
    q = random_configurations(nom, n_poses, rng, limits=REGION)
    data = simulate_measurements(truth, q, rng, sigma_m=SIGMA_M, targets=("smr",), transmission=tx)
    kw = {"sigma_m": SIGMA_M}
    final = identify(nom, data, **kw).model
    t0 = time.perf_counter()
    _, _fig_map = RC.choose_residual_map(nom, data, identify_kw=kw, final=final)
    t_map = time.perf_counter() - t0
    t0 = time.perf_counter()
    choice = RC.choose_correction(nom, data, identify_kw=kw, final=final)
    t_choice = time.perf_counter() - t0
    fig = choice.figures
    cv = ", ".join(f"{f} {v['rms_m'] * 1e3:.4f}" for f, v in fig["families"].items())
    curve = ", ".join(f"{p['poses']}: {p['rms_m'] * 1e3:.4f}" for p in fig["learning_curve"])
    print(f"N = {n_poses} poses (seed {seed}): CV RMS mm: {cv}; kept {fig['chosen']}")
    print(f"  learning curve of {fig['best']} (poses: mm): {curve}")
    print(f"  time: nested choice {t_choice:.1f} s; baseline, the map alone {t_map:.1f} s")
    qh = random_configurations(nom, 1000, rng, limits=REGION)
    clean = simulate_measurements(truth, qh, rng, sigma_m=0.0, targets=("smr",), transmission=tx)
    p_tool = np.array([final.target(t) for t in clean.target])
    geometric = predict(final, clean.q, p_tool).p_world
    before = clean.p_world - geometric
    line = [f"geometric model {rms(before) * 1e3:.4f} mm"]
    for fam in ("map", "transmission", "trees"):
        c = choice.correction if fam == choice.family else RC.fit_family(fam, nom, final, data, kw)
        corr, inside = c.evaluate(clean.q, p_tool)
        left = rms((before - corr)[inside]) / rms(before[inside])
        line.append(f"{fam} leaves {100 * left:.0f} % ({100 * inside.mean():.0f} % inside)")
    print("  hold-out against the truth: " + "; ".join(line))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, nargs="+", default=[500, 1000, 2000])
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    for n in args.poses:
        run(n, args.seed)


if __name__ == "__main__":
    main()
