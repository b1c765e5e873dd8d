"""Benchmark of identification (issue "Calibration core", item 9).

A synthetic UR10e whose every link carries a small random 6-DOF error (``simulate.perturbed``:
axis tilts and shifts, joint offsets, home pose), plus base and tool errors, measured
position-only at the tool point with a tracker noise of 0.02 mm per axis. For N rows it reports:

- our solve time (the whole ``identify()`` call: registration, identifiability selection,
  Levenberg-Marquardt with the analytic Jacobian, covariance and observability statistics; best
  of ``--repeat`` runs), iterations, and the peak memory of that call (``tracemalloc`` peak of a
  separate run, so that tracing does not slow the timed runs);
- the hold-out RMS and max position error of the identified model against the truth on 2,000
  fresh, noise-free configurations;
- side by side, in the same run: ``scipy.optimize.least_squares`` with its default
  finite-difference Jacobian (``jac="2-point"``, ``method="trf"``, default tolerances), from the
  same start (our registered start model) over the same free parameters, with the same
  residuals; its time counts only the ``least_squares`` call (registration and selection are
  given to it for free);
- the hold-out RMS of identifying in the true parameterisation (``poe``, via
  ``conventions.to_poe`` of the nominal) on the same data;
- the wall time of ``recal identify`` on 4,000 rows as a whole process.

Run: ``python bench/identify.py`` (about a minute or two); ``--sizes 1000 10000`` for fewer.
BLAS runs single-threaded unless ``OPENBLAS_NUM_THREADS`` is set (see the note at the imports).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

# Single-threaded BLAS unless the caller says otherwise: identification makes many small BLAS and
# LAPACK calls, and multithreaded OpenBLAS slows those down badly on a busy (shared) machine.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import scipy
from scipy.optimize import least_squares

from calibration import robots
from calibration.conventions import to_poe
from calibration.identify import identify
from calibration.kinematics import target_positions
from calibration.model import model_to_dict
from calibration.parameters import apply_step
from calibration.simulate import perturbed, random_configurations, simulate_measurements

SIGMA_M = 20e-6
TOOL = np.array([0.03, 0.0, 0.08, 0.0, 0.0, 0.0])  # a reflector 80 mm out and 30 mm off the flange axis


def machine() -> str:
    cpu = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem_kb = int(
            next(x for x in Path("/proc/meminfo").read_text().splitlines() if x.startswith("MemTotal")).split()[1]
        )
        mem = f"{mem_kb / 2**20:.1f} GiB"
    except (OSError, StopIteration):
        mem = "?"
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{os.cpu_count()} CPUs ({cpu}), {mem} RAM, Python {platform.python_version()}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}, OPENBLAS_NUM_THREADS={blas}; load average {load}"
    )


def scenario(seed: int = 7):
    rng = np.random.default_rng(seed)
    nominal = dataclasses.replace(robots.nominal("ur10e"), tool=TOOL)
    truth = perturbed(
        nominal,
        rng,
        base_length_m=2e-3,
        base_angle_rad=np.deg2rad(0.1),
        tool_length_m=0.5e-3,
        tool_angle_rad=np.deg2rad(0.1),
    )
    q_holdout = random_configurations(nominal, 2000, rng)
    return nominal, truth, rng, q_holdout, target_positions(truth, q_holdout)


def holdout_errors(model, q_holdout, p_true) -> tuple[float, float]:
    e = np.linalg.norm(target_positions(model, q_holdout) - p_true, axis=1)
    return float(np.sqrt(np.mean(e**2))), float(e.max())


def best_time(fn, repeat: int):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def peak_memory(fn) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def fd_baseline(result, data):
    """Plain least_squares, finite-difference Jacobian, same start, parameters and residuals."""
    start, params = result.start_model, list(result.params)

    def residuals(x):
        m = apply_step(start, params, x)
        return ((data.p_world - target_positions(m, data.q)) / SIGMA_M).reshape(-1)

    sol = least_squares(residuals, np.zeros(len(params)))  # jac="2-point", method="trf"
    return sol, apply_step(start, params, sol.x)


def cli_wall_time(nominal, truth, rng, rows: int = 4000, repeat: int = 3) -> float:
    """Whole-process wall time of `recal identify` on ``rows`` measurement rows (best of ``repeat``)."""
    data = simulate_measurements(truth, random_configurations(nominal, rows, rng), rng, sigma_m=SIGMA_M)
    u = nominal.units  # mm, deg
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        (d / "nominal.json").write_text(json.dumps(model_to_dict(nominal)))
        q = data.q / u.angle_rad
        p = data.p_world / u.length_m
        header = ",".join([f"q{i + 1}" for i in range(6)] + ["x", "y", "z"])
        lines = [header] + [",".join(f"{v:.10g}" for v in row) for row in np.hstack([q, p])]
        (d / "meas.csv").write_text("\n".join(lines) + "\n")
        exe = Path(sys.executable).with_name("recal")
        cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "service.cli"]
        cmd += [
            "identify",
            "--model",
            str(d / "nominal.json"),
            "--data",
            str(d / "meas.csv"),
            "--out",
            str(d / "out.json"),
            "--report",
            str(d / "report.json"),
        ]
        best = float("inf")
        for _ in range(repeat):
            t = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            best = min(best, time.perf_counter() - t)
    return best


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument(
        "--repeat", type=int, default=3, help="rounds of interleaved timed runs per size (the best is reported)"
    )
    ap.add_argument(
        "--baseline-max",
        type=int,
        default=100000,
        help="run the finite-difference baseline on at most this many rows (subsample above)",
    )
    ap.add_argument("--no-fd-memory", action="store_true", help="skip the traced run of the baseline (saves its time)")
    return ap.parse_args(argv)


def measure_size(N: int, nominal, truth, rng, q_holdout, p_true, args) -> tuple[dict, int]:
    """N rows simulated and identified by ours, the finite-difference baseline and in the true
    (poe) parameterisation: (the row of figures, how many parameters are not identifiable)."""
    data = simulate_measurements(truth, random_configurations(nominal, N, rng), rng, sigma_m=SIGMA_M)
    sub = data if N <= args.baseline_max else data.subset(np.arange(args.baseline_max))
    # interleaved, so that both see the same (shared, noisy) machine; the best of each is kept
    t_ours = t_fd = float("inf")
    for _ in range(args.repeat if N <= 10000 else 2):
        t, res = best_time(lambda data=data: identify(nominal, data, sigma_m=SIGMA_M), 3 if N <= 10000 else 1)
        t_ours = min(t_ours, t)
        t, (sol, m_fd) = best_time(lambda res=res, sub=sub: fd_baseline(res, sub), 1)
        t_fd = min(t_fd, t)
    mem_ours = peak_memory(lambda data=data: identify(nominal, data, sigma_m=SIGMA_M))
    rms, mx = holdout_errors(res.model, q_holdout, p_true)
    mem_fd = peak_memory(lambda res=res, sub=sub: fd_baseline(res, sub)) if not args.no_fd_memory else float("nan")
    rms_fd, _ = holdout_errors(m_fd, q_holdout, p_true)
    poe = identify(to_poe(nominal), data, sigma_m=SIGMA_M)
    rms_poe, _ = holdout_errors(poe.model, q_holdout, p_true)
    row = dict(
        N=N,
        t=t_ours,
        it=res.iterations,
        mem=mem_ours,
        rms=rms,
        max=mx,
        P=len(res.params),
        t_fd=t_fd,
        njev=sol.njev,
        mem_fd=mem_fd,
        rms_fd=rms_fd,
        n_fd=len(sub),
        rms_poe=rms_poe,
    )
    return row, len(res.unidentifiable)


def print_row(r: dict) -> None:
    N = r["N"]
    fd_note = "" if r["n_fd"] == N else f"  (FD on the first {r['n_fd']} rows)"
    print(
        f"{N:>7} | {r['t']:7.3f} {r['t'] / N * 1e6:6.1f} {r['it']:>4} {r['mem'] / 2**20:7.1f} {r['rms'] * 1e6:7.2f} "
        f"{r['max'] * 1e6:7.2f} | {r['t_fd']:7.3f} {r['njev']:>6} {r['mem_fd'] / 2**20:7.1f} {r['rms_fd'] * 1e6:7.2f} | "
        f"{r['t_fd'] / r['t'] * (N / r['n_fd']):7.1f}x | {r['rms_poe'] * 1e6:10.2f} {r['rms'] / r['rms_poe']:5.2f}"
        f"{fd_note}",
        flush=True,
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    print(f"machine: {machine()}")
    nominal, truth, rng, q_holdout, p_true = scenario()
    print(
        f"truth: {truth.name}; nominal hold-out error RMS {holdout_errors(nominal, q_holdout, p_true)[0] * 1e3:.3f} mm "
        f"(before registration); noise {SIGMA_M * 1e6:.0f} um per axis; hold-out 2000 noise-free configurations"
    )
    head = (
        f"{'N':>7} | {'ours s':>7} {'us/row':>6} {'iter':>4} {'peak MB':>7} {'RMS um':>7} {'max um':>7} | "
        f"{'FD s':>7} {'Jevals':>6} {'peak MB':>7} {'RMS um':>7} | {'speed-up':>8} | {'poe RMS um':>10} {'ratio':>5}"
    )
    for k, N in enumerate(args.sizes):
        r, unidentifiable = measure_size(N, nominal, truth, rng, q_holdout, p_true, args)
        if k == 0:
            print(f"free parameters: {r['P']} (ours and the baseline); {unidentifiable} not identifiable")
            print(head)
            print("-" * len(head))
        print_row(r)
    t_cli = cli_wall_time(nominal, truth, rng)
    print(
        f"\n`recal identify` on 4,000 rows, whole process (start, read, identify, write model and report): {t_cli:.2f} s"
    )
    print(
        "Notes: 'ours s' is the whole identify() call, 'FD s' the least_squares call alone, from our registered "
        "start; both are the best of interleaved runs (up to N = 10,000: --repeat rounds of 3 of ours and 1 of the "
        "baseline; above: 2 rounds of 1 and 1); 'speed-up' = FD time / ours "
        "(scaled by N / FD rows when the baseline ran on a subsample); peak MB = tracemalloc peak of one call "
        "(nan: not measured); RMS/max = hold-out position error against the noise-free truth; "
        "'poe RMS' = identifying in the true (poe) parameterisation on the same data, 'ratio' = ours / poe."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
