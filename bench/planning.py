"""Observation planning benchmark (``python bench/planning.py [--seeds 20] [--draws 10] [--random 10]``;
``--quick`` for a 4-cell smoke run).

A UR10e (every link perturbed: ``simulate.perturbed``, 0.5 mm / 0.05° / 0.1° offsets; base off by
2 mm and 0.1°, the reflector 0.5 mm off its nominal place) stands 2.5 m in front of a laser
tracker (noise 0.02 mm per axis). The reflector sits 30 mm off the flange axis, 80 mm out, and
faces along the tool z axis with a 30° acceptance cone; the beam must clear the arm's stick
figure by 50 mm; the reflector must be in a 3 m x 3 m x 1.9 m box in front of the tracker. For
each seed (a different robot, candidate set and hold-out set):

- 2,000 feasible candidate configurations;
- 30 poses planned (the default criterion D, I and the eigenvalue criteria) against
  ``--random`` designs of 30 poses drawn at random from the same candidates (random choice is a
  distribution of designs: one draw per cell compares against a lucky or unlucky draw);
- each design measured ``--draws`` times (fresh noise) and identified (``identify``, defaults);
  the hold-out error is the identified model's reflector position against the truth's (no
  measurement noise), averaged over the draws, on 1,000 fresh configurations of the working
  volume (reflector in the box, any orientation: where the robot will work) and on 1,000 of the
  measurable region (in the box and in sight: the candidates' own distribution);
- the expected hold-out RMS of each design: σ²(JᵀJ)⁻¹ propagated to the same 1,000 working-volume
  configurations, i.e. the mean of the simulated figure over infinitely many noise draws (for the
  linearised model), without the noise of a finite number of draws;
- the predicted RMS of each design (``planning.plan``'s own random evaluation configurations, not
  the hold-out set): what a technician sees before measuring.

The same cells compare the criteria (O1 is left out: at a fixed number of poses it gives D's
design). Then, on the first cell: how many random poses give the predicted accuracy of 30
planned ones; and planning times.

Prints Markdown (the tables of docs/benchmarks.md, section "Observation planning").
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # many small LAPACK calls: threads only cost here
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from calibration import planning, robots
from calibration.identify import identify
from calibration.kinematics import target_positions
from calibration.simulate import perturbed, simulate_measurements

SMR = np.array([0.03, 0.0, 0.08])
SIGMA_M = 20e-6
K = 30


def cell():
    nominal = dataclasses.replace(
        robots.nominal("ur10e"), targets={"smr": SMR}, base=np.array([2.5, 0.0, 0.0, 0.0, 0.0, np.pi])
    )
    sight = planning.LineOfSight(cone_rad=np.deg2rad(30), clearance_m=0.05, near_target_m=0.1)
    box = planning.Volume.box([1.0, -1.5, 0.1], [4.0, 1.5, 2.0])
    return nominal, sight, box


def truth_of(nominal, rng):
    t = perturbed(nominal, rng, base_length_m=2e-3 / np.sqrt(3), base_angle_rad=np.deg2rad(0.1) / np.sqrt(3))
    return dataclasses.replace(t, targets={"smr": SMR + rng.normal(0, 0.5e-3 / np.sqrt(3), 3)})


def holdout_errors(nominal, truth, q, holdouts, rng, draws):
    """Mean over ``draws`` noise draws of the hold-out RMS, p95 and max (m) of the model identified
    from measurements at ``q``, on each hold-out set: (3 · len(holdouts),)."""
    out = []
    for _ in range(draws):
        data = simulate_measurements(truth, q, rng, sigma_m=SIGMA_M, targets=("smr",))
        fit = identify(nominal, data, sigma_m=SIGMA_M)
        row = []
        for q_hold in holdouts:
            e = np.linalg.norm(
                target_positions(fit.model, q_hold, "smr") - target_positions(truth, q_hold, "smr"), axis=1
            )
            row += [np.sqrt(np.mean(e**2)), np.percentile(e, 95), e.max()]
        out.append(row)
    return np.mean(out, axis=0)


def predicted_rms(nominal, q, rng, box, evaluation=None):
    """The predicted RMS of a given design: plan over exactly its poses (on ``evaluation`` when
    given: the expected hold-out RMS there)."""
    return planning.plan(
        nominal,
        q,
        len(q),
        targets=("smr",),
        sigma_m=SIGMA_M,
        rng=rng,
        volume=box,
        evaluation=evaluation,
        exchange=False,
    ).predicted_rms_m


def fmt(values_m, digits=4):
    v = np.asarray(values_m) * 1e3
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return f"{med:.{digits}f} ({q1:.{digits}f}–{q3:.{digits}f})"


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


def poses_sweep(nominal, cand, box) -> None:
    """Predicted RMS of planned and random designs against the number of poses (first cell)."""
    rng = np.random.default_rng(9)
    print("\nPredicted RMS (mm) against the number of poses (first cell; random: median of 10 draws):\n")
    print("| poses | planned (I) | planned (D, default) | random | random / planned (I) |")
    print("|---|---|---|---|---|")
    for k in (10, 12, 15, 20, 30, 60):
        p = {
            c: planning.plan(
                nominal,
                cand,
                k,
                targets=("smr",),
                sigma_m=SIGMA_M,
                volume=box,
                criterion=c,
                rng=np.random.default_rng(1),
            ).predicted_rms_m
            for c in ("I", "D")
        }
        v = np.median(
            [
                predicted_rms(nominal, cand[rng.choice(len(cand), k, replace=False)], np.random.default_rng(1), box)
                for _ in range(10)
            ]
        )
        print(f"| {k} | {p['I'] * 1e3:.4f} | {p['D'] * 1e3:.4f} | {v * 1e3:.4f} | {v / p['I']:.2f} |")


CRITERIA = ("I", "D", "O3", "O4", "condition")  # O1 gives D's design (same determinant at fixed K)


def ratio_line(label, planned, random_mean, random_each) -> str:
    """Per-cell ratio of a planned design's figure to the mean of the cell's random designs, and how
    often it beats a single random design."""
    ratio = planned / random_mean
    wins = int(np.sum(planned[:, None] < random_each))
    return (
        f"| {label} | {np.median(ratio):.3f} | {ratio.min():.3f}–{ratio.max():.3f} | "
        f"{int(np.sum(ratio < 1))} of {len(ratio)} | {wins} of {random_each.size} |"
    )


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="simulated cells (default 20)")
    ap.add_argument("--draws", type=int, default=10, help="noise draws per design (default 10)")
    ap.add_argument("--random", type=int, default=10, help="random designs per cell (default 10)")
    ap.add_argument("--quick", action="store_true", help="4 cells, 4 draws, 4 random designs, no extra tables")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.draws, args.random = 4, 4, 4
    return args


@dataclasses.dataclass
class Cells:
    """What the simulated cells gave, per design name (the criteria, ``random0``..): per cell, the
    hold-out errors (working volume RMS, p95, max; measurable region RMS, p95, max) and the
    predictions (predicted RMS, p95, expected hold-out RMS); the planning and candidate times; the
    first cell's candidates and its I design."""

    err: dict[str, list]
    pred: dict[str, list]
    t_plan: dict[str, list[float]]
    t_gen: list[float]
    keep: dict


def designs_of(nominal, cand, box, seed: int, rng, n_random: int, t_plan: dict) -> dict:
    """A cell's designs of ``K`` poses: one planned per criterion (its time added to ``t_plan``),
    and ``n_random`` drawn at random from the same candidates."""
    designs = {}
    for crit in CRITERIA:
        t0 = time.perf_counter()
        designs[crit] = planning.plan(
            nominal,
            cand,
            K,
            targets=("smr",),
            sigma_m=SIGMA_M,
            criterion=crit,
            volume=box,
            rng=np.random.default_rng(seed),
        )
        t_plan[crit].append(time.perf_counter() - t0)
    for k in range(n_random):
        designs[f"random{k}"] = planning.plan(
            nominal,
            cand[rng.choice(len(cand), K, replace=False)],
            K,
            targets=("smr",),
            sigma_m=SIGMA_M,
            volume=box,
            rng=np.random.default_rng(seed),
            exchange=False,
        )
    return designs


def simulate_cells(args, nominal, sight, box) -> Cells:
    """Every cell (``--seeds``): its truth, candidates and hold-out sets, its designs, each measured
    and identified ``--draws`` times; a line per cell on stderr."""
    R = args.random
    names = (*CRITERIA, *(f"random{k}" for k in range(R)))
    out = Cells({name: [] for name in names}, {name: [] for name in names}, {c: [] for c in CRITERIA}, [], {})
    err, pred = out.err, out.pred
    for seed in range(args.seeds):
        rng = np.random.default_rng(1000 + seed)
        truth = truth_of(nominal, rng)
        t0 = time.perf_counter()
        cand = planning.generate_candidates(nominal, 2000, rng, targets=("smr",), volume=box, sight=sight)
        out.t_gen.append(time.perf_counter() - t0)
        q_work = planning.generate_candidates(nominal, 1000, rng, targets=("smr",), volume=box)
        q_seen = planning.generate_candidates(nominal, 1000, rng, targets=("smr",), volume=box, sight=sight)
        designs = designs_of(nominal, cand, box, seed, rng, R, out.t_plan)
        for name, r in designs.items():
            # the same noise draws for every design of a cell (common random numbers)
            err[name].append(
                holdout_errors(nominal, truth, r.q, (q_work, q_seen), np.random.default_rng(5000 + seed), args.draws)
            )
            pred[name].append((r.predicted_rms_m, r.predicted_p95_m, predicted_rms(nominal, r.q, None, box, q_work)))
        if seed == 0:
            out.keep = dict(cand=cand, res=designs["I"])
        rnd = np.mean([err[f"random{k}"][-1][0] for k in range(R)])
        print(
            f"seed {seed}: "
            + ", ".join(f"{n} {err[n][-1][0] * 1e3:.4f}" for n in CRITERIA)
            + f", random (mean of {R}) {rnd * 1e3:.4f} mm",
            file=sys.stderr,
        )
    return out


def print_planned_vs_random(args, E, PR, rand_E, rand_PR) -> None:
    """The tables "Planned against random: 30 poses": the figures, the per-cell ratios, and the
    prediction against the simulated hold-out."""
    print(f"Machine: {machine()}.\n")
    print(
        f"{args.seeds} cells; per cell {len(CRITERIA)} planned designs and {args.random} random designs of {K} poses, "
        f"each measured {args.draws} times (the same noise draws for every design of a cell). Hold-out (noise-free, "
        "1,000 fresh configurations per cell): the working volume (reflector in the box, any orientation) and the "
        "measurable region (in the box and in sight of the tracker: the candidates' distribution). Random: the "
        "mean over the cell's random designs. Median (interquartile range) over the cells, mm.\n"
    )
    print(
        "| 30 poses | working volume: RMS | p95 | max | measurable region: RMS | max | expected RMS (working volume) "
        "| predicted RMS |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, label in (
        ("I", "planned (I)"),
        ("D", "planned (D, default)"),
        ("random", "random from the same candidates"),
    ):
        e, p = E[name], PR[name]
        print(
            f"| {label} | {fmt(e[:, 0])} | {fmt(e[:, 1])} | {fmt(e[:, 2])} | {fmt(e[:, 3])} | {fmt(e[:, 5])} | "
            f"{fmt(p[:, 2])} | {fmt(p[:, 0])} |"
        )
    print(
        "\nPlanned / random, per cell (planned against the mean of the cell's random designs; last column: "
        "against each random design alone):\n"
    )
    print("| figure | median ratio | range | cells better | single random designs beaten |")
    print("|---|---|---|---|---|")
    for crit in ("I", "D"):
        for label, col, src, rs in (
            ("working volume, RMS", 0, E, rand_E),
            ("working volume, max", 2, E, rand_E),
            ("measurable region, RMS", 3, E, rand_E),
            ("expected RMS, working volume", 2, PR, rand_PR),
        ):
            print(ratio_line(f"{crit}: {label}", src[crit][:, col], src["random"][:, col], rs[:, :, col].T))
    print(
        f"\nPredicted/actual RMS over the working volume (medians): planned (I) "
        f"{np.median(PR['I'][:, 0] / E['I'][:, 0]):.3f}, "
        f"random {np.median(rand_PR[:, :, 0] / rand_E[:, :, 0]):.3f}.\n"
    )


def print_criteria(E, PR, t_plan) -> None:
    print("Criteria (same cells, 30 poses; medians over the cells, mm; time: planning, median):\n")
    print(
        "| criterion | predicted RMS | predicted p95 | expected hold-out RMS | hold-out RMS (working volume) | "
        "hold-out max | planning time (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in (*CRITERIA, "random"):
        tp = f"{np.median(t_plan[name]):.2f}" if name in t_plan else "–"
        print(
            f"| {name} | {np.median(PR[name][:, 0]) * 1e3:.4f} | {np.median(PR[name][:, 1]) * 1e3:.4f} | "
            f"{np.median(PR[name][:, 2]) * 1e3:.4f} | {np.median(E[name][:, 0]) * 1e3:.4f} | "
            f"{np.median(E[name][:, 2]) * 1e3:.4f} | {tp} |"
        )


def random_poses_needed(nominal, cand, res, box) -> None:
    """How many random poses match 30 planned ones (predicted), on the first cell's candidates."""
    rng = np.random.default_rng(7)
    print(
        "\nRandom poses needed to match the predicted accuracy of 30 planned ones (first cell, median of 10 draws):\n"
    )
    print("| random poses | predicted RMS (mm) |")
    print("|---|---|")
    for k in (30, 40, 50, 60, 80):
        v = [predicted_rms(nominal, cand[rng.choice(len(cand), k, replace=False)], rng, box) for _ in range(10)]
        print(f"| {k} | {np.median(v) * 1e3:.4f} |")
    print(f"| 30 planned (I) | {res.predicted_rms_m * 1e3:.4f} |")


def planning_times(nominal) -> None:
    print("\nPlanning time (greedy + exchange; candidates drawn without constraints):\n")
    print("| candidates | poses | I: time (s) | swaps | D: time (s) | swaps |")
    print("|---|---|---|---|---|---|")
    for n_c, k in ((2000, 30), (5000, 30), (5000, 60)):
        c = planning.generate_candidates(nominal, n_c, np.random.default_rng(n_c), targets=("smr",))
        cells = []
        for crit in ("I", "D"):
            t0 = time.perf_counter()
            r = planning.plan(nominal, c, k, targets=("smr",), sigma_m=SIGMA_M, criterion=crit)
            cells.append(f"{time.perf_counter() - t0:.2f} | {r.swaps}")
        print(f"| {n_c} | {k} | {' | '.join(cells)} |")


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    nominal, sight, box = cell()
    sim = simulate_cells(args, nominal, sight, box)
    E = {n: np.array(v) for n, v in sim.err.items()}
    PR = {n: np.array(v) for n, v in sim.pred.items()}
    rand_E = np.stack([E[f"random{k}"] for k in range(args.random)], axis=0)  # (R, cells, 6)
    rand_PR = np.stack([PR[f"random{k}"] for k in range(args.random)], axis=0)
    E["random"], PR["random"] = rand_E.mean(axis=0), rand_PR.mean(axis=0)

    print_planned_vs_random(args, E, PR, rand_E, rand_PR)
    print_criteria(E, PR, sim.t_plan)
    if args.quick:
        print(f"\nWhole benchmark {time.perf_counter() - t_start:.0f} s.")
        return 0
    random_poses_needed(nominal, sim.keep["cand"], sim.keep["res"], box)
    poses_sweep(nominal, sim.keep["cand"], box)
    planning_times(nominal)
    print(
        f"\nCandidate generation with the line-of-sight and volume tests: median {np.median(sim.t_gen):.2f} s "
        f"for 2,000 candidates; whole benchmark {time.perf_counter() - t_start:.0f} s."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
