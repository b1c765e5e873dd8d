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
