"""Simulated cells in subprocesses, for driver tests across processes.

``cell_factory(*args)`` starts ``python -m fakes.cell --truth <truth> --host 127.0.0.N *args``
on a free loopback address of this module's pool (127.0.0.2 ... 127.0.0.18: the UR
controller's ports are fixed, so every cell needs an address of its own; 127.0.0.19 stays
empty), waits for the endpoint line and returns a ``RunningCell``; every cell still running
at the end of the session is stopped.
``fake_cell`` is one shared cell at time scale 0, ``timed_cell`` one at time scale 0.25.

The cells die with the test process (Linux parent-death signal), so a crashed test run leaves
no fake holding the ports.

The project runs pytest with ``--import-mode=importlib``, which does not put test directories
on ``sys.path``; this directory goes there so that test modules can import the shared
``robot_contract`` module.
"""

from __future__ import annotations

import ctypes
import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from fakes.cell import FAKES

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

REPO = Path(__file__).resolve().parents[2]
_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
POOL = [f"{NET}.{i}" for i in range(2, 19)]
ABSENT_HOST = f"{NET}.19"  # never given a cell: an absent controller
START_TIMEOUT_S = 20.0
DEVICES = tuple(fake["key"] for fake in FAKES)  # fakes.cell's --no-KEY flags

# The simulated robot: a UR5e whose true geometry differs from the nominal one by up to a
# millimetre and a few hundredths of a degree, with a reflector and three tooling balls.
TRUTH_PATH = Path(__file__).with_name("ur5e_truth.json")


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the parent (the test process) dies."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass  # not Linux: the session teardown still stops the cells


class RunningCell:
    """One ``fakes.cell`` process: its ``host``, ``endpoint`` line (dict) and ``stop``."""

    def __init__(self, process: subprocess.Popen, host: str, endpoint: dict, stderr_path: str):
        self.process = process
        self.host = host
        self.endpoint = endpoint
        self.stderr_path = stderr_path

    @property
    def modbus_port(self) -> int:
        return int(self.endpoint["modbus"].rsplit(":", 1)[1])

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it does not end within 5 s. Idempotent."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()

    def kill(self) -> None:
        """The controller vanishes: SIGKILL, no goodbye on any connection."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()

    def stderr(self) -> str:
        return Path(self.stderr_path).read_text(errors="replace")


def subprocess_env() -> dict:
    """The environment for a child Python that must import this repository's packages."""
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    return dict(os.environ, PYTHONPATH=path)


def start_cell(truth_path: Path, host: str, *args: str) -> RunningCell:
    """Start a cell on ``host`` and wait for its endpoint line; raise if it does not come."""
    stderr = tempfile.NamedTemporaryFile(prefix="fake-cell-", suffix=".log", delete=False)  # noqa: SIM115 (closed once Popen has it; the name is kept for the log)
    process = subprocess.Popen(
        [sys.executable, "-m", "fakes.cell", "--truth", str(truth_path), "--host", host, *args],
        stdout=subprocess.PIPE,
        stderr=stderr,
        cwd=REPO,
        env=subprocess_env(),
        # a prctl() call only, so safe before exec in a threaded parent
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,  # noqa: PLW1509
    )
    stderr.close()
    cell = RunningCell(process, host, {}, stderr.name)
    deadline = time.monotonic() + START_TIMEOUT_S
    line = b""
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([process.stdout], [], [], max(deadline - time.monotonic(), 0))
        if not ready:
            cell.stop()
            raise RuntimeError(f"fake cell on {host}: no endpoint line within {START_TIMEOUT_S} s")
        chunk = os.read(process.stdout.fileno(), 4096)
        if not chunk:
            process.wait()
            raise RuntimeError(f"fake cell on {host} exited {process.returncode}: {cell.stderr()}")
        line += chunk
    cell.endpoint = json.loads(line)
    return cell


def host_is_free(host: str) -> bool:
    """Nothing listens on the UR dashboard or RTDE port of ``host``."""
    for port in (29999, 30004):
        with socket.socket() as sock:
            sock.settimeout(0.2)
            if sock.connect_ex((host, port)) == 0:
                return False
    return True


@pytest.fixture(scope="session")
def truth_path() -> Path:
    return TRUTH_PATH


@pytest.fixture(scope="session")
def cell_truth():
    """The cells' true robot (``KinematicModel``; its robot starts at all joints zero)."""
    from calibration.model import model_from_dict

    return model_from_dict(json.loads(TRUTH_PATH.read_text()))


@pytest.fixture(scope="session")
def cell_factory(truth_path):
    """``start(*args, truth=None) -> RunningCell`` on a free pool address (``truth``: another
    truth file than the shared one); all stopped at session end."""
    started: list[RunningCell] = []

    def start(*args: str, truth: Path | None = None) -> RunningCell:
        in_use = {c.host for c in started if c.process.poll() is None}
        errors = []
        for host in POOL:
            if host in in_use or not host_is_free(host):
                continue
            try:
                cell = start_cell(truth or truth_path, host, *args)
            except RuntimeError as exc:  # for example another test run holds this address
                errors.append(str(exc))
                continue
            started.append(cell)
            return cell
        raise RuntimeError(f"no free loopback address for a fake cell: {errors}")

    yield start
    for cell in started:
        cell.stop()


@pytest.fixture(scope="session")
def free_host() -> str:
    """A loopback address where nothing listens (an absent controller)."""
    if not host_is_free(ABSENT_HOST):
        pytest.skip(f"something listens on {ABSENT_HOST}")
    return ABSENT_HOST


@pytest.fixture(scope="session")
def fake_cell(cell_factory) -> RunningCell:
    """A cell at time scale 0 shared by the whole session."""
    return cell_factory("--seed", "1")


@pytest.fixture(scope="session")
def timed_cell(cell_factory) -> RunningCell:
    """A cell whose motions take a quarter of their real duration."""
    return cell_factory("--seed", "2", "--time-scale", "0.25")


@pytest.fixture
def fault_cell(cell_factory):
    """``start(*args, only=(), faults=())``: a cell for one test, stopped when the test ends.

    ``only`` names the devices to simulate (the keys of the cell's ``--no-KEY`` flags: ``ur``,
    ``modbus``, ``tracker``, ``cmm``, ``can``; all when empty), ``faults`` the ``--fault``
    values (``"garble_at=5"``): each device counts its own requests, so a fault meant for one
    device would also hit the others.
    """
    cells: list[RunningCell] = []

    def start(*args: str, only: tuple[str, ...] = (), faults: tuple[str, ...] = ()) -> RunningCell:
        flags = [f"--no-{key}" for key in DEVICES if only and key not in only]
        flags += [flag for fault in faults for flag in ("--fault", fault)]
        cells.append(cell_factory(*flags, *args))
        return cells[-1]

    yield start
    for cell in cells:
        cell.stop()
