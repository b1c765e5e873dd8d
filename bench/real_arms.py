"""Recal on public measured data of UR-class arms (issue 28, second "done when" bullet).

Two public data sets, read where the user keeps them (never copied into this repository):

- ``ur10``: Landgraf et al. (2021), https://github.com/christianlandgraf/ipa-robot-accuracy
  (MIT): a UR10 measured with a Leica AT960 laser tracker and a T-Mac (full 6-D pose).
  ``Series_C/measurements_random_poses.csv`` has 2,773 random poses (``--series`` picks another).
- ``ur5``: Jacobi (2025), https://github.com/pauljac7700/serial_robots_datasets (MIT): a UR5
  measured with an API GTS3800 tracker at one SMR, 1,000 grid poses
  (``UR5/3D_UR5_uncalibrated_grid_cleaned.csv``).

The script converts the data set to Recal's files (a nominal model of the CB-series arm from its
data sheet, a ``recal.measurements/1`` CSV), splits the poses once, seeded, into 80 % for
identification and 20 % held out, and runs the real CLI on them:

1. ``recal identify`` (the geometric model alone), validated on the held-out 20 %;
2. ``recal identify --residual-map auto``: the nested 5-fold cross-validation of every family on
   the 80 % (each family's CV RMS, the family kept), and the hold-out 20 % with the kept correction.

It prints one table (hold-out RMS, the nested-CV RMS per family, the 95 % bound's coverage on
the hold-out). Nothing is tuned on the hold-out.

Run: ``python bench/real_arms.py ur10 /work/data/ur10_landgraf`` or
``python bench/real_arms.py ur5 /work/data/ur5_jacobi`` (add ``--work DIR`` to keep the files).
``python bench/real_arms.py ur10 DIR --series B --apply-to C`` identifies on all of Series B and
holds out all of Series C, whose joint ranges are disjoint from B's: the region check.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from calibration.transforms import matrix_to_quat, rot

# CB-series data sheets (Universal Robots' published DH parameters, mm and degrees): the public
# data are of a UR10 and a UR5 (not the e-series in the robot library).
CB_SERIES_DH_MM = {
    "ur10": {"d": (127.3, 0.0, 0.0, 163.941, 115.7, 92.2), "a": (0.0, -612.0, -572.3, 0.0, 0.0, 0.0)},
    "ur5": {"d": (89.159, 0.0, 0.0, 109.15, 94.65, 82.3), "a": (0.0, -425.0, -392.25, 0.0, 0.0, 0.0)},
}
ALPHA_DEG = (90.0, 0.0, 0.0, 90.0, -90.0, 0.0)
HOLDOUT_SHARE = 0.2
SEED = 20261128


def nominal_model(arm: str, tool: list[float], targets: dict[str, list[float]]) -> dict:
    """A ``recal.model/1`` document of a CB-series arm from its data sheet."""
    dh = CB_SERIES_DH_MM[arm]
    joints = [
        {
            "name": f"j{i + 1}",
            "type": "revolute",
            "theta": 0.0,
            "d": dh["d"][i],
            "a": dh["a"][i],
            "alpha": ALPHA_DEG[i],
            "lower": -360.0,
            "upper": 360.0,
        }
        for i in range(6)
    ]
    return {
        "format": "recal.model/1",
        "name": f"{arm}-nominal",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "base": [0.0] * 6,
        "joints": joints,
        "tool": tool,
        "targets": targets,
    }


def _decimal_comma(text: str) -> float:
    return float(text.replace(",", "."))


def ur10_rows(root: Path, series: str) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """Joint readings (deg), the T-Mac's position (mm) and orientation (qw, qx, qy, qz) in the tracker frame.

    The files use ';' and decimal commas; the tracker's orientation is intrinsic X-Y-Z Euler
    angles in degrees (the data set's own ``dataset.py`` reads them with ``from_euler('XYZ')``).
    """
    names = {
        "A": "measurements_grid.csv",
        "B": "measurements_joint_configurations.csv",
        "C": "measurements_random_poses.csv",
    }
    path = root / f"Series_{series}" / names[series]
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f, delimiter=";"))
    joints = [
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    ]
    q_deg = np.degrees([[_decimal_comma(r[j]) for j in joints] for r in rows])
    p_mm = np.array([[_decimal_comma(r[f"measurement_{a}"]) for a in "xyz"] for r in rows])
    e_rad = np.radians([[_decimal_comma(r[f"measurement_r{a}"]) for a in "xyz"] for r in rows])
    R = rot(0, e_rad[:, 0]) @ rot(1, e_rad[:, 1]) @ rot(2, e_rad[:, 2])
    stamps = [r["Timestamp"] for r in rows]
    return stamps, np.column_stack([q_deg, p_mm]), matrix_to_quat(R)


def ur5_rows(root: Path, sign: float) -> np.ndarray:
    """Joint readings (deg) and the SMR's measured position (mm) in the registered base frame.

    The data give the commanded target ``x_t`` and ``x_dif`` ("the difference between the target
    and the achieved position"); the achieved position is ``x_t + sign * x_dif``. The README does
    not say which sign: ``--ur5-sign`` picks it, and the default was chosen by the geometric
    fit's residual on the identification rows only (see docs/benchmarks.md).
    """
    path = root / "UR5" / "3D_UR5_uncalibrated_grid_cleaned.csv"
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    q_deg = np.array([[float(r[f"joint_{i}"]) for i in range(1, 7)] for r in rows])
    target = np.array([[float(r[f"{a}_t"]) for a in "xyz"] for r in rows])
    dif = np.array([[float(r[f"{a}_dif"]) for a in "xyz"] for r in rows])
    return np.column_stack([q_deg, target + sign * dif])


def write_measurements(path: Path, q_p: np.ndarray, quat: np.ndarray | None, target: str) -> None:
    header = ["q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z"]
    if quat is not None:
        header += ["qw", "qx", "qy", "qz"]
    header += ["target", "pose_id"]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for i, row in enumerate(q_p):
            extra = [f"{v:.10g}" for v in quat[i]] if quat is not None else []
            w.writerow([f"{v:.10g}" for v in row] + extra + [target, i])


def split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """One seeded split of the poses: (identification, hold-out) indices."""
    order = np.random.default_rng(SEED).permutation(n)
    n_hold = int(round(HOLDOUT_SHARE * n))
    return np.sort(order[n_hold:]), np.sort(order[:n_hold])


def run_identify(work: Path, tag: str, extra: list[str], sigma: list[str]) -> dict:
    recal = Path(sys.executable).with_name("recal")
    report = work / f"report_{tag}.json"
    cmd = [str(recal), "identify", "--model", str(work / "nominal.json"), "--data", str(work / "train.csv"),
           "--validate", str(work / "holdout.csv"), "--out", str(work / f"model_{tag}.json"),
           "--report", str(report), *sigma, *extra]  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)  # exit 3 is an answer too
    elapsed = time.perf_counter() - t0
    print(f"$ {' '.join(cmd[1:])}\n  exit {done.returncode} in {elapsed:.0f} s\n  {done.stdout.strip()}")
    if done.stderr.strip():
        print("  stderr: " + done.stderr.strip().replace("\n", "\n  stderr: "))
    out = json.loads(report.read_text()) if report.exists() else {}
    out["_exit"], out["_elapsed_s"] = done.returncode, elapsed
    return out


def holdout_coverage(work: Path, tag: str, target: str, sigma_mm: float) -> dict:
    """The hold-out errors of ``recal predict`` with the model ``tag`` (its correction applied) against its 95 % bound.

    ``predict --uncertainty`` gives u95, the model's own 95 % radius; the instrument's noise is
    added as ``identify --validate`` does: inside when ``|e|^2 <= u95^2 + chi2_3(0.95) sigma^2``.
    """
    recal = Path(sys.executable).with_name("recal")
    out = work / f"predict_{tag}.csv"
    cmd = [str(recal), "predict", "--model", str(work / f"model_{tag}.json"), "--joints", str(work / "holdout.csv"),
           "--uncertainty", "--quiet", "--out", str(out)] + (["--target", target] if target else [])  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)  # exit 3 is an answer too
    if done.returncode not in (0, 3) or not out.exists():
        return {"error": done.stderr.strip()}
    with out.open(newline="") as f:
        pred = list(csv.DictReader(f))
    with (work / "holdout.csv").open(newline="") as f:
        meas = list(csv.DictReader(f))
    e = np.array([[float(m[a]) - float(p[a]) for a in "xyz"] for m, p in zip(meas, pred, strict=True)])
    u95 = np.array([float(p["u95"]) for p in pred])
    outside = np.array(["outside" in p["flags"] for p in pred])
    err = np.linalg.norm(e, axis=1)
    inside = err**2 <= u95**2 + 7.8147 * sigma_mm**2
    return {
        "rms": float(np.sqrt(np.mean(err**2))),
        "covered": float(np.mean(inside)),
        "covered_in_region": float(np.mean(inside[~outside])) if np.any(~outside) else float("nan"),
        "flagged_outside": int(np.sum(outside)),
        "median_u95": float(np.median(u95)),
    }


def prepare(args: argparse.Namespace, work: Path) -> tuple[list[str], str]:
    """Write nominal.json, train.csv and holdout.csv; return the sigma options and a description."""
    if args.arm == "ur10" and args.apply_to:
        return prepare_across_series(args, work)
    if args.arm == "ur10":
        _, q_p, quat = ur10_rows(Path(args.data), args.series)
        # The T-Mac frame sits about 109 mm beyond the flange (the data set's Trafo_TM_F_init.txt);
        # the identification finds the rest (full-pose rows determine the whole tool frame).
        model = nominal_model("ur10", [0.0, 0.0, 109.0, 0.0, 0.0, 0.0], {})
        target = ""
        sigma = ["--sigma", str(args.sigma), "--sigma-angle", str(args.sigma_angle)]
        what = f"UR10, Series {args.series}: {len(q_p)} full poses (AT960 + T-Mac)"
    else:
        q_p, quat = ur5_rows(Path(args.data), args.ur5_sign), None
        model = nominal_model("ur5", [0.0] * 6, {"smr": [0.0, 0.0, 0.0]})
        target = "smr"
        sigma = ["--sigma", str(args.sigma)]
        what = f"UR5: {len(q_p)} grid poses (GTS3800, one SMR, x = x_t {'+' if args.ur5_sign > 0 else '-'} x_dif)"
    fit, hold = split(len(q_p))
    (work / "nominal.json").write_text(json.dumps(model, indent=1))
    write_measurements(work / "train.csv", q_p[fit], None if quat is None else quat[fit], target)
    write_measurements(work / "holdout.csv", q_p[hold], None if quat is None else quat[hold], target)
    return sigma, f"{what}; identification {len(fit)}, hold-out {len(hold)} (seeded split)"


def prepare_across_series(args: argparse.Namespace, work: Path) -> tuple[list[str], str]:
    """``--apply-to``: every pose of ``--series`` for identification, every pose of the other
    series held out (issue 28: a correction fitted on one series made another, with disjoint
    joint ranges, worse). Both series are in the same tracker frame (the data set's own
    ``dataset.py`` reads them alike); what differs is the region of joint space."""
    _, q_p, quat = ur10_rows(Path(args.data), args.series)
    _, q_p_other, quat_other = ur10_rows(Path(args.data), args.apply_to)
    model = nominal_model("ur10", [0.0, 0.0, 109.0, 0.0, 0.0, 0.0], {})
    (work / "nominal.json").write_text(json.dumps(model, indent=1))
    write_measurements(work / "train.csv", q_p, quat, "")
    write_measurements(work / "holdout.csv", q_p_other, quat_other, "")
    ranges = "; ".join(
        f"{name}: j1 {q[:, 0].min():.0f} to {q[:, 0].max():.0f} deg"
        for name, q in ((args.series, q_p), (args.apply_to, q_p_other))
    )
    sigma = ["--sigma", str(args.sigma), "--sigma-angle", str(args.sigma_angle)]
    return sigma, (
        f"UR10 across series: identified on all {len(q_p)} poses of Series {args.series}, "
        f"applied to all {len(q_p_other)} of Series {args.apply_to} ({ranges})"
    )


def across_series_check(work: Path) -> dict:
    """Pose by pose on the other series: the corrected model's error against the geometric
    model's, and whether every pose where they differ is inside the correction's region (issue 28:
    outside it, nothing worse than the geometric model, and flagged)."""
    out = {}
    for tag in ("geometric", "auto"):
        with (work / f"predict_{tag}.csv").open(newline="") as f:
            out[tag] = list(csv.DictReader(f))
    with (work / "holdout.csv").open(newline="") as f:
        meas = list(csv.DictReader(f))
    err = {
        tag: np.linalg.norm(
            [[float(m[a]) - float(p[a]) for a in "xyz"] for m, p in zip(meas, rows, strict=True)], axis=1
        )
        for tag, rows in out.items()
    }
    flagged = np.array(["outside" in p["flags"] for p in out["auto"]])
    differs = np.abs(err["auto"] - err["geometric"]) > 1e-9
    return {
        "poses": len(meas),
        "flagged_outside": int(flagged.sum()),
        "rms_geometric": float(np.sqrt(np.mean(err["geometric"] ** 2))),
        "rms_corrected": float(np.sqrt(np.mean(err["auto"] ** 2))),
        "flagged_poses_differing_from_geometric": int(np.sum(differs & flagged)),
        "unflagged_poses": int(np.sum(~flagged)),
        "unflagged_worse_than_geometric": int(np.sum((err["auto"] > err["geometric"] + 1e-9) & ~flagged)),
    }


def summary(name: str, rep: dict) -> list[str]:
    val = rep.get("validation", {})
    lines = [
        f"{name}: exit {rep['_exit']}, {rep['_elapsed_s']:.0f} s; hold-out RMS {val.get('rms', float('nan')):.4f} mm"
        f" (max {val.get('max', float('nan')):.3f}), inside the predicted 95 % bound"
        f" {100 * val.get('inside_predicted_95', float('nan')):.1f} %;"
        f" before {val.get('before', {}).get('rms', float('nan')):.3f} mm"
    ]
    rm = rep.get("residual_map")
    if rm:
        fams = ", ".join(f"{k} {v['rms']:.4f}" for k, v in rm.get("families", {}).items())
        lines.append(
            f"  nested {rm.get('folds')}-fold CV RMS (mm): {fams}; best {rm.get('best')}, kept {rm.get('chosen')}"
        )
        if rm.get("learning_curve"):
            lc = ", ".join(f"{p['poses']}: {p['rms']:.4f}" for p in rm["learning_curve"])
            lines.append(f"  learning curve (poses: RMS mm): {lc}")
        if rm.get("validation"):
            lines.append(f"  hold-out with the correction: {json.dumps(rm['validation'])}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("arm", choices=["ur10", "ur5"])
    ap.add_argument("data", help="the data set's checkout (kept outside this repository)")
    ap.add_argument("--series", default="C", choices=["A", "B", "C"], help="UR10 series (default C: random poses)")
    ap.add_argument(
        "--apply-to",
        choices=["A", "B", "C"],
        help="UR10: identify on all of --series and hold out all of this other series (the region check)",
    )
    ap.add_argument("--ur5-sign", type=float, default=1.0, choices=[1.0, -1.0])
    ap.add_argument("--sigma", type=float, default=0.02, help="tracker noise per axis, mm")
    ap.add_argument("--sigma-angle", type=float, default=0.005, help="T-Mac orientation noise, deg")
    ap.add_argument("--work", help="keep the converted files here (default: a temporary directory)")
    ap.add_argument("--skip-geometric", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        sigma, what = prepare(args, work)
        print(f"{what}\nmachine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
        results = {}
        if not args.skip_geometric:
            results["geometric"] = run_identify(work, "geometric", [], sigma)
        results["auto"] = run_identify(work, "auto", ["--residual-map", "auto"], sigma)
        target = "smr" if args.arm == "ur5" else ""
        print()
        for name, rep in results.items():
            print("\n".join(summary(name, rep)))
            cov = holdout_coverage(work, name, target, args.sigma)
            print(f"  recal predict on the hold-out (correction applied): {json.dumps(cov)}")
        if args.apply_to and "geometric" in results:
            print(f"across series, pose by pose: {json.dumps(across_series_check(work))}")


if __name__ == "__main__":
    main()
