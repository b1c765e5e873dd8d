"""The session-runner contract (tests/runner_contract.py) against the fleet's runner: sessions
queued by two API processes for two ``recal worker`` processes (PostgreSQL)."""

from __future__ import annotations

import pytest
from runner_contract import RunnerContract
from sqlmodel import Session, select

from service.models import Measurement


class FleetDeployment:
    def __init__(self, fleet):
        self.fleet = fleet
        self.killed: str | None = None

    def api(self, i: int = 0):
        return self.fleet.api(i)

    def add_cell(self, time_scale: float) -> dict:
        return self.fleet.add_cells(["north"], time_scale=time_scale)[0]

    def crash(self, session_id: int) -> None:
        self.killed = self.fleet.owner_name(session_id)
        assert self.killed is not None, "no worker holds the session"
        self.fleet.workers[self.killed].kill()

    def after_crash(self) -> None:
        pass  # the reaper interrupts the session when its lease runs out; the other worker resumes it

    def stored(self, session_id: int) -> dict:
        with Session(self.fleet.engine) as db:
            rows = db.exec(select(Measurement).where(Measurement.session_id == session_id)).all()
            return {(m.seq, m.target): (m.id, m.x, m.y, m.z) for m in rows}

    def restore(self) -> None:
        """Start the killed worker again, for the module's next tests."""
        if self.killed is not None:
            sites = self.fleet.workers[self.killed].sites
            self.fleet.start_worker(self.killed, sites)
            self.killed = None


class TestFleetRunner(RunnerContract):
    @pytest.fixture
    def deployment(self, fleet):
        d = FleetDeployment(fleet)
        yield d
        d.restore()
