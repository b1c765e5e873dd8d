"""``recal fake-cell`` (``python -m fakes.cell``): the endpoint line, flags and shutdown."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

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
        capture_output=True, text=True, timeout=timeout_s, cwd=REPO, env=subprocess_env(),
    )


def test_endpoint_line_is_the_only_output_and_sigterm_ends_the_cell(cell_factory):
    cell = cell_factory("--seed", "7")
    line = cell.endpoint
    assert line["ready"] is True
    assert line["rtde"] == cell.host
    host, port = line["modbus"].rsplit(":", 1)
    assert host == cell.host and int(port) > 0
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
        [sys.executable, "-m", "fakes.ur_controller", "--truth", str(truth_path),
         "--host", free_host],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=REPO, env=subprocess_env(),
    )
    try:
        assert json.loads(process.stdout.readline()) == {"ready": True, "rtde": free_host}
    finally:
        process.terminate()
        assert process.wait(timeout=10) == 0
        process.stdout.close()
