"""The task queue: Procrastinate on the fleet's PostgreSQL store.

A session is one job of the task ``recal.run_session`` (``{"session_id": N}``):

- queue ``site:<site>`` of the session's cell: a worker serves the sites whose networks it
  reaches (``recal worker --site``);
- ``lock`` ``cell:<id>``: Procrastinate runs at most one job per lock at a time (a unique index
  on the jobs table), on top of the session lease in our own tables;
- ``queueing_lock`` ``session:<id>``: one waiting job per session, however often it is resumed.

The job is deferred in the same transaction as the session's ``planned`` state
(:func:`defer_session`, called by the API routes through ``FleetRunner.queue``), so a
session is never queued twice and never stored planned without its job.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
from typing import Any

import psycopg
from procrastinate import App, PsycopgConnector, SyncPsycopgConnector, exceptions, sql
from procrastinate.jobs import Job
from procrastinate.schema import SchemaManager
from sqlalchemy import text
from sqlalchemy.engine import Engine, make_url
from sqlmodel import Session

from calibration.errors import RecalError

from ..models import Cell, RunSession
from ..settings import Settings

log = logging.getLogger("recal.fleet")

TASK = "recal.run_session"
# Connecting to PostgreSQL on a machine that is busy (a night's sessions starting together) can
# take seconds; a shorter limit turns load into errors.
CONNECT_TIMEOUT_S = 15
# LISTEN/NOTIFY channel names are at most 63 bytes; Procrastinate's prefix takes 23.
_MAX_SITE = 35


class FleetConfigError(RecalError, ValueError):
    """The settings do not describe a fleet (one line for the user)."""


def queue_for_site(site: str) -> str:
    """The queue of a site's sessions."""
    if len(site.encode()) <= _MAX_SITE:
        return f"site:{site}"
    return "site:#" + hashlib.sha1(site.encode()).hexdigest()[:20]


def libpq_url(settings: Settings) -> str:
    """The store's URL as libpq (psycopg) takes it; the fleet needs PostgreSQL."""
    if not settings.database_url or not settings.database_url.startswith("postgresql"):
        raise FleetConfigError(
            "RECAL_ENGINE=procrastinate needs RECAL_DATABASE_URL=postgresql+psycopg://... "
            "(the queue lives in the fleet's PostgreSQL store)"
        )
    return make_url(settings.database_url).set(drivername="postgresql").render_as_string(hide_password=False)


def ensure_schema(engine: Engine) -> None:
    """Create Procrastinate's tables in the store if they are missing (once, whichever process
    starts first: under the same advisory lock as our migrations)."""
    with engine.begin() as conn:
        conn.execute(text("SELECT pg_advisory_xact_lock(72430111)"))
        if conn.execute(text("SELECT to_regclass('procrastinate_jobs')")).scalar() is None:
            log.info("creating the task queue's tables (procrastinate schema)")
            conn.connection.driver_connection.execute(SchemaManager.get_schema())


def sync_app(settings: Settings, *, max_size: int = 4) -> App:
    """A Procrastinate app for synchronous use (API processes, reapers), opened."""
    app = App(
        connector=SyncPsycopgConnector(
            conninfo=libpq_url(settings), min_size=1, max_size=max_size, kwargs={"connect_timeout": CONNECT_TIMEOUT_S}
        )
    )
    app.open()
    return app


def _connection_lost(exc: BaseException) -> bool:
    cause = exc.__cause__ if isinstance(exc, exceptions.ConnectorException) else exc
    return isinstance(cause, psycopg.OperationalError)


class ResilientConnector(PsycopgConnector):
    """Procrastinate's asyncio connector, riding out a database restart.

    Procrastinate stops a worker when a side task (heartbeat, LISTEN) or a fetch fails: here a
    lost connection is retried instead (the pool replaces dead connections), a fetch that
    cannot reach the database finds no job (the worker polls again), and LISTEN reconnects."""

    RETRY_FOR_S = 120.0

    async def _retrying(self, fn, query, arguments: dict[str, Any]):
        delay, waited = 0.2, 0.0
        while True:
            try:
                return await fn(query, **arguments)
            except exceptions.ConnectorException as exc:
                if not _connection_lost(exc) or waited >= self.RETRY_FOR_S:
                    raise
                if query == sql.queries["fetch_job"]:
                    log.warning("fetching a job: the database is unreachable (%s); polling again", exc.__cause__)
                    return {"id": None}
                log.warning("the database is unreachable (%s); retrying in %.1f s", exc.__cause__, delay)
                await asyncio.sleep(delay)
                waited += delay
                delay = min(delay * 2, 5.0)

    async def execute_query_async(self, query, **arguments):
        return await self._retrying(super().execute_query_async, query, arguments)

    async def execute_query_one_async(self, query, **arguments):
        return await self._retrying(super().execute_query_one_async, query, arguments)

    async def execute_query_all_async(self, query, **arguments):
        return await self._retrying(super().execute_query_all_async, query, arguments)

    async def listen_notify(self, on_notification, channels) -> None:
        delay = 0.2
        while True:
            try:
                await super().listen_notify(on_notification=on_notification, channels=channels)
                return
            except exceptions.ConnectorException as exc:
                if not _connection_lost(exc):
                    raise
                log.warning("LISTEN: the database is unreachable (%s); reconnecting in %.1f s", exc.__cause__, delay)
                await asyncio.sleep(delay)
                delay = min(delay * 2, 5.0)
            except psycopg.OperationalError as exc:
                log.warning("LISTEN: the database is unreachable (%s); reconnecting in %.1f s", exc, delay)
                await asyncio.sleep(delay)
                delay = min(delay * 2, 5.0)


def worker_app(settings: Settings, *, max_size: int) -> App:
    """The asyncio Procrastinate app a worker runs (open it with ``open_async``)."""
    return App(
        connector=ResilientConnector(
            conninfo=libpq_url(settings), min_size=2, max_size=max_size, kwargs={"connect_timeout": CONNECT_TIMEOUT_S}
        )
    )


def defer_session(db: Session, app: App, run: RunSession, cell: Cell) -> int | None:
    """Queue ``run`` for a worker of its cell's site, in ``db``'s transaction (the caller
    commits). Returns the job id, or None when a job for the session is waiting already."""
    job = Job(
        queue=queue_for_site(cell.site),
        lock=f"cell:{cell.id}",
        queueing_lock=f"session:{run.id}",
        task_name=TASK,
        task_kwargs={"session_id": run.id},
    )
    try:
        with db.begin_nested():  # a refused duplicate rolls back to here, not the whole transaction
            conn = db.connection().connection.driver_connection  # psycopg's, inside the SAVEPOINT
            return app.job_manager.defer_job(job, connection=conn).id
    except exceptions.AlreadyEnqueued:
        return None


def cancel_waiting(app: App, session_id: int) -> bool:
    """Cancel the session's job if it is still waiting in its queue; True if one was."""
    cancelled = False
    for job in app.job_manager.list_jobs(task=TASK, queueing_lock=f"session:{session_id}", status="todo"):
        cancelled |= app.job_manager.cancel_job_by_id(job.id)
    return cancelled


def session_jobs(app: App, status: str) -> dict[int, Job]:
    """``{session id: job}`` of the session jobs in ``status`` (``todo``, ``doing``)."""
    out = {}
    for job in app.job_manager.list_jobs(task=TASK, status=status):
        sid = job.task_kwargs.get("session_id")
        if isinstance(sid, int):
            out[sid] = job
    return out


def fail_job(app: App, job_id: int) -> bool:
    """End a job left ``doing`` by a vanished worker as ``failed`` (frees its cell's lock)."""
    try:
        if not app.job_manager.cancel_job_by_id(job_id, abort=True):
            return False
        app.job_manager.retry_job_by_id(job_id, retry_at=_now())  # doing + abort requested -> failed
        return True
    except exceptions.ConnectorException as exc:
        log.info("job %s ended meanwhile: %s", job_id, exc.__cause__ or exc)
        return False


def _now():
    from datetime import UTC, datetime

    return datetime.now(UTC)
