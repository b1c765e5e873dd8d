"""An aborted session is stored aborted before its devices are closed (so the abort is answered
at once, session_loop.run_session), and keeps its cell's lease until they are: a session
started on the cell meanwhile waits for that, neither opening the robot while the old
connections close nor being refused as if the cell were driven."""

from __future__ import annotations

import threading
import time
from datetime import timedelta

from sqlmodel import Session

from service.models import Cell, RunSession, utcnow
from service.store import acquire_lease, as_utc, make_engine, migrate, release_lease


def _cell_with(db: Session, state: str, owner: str = "embedded") -> tuple[int, RunSession]:
    """A cell with a session in ``state`` that holds the cell's lease, and a new planned one."""
    cell = Cell(name=f"c-{state}", model={}, devices={})
    db.add(cell)
    db.commit()
    old = RunSession(
        cell_id=cell.id, kind="verify", state=state, lease_owner=owner, lease_expires=utcnow() + timedelta(seconds=30)
    )
    new = RunSession(cell_id=cell.id, kind="verify", state="planned")
    db.add_all([old, new])
    db.commit()
    return old.id, new


def test_a_new_session_waits_for_an_aborted_one_to_close_its_devices(settings):
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    try:
        with Session(engine) as db:
            old_id, new = _cell_with(db, "aborted")
            # still closing: not taken, and not refused at once either
            t0 = time.monotonic()
            assert acquire_lease(db, new, "embedded", closing_wait_s=0.3) is False
            assert time.monotonic() - t0 >= 0.3
            released = threading.Event()

            def close_devices():
                time.sleep(0.3)
                with Session(engine) as other:
                    release_lease(other, other.get(RunSession, old_id), "embedded")
                released.set()

            closer = threading.Thread(target=close_devices)
            closer.start()
            assert acquire_lease(db, new, "embedded", closing_wait_s=10.0) is True
            assert released.is_set(), "the lease was taken while the aborted session still held it"
            closer.join()
            db.refresh(new)
            assert new.lease_owner == "embedded" and as_utc(new.lease_expires) > utcnow()
    finally:
        engine.dispose()
