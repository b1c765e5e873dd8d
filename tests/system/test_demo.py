"""`recal demo` as a newcomer runs it (issue 12): it says its RECAL_HOME and the token to use,
a token made with `recal token create` in that RECAL_HOME works with its service, and `kill`
(SIGTERM) stops its service and simulated cell as Ctrl-C does."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np

from service.processes import free_port

from .conftest import emscon_sigma_m, next_host


def _refused(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return False
    except OSError:
        return True


def _children(pid: int) -> set[int]:
    """The process ids of ``pid``'s children (Linux /proc)."""
    out = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as f:
            out |= {int(c) for c in f.read().split()}
    return out


def _gone(pids: set[int], timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while any(os.path.exists(f"/proc/{p}") and _state(p) != "Z" for p in pids):
        assert time.monotonic() < deadline, f"children of recal demo outlived it: {pids}"
        time.sleep(0.1)


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "X"


def _get(url: str, token: str) -> dict:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


def test_demo_prints_its_home_and_token_and_sigterm_stops_its_children(tmp_path):
    home, host, port = tmp_path / "demo", next_host(), free_port()
    env = {**os.environ, "RECAL_HOME": str(home)}  # the demo takes RECAL_HOME as its folder
    demo = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "demo", "--host", host, "--port", str(port), "--time-scale", "0.2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        lines, url, deadline = [], None, time.monotonic() + 60
        while url is None:
            assert time.monotonic() < deadline and demo.poll() is None, lines
            line = demo.stdout.readline()
            lines.append(line)
            m = re.search(r"service ready at (http://\S+)", line)
            url = m.group(1) if m else None
        text = "".join(lines)
        assert f"RECAL_HOME={home}" in text, text
        printed = re.search(r"technician token: (rc_\S+)", text).group(1)
        assert _get(f"{url}/api/v1/me", printed)["role"] == "technician"
        # a token made the way the README says works with the demo's service
        made = subprocess.run(
            [sys.executable, "-m", "service.cli", "token", "create", "--role", "viewer"],
            capture_output=True,
            text=True,
            env=env,
            timeout=60,
        )
        assert made.returncode == 0, made.stderr
        assert _get(f"{url}/api/v1/me", made.stdout.strip())["role"] == "viewer"
        # a session is under way (time scale 0.2: about a pose a second); then `kill`
        deadline = time.monotonic() + 60
        while not _get(f"{url}/api/v1/sessions/1", printed)["measured"]:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        # it measures through the Leica tracker on emScon (the simulated cell's default): the
        # cell names it, and each stored sigma is the emScon fake's MPE-based one at that range
        # (the line-protocol tracker would give a constant 20 um)
        assert "emscon" in _get(f"{url}/api/v1/cells/1", printed)["devices"]
        rows = _get(f"{url}/api/v1/sessions/1/measurements", printed)
        assert rows
        assert np.allclose([r["sigma"] for r in rows], emscon_sigma_m(rows), rtol=1e-3), rows
        children = _children(demo.pid)
        assert len(children) == 2, children  # the service and the simulated cell
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(30) == 0
        _gone(children)
        deadline = time.monotonic() + 10  # its children are gone: nothing answers on their ports
        while not (_refused("127.0.0.1", port) and _refused(host, 29999) and _refused(host, 10001)):
            assert time.monotonic() < deadline, "the demo's service or simulated cell outlived it"
            time.sleep(0.1)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(10)


def test_sigterm_while_the_demo_starts_leaves_no_child(tmp_path):
    # killed while its service is still starting (it takes seconds to answer): nothing is left running
    demo = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "demo",
            "--dir",
            str(tmp_path / "demo"),
            "--host",
            next_host(),
            "--port",
            str(free_port()),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline, children = time.monotonic() + 30, set()
        while len(children) < 2:  # the simulated cell is up and the service process started
            assert time.monotonic() < deadline and demo.poll() is None
            children = _children(demo.pid)
            time.sleep(0.02)
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(30) == 0
        _gone(children)
        assert "service ready" not in demo.stdout.read()  # it was stopped while starting
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(10)


def test_the_demo_leaves_its_measurements_for_the_cli(tmp_path):
    """The demo's folder holds what the service measured as the CLI reads it (issue 27): the pose
    session's measurements and the last verification's, in nominal.json's units. `recal accuracy`
    of the identified model on the verification gives the demo's "after" figures, and `recal
    identify` identifies the robot from the pose session's file."""
    out = tmp_path / "demo"
    demo = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--dir", str(out), "--host", next_host()]
        + ["--port", str(free_port()), "--time-scale", "0", "--poses", "30", "--exit"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert demo.returncode == 0, demo.stdout + demo.stderr
    assert "verify-after.csv" in demo.stdout and "try the CLI on them" in demo.stdout
    # the time printed is the session's (moves and measurements, then the identification), said as such
    assert re.search(
        r"identified \d+ parameters; residual RMS [0-9.]+ mm \(the session, 30 poses moved to and "
        r"measured, then the identification, took [0-9.]+ s\)",
        demo.stdout,
    ), demo.stdout
    for name in ("measurements.csv", "verify-after.csv"):
        text = (out / name).read_text()
        assert text.startswith("# session ") and "q1,q2,q3,q4,q5,q6,x,y,z" in text.replace(" ", ""), text[:300]
    after_rms = float(re.search(r"accuracy after:\s+RMS ([0-9.]+) mm", demo.stdout).group(1))
    acc = subprocess.run(
        [sys.executable, "-m", "service.cli", "accuracy", "--model", "identified.json"]
        + ["--data", "verify-after.csv", "--out", "acc.json"],
        capture_output=True,
        text=True,
        cwd=out,
        timeout=120,
    )
    assert acc.returncode == 0 and "warning" not in acc.stderr, acc.stderr
    rep = json.loads((out / "acc.json").read_text())
    assert rep["measurements"] == 20 and rep["units"]["length"] == "mm"
    assert rep["errors"]["rms"] < 0.1 and abs(rep["errors"]["rms"] - after_rms) < 0.02, (rep["errors"], after_rms)
    ident = subprocess.run(
        [sys.executable, "-m", "service.cli", "identify", "--model", "nominal.json"]
        + ["--data", "measurements.csv", "--out", "cli.json"],
        capture_output=True,
        text=True,
        cwd=out,
        timeout=300,
    )
    assert ident.returncode in (0, 3) and (out / "cli.json").exists(), ident.stderr
