"""The reaper: sessions whose worker vanished become ``interrupted`` (resumable, measurements
kept), jobs that vanished workers left ``doing`` are ended so that their cell's lock is free,
and sessions left ``planned`` without a job are queued again.

Every worker and every API process runs one (a thread, every third of the lease); they may run
at once: each change is a conditional update that only one of them makes. A busy machine makes
everything slower, never one of these: a worker that is alive shows it by its lease (renewed by
its monitor, or by the session itself before its next move) and by its heartbeat in the task
queue (``procrastinate_workers``), and a session that never moved is queued again, not
interrupted.

1. A session ``planned`` or ``running`` whose lease expired (its worker stopped renewing it:
   killed, powered off, cut off from the database for longer than the lease) -> ``interrupted``.
2. A ``doing`` job whose worker has sent no heartbeat for a whole lease period (the worker is
   gone) and whose session holds no live lease -> the job is ended ``failed``, so that the
   cell's lock is free (a session it had started is interrupted by 1.; one it had not yet
   claimed is queued again by 3.).
3. A ``planned`` session that nobody has claimed and that has no job waiting or running for a
   whole lease period (a worker gave its job up; a session planned outside the API, e.g. by
   hand in the database) -> queued. Nothing has moved: it runs as it was asked to. A pause or
   abort asked meanwhile is honoured by the worker that claims it.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import timedelta

from sqlalchemy import text, update
from sqlmodel import Session, select

from ..models import ACTIVE, Cell, RunSession, utcnow
from ..store import as_utc, database_unavailable
from . import jobs

log = logging.getLogger("recal.fleet.reaper")


class Reaper:
    def __init__(self, engine, app, ttl_s: float, *, name: str = "reaper"):
        self.engine, self.app, self.ttl_s, self.name = engine, app, ttl_s, name
        self.grace_s = max(1.0, ttl_s / 6)
        self.interval_s = max(0.5, ttl_s / 3)
        self._suspect_planned: dict[int, float] = {}  # session id -> when first seen planned without a job
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the passes

    def reap_once(self) -> list[int]:
        """One pass; returns the sessions it interrupted."""
        now = utcnow()
        cutoff = now - timedelta(seconds=self.grace_s)
        out: list[int] = []
        with Session(self.engine) as db:
            res = db.exec(
                update(RunSession)
                .where(
                    RunSession.state.in_(ACTIVE),
                    RunSession.lease_expires.is_not(None),
                    RunSession.lease_expires < cutoff,
                )
                .values(
                    state="interrupted",
                    updated_at=now,
                    requested=None,
                    reason="its worker stopped renewing its hold on the cell (the worker died or lost "
                    "the database); every measurement it reported is kept: resume it to continue",
                )
                .returning(RunSession.id)
            )
            out += list(res.scalars().all())
            db.commit()
        if out:
            log.warning("%s: sessions interrupted, their worker is gone: %s", self.name, out)
            doing = jobs.session_jobs(self.app, "doing")
            for sid in out:  # their worker stopped moving before the lease ran out: free the cell's lock now
                if sid in doing:
                    jobs.fail_job(self.app, doing[sid].id)
        self._orphan_jobs(cutoff)
        self._requeue_unclaimed()
        return out

    def _orphan_jobs(self, cutoff) -> None:
        doing = jobs.session_jobs(self.app, "doing")
        if not doing:
            return
        with Session(self.engine) as db:
            alive = set(
                db.exec(
                    text(
                        "SELECT id FROM procrastinate_workers WHERE last_heartbeat > now() - make_interval(secs => :s)"
                    ),
                    params={"s": self.ttl_s},
                )
                .scalars()
                .all()
            )
            for sid, job in doing.items():
                if job.worker_id in alive:
                    continue
                run = db.get(RunSession, sid)
                if (
                    run is not None
                    and run.state in ACTIVE
                    and run.lease_expires is not None
                    and as_utc(run.lease_expires) >= cutoff
                ):
                    continue  # its lease is live: pass 1 decides when it runs out
                if jobs.fail_job(self.app, job.id):
                    log.warning("%s: job %s of session %s: its worker is gone; ended as failed", self.name, job.id, sid)

    def _requeue_unclaimed(self) -> None:
        mono = time.monotonic()
        with Session(self.engine) as db:
            planned = db.exec(
                select(RunSession.id).where(RunSession.state == "planned", RunSession.lease_expires.is_(None))
            ).all()
        if not planned:
            self._suspect_planned = {}
            return
        queued = set(jobs.session_jobs(self.app, "todo")) | set(jobs.session_jobs(self.app, "doing"))
        self._suspect_planned = {sid: self._suspect_planned.get(sid, mono) for sid in planned if sid not in queued}
        for sid, since in list(self._suspect_planned.items()):
            if mono - since >= self.ttl_s:
                self._suspect_planned.pop(sid, None)
                if self._requeue(sid):
                    log.warning(
                        "%s: session %s was planned with no job for a worker for %.0f s: queued it again",
                        self.name,
                        sid,
                        mono - since,
                    )

    def _requeue(self, sid: int) -> bool:
        with Session(self.engine) as db:
            run = db.get(RunSession, sid, with_for_update=True)
            if run is None or run.state != "planned" or run.lease_expires is not None:
                return False  # claimed or ended meanwhile
            job_id = jobs.defer_session(db, self.app, run, db.get(Cell, run.cell_id))
            db.commit()
            return job_id is not None

    # ------------------------------------------------------------------ the thread

    def start(self) -> Reaper:
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        failing = False
        while not self._stop.wait(self.interval_s):
            try:
                self.reap_once()
                failing = False
            except Exception as exc:  # the reaper must outlive a database restart
                if not failing:
                    level = (
                        logging.WARNING if database_unavailable(exc) or "connect" in str(exc).lower() else logging.ERROR
                    )
                    log.log(level, "%s: pass failed: %s", self.name, exc, exc_info=level == logging.ERROR)
                failing = True

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
