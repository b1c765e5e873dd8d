"""Compensation benchmark (``python bench/compensate.py [--points 100000] [--repeat 2]``).

A UR10e as ``recal identify`` describes it after calibration: the nominal DH model with
Hayati links on the parallel axes 2-3-4, every link parameter off by a little (0.5 mm lengths,
0.05° twists, 0.1° joint offsets) and the base where the tracker sees it (1.9 m away, turned
130°). The task: N points planned on the nominal model, to be reached in the world:
``X_d = T_nominal_world⁻¹ · F_nominal(q_planned)``.

Two task sets: "typical" configurations (arm bent 25°-155° at the elbow, shoulder -160°..-20°,
wrist 25°-155° away from its singularity, the rest anywhere) and "anywhere" (every joint uniform
in ±180°, singularities included).

Reported, per mode (best of ``--repeat`` runs; the machine is shared):

- time of the whole batch (joints: nominal closed form + Newton on the identified model + flags;
  targets: Algorithm B through the nominal closed form + flags), and of the book's Algorithm A
  (nominal-Jacobian chord iteration) for comparison;
- accuracy reached, checked independently of the solvers: the identified model's forward
  kinematics at the commands (joints) or at what the nominal closed form makes of the corrected
  targets (targets), against ``X_d``;
- convergence, iterations and flags;
- the wall time of ``recal compensate`` on the same task as a CSV file (read, compensate, write);
- a robot without a closed-form inverse (a PUMA 560 with the same kind of errors): joints mode
  started from the numerical nominal inverse (``ik.numerical_ik``), for task rows that carry
  their planned joints and for pose-only rows solved from one ``--qnear`` (``--puma-points``).

Prints Markdown (docs/benchmarks.md, section "Compensation").
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from calibration import robots
from calibration.compensation import (
    FLAGS,
    compensate_joints,
    compensate_targets,
    frame_map,
    inverse_jacobian_iteration,
    nominal_solution,
)
from calibration.conventions import hayati_for_parallel_axes
from calibration.ik import inverse_kinematics
from calibration.kinematics import fk
from calibration.model import model_to_dict
from calibration.parameters import apply_step, candidate_parameters
from calibration.transforms import matrix_to_quat, matrix_to_rotvec


def identified(robot: str, *, seed: int, base, q_range_rad: float):
    """``robot`` as identification describes it (Hayati links, every link parameter off), its
    base ``base`` (x, y, z m, rx, ry, rz rad) from the tracker; and the nominal's frame in that
    world, fitted over configurations within ±``q_range_rad``."""
    rng = np.random.default_rng(seed)
    nominal = robots.nominal(robot)
    m, _ = hayati_for_parallel_axes(nominal)
    params = candidate_parameters(m, base=False, tool=False)
    sig = [
        0.5e-3 if p.kind == "length" else np.deg2rad(0.1) if p.name.endswith(".theta") else np.deg2rad(0.05)
        for p in params
    ]
    m = apply_step(m, params, rng.normal(0.0, sig))
    ident = dataclasses.replace(m, base=np.asarray(base, dtype=float), name=f"{robot}-identified")
    return nominal, ident, frame_map(ident, nominal, rng.uniform(-q_range_rad, q_range_rad, (256, 6)))


def identified_ur10e():
    return identified("ur10e", seed=1, base=[1.8, -0.6, 0.3, 0.002, -0.004, np.deg2rad(130.0)], q_range_rad=np.pi)


def identified_puma():
    """A PUMA 560, the base 1.5 m from the tracker and turned."""
    return identified("puma560", seed=3, base=[1.5, 0.3, 0.2, 0.001, 0.002, np.deg2rad(60.0)], q_range_rad=1.5)


def puma_configurations(kind: str, n: int, seed: int = 4) -> np.ndarray:
    """ "typical": a task region (shoulder bent, elbow bent 25-85° from stretched, wrist 20-90°
    from its singularity: one elbow and one wrist branch); "anywhere": uniform within the joint
    limits (revolute joints within ±180°), singular zones included."""
    rng = np.random.default_rng(seed)
    if kind == "typical":
        lo, hi = np.radians([-90, -80, 115, -90, 20, -180]), np.radians([90, -10, 175, 90, 90, 180])
    else:
        lim = np.clip(robots.nominal("puma560").joint_limits, -np.pi, np.pi)
        lo, hi = lim[:, 0], lim[:, 1]
    return rng.uniform(lo, hi, (n, 6))


def run_puma(n: int, repeat: int) -> None:
    nominal, ident, M = identified_puma()
    print(f"### {n:,} task points, PUMA 560 (no closed-form inverse)\n")
    print(
        "| task rows | time (s) | converged | reached position (µm): median / max over converged | "
        "iterations (nominal inverse), mean | the planned configuration found | flags |"
    )
    print("|---|---|---|---|---|---|---|")
    for kind in ("typical", "anywhere"):
        q = puma_configurations(kind, n)
        X = np.linalg.inv(M) @ fk(nominal, q)
        q_near = np.radians([0, -45, 145, 0, 55, 0]) if kind == "typical" else np.radians([0, -90, 90, 0, 45, 0])
        for rows, start, keep in (("with their planned q1..q6", q, True), ("pose only, one --qnear", q_near, False)):
            if kind == "anywhere" and keep:
                continue  # the same as typical: Newton from the planned joints

            def joints(X=X, start=start, keep=keep):
                sol = nominal_solution(nominal, M @ X, start, keep_branch=keep)
                return sol, compensate_joints(
                    ident, X, sol.q, reachable=sol.reachable, branch_changed=sol.branch_changed
                )

            t, (sol, c) = best_of(repeat, joints)
            dp, _ = reach(ident, c.q, X)
            ok = c.converged
            same = np.mean(np.max(np.abs(sol.q - q), axis=1) < 1e-6)
            flags = ", ".join(f"{f} {c.count(f)}" for f in FLAGS if c.count(f))
            print(
                f"| {kind}, {rows} | {t:.2f} | {ok.mean() * 100:.2f}% | {fmt_um(np.median(dp[ok]))} / "
                f"{fmt_um(dp[ok].max())} | {sol.iterations.mean():.1f} | {same * 100:.1f}% | {flags} |"
            )
    print()


def configurations(kind: str, n: int, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    if kind == "typical":
        q[:, 1] = rng.uniform(np.deg2rad(-160), np.deg2rad(-20), n)
        q[:, 2] = rng.uniform(np.deg2rad(25), np.deg2rad(155), n) * rng.choice([-1, 1], n)
        q[:, 4] = rng.uniform(np.deg2rad(25), np.deg2rad(155), n) * rng.choice([-1, 1], n)
    return q


def best_of(repeat, fn):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def reach(model, q, X):
    T = fk(model, q)
    dp = np.linalg.norm(T[:, :3, 3] - X[:, :3, 3], axis=1)
    dr = np.linalg.norm(matrix_to_rotvec(T[:, :3, :3] @ np.swapaxes(X[:, :3, :3], 1, 2)), axis=1)
    return dp, dr


def fmt_um(x):
    return f"{x * 1e6:.3g}"


def run_set(kind, n, repeat, nominal, ident, M):
    q = configurations(kind, n)
    X = np.linalg.inv(M) @ fk(nominal, q)
    before, _ = reach(ident, q, X)
    rows = []

    def joints():
        start = nominal_solution(nominal, M @ X, q)
        return compensate_joints(ident, X, start.q, reachable=start.reachable)

    tj, cj = best_of(repeat, joints)
    dp, dr = reach(ident, cj.q, X)
    rows.append(("joints (Newton on the identified model)", tj, cj, dp, dr))

    tt, ct = best_of(repeat, lambda: compensate_targets(ident, nominal, X, q, T_nominal_world=M))
    ctrl = inverse_kinematics(nominal, ct.T_command, q)  # the controller, on the corrected targets
    dp_t, dr_t = reach(ident, ctrl.q, X)
    rows.append(("targets (Algorithm B, nominal closed form)", tt, ct, dp_t, dr_t))

    ta, (qa, ia, conv_a) = best_of(1, lambda: inverse_jacobian_iteration(ident, nominal, X, q, T_nominal_world=M))
    dp_a, dr_a = reach(ident, qa, X)
    return q, X, before, rows, (ta, qa, ia, conv_a, dp_a, dr_a)


def cli_time(n, nominal, ident, M, q, X):
    """Wall time of `recal compensate` on an n-row task CSV (mm, deg), joints and targets."""
    import json

    from service.files import save_model

    out = {}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        save_model(
            d / "identified.json",
            dataclasses.replace(ident, units=nominal.units),
            {"identification": {"nominal": model_to_dict(nominal)}},
        )
        quat = matrix_to_quat(X[:n, :3, :3])
        pos = X[:n, :3, 3] * 1000
        qd = np.degrees(q[:n])
        with open(d / "task.csv", "w") as f:
            f.write("x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6\n")
            for i in range(n):
                f.write(
                    ",".join(f"{v:.6f}" for v in pos[i])
                    + ","
                    + ",".join(f"{v:.12f}" for v in quat[i])
                    + ","
                    + ",".join(f"{v:.8f}" for v in qd[i])
                    + "\n"
                )
        exe = Path(sys.executable).with_name("recal")
        cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "service.cli"]
        for mode in ("joints", "targets"):
            t = time.perf_counter()
            r = subprocess.run(
                [
                    *cmd,
                    "compensate",
                    "--model",
                    "identified.json",
                    "--task",
                    "task.csv",
                    "--out",
                    "out.csv",
                    "--mode",
                    mode,
                    "--report",
                    "r.json",
                ],
                cwd=d,
                capture_output=True,
                text=True,
                check=False,  # the exit status is one of the figures
            )
            out[mode] = (
                time.perf_counter() - t,
                r.returncode,
                r.stdout.strip(),
                json.loads((d / "r.json").read_text())["summary"] if r.returncode == 0 else r.stderr,
            )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--cli-points", type=int, default=100_000)
    ap.add_argument("--puma-points", type=int, default=20_000, help="PUMA 560 (numerical inverse) task points")
    ap.add_argument("--no-ur", action="store_true", help="only the PUMA 560 section")
    args = ap.parse_args(argv)
    nominal, ident, M = identified_ur10e()
    print(
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; Python "
        f"{platform.python_version()}, numpy {np.__version__}.\n"
    )
    cli_inputs = None
    for kind in () if args.no_ur else ("typical", "anywhere"):
        q, X, before, rows, alg_a = run_set(kind, args.points, args.repeat, nominal, ident, M)
        if kind == "typical":
            cli_inputs = (q, X)
        print(f"### {args.points:,} task points, {kind} configurations\n")
        print(
            f"Before compensation the identified robot misses by median {np.median(before) * 1e3:.2f} mm, "
            f"max {before.max() * 1e3:.2f} mm.\n"
        )
        print(
            "| mode | time (s) | converged | reached position (µm): median / p99.9 / max over converged | "
            "orientation max (µrad) | iterations median / max | flags |"
        )
        print("|---|---|---|---|---|---|---|")
        for name, t, c, dp, dr in rows:
            ok = c.converged
            flags = ", ".join(f"{f} {c.count(f)}" for f in FLAGS if c.count(f))
            print(
                f"| {name} | {t:.2f} | {ok.mean() * 100:.2f}% | {fmt_um(np.median(dp[ok]))} / "
                f"{fmt_um(np.percentile(dp[ok], 99.9))} / {fmt_um(dp[ok].max())} | {dr[ok].max() * 1e6:.3g} | "
                f"{int(np.median(c.iterations))} / {int(c.iterations.max())} | {flags} |"
            )
        ta, qa, ia, conv_a, dp_a, dr_a = alg_a
        clean = rows[0][2].converged & conv_a & (rows[0][2].flags == 0)
        agree = np.degrees(np.abs(qa[clean] - rows[0][2].q[clean])).max()
        agree_b = np.degrees(np.abs(rows[1][2].q[clean] - rows[0][2].q[clean])).max()
        print(
            f"| book Algorithm A (nominal Jacobian) | {ta:.2f} | {conv_a.mean() * 100:.2f}% | "
            f"{fmt_um(np.median(dp_a[conv_a]))} / {fmt_um(np.percentile(dp_a[conv_a], 99.9))} / "
            f"{fmt_um(dp_a[conv_a].max())} | {dr_a[conv_a].max() * 1e6:.3g} | "
            f"{int(np.median(ia))} / {int(ia.max())} | |\n"
        )
        print(
            f"Cross-method agreement (T17) on the {clean.sum():,} unflagged points: Algorithm A vs Newton "
            f"max {agree:.2g}°, Algorithm B vs Newton max {agree_b:.2g}°.\n"
        )
    if args.puma_points:
        run_puma(args.puma_points, args.repeat)
    if args.cli_points and cli_inputs is not None:
        q, X = cli_inputs
        res = cli_time(min(args.cli_points, len(q)), nominal, ident, M, q, X)
        print(f"### `recal compensate` on a {min(args.cli_points, len(q)):,}-row task CSV (whole process)\n")
        print("| mode | wall time (s) | summary |")
        print("|---|---|---|")
        for mode, (t, _rc, _out, summary) in res.items():
            s = (
                summary
                if isinstance(summary, str)
                else (f"{summary['converged']:,} converged, residual max {summary['residual_max']:.3g} mm")
            )
            print(f"| {mode} | {t:.1f} | {s} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
