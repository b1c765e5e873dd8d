"""A worker's hold on a cell under load (docs/fleet.md): when its monitor thread is late (a
busy machine), the session renews its own lease before its next move instead of stopping; it
stops, saying why, only once the store says the hold is gone (the reaper of another process
took it after it ran out)."""

from __future__ import annotations

import time
from datetime import timedelta

import pytest
from sqlmodel import Session

from service.fleet import jobs
from service.fleet.reaper import Reaper
from service.fleet.worker import Monitor
from service.models import Cell, RunSession, utcnow
from service.session_loop import Control, SessionStopped
from service.settings import Settings
from service.store import as_utc

OWNER = "worker:test:host:1"


def test_a_late_lease_is_renewed_by_the_session_and_a_lost_one_stops_it(make_fleet):
    f = make_fleet(ttl_s=5.0)
    jobs.ensure_schema(f.engine)
    with Session(f.engine) as db:
        cell = Cell(name="c", model={}, devices={})
        db.add(cell)
        db.commit()
        run = RunSession(
            cell_id=cell.id,
            kind="verify",
            state="running",
            lease_owner=OWNER,
            lease_expires=utcnow() + timedelta(seconds=1),
        )
        db.add(run)
        db.commit()
        sid = run.id
    monitor = Monitor(f.engine, "", OWNER, ttl_s=5.0)  # its thread not started: as late as can be
    control = Control(renew=lambda: monitor.renew({sid}))
    monitor.add(sid, control)
    control.lease_valid_until = time.monotonic() - 0.1
    control.check()  # renewed, goes on
    assert control.lease_valid_until > time.monotonic()
    assert as_utc(f.session_row(sid).lease_expires) > utcnow() + timedelta(seconds=4)

    # The hold runs out unrenewed and the reaper of another process interrupts the session.
    with Session(f.engine) as db:
        row = db.get(RunSession, sid)
        row.lease_expires = utcnow() - timedelta(seconds=5)
        db.add(row)
        db.commit()
    app = jobs.sync_app(Settings(database_url=f.db_url, engine="procrastinate"), max_size=1)
    try:
        assert Reaper(f.engine, app, 5.0).reap_once() == [sid]
    finally:
        app.close()
    control.lease_valid_until = time.monotonic() - 0.1
    with pytest.raises(SessionStopped) as stopped:
        control.check()
    assert stopped.value.state == "interrupted"
    assert "ran out before it was renewed" in stopped.value.reason and "resume" in stopped.value.reason
    assert f.session_row(sid).state == "interrupted"
