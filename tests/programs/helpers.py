"""What the program tests share: the models on disk, running `recal compensate`, and what the
compensated program makes a simulated true robot do (a nominal controller's inverse kinematics,
here damped Newton from the joints the program was planned with, which are in the written
configuration)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from calibration.ik import solve_ik
from calibration.kinematics import fk
from calibration.model import model_to_dict
from service.files import save_model

from .arms import arm, true_robot

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
NUMBER = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300)


def models(d: Path, brand: str, seed: int = 1):
    """The nominal and the true robot of ``brand``, written to ``d`` (the identified model records
    its nominal, as `recal identify` writes it)."""
    nominal = arm(brand)
    true = true_robot(nominal, seed)
    save_model(d / "nominal.json", nominal)
    save_model(d / "identified.json", true, {"identification": {"nominal": model_to_dict(nominal)}})
    return nominal, true


def frame_of(true, nominal):
    from calibration.compensation import nominal_world_frame

    return nominal_world_frame(true, nominal, None)[0]


def skeleton(data: bytes) -> bytes:
    """The file with every number replaced by ``#``: what must not change at all."""
    return NUMBER.sub(b"#", data)


def numbers(data: bytes) -> list[bytes]:
    return NUMBER.findall(data)


def reached(model_with_tool, nominal_with_tool, X_command_nominal, q_planned):
    """Where the true robot goes when the nominal controller is sent ``X_command_nominal``
    (N, 4, 4, the nominal's world): the controller's joints by Newton on the nominal model from
    the planned joints (the written configuration), then the true robot's forward kinematics."""
    r = solve_ik(nominal_with_tool, X_command_nominal, q_planned, position_tol_m=1e-12, rotation_tol_rad=1e-12)
    assert r.converged.all()
    assert np.abs(r.q - q_planned).max() < np.radians(5)  # same branch and turns
    return fk(model_with_tool, r.q)


def pose_error(A, B):
    dp = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    dR = np.einsum("nij,nik->njk", A[:, :3, :3], B[:, :3, :3])
    ang = np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1))
    return dp, ang


def csv_path_targets(d: Path, name: str, true_t, nom_t, X_d, q_planned):
    """The task CSV's targets mode on the same desired poses, through `recal compensate --mode
    targets`: ``true_t`` (the identified robot with the program's tool) as the model, ``nom_t``
    (the nominal with it) as ``--nominal``, a row per pose ``X_d`` (N, 4, 4, world frame, SI) with
    its planned joints ``q_planned`` (N, 6, rad: the branch). Returns the targets the CSV path
    writes for the nominal controller (N, 4, 4, SI)."""
    import csv

    from calibration.transforms import matrix_to_quat, quat_to_matrix

    save_model(d / f"{name}-identified.json", true_t)
    save_model(d / f"{name}-nominal.json", nom_t)
    cols = ["x", "y", "z", "qw", "qx", "qy", "qz"] + [f"q{i}" for i in range(1, 7)]
    lines = [",".join(cols)]
    for X, q in zip(X_d, q_planned):
        vals = list(X[:3, 3] * 1e3) + list(matrix_to_quat(X[:3, :3])) + list(np.degrees(q))
        lines.append(",".join(repr(float(v)) for v in vals))
    (d / f"{name}.csv").write_text("\n".join(lines) + "\n")
    r = recal(
        "compensate",
        "--model",
        f"{name}-identified.json",
        "--nominal",
        f"{name}-nominal.json",
        "--task",
        f"{name}.csv",
        "--out",
        f"{name}-out.csv",
        "--mode",
        "targets",
        cwd=d,
    )
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader((d / f"{name}-out.csv").open()))
    assert len(rows) == len(X_d) and all(row["converged"] == "1" for row in rows), rows
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, row in enumerate(rows):
        out[k, :3, 3] = [float(row[c]) * 1e-3 for c in "xyz"]
        out[k, :3, :3] = quat_to_matrix(np.array([float(row[c]) for c in ("qw", "qx", "qy", "qz")]))
    return out


def compare_with_csv_path(d: Path, cases: dict):
    """The program path against the CSV path, per tool (``cases``: tool key -> (true_t, nom_t,
    [(X_d, q_planned, X_program), ...]), ``X_program`` the compensated program target in the
    nominal's world, SI). Returns, over all targets, the largest position (m) and angle (rad)
    errors of the true robot sent the program's targets and sent the CSV's, and the largest
    position and angle differences between the two paths' targets."""
    prog_dp = prog_da = csv_dp = csv_da = diff_dp = diff_da = 0.0
    for key, (true_t, nom_t, rows) in cases.items():
        X_d = np.array([r[0] for r in rows])
        q_plan = np.array([r[1] for r in rows])
        X_prog = np.array([r[2] for r in rows])
        X_csv = csv_path_targets(d, f"csv-{key}", true_t, nom_t, X_d, q_plan)
        for X_sent, acc in ((X_prog, "prog"), (X_csv, "csv")):
            dp, da = [], []
            for k in range(len(rows)):
                e = pose_error(reached(true_t, nom_t, X_sent[k : k + 1], q_plan[k : k + 1]), X_d[k : k + 1])
                dp.append(e[0][0])
                da.append(e[1][0])
            if acc == "prog":
                prog_dp, prog_da = max(prog_dp, *dp), max(prog_da, *da)
            else:
                csv_dp, csv_da = max(csv_dp, *dp), max(csv_da, *da)
        dp, da = pose_error(X_prog, X_csv)
        diff_dp, diff_da = max(diff_dp, dp.max()), max(diff_da, da.max())
    return prog_dp, prog_da, csv_dp, csv_da, diff_dp, diff_da
