"""``recal fake-cell`` (``python -m fakes.cell``): the endpoint line, flags and shutdown."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

REPO = Path(__file__).resolve().parents[2]
TRUTH_PATH = Path(__file__).with_name("ur5e_truth.json")


def subprocess_env() -> dict:
    """The environment for a child Python that must import this repository's packages."""
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    return dict(os.environ, PYTHONPATH=path)


def run_cell(*args: str, timeout_s: float = 20.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fakes.cell", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
        env=subprocess_env(),
    )


def test_endpoint_line_is_the_only_output_and_sigterm_ends_the_cell(cell_factory):
    cell = cell_factory("--seed", "7")
    line = cell.endpoint
    assert line["ready"] is True
    assert line["rtde"] == cell.host
    for key in ("modbus", "emscon"):  # "HOST:PORT" (the Leica tracker's emScon server: 700, or ephemeral)
        host, port = line[key].rsplit(":", 1)
        assert host == cell.host and int(port) > 0, line
    started = time.monotonic()
    cell.process.send_signal(signal.SIGTERM)
    assert cell.process.wait(timeout=10) == 0
    assert time.monotonic() - started < 5.0
    assert cell.process.stdout.read() == b""  # exactly one line on stdout


def test_left_out_devices_leave_their_keys_out(cell_factory):
    cell = cell_factory("--no-ur", "--no-tracker", "--no-emscon", "--no-cmm", "--no-can")
    assert set(cell.endpoint) == {"ready", "modbus"}


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--fault", "no_such_fault=1"], "--fault 'no_such_fault=1'"),
        (["--fault", "protective_stop_at_move=x"], "protective_stop_at_move=x"),
        (["--noise", "tracker_m"], "--noise 'tracker_m'"),
        (["--time-scale", "-1"], "--time-scale"),
    ],
)
def test_bad_flags_give_one_line_naming_them(args, expected):
    done = run_cell("--truth", str(TRUTH_PATH), "--host", f"{NET}.19", *args)
    assert done.returncode != 0
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], done.stderr


def test_unreadable_truth_file_is_named(tmp_path):
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": "recal.model/1",\n "units": ')
    cases = ((tmp_path / "missing.json", "missing.json"), (broken, "broken.json: line 2"))
    for path, expected in cases:
        done = run_cell("--truth", str(path), "--host", f"{NET}.19")
        assert done.returncode != 0 and done.stdout == ""
        assert expected in done.stderr, done.stderr


def test_ur_controller_alone(truth_path, free_host):
    process = subprocess.Popen(
        [sys.executable, "-m", "fakes.ur_controller", "--truth", str(truth_path), "--host", free_host],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        cwd=REPO,
        env=subprocess_env(),
    )
    try:
        assert json.loads(process.stdout.readline()) == {"ready": True, "rtde": free_host}
    finally:
        process.terminate()
        assert process.wait(timeout=10) == 0
        process.stdout.close()


@pytest.mark.parametrize(
    "block, expected",
    [
        ({"published": "ur7e"}, "ur_factory_calibration.published: expected one of ur3e, ur5e, ur10e, ur16e"),
        ({"published": "ur5e", "delta_theta": [0.0] * 5}, "ur_factory_calibration.delta_theta: expected a list of 6"),
    ],
)
def test_a_bad_factory_calibration_block_is_named(tmp_path, block, expected):
    doc = json.loads(TRUTH_PATH.read_text())
    doc["ur_factory_calibration"] = block
    path = tmp_path / "truth.json"
    path.write_text(json.dumps(doc))
    done = run_cell("--truth", str(path), "--host", f"{NET}.19")
    assert done.returncode != 0 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "truth.json" in lines[0] and expected in lines[0], done.stderr


def test_factory_calibrations_round_trip_and_come_out_linearised():
    """What --factory-seed draws: millimetres from the published table at the flange, joints
    2-4 in the linearised form (large delta_d, sum near zero), the block readable again."""
    from calibration.kinematics import fk
    from calibration.robots import nominal
    from fakes.world import FactoryCalibration, draw_factory_calibration

    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (200, 6))
    for seed in range(3):
        f = draw_factory_calibration("ur10e", seed)
        again = FactoryCalibration.from_dict(json.loads(json.dumps(f.to_dict())))
        assert again == f
        d = np.linalg.norm(fk(f.model(), q)[:, :3, 3] - fk(nominal("ur10e"), q)[:, :3, 3], axis=1)
        assert 0.3e-3 < d.max() < 10e-3, d.max()
        assert min(abs(v) for v in f.delta_d[1:4]) > 1.0 and abs(sum(f.delta_d[1:4])) < 1e-3
        assert max(abs(v) for v in (*f.delta_d[:1], *f.delta_d[4:])) < 5e-3
