"""Long verbs report progress on stderr when a person watches (stderr a terminal), and not with
``--quiet`` or when stderr is a file or a pipe (issue 25: `identify` on 200k rows was silent for
17 s). The terminal is a real pseudo-terminal: the console script cannot tell it from a person's."""

from __future__ import annotations

import dataclasses
import os
import pty
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.model import Units
from calibration.simulate import perturbed, random_configurations, simulate_measurements

from .test_identify_predict import write_measurements, write_model

RECAL = [str(Path(sys.executable).with_name("recal"))]
MM_DEG = Units("mm", "deg")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("progress")
    rng = np.random.default_rng(4)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.03, 0.0, 0.08])})
    truth = perturbed(nominal, rng, base_length_m=3e-3, base_angle_rad=1e-3)
    data = simulate_measurements(truth, random_configurations(nominal, 40, rng), rng, targets=("smr",))
    write_model(d / "nominal.json", nominal, MM_DEG)
    write_measurements(d / "meas.csv", nominal, data, MM_DEG)
    return d


def _on_a_terminal(args, cwd) -> tuple[int, str]:
    """Run ``recal args`` with stderr on a pseudo-terminal; its exit status and what it showed there."""
    leader, follower = pty.openpty()
    proc = subprocess.Popen([*RECAL, *args], cwd=cwd, stdout=subprocess.DEVNULL, stderr=follower)
    os.close(follower)
    shown = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the terminal closed: the process ended
            break
        if not chunk:
            break
        shown += chunk
    os.close(leader)
    return proc.wait(timeout=120), shown.decode()


VERBS = {
    "identify": ["identify", "--model", "nominal.json", "--data", "meas.csv", "--out", "id.json"],
    "predict": ["predict", "--model", "nominal.json", "--joints", "meas.csv", "--out", "p.csv"],
    "accuracy": ["accuracy", "--model", "nominal.json", "--data", "meas.csv"],
}


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_progress_on_a_terminal_and_none_when_quiet_or_redirected(files, verb):
    status, shown = _on_a_terminal(VERBS[verb], files)
    assert status == 0, shown
    assert "reading meas.csv ..." in shown, shown
    status, shown = _on_a_terminal([*VERBS[verb], "--quiet"], files)
    assert status == 0 and "reading" not in shown, shown
    # redirected: nothing of the progress reaches a file
    proc = subprocess.run([*RECAL, *VERBS[verb]], cwd=files, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "reading" not in proc.stderr, proc.stderr
