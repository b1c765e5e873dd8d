"""The fleet against real processes: two API processes and two workers on one PostgreSQL store,
simulated cells on several sites (issue: a fleet of cells).

Worker ``w1`` serves sites north, south and east; ``w2`` north and south; nobody serves site
``nowhere``. Each worker runs at most four sessions at once, so seven concurrent sessions need
both. The lease lasts 5 s here (30 s by default), so a killed worker's session is interrupted
within seconds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from sqlmodel import Session

from service.models import RunSession
from service.processes import start_service


def _start(api, cell, **body):
    return api.call("POST", f"/cells/{cell['id']}/sessions", body)


def test_all_cells_calibrated_concurrently_across_both_workers_and_api_processes(fleet):
    cells = fleet.add_cells(["north", "north", "north", "south", "south", "south", "east"], time_scale=0.02)
    started = [_start(fleet.api(i % 2), c, kind="pose", count=20) for i, c in enumerate(cells)]
    done = [fleet.api((i + 1) % 2).wait_session(s["id"], 120, poll_s=0.1) for i, s in enumerate(started)]
    for s in done:
        assert s["state"] == "completed", s
        assert s["measured"] == 20 and s["calibration_id"] is not None
    owners = {s["id"]: fleet.owner_name(s["id"]) for s in done}
    assert set(owners.values()) == {"w1", "w2"}, owners  # 7 sessions, at most 4 per worker
    assert owners[done[-1]["id"]] == "w1"  # site east: only w1 serves it
    # they ran at the same time: each started before the first one ended
    rows = [fleet.session_row(s["id"]) for s in done]
    first_end = min(r.updated_at for r in rows)
    assert sum(r.created_at < first_end for r in rows) == len(rows)
    for s in done:
        seqs = [m["seq"] for m in fleet.api().call("GET", f"/sessions/{s['id']}/measurements")]
        assert sorted(seqs) == list(range(20))


def test_a_session_for_a_site_no_worker_serves_waits_and_can_be_aborted(fleet):
    (cell,) = fleet.add_cells(["nowhere"])
    s = _start(fleet.api(0), cell, kind="verify", count=5)
    # the workers are taking work meanwhile: a session of a site they serve, queued after it,
    # runs to its end (a condition, not a pause: it shows they polled the queue since)
    (served,) = fleet.add_cells(["north"])
    later = _start(fleet.api(0), served, kind="verify", count=5)
    assert fleet.api(1).wait_session(later["id"], 60, poll_s=0.1)["state"] == "completed"
    assert fleet.api(1).call("GET", f"/sessions/{s['id']}")["state"] == "planned"  # queued, nobody moved
    # an API process starting and stopping meanwhile leaves it queued (it is not that process's)
    fleet.start_api().stop()
    assert fleet.api(1).call("GET", f"/sessions/{s['id']}")["state"] == "planned"
    a = fleet.api(1).call("POST", f"/sessions/{s['id']}/abort")
    assert a["state"] == "aborted" and a["measured"] == 0
    jobs = fleet.sql("SELECT status FROM procrastinate_jobs WHERE args->>'session_id' = :sid", sid=str(s["id"]))
    assert [j[0] for j in jobs] == ["cancelled"]
    # the cell is free again: a new session can start (and waits, like the first)
    s2 = _start(fleet.api(0), cell, kind="verify", count=5)
    assert fleet.api(0).call("POST", f"/sessions/{s2['id']}/pause")["state"] == "paused"


def test_a_session_left_planned_without_a_job_is_queued_again_and_runs(fleet):
    (cell,) = fleet.add_cells(["north"])
    # What an API process that stopped between the session and its job, or a worker that gave
    # the job up before claiming the session, leaves behind: planned, nothing queued.
    with Session(fleet.engine) as db:
        run = RunSession(cell_id=cell["id"], kind="verify", planned=5, target="smr", created_by="test")
        db.add(run)
        db.commit()
        sid = run.id
    done = fleet.api().wait_session(sid, 8 * fleet.ttl_s, poll_s=0.1)
    assert done["state"] == "completed" and done["measured"] == 5, done  # queued again, not interrupted


def test_nightly_all_checks_every_cell_of_a_site_and_prints_a_summary(fleet):
    fresh = fleet.add_cells(["south", "south"])  # never calibrated: the verify finds them off
    env = {**os.environ, "RECAL_TOKEN": fleet.tokens["job"]}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "nightly",
            "--all",
            "--site",
            "south",
            "--url",
            fleet.apis[1].ready["url"],
            "--timeout",
            "120",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    print(r.stdout, r.stderr)
    south = [c for c in fleet.api().call("GET", "/cells?site=south")]
    assert r.returncode == 10, r
    lines = r.stdout.splitlines()
    assert lines[0].split()[:3] == ["cell", "site", "verify"]
    for c in south:
        assert any(line.startswith(c["name"] + " ") for line in lines), (c["name"], r.stdout)
    for c in fresh:
        row = next(line for line in lines if line.startswith(c["name"] + " "))
        assert "recalibrated" in row, row
        assert fleet.api().call("GET", f"/cells/{c['id']}")["last_calibration_id"] is not None
    assert f"{len(south)} cells:" in r.stdout and "0 need a person" in r.stdout


def test_nightly_waits_through_a_restart_of_the_api_replica_it_talks_to(fleet):
    """The replica the nightly job polls goes away mid-run and comes back on the same address:
    the sessions run on in the workers meanwhile, the job waits for the replica (no session
    started twice) and reports every cell recalibrated."""
    cells = fleet.add_cells(["east"], time_scale=0.02)  # slow enough to be mid-run when the replica stops
    env = {**os.environ, "RECAL_TOKEN": fleet.tokens["job"]}
    url = fleet.apis[1].ready["url"]
    job = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "nightly", "--all", "--site", "east", "--url", url, "--timeout", "120"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while not (
            rows := fleet.sql("SELECT id FROM session WHERE cell_id = :c AND kind = 'verify'", c=cells[0]["id"])
        ):
            assert time.monotonic() < deadline and job.poll() is None, "the nightly job started no session"
            time.sleep(0.1)
        fleet.apis[1].stop()
        # the workers go on while the replica is away (the job's polls are refused meanwhile):
        # wait until the session has stored two more configurations than when it went away
        stored = "SELECT count(*) FROM measurement WHERE session_id = :s"
        before = fleet.sql(stored, s=rows[0][0])[0][0]
        deadline = time.monotonic() + 60
        while fleet.sql(stored, s=rows[0][0])[0][0] < before + 2 and fleet.session_row(rows[0][0]).state == "running":
            assert time.monotonic() < deadline, "the session stopped measuring while the replica was away"
            time.sleep(0.1)
        fleet.apis[1] = start_service(
            fleet.home, int(url.rsplit(":", 1)[1]), env=fleet.env, log_path=fleet.home / "api1-restarted.log"
        )
        out, err = job.communicate(timeout=240)
    finally:
        if job.poll() is None:
            job.kill()
    print(out, err)
    assert job.returncode == 10, (out, err)
    east = fleet.api().call("GET", "/cells?site=east")
    assert f"{len(east)} cells:" in out and "0 need a person" in out
    row = next(line for line in out.splitlines() if line.startswith(cells[0]["name"] + " "))
    assert "recalibrated" in row, row
    kinds = [r[0] for r in fleet.sql("SELECT kind FROM session WHERE cell_id = :c ORDER BY id", c=cells[0]["id"])]
    assert kinds == ["verify", "pose"], kinds  # each started once
