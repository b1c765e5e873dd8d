"""The reaper: sessions whose worker vanished become ``interrupted`` (resumable, measurements
kept), and the jobs those workers left ``doing`` are ended so that their cell's lock is free.

Every worker and every API process runs one (a thread, every third of the lease); they may run
at once: each change is a conditional update that only one of them makes.

1. A session ``planned`` or ``running`` whose lease expired (its worker stopped renewing it:
   killed, powered off, cut off from the database for longer than the lease) -> ``interrupted``.
2. A ``doing`` job whose session has had no live lease for a whole lease period -> the job is
   ended ``failed`` (the worker is gone or lost track of it), its session interrupted if active.
3. A ``planned`` session with no job waiting or running for a whole lease period (the API
   process stopped between the session and its job; cannot happen when both are in one
   transaction, kept as a safety net) -> ``interrupted``.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import timedelta

from sqlalchemy import update
from sqlmodel import Session, select

from ..models import RunSession, utcnow
from ..orchestrator import database_unavailable
from ..store import _aware
from . import jobs

log = logging.getLogger("recal.fleet.reaper")

ACTIVE = ("planned", "running")


class Reaper:
    def __init__(self, engine, app, ttl_s: float, *, name: str = "reaper"):
        self.engine, self.app, self.ttl_s, self.name = engine, app, ttl_s, name
        self.grace_s = max(1.0, ttl_s / 6)
        self.interval_s = max(0.5, ttl_s / 3)
        self._suspect_jobs: dict[int, float] = {}  # job id -> when first seen without a live lease
        self._suspect_planned: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the passes

    def reap_once(self) -> list[int]:
        """One pass; returns the sessions it interrupted."""
        now = utcnow()
        cutoff = now - timedelta(seconds=self.grace_s)
        out: list[int] = []
        with Session(self.engine) as db:
            res = db.exec(update(RunSession)
                          .where(RunSession.state.in_(ACTIVE), RunSession.lease_expires.is_not(None),
                                 RunSession.lease_expires < cutoff)
                          .values(state="interrupted", updated_at=now, requested=None,
                                  reason="its worker stopped renewing its hold on the cell (the worker died or lost "
                                         "the database); every measurement it reported is kept: resume it to continue")
                          .returning(RunSession.id))
            out += list(res.scalars().all())
            db.commit()
        if out:
            log.warning("%s: sessions interrupted, their worker is gone: %s", self.name, out)
            doing = jobs.session_jobs(self.app, "doing")
            for sid in out:  # their worker stopped moving before the lease ran out: free the cell's lock now
                if sid in doing:
                    jobs.fail_job(self.app, doing[sid])
        out += self._orphan_jobs(cutoff)
        out += self._unqueued_sessions()
        return out

    def _orphan_jobs(self, cutoff) -> list[int]:
        doing = jobs.session_jobs(self.app, "doing")
        mono = time.monotonic()
        suspects = {}
        with Session(self.engine) as db:
            for sid, job_id in doing.items():
                run = db.get(RunSession, sid)
                live = (run is not None and run.lease_expires is not None and _aware(run.lease_expires) >= cutoff
                        and run.state in ACTIVE)
                if not live:
                    suspects[job_id] = (sid, self._suspect_jobs.get(job_id, mono))
        self._suspect_jobs = {j: t for j, (_, t) in suspects.items()}
        out = []
        for job_id, (sid, since) in suspects.items():
            if mono - since < self.ttl_s:
                continue
            if jobs.fail_job(self.app, job_id):
                log.warning("%s: job %s of session %s had no live worker: ended as failed", self.name, job_id, sid)
            if self._interrupt(sid, "its worker lost track of it; every measurement it reported is kept: resume it to "
                                    "continue"):
                out.append(sid)
            self._suspect_jobs.pop(job_id, None)
        return out

    def _unqueued_sessions(self) -> list[int]:
        mono = time.monotonic()
        with Session(self.engine) as db:
            planned = db.exec(select(RunSession.id).where(RunSession.state == "planned",
                                                          RunSession.lease_expires.is_(None))).all()
        if not planned:
            self._suspect_planned = {}
            return []
        queued = set(jobs.session_jobs(self.app, "todo")) | set(jobs.session_jobs(self.app, "doing"))
        self._suspect_planned = {sid: self._suspect_planned.get(sid, mono) for sid in planned if sid not in queued}
        out = []
        for sid, since in list(self._suspect_planned.items()):
            if mono - since >= self.ttl_s and self._interrupt(
                    sid, "it was never queued for a worker (the API process stopped?): resume it to run it", state="planned"):
                out.append(sid)
                self._suspect_planned.pop(sid, None)
        return out

    def _interrupt(self, sid: int, reason: str, *, state: str | None = None) -> bool:
        with Session(self.engine) as db:
            q = update(RunSession).where(RunSession.id == sid)
            q = q.where(RunSession.state == state) if state else q.where(RunSession.state.in_(ACTIVE))
            res = db.exec(q.values(state="interrupted", reason=reason, updated_at=utcnow(), requested=None))
            db.commit()
            return res.rowcount > 0

    # ------------------------------------------------------------------ the thread

    def start(self) -> "Reaper":
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        failing = False
        while not self._stop.wait(self.interval_s):
            try:
                self.reap_once()
                failing = False
            except Exception as exc:  # noqa: BLE001 - the reaper must outlive a database restart
                if not failing:
                    level = logging.WARNING if database_unavailable(exc) or "connect" in str(exc).lower() else logging.ERROR
                    log.log(level, "%s: pass failed: %s", self.name, exc, exc_info=level == logging.ERROR)
                failing = True

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
