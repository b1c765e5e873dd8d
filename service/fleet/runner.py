"""``FleetRunner``: what an API process uses when ``RECAL_ENGINE=procrastinate``.

The same methods as the embedded :class:`service.session_loop.EmbeddedRunner`, but nothing runs
here: ``queue`` puts the session's job on the queue of its cell's site in the API request's own
transaction (the session is stored planned and queued at once; ``start`` does the same in a
transaction of its own), ``pause`` and ``abort`` go through the database (``session.requested``,
and a NOTIFY on ``recal_control`` so that the worker running the session hears it at once),
and a job still waiting in its queue is cancelled outright.
"""

from __future__ import annotations

import logging
import os
import socket
import time

from sqlalchemy import text, update
from sqlmodel import Session

from ..models import Cell, RunSession
from ..settings import Settings
from ..store import held_by_other
from . import jobs
from .reaper import Reaper

log = logging.getLogger("recal.fleet")

CONTROL_CHANNEL = "recal_control"


class FleetRunner:
    """Queues sessions for the fleet's workers and relays pause and abort to them; a
    :class:`service.runners.SessionRunner`."""

    distributed = True  # sessions run in other processes: an API start must not interrupt them

    def __init__(self, engine, settings: Settings):
        self.engine, self.settings = engine, settings
        # Leases nothing: the app's "interrupt what this process was running" on shutdown is a no-op.
        self.owner = f"api:{socket.gethostname()}:{os.getpid()}"
        jobs.libpq_url(settings)  # PostgreSQL, or one clear line
        jobs.ensure_schema(engine)
        self.app = jobs.sync_app(settings)
        self.reaper = Reaper(engine, self.app, settings.effective_lease_ttl_s, name="api-reaper").start()

    def queue(self, db: Session, run: RunSession) -> bool:
        """Queue ``run`` (planned, flushed) for a worker of its cell's site in the caller's
        transaction: the caller commits the session and its job at once, so a session is never
        stored planned without its job. False when a worker holds it already (nothing queued)."""
        if held_by_other(run, self.owner):
            return False  # two resumes at once: a worker has it already
        run.requested = None
        # Marked queued, not leased: a worker that had it before (and lost it) may not write
        # its state any more (run_session checks the owner), the next worker takes the lease.
        run.lease_owner, run.lease_expires = f"queued:{self.owner}", None
        db.add(run)
        jobs.defer_session(db, self.app, run, db.get(Cell, run.cell_id))
        return True

    def start(self, session_id: int) -> None:
        """Queue the session (planned) for a worker of its cell's site, in a transaction of its
        own, under a lock on its row. The API routes queue in their own transaction
        (:meth:`queue`) and call this only when that found a worker holding the session: then
        this queues nothing either, unless the worker let the session go meanwhile."""
        with Session(self.engine) as db:
            run = db.get(RunSession, session_id, with_for_update=True)
            if run.state == "planned" and self.queue(db, run):
                db.commit()

    def _request(self, session_id: int, what: str) -> bool:
        """Record ``what`` for the session; False when nothing will act on it (the route then
        records the state itself)."""
        with Session(self.engine) as db:
            res = db.exec(
                update(RunSession)
                .where(RunSession.id == session_id, RunSession.state.in_(("planned", "running")))
                .values(requested=what)
            )
            if res.rowcount:
                db.exec(text("SELECT pg_notify(:c, :p)"), params={"c": CONTROL_CHANNEL, "p": f"{session_id}:{what}"})
            db.commit()
        if not res.rowcount:
            return False
        if jobs.cancel_waiting(self.app, session_id):
            return False  # it never started: nothing moved, nothing to stop
        return bool(jobs.session_jobs(self.app, "doing").get(session_id))

    def pause(self, session_id: int) -> bool:
        return self._request(session_id, "pause")

    def abort(self, session_id: int) -> bool:
        """The worker running the session stops the robot as soon as it hears it."""
        return self._request(session_id, "abort")

    def is_active(self, session_id: int) -> bool:
        with Session(self.engine) as db:
            run = db.get(RunSession, session_id)
            return run is not None and run.state in ("planned", "running")

    def wait(self, session_id: int, timeout_s: float | None = None) -> None:
        # Polled often: the abort route answers once the worker has stored the end (a read by
        # primary key; every 0.2 s had added up to 0.2 s to an abort's answer).
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.is_active(session_id) and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.02)

    def not_ready(self) -> str | None:
        """Always ready: its queue is in the database, which ``/ready`` checks itself."""
        return None

    def shutdown(self, timeout_s: float = 5.0) -> None:
        self.reaper.stop()
        self.app.close()
