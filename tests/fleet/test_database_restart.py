"""The fleet's store (and queue: Procrastinate lives in the same PostgreSQL) restarted in the
middle of a run: no measurement is lost or duplicated, the sessions finish, the queue works on.

This restarts the machine's PostgreSQL cluster (``pg_ctlcluster ... restart``), which drops
every connection to it for a second or two, and makes sure it runs again at the end whatever
happens. Set ``RECAL_TEST_NO_PG_RESTART=1`` to leave it alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from sqlmodel import Session, select

from service.client import ApiError, ServiceError
from service.models import Measurement


def _cluster() -> list[str] | None:
    if os.environ.get("RECAL_TEST_NO_PG_RESTART") or shutil.which("pg_ctlcluster") is None or os.geteuid() != 0:
        return None
    versions = sorted(p.name for p in Path("/etc/postgresql").glob("*") if (p / "main").is_dir())
    return [versions[-1], "main"] if versions else None


def _pg(action: str, cluster: list[str]) -> None:
    subprocess.run(
        ["pg_ctlcluster", "--skip-systemctl-redirect", *cluster, action], check=True, timeout=120, capture_output=True
    )


def _ready() -> bool:
    return (
        subprocess.run(["pg_isready", "-h", "127.0.0.1", "-p", "5432", "-t", "2"], capture_output=True).returncode == 0
    )


def _get(api, sid):
    """GET a session, riding out the API's own errors while the database is away."""
    deadline = time.monotonic() + 60
    while True:
        try:
            return api.call("GET", f"/sessions/{sid}")
        except (ApiError, ServiceError):
            assert time.monotonic() < deadline, "the API did not recover from the database restart"
            time.sleep(0.2)


@pytest.mark.serial  # it restarts PostgreSQL under every other test: `make test` runs it alone
def test_database_restart_mid_run_loses_and_duplicates_no_measurement(make_fleet):
    cluster = _cluster()
    if cluster is None:
        pytest.skip("restarting PostgreSQL needs root and pg_ctlcluster (or RECAL_TEST_NO_PG_RESTART is set)")
    f = make_fleet(ttl_s=30.0)  # a 30 s lease (the default) outlasts the restart
    f.start_api()
    f.start_worker("w1", ["north"])
    f.start_worker("w2", ["north"])
    cells = f.add_cells(["north"] * 4, time_scale=0.05)
    api = f.api()
    started = [api.call("POST", f"/cells/{c['id']}/sessions", {"kind": "pose", "count": 40}) for c in cells]
    deadline = time.monotonic() + 60
    while min(api.call("GET", f"/sessions/{s['id']}")["measured"] for s in started) < 4:
        assert time.monotonic() < deadline, "the sessions did not progress"
        time.sleep(0.05)
    ids = [s["id"] for s in started]
    try:
        _pg("restart", cluster)
        with Session(f.engine) as db:  # measurements the service reported before and during the restart
            before = {
                (m.session_id, m.seq, m.target): (m.id, m.x, m.y, m.z)
                for m in db.exec(select(Measurement).where(Measurement.session_id.in_(ids))).all()
            }
        mid = {s: max((k[1] for k in before if k[0] == s), default=-1) for s in ids}
        deadline = time.monotonic() + 180
        while True:
            states = {sid: _get(api, sid) for sid in ids}
            if all(s["state"] not in ("planned", "running") for s in states.values()):
                break
            assert time.monotonic() < deadline, states
            time.sleep(0.3)
    finally:
        if not _ready():
            _pg("start", cluster)
    assert all(s["state"] == "completed" for s in states.values()), states
    assert any(m < 39 for m in mid.values()), "the restart came after the sessions ended: nothing was tested"
    with Session(f.engine) as db:
        rows = db.exec(select(Measurement).where(Measurement.session_id.in_(ids))).all()
    for sid in ids:
        seqs = sorted(m.seq for m in rows if m.session_id == sid)
        assert seqs == list(range(40)), f"session {sid}: every configuration exactly once"
    after = {(m.session_id, m.seq, m.target): (m.id, m.x, m.y, m.z) for m in rows}
    for key, value in before.items():
        assert after[key] == value, "a measurement reported before the restart changed"
    # the queue works on: LISTEN reconnected, workers fetch new jobs
    s = api.call("POST", f"/cells/{cells[0]['id']}/sessions", {"kind": "verify", "count": 5})
    assert api.wait_session(s["id"], 60)["state"] == "completed"
    for name in ("w1", "w2"):
        assert f.workers[name].popen.poll() is None, f"worker {name} died with the database"
