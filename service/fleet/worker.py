"""The worker process (``recal worker --site ...``): runs the sessions queued for its sites.

Per job (one session): claim the session (it must still be ``planned``; a pause or abort asked
while it waited is honoured without moving), take the cell's lease, then ``run_session`` as the
embedded default does, in a thread. Around it, one monitor thread for the whole process, on
database connections of its own (a busy session pool cannot hold it up):

- renews the lease of every session it runs every sixth of the lease; a session whose lease
  was not renewed in time (the monitor late: a loaded machine) renews it itself before its
  next move (``Control.renew``), standing still meanwhile. Only if the store says the hold is
  gone (the reaper of another process took it after it ran out) does the session stop,
  ``interrupted``: by then it stands still, so no other worker can ever drive it at the same
  time;
- carries pause and abort requests (``session.requested``; LISTEN ``recal_control`` wakes it at
  once, a poll every 0.25 s is the fallback); an abort stops the robot immediately.

The database going away or answering slowly: claiming a session waits for it (the job is not
given up, the session stays queued); measurement commits are retried (session_loop); if a
session still cannot go on, the worker waits for the database and, if it still holds the lease,
continues the session where it stopped; otherwise the session ends ``interrupted``.
SIGTERM / SIGINT: no new job; every running session stops between two steps as
``interrupted`` (resumable), then the process exits.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta

import psycopg
from sqlalchemy import create_engine, text, update
from sqlmodel import Session

from ..models import ACTIVE, RunSession, utcnow
from ..session_loop import Control, run_session, store_abort
from ..settings import Settings
from ..store import acquire_lease, database_unavailable, held_by_other, migrate, set_state
from . import jobs
from .reaper import Reaper
from .runner import CONTROL_CHANNEL

log = logging.getLogger("recal.fleet.worker")


class Monitor:
    """Lease renewal and pause/abort requests for the sessions this process runs."""

    def __init__(self, engine, conninfo: str, owner: str, ttl_s: float):
        self.engine, self.conninfo, self.owner, self.ttl_s = engine, conninfo, owner, ttl_s
        self.safety_s = max(1.0, ttl_s / 6)  # stop moving this long before the lease runs out
        self.renew_every_s = ttl_s / 6  # five chances to renew before the session has to itself
        self.controls: dict[int, Control] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._listen: psycopg.Connection | None = None
        self._thread = threading.Thread(target=self._loop, name="monitor", daemon=True)
        self._next_renew = 0.0

    def add(self, sid: int, control: Control) -> None:
        with self._lock:
            self.controls[sid] = control

    def remove(self, sid: int) -> None:
        with self._lock:
            self.controls.pop(sid, None)

    def snapshot(self) -> dict[int, Control]:
        with self._lock:
            return dict(self.controls)

    def valid_until(self, t0: float) -> float:
        return t0 + self.ttl_s - self.safety_s

    def renew(self, sids) -> set[int]:
        """Renew the leases this process holds on ``sids``; returns those renewed."""
        if not sids:
            return set()
        t0 = time.monotonic()
        with Session(self.engine) as db:
            res = db.exec(
                update(RunSession)
                .where(
                    RunSession.id.in_(list(sids)), RunSession.lease_owner == self.owner, RunSession.state.in_(ACTIVE)
                )
                .values(lease_expires=utcnow() + timedelta(seconds=self.ttl_s))
                .returning(RunSession.id)
            )
            renewed = set(res.scalars().all())
            db.commit()
        controls = self.snapshot()
        for sid in sids:
            c = controls.get(sid)
            if c is None:
                continue
            if sid in renewed:
                c.lease_valid_until = self.valid_until(t0)
            else:  # reaped or taken over: never move again
                c.interrupt_reason = (
                    "this worker's hold on the cell ran out before it was renewed and the cell was "
                    "released; every measurement reported is kept: resume the session to continue"
                )
                c.interrupt.set()
        return renewed

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)
        if self._listen is not None:
            self._listen.close()

    def _wait(self, timeout_s: float) -> None:
        """Sleep up to ``timeout_s``, woken early by a NOTIFY on the control channel."""
        try:
            if self._listen is None or self._listen.closed:
                self._listen = psycopg.connect(self.conninfo, autocommit=True, connect_timeout=3)
                self._listen.execute(f"LISTEN {CONTROL_CHANNEL}")
            for _ in self._listen.notifies(timeout=timeout_s, stop_after=1):
                pass
        except psycopg.Error:
            if self._listen is not None:
                self._listen.close()
            self._listen = None
            self._stop.wait(timeout_s)

    def _loop(self) -> None:
        failing = False
        while not self._stop.is_set():
            controls = self.snapshot()
            if not controls:
                self._stop.wait(0.25)
                continue
            try:
                with Session(self.engine) as db:
                    rows = db.exec(
                        text("SELECT id, requested FROM session WHERE id = ANY(:ids)"), params={"ids": list(controls)}
                    ).all()
                for sid, req in rows:
                    c = controls.get(sid)
                    if c is not None and req:
                        self._apply(sid, c, req)
                if time.monotonic() >= self._next_renew:
                    self._next_renew = time.monotonic() + self.renew_every_s
                    self.renew(set(controls))
                failing = False
            except Exception as exc:  # noqa: BLE001 - keep monitoring through a database restart
                if not failing:
                    log.warning("monitor: %s", exc)
                failing = True
            self._wait(0.25)

    def _apply(self, sid: int, c: Control, req: str) -> None:
        if req == "abort" and not c.abort.is_set():
            log.info("session %s: abort requested, stopping the robot", sid)
            certain = c.request_abort()
            # in a thread: a real robot's stop returns once it has decelerated; then, as the
            # embedded runner does, a certain abort is stored at once (session_loop.store_abort)
            threading.Thread(target=_stop_robot, args=(self.engine, sid, c, certain), daemon=True).start()
        elif req == "pause" and not c.pause.is_set():
            log.info("session %s: pause requested", sid)
            c.pause.set()


def _stop_robot(engine, sid: int, c: Control, certain: bool) -> None:
    devs = c.devices
    if devs is not None and devs.robot is not None:
        try:
            devs.robot.stop()
        except Exception:  # noqa: BLE001 - the session stops the robot again on its way out
            pass
    if certain:
        store_abort(engine, sid, c)


class WorkerRuntime:
    """A worker process: its engine, monitor, reaper and the Procrastinate worker."""

    def __init__(self, settings: Settings, *, name: str, sites: list[str] | None, concurrency: int):
        self.settings, self.name, self.sites, self.concurrency = settings, name, sites, concurrency
        self.ttl_s = settings.effective_lease_ttl_s
        self.owner = f"worker:{name}:{socket.gethostname()}:{os.getpid()}"
        conninfo = jobs.libpq_url(settings)
        # One connection per running session (run_session holds one between its commits), one
        # for claiming the next, a few for bursts; no more: PostgreSQL's connections are few
        # (docs/fleet.md, sizing), and a server out of them refuses everyone.
        self.engine = create_engine(
            settings.database_url,
            pool_pre_ping=True,
            pool_size=concurrency + 1,
            max_overflow=4,
            connect_args={"connect_timeout": jobs.CONNECT_TIMEOUT_S},
        )
        # The monitor and the reaper on connections of their own: however busy the sessions, the
        # leases are renewed on time. (A session renewing its own late lease uses these too.)
        self.control_engine = create_engine(
            settings.database_url,
            pool_pre_ping=True,
            pool_size=2,
            max_overflow=2,
            connect_args={"connect_timeout": jobs.CONNECT_TIMEOUT_S},
        )
        migrate(self.engine)
        jobs.ensure_schema(self.engine)
        self.monitor = Monitor(self.control_engine, conninfo, self.owner, self.ttl_s)
        self.jobs_sync = jobs.sync_app(settings, max_size=2)
        self.reaper = Reaper(self.control_engine, self.jobs_sync, self.ttl_s, name=f"{name}-reaper")
        self.app = jobs.worker_app(settings, max_size=4)
        self.app.task(name=jobs.TASK, pass_context=True)(self.run_job)
        self.queues = None if sites is None else [jobs.queue_for_site(s) for s in sites]
        self.stopping = threading.Event()
        # As the embedded runner: planning and identification of this worker's sessions take at
        # most heavy_workers cores at once (service.control.heavy_slot), so that many sessions
        # finishing together do not starve the ones still moving (their pause, abort, renewals).
        self.heavy = threading.BoundedSemaphore(settings.heavy_workers)

    # ------------------------------------------------------------------ one job

    def run_job(self, context, session_id: int) -> str:
        control = Control(renew=lambda: self.monitor.renew({session_id}), heavy=self.heavy)
        outcome = self._claim_patiently(session_id, control)
        if outcome is not None:
            log.info("session %s: %s", session_id, outcome)
            return outcome
        self.monitor.add(session_id, control)
        try:
            return self._run(session_id, control)
        finally:
            self.monitor.remove(session_id)

    def _claim_patiently(self, sid: int, control: Control) -> str | None:
        """``_claim``, waiting for a store that is away or slow to answer (a loaded machine)
        instead of giving the job up. Nothing has moved yet: waiting is always safe. If the
        store stays away, the job fails and the session stays ``planned``: the reaper queues it
        again once the store is back (service.fleet.reaper)."""
        deadline = time.monotonic() + max(2 * self.ttl_s, 30.0)
        delay = 0.2
        while True:
            try:
                return self._claim(sid, control)
            except Exception as exc:  # the session must end in a state, never a traceback
                if not database_unavailable(exc):
                    log.error("session %s: %s", sid, traceback.format_exc())
                    self._end_if_ours(
                        sid, "failed", f"internal error in the worker: {type(exc).__name__}: {exc}", claiming=True
                    )
                    return "failed"
                if self.stopping.is_set() or time.monotonic() + delay > deadline:
                    raise
                log.warning(
                    "session %s: cannot claim it yet, the database is unreachable or slow (%s); retrying",
                    sid,
                    getattr(exc, "orig", None) or exc,
                )
                time.sleep(delay)
                delay = min(2 * delay, 5.0)

    def _claim(self, sid: int, control: Control) -> str | None:
        """Take the session for this process; None when taken, else why not."""
        with Session(self.engine) as db:
            run = db.get(RunSession, sid)
            if run is None:
                return "no such session"
            if run.state != "planned":
                return f"nothing to do, the session is {run.state}"
            if run.requested in ("pause", "abort"):
                state = "paused" if run.requested == "pause" else "aborted"
                set_state(db, run, state, f"{state} on request")
                return state
            t0 = time.monotonic()
            if not acquire_lease(db, run, self.owner, ttl_s=self.ttl_s):
                db.refresh(run)
                if held_by_other(run, self.owner):
                    return f"another worker holds it ({run.lease_owner})"
                set_state(db, run, "paused", "another session is driving this cell")
                return "paused"
            db.refresh(run)
            if run.state != "planned":  # interrupted or aborted between our look and our lease
                return f"nothing to do, the session is {run.state}"
            control.lease_valid_until = self.monitor.valid_until(t0)
            return None

    def _run(self, sid: int, control: Control) -> str:
        attempts = 0
        while True:
            try:
                return run_session(self.engine, self.settings, sid, control, owner=self.owner, leased=True)
            except Exception as exc:  # noqa: BLE001 - the session must end in a state, never a traceback
                if not database_unavailable(exc):
                    log.error("session %s: %s", sid, traceback.format_exc())
                    self._end_if_ours(sid, "failed", f"internal error in the worker: {type(exc).__name__}: {exc}")
                    return "failed"
                attempts += 1
                log.warning("session %s: the database is unreachable (%s); waiting for it", sid, exc.orig or exc)
                if attempts > 5 or not self._wait_for_database(sid, control):
                    break
                log.info("session %s: the database is back and the cell still ours; continuing", sid)
        self._end_if_ours(
            sid,
            "interrupted",
            "the database was unreachable for longer than the lease; every "
            "measurement reported is kept: resume the session to continue",
        )
        return "interrupted"

    def _wait_for_database(self, sid: int, control: Control) -> bool:
        """Wait for the store; True if it is back and this process still holds the session."""
        deadline = time.monotonic() + max(2 * self.ttl_s, 30.0)
        while time.monotonic() < deadline:
            if control.interrupt.is_set() or control.abort.is_set():
                return False
            try:
                return sid in self.monitor.renew({sid})
            except Exception:  # noqa: BLE001 - still away
                time.sleep(0.5)
        return False

    def _end_if_ours(self, sid: int, state: str, reason: str, *, claiming: bool = False) -> None:
        """Record the session's end if this process holds it (``claiming``: or nobody does yet)."""
        deadline = time.monotonic() + max(2 * self.ttl_s, 30.0)
        ours = RunSession.lease_owner == self.owner
        if claiming:
            ours = ours | RunSession.lease_expires.is_(None)
        while True:
            try:
                with Session(self.engine) as db:
                    db.exec(
                        update(RunSession)
                        .where(RunSession.id == sid, ours, RunSession.state.in_(ACTIVE))
                        .values(state=state, reason=reason, updated_at=utcnow(), lease_expires=utcnow())
                    )
                    db.commit()
                return
            except Exception:  # noqa: BLE001 - the store may fail in any way while it restarts; the reaper ends it else
                if time.monotonic() > deadline:
                    log.error("session %s: could not record it %s; the reaper will", sid, state)
                    return
                time.sleep(1.0)

    def interrupt_all(self, reason: str) -> None:
        for c in self.monitor.snapshot().values():
            c.interrupt_reason = reason
            c.interrupt.set()

    # ------------------------------------------------------------------ the process

    async def serve(self, on_ready=None) -> None:
        loop = asyncio.get_running_loop()
        # Procrastinate runs synchronous tasks in the loop's default executor: one thread per session.
        loop.set_default_executor(ThreadPoolExecutor(max_workers=self.concurrency + 4, thread_name_prefix="session"))
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        async with self.app.open_async():
            self.monitor.start()
            self.reaper.start()
            if on_ready is not None:
                on_ready()
            while not stop.is_set():
                worker = asyncio.create_task(
                    self.app.run_worker_async(
                        queues=self.queues,
                        name=self.name,
                        concurrency=self.concurrency,
                        install_signal_handlers=False,
                        listen_notify=True,
                        fetch_job_polling_interval=1.0,
                        delete_jobs="successful",
                        update_heartbeat_interval=max(1.0, self.ttl_s / 3),
                        stalled_worker_timeout=max(3.0, self.ttl_s),
                        shutdown_graceful_timeout=None,
                    )
                )
                stopper = asyncio.create_task(stop.wait())
                done, _ = await asyncio.wait({worker, stopper}, return_when=asyncio.FIRST_COMPLETED)
                if stopper in done:
                    log.info("stopping: running sessions stop between two steps, as interrupted")
                    self.stopping.set()
                    self.interrupt_all(
                        "the worker was stopped; every measurement reported is kept: resume the session to continue"
                    )
                    worker.cancel()
                    try:
                        await worker
                    except BaseException:  # noqa: BLE001 - cancelled, as asked
                        pass
                    break
                stopper.cancel()
                err = None if worker.cancelled() else worker.exception()
                log.warning("the job loop stopped (%s); starting it again", err)
                await asyncio.sleep(1.0)
        self.monitor.stop()
        self.reaper.stop()
        self.jobs_sync.close()
        self.engine.dispose()
        self.control_engine.dispose()


def run_worker(settings: Settings, *, name: str, sites: list[str] | None, concurrency: int) -> int:
    rt = WorkerRuntime(settings, name=name, sites=sites, concurrency=concurrency)

    def ready():
        print(
            json.dumps(
                {
                    "ready": True,
                    "worker": name,
                    "owner": rt.owner,
                    "pid": os.getpid(),
                    "sites": sites,
                    "queues": rt.queues,
                    "concurrency": concurrency,
                }
            ),
            flush=True,
        )

    asyncio.run(rt.serve(on_ready=ready))
    return 0
