"""What the Makefile promises (README): `make test` runs the serial tests whatever the parallel
run gave, and fails when either failed; `make demo` takes HOST and PORT. Run with a stand-in
for the virtual environment's python that records its arguments and answers a chosen status
(`-o` keeps make from installing anything or looking for Chromium)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make here")


def _make(tmp_path, *args, parallel=0, serial=0):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    calls = tmp_path / "calls"
    python = bin_dir / "python"
    python.write_text(
        f'#!/bin/sh\necho "$*" >> {calls}\ncase "$*" in *"-n 2"*) exit {parallel};; *) exit {serial};; esac\n'
    )
    python.chmod(0o755)
    done = subprocess.run(
        ["make", "--no-print-directory", "-o", "browser", "-o", ".venv/.installed", *args, f"BIN={bin_dir}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return done, (calls.read_text().splitlines() if calls.exists() else [])


@pytest.mark.parametrize(
    "parallel, serial, fails, said",
    [
        (1, 0, True, "the parallel run failed (pytest status 1)"),
        (0, 1, True, "the serial run failed (pytest status 1)"),
        (1, 2, True, "the parallel run failed (pytest status 1)"),
        (0, 0, False, ""),
        (0, 5, False, ""),  # PYTEST_ARGS naming files without serial tests: nothing to run is no failure
    ],
)
def test_make_test_runs_the_serial_tests_whatever_the_parallel_run_gave(tmp_path, parallel, serial, fails, said):
    done, calls = _make(tmp_path, "test", parallel=parallel, serial=serial)
    assert len(calls) == 2 and "-n 2" in calls[0] and calls[1].endswith("-m serial"), calls
    assert (done.returncode != 0) == fails, done.stderr
    assert said in done.stderr


def test_make_demo_takes_host_and_port(tmp_path):
    done, _calls = _make(tmp_path, "-n", "demo", "HOST=127.0.0.9", "PORT=8123")
    assert done.returncode == 0, done.stderr
    assert f"{tmp_path / 'bin'}/recal demo --host 127.0.0.9 --port 8123" in done.stdout
    done, _ = _make(tmp_path, "-n", "demo")
    assert "recal demo --host 127.0.0.2 --port 8000" in done.stdout  # recal demo's own defaults


def test_the_readme_says_which_octet_the_workers_take(monkeypatch):
    import importlib.util
    import os

    # loading the conftest again sets RECAL_TEST_NET (shifting a worker's net once more): restored after
    monkeypatch.setenv("RECAL_TEST_NET", os.environ.get("RECAL_TEST_NET", "127.0.0"))

    spec = importlib.util.spec_from_file_location("top_conftest", ROOT / "tests" / "conftest.py")
    conftest = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conftest)
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "worker `gwN` adds 100 + N to its **third** octet" in readme
    for net, worker in (("127.0.0", "gw0"), ("127.0.0", "gw1"), ("127.0.80", "gw0"), ("127.0.80", "gw1")):
        assert f"`{conftest.worker_net(net, worker)}.x`" in readme
    assert conftest.worker_net("127.0.80", "") == "127.0.80"
