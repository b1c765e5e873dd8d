"""``recal nightly --cell`` through the real service and a simulated cell, each exit status:
10 (drifted: recalibrated, task files compensated again), 0 (accurate), 1 (a session did not
complete), 2 (bad arguments), 3 (service unreachable, or the token refused)."""

from __future__ import annotations

import json
import os
import re

from service.cli import main
from service.processes import free_port

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

TASK = "q1,q2,q3,q4,q5,q6\n10,-80,90,-100,70,20\n-30,-100,60,-50,-80,0\n"


def nightly(monkeypatch, capsys, *args, token: str | None = None) -> tuple[int, str, str]:
    monkeypatch.delenv("RECAL_TOKEN", raising=False)
    if token is not None:
        monkeypatch.setenv("RECAL_TOKEN", token)
    status = main(["nightly", *args])
    out = capsys.readouterr()
    return status, out.out.strip(), out.err.strip()


def test_nightly_exit_statuses(stack, models, register, monkeypatch, capsys):
    url = stack.service.ready["url"]
    job = stack.tokens["job"]
    cell, _ = register(name="weld-3")  # never calibrated: the nominal model is millimetres off
    stack.api().call("POST", f"/cells/{cell['id']}/tasks", {"name": "weld.csv", "content": TASK})

    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-3", "--url", url, token=job)
    assert status == 10, (out, err)
    assert out.startswith("weld-3: drifted (verify RMS") and "-> recalibrated: calibration" in out
    assert out.endswith("1 task files compensated") and "\n" not in out
    cal = stack.api().call("GET", f"/cells/{cell['id']}")["last_calibration_id"]
    assert cal is not None and f"calibration {cal}," in out

    status, out, err = nightly(monkeypatch, capsys, "--cell", str(cell["id"]), "--url", url, token=job)
    assert status == 0, (out, err)
    assert out.startswith("weld-3: accurate, verify RMS") and "threshold 0.1 mm" in out

    # a calibrated cell recalibrated (a threshold it cannot meet): the new calibration waits as a
    # candidate, and is put in use (and the tasks recompensated) only when a verify session passes it
    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-3", "--threshold", "1e-9", "--url", url, token=job)
    new = max(c["id"] for c in stack.api().call("GET", f"/cells/{cell['id']}/calibrations"))
    current = stack.api().call("GET", f"/cells/{cell['id']}")["last_calibration_id"]
    assert new != cal, (out, err)
    if status == 10:  # it passed: in use, tasks recompensated with it
        assert f"-> recalibrated: calibration {new}," in out and current == new, (out, err)
    else:
        assert status == 1 and f"calibration {new} not put in use" in out and current == cal, (out, err)
        assert stack.api().call("GET", f"/calibrations/{new}")["status"] == "candidate"

    # a cell whose devices do not answer: the verify session pauses, a person must look
    stack.api().call(
        "POST",
        "/cells",
        {
            "name": "dark",
            "model": json.loads(models["nominal"].read_text()),
            "devices": {"rtde": f"{NET}.19", "tracker": f"socket://{NET}.19:9"},
            "drift_threshold": 0.1,
        },
    )
    status, out, err = nightly(monkeypatch, capsys, "--cell", "dark", "--url", url, token=job)
    assert status == 1, (out, err)
    assert out.startswith("dark: verify session") and "paused" in out and "devices" in out

    # bad arguments
    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-3", "--url", url)
    assert status == 2 and "no token" in err
    status, out, err = nightly(
        monkeypatch, capsys, "--cell", "weld-3", "--url", url, "--token-file", str(stack.home / "missing.token")
    )
    assert status == 2 and "missing.token" in err
    status, out, err = nightly(monkeypatch, capsys, "--url", url, token=job)
    assert status == 2 and "--cell" in err

    # the service refuses the token, or cannot be reached
    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-3", "--url", url, token="rc_wrong")
    assert status == 3 and "401" in err
    nobody = f"http://127.0.0.1:{free_port()}"
    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-3", "--url", nobody, token=job)
    assert status == 3 and "cannot reach" in err


def test_nightly_exits_3_naming_targets_not_compensated(stack, register, monkeypatch, capsys):
    """A drifted cell recalibrated whose task file has a target 5 m out of reach: the file is
    compensated and stored, but one target is left as written, so the job exits 3 as ``recal
    compensate`` does, its line counting it and naming the file and the compensation whose report
    rows say which (it exited 10 before, as if everything had been done)."""
    url = stack.service.ready["url"]
    cell, _ = register(name="weld-4")
    task = {"name": "far.csv", "content": "x,y,z,qw,qx,qy,qz\n400,100,500,0,1,0,0\n5000,100,500,0,1,0,0\n"}
    stack.api().call("POST", f"/cells/{cell['id']}/tasks", {**task, "mode": "targets"})
    status, out, err = nightly(monkeypatch, capsys, "--cell", "weld-4", "--url", url, token=stack.tokens["job"])
    assert status == 3, (out, err)
    assert "-> recalibrated: calibration" in out and "\n" not in out
    m = re.search(r"(\d+) targets not compensated \(far\.csv: (\d+) \(compensation (\d+)\)", out)
    assert m and m.group(1) == m.group(2), out
    report = stack.api().call("GET", f"/compensations/{m.group(3)}/report")["report"]
    left = [p for p in report["points"] if not p["converged"]]
    assert len(left) == int(m.group(1)) >= 1 and report["points"][1] in left  # the far one at least


def test_nightly_all_exit_status_counts_a_shortfall_after_failures_and_before_recalibrations():
    """``--all``: a cell recalibrated with targets not compensated makes the job exit 3 (not the
    10 of a clean recalibration), below a cell that needs a person (1) and an unreachable
    service (3, no shortfall); the summary counts it as recalibrated, not as needing a person."""
    from service.commands.nightly import _report, fleet_status

    def cell(name, status, shortfall=None):
        r = {"cell": name, "site": "", "status": status, "result": "", "line": f"{name}: ...", "seconds": 1.0}
        r.update(verify_rms=None, unit="mm", threshold=None, calibration_id=None, tasks=None)
        return {**r, "shortfall": shortfall} if shortfall else r

    ok, recal, short = cell("a", 0), cell("b", 10), cell("c", 3, shortfall=2)
    assert fleet_status([ok, recal]) == 10
    assert fleet_status([ok, recal, short]) == 3
    assert fleet_status([short, cell("d", 1)]) == 1
    assert fleet_status([short, cell("e", 3)]) == 3
    text = _report([ok, recal, short])
    assert "3 cells: 1 accurate, 2 recalibrated (1 with targets not compensated), 0 need a person" in text
