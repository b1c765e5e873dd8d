"""A measurement commit that meets a database blip (docs/fleet.md): it is retried, and a commit
that went through although its answer was lost is not stored twice (the unique constraint
(session, seq, target) refuses the copy)."""

from __future__ import annotations

from typing import ClassVar

import pytest
from sqlalchemy.exc import OperationalError
from sqlmodel import Session, select

from service.models import Cell, Measurement, RunSession
from service.session_loop import Control, commit_measurements
from service.settings import Settings
from service.store import make_engine, migrate


class FlakySession(Session):
    """Its commits fail as planned: ``before`` (nothing stored), ``after`` (stored, answer lost)."""

    plan: ClassVar[list[str]] = []  # set by each test, read by every session

    def commit(self):
        mode = self.plan.pop(0) if self.plan else None
        if mode == "before":
            raise OperationalError("COMMIT", {}, ConnectionError("server closed the connection unexpectedly"))
        super().commit()
        if mode == "after":
            raise OperationalError("COMMIT", {}, ConnectionError("server closed the connection unexpectedly"))


@pytest.fixture
def store(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with Session(engine) as db:
        cell = Cell(name="c", model={}, devices={})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="pose")
        db.add(run)
        db.commit()
        sid = run.id
    yield engine, sid
    engine.dispose()


def _row(sid: int, seq: int) -> Measurement:
    return Measurement(session_id=sid, seq=seq, target="smr", q=[0.0] * 6, x=1.0 + seq, y=2.0, z=3.0)


@pytest.mark.parametrize("plan", [["before"], ["before", "before"], ["after"], ["before", "after"]])
def test_a_measurement_commit_survives_a_database_blip_exactly_once(store, plan):
    engine, sid = store
    settings = Settings(lease_ttl_s=10.0)
    with FlakySession(engine) as db:
        db.plan = list(plan)
        commit_measurements(db, [_row(sid, 0)], settings, Control())
        db.plan = []
        commit_measurements(db, [_row(sid, 1)], settings, Control())
    with Session(engine) as db:
        rows = db.exec(select(Measurement).where(Measurement.session_id == sid)).all()
    assert sorted(r.seq for r in rows) == [0, 1]


def test_a_real_duplicate_is_still_an_error(store):
    from sqlalchemy.exc import IntegrityError

    engine, sid = store
    with Session(engine) as db:
        commit_measurements(db, [_row(sid, 0)], Settings(), Control())
        with pytest.raises(IntegrityError):
            commit_measurements(db, [_row(sid, 0)], Settings(), Control())


def test_the_retry_gives_up_when_the_lease_would_run_out(store):
    import time

    engine, sid = store
    control = Control()
    control.lease_valid_until = time.monotonic() + 0.5
    with FlakySession(engine) as db:
        db.plan = ["before"] * 20
        with pytest.raises(OperationalError):
            commit_measurements(db, [_row(sid, 0)], Settings(lease_ttl_s=10.0), control)
