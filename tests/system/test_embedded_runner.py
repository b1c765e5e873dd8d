"""The session-runner contract (tests/runner_contract.py) against the embedded runner: sessions
in threads of the service process, on SQLite (and its crash case on PostgreSQL too)."""

from __future__ import annotations

import pytest
from runner_contract import RunnerContract
from sqlmodel import Session, select

from service.models import Measurement
from service.settings import Settings
from service.store import make_engine


class Embedded:
    def __init__(self, stack, register):
        self.stack, self.register = stack, register

    def api(self, i: int = 0):
        return self.stack.api()

    def add_cell(self, time_scale: float) -> dict:
        return self.register(time_scale=time_scale)[0]

    def crash(self, session_id: int) -> None:
        self.stack.kill()

    def after_crash(self) -> None:
        self.stack.start()  # a restart interrupts what the killed process was running

    def stored(self, session_id: int) -> dict:
        engine = make_engine(Settings(home=self.stack.home, database_url=self.stack.db_url).effective_database_url)
        try:
            with Session(engine) as db:
                rows = db.exec(select(Measurement).where(Measurement.session_id == session_id)).all()
                return {(m.seq, m.target): (m.id, m.x, m.y, m.z) for m in rows}
        finally:
            engine.dispose()


@pytest.mark.parametrize("db_url", ["sqlite"], indirect=True)
class TestEmbeddedRunner(RunnerContract):
    @pytest.fixture
    def deployment(self, stack, register):
        return Embedded(stack, register)


@pytest.mark.parametrize("db_url", ["postgres"], indirect=True)
class TestEmbeddedRunnerOnPostgreSQL:
    """On PostgreSQL the crash case only: what the store must survive (the other cases exercise
    the runner, the same on either store, and the fleet's run them on PostgreSQL)."""

    @pytest.fixture
    def deployment(self, stack, register):
        return Embedded(stack, register)

    test_a_crash_mid_session_interrupts_it_and_resume_loses_and_duplicates_nothing = (
        RunnerContract.test_a_crash_mid_session_interrupts_it_and_resume_loses_and_duplicates_nothing
    )
