"""Measurements taken elsewhere (another instrument, another program) stored in a cell's history
as if a session had taken them, and concluded as that kind of session concludes."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from sqlmodel import Session

from calibration.model import model_from_dict

from . import records
from .analysis import HANDED_OVER, AnalysisError
from .kinds import finish_session
from .models import Cell, ImportedFile, RunSession, SessionPlan
from .problems import Invalid
from .store import audit, delete_session_rows

# What an imported session says until its analysis has ended (committed with its measurements).
INTERRUPTED = "import interrupted before its analysis ended (the service stopped); import the file again"


def check_row_count(body: bytes, max_rows: int) -> None:
    """:class:`Invalid` when ``body`` has more than ``max_rows`` data rows (lines that are not
    blank, not comments, not the header), counted on the bytes before anything is parsed."""
    n = sum(1 for line in body.splitlines() if line.strip() and not line.lstrip().startswith(b"#")) - 1
    if n > max_rows:
        raise Invalid(
            "body",
            f"at most {max_rows} rows per import (the service's RECAL_MAX_IMPORT_ROWS setting), got {n}; "
            "split the file into several imports",
        )


def _mark_failed(db: Session, session_id: int, reason: str) -> None:
    run = db.get(RunSession, session_id)
    if run is not None:
        run.state, run.reason = "failed", reason[:2000]
        db.add(run)
        db.commit()


def import_measurements(
    db: Session, cell: Cell, body: bytes, *, kind: str, name: str, actor: str, settings
) -> RunSession:
    """Externally measured data (a measurement CSV, contracts §3, in the units of the cell's
    nominal model) stored as a completed session of ``kind`` (``pose``: identified as a pose
    session is; ``verify``: the cell's current model checked against it). Nothing is kept when
    the data cannot conclude. Bad rows, or more than ``settings.max_import_rows`` of them (counted
    before anything is parsed): :class:`~service.problems.Invalid` naming row and column.

    The session is stored ``failed`` ("interrupted before its analysis ended") with its
    measurements and becomes ``completed`` once its result is committed: a process that dies
    during the analysis, or an analysis that breaks unexpectedly, leaves a failed session that
    says why, never a completed one without its calibration."""
    from .files import InputError, read_measurements

    model = model_from_dict(cell.model)
    safe_name = Path(name).name or "measurements.csv"
    check_row_count(body, settings.max_import_rows)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / safe_name
        path.write_bytes(body)
        try:
            data = read_measurements(path, model)
        except InputError as exc:
            raise Invalid("body", str(exc).replace(str(path), safe_name)) from None
    device = "cmm" if data.quat is not None and not np.all(np.isnan(data.quat)) else "tracker"
    run = RunSession(
        cell_id=cell.id,
        kind=kind,
        state="failed",
        reason=INTERRUPTED,
        planned=len(data),
        device=device,
        target=None,
        plan=data.q.tolist(),
        created_by=actor,
    )
    run.record_plan(SessionPlan(imported=ImportedFile(safe_name, len(data)), nominal_version=cell.model_version))
    # Nothing else writes this session meanwhile: its row (with the plan, a 100,000-row import's
    # 12 MB of JSON) is not read back after each commit (that cost 2.3 s).
    expire = db.expire_on_commit
    db.expire_on_commit = False
    try:
        return _store_and_conclude(db, cell, run, data, kind=kind, name=safe_name, actor=actor, settings=settings)
    finally:
        db.expire_on_commit = expire


def _store_and_conclude(
    db: Session, cell: Cell, run: RunSession, data, *, kind: str, name: str, actor: str, settings
) -> RunSession:
    safe_name = name
    db.add(run)
    db.flush()
    records.insert_measurements(db, run.id, data)
    db.commit()
    handed = db.info.setdefault(HANDED_OVER, {})
    handed[run.id] = records.as_stored(run, data)  # what reading the rows back would give
    try:
        finish_session(db, run, cell, settings)  # commits the result; the session still says failed
    except (AnalysisError, ValueError, np.linalg.LinAlgError) as exc:  # the data cannot conclude
        db.rollback()
        delete_session_rows(db, run.id)
        db.commit()
        raise Invalid("body", f"{safe_name}: {exc}") from None
    except Exception as exc:  # not the data's fault: the session says what broke, then 500
        db.rollback()
        _mark_failed(db, run.id, f"the analysis failed: {type(exc).__name__}: {exc}")
        raise
    finally:
        handed.pop(run.id, None)
    run.state, run.reason = "completed", None  # only now: never completed without its result
    db.add(run)
    db.commit()
    audit(
        db,
        actor=actor,
        action="import measurements",
        subject=f"session {run.id}",
        detail={
            "cell": cell.id,
            "kind": kind,
            "name": safe_name,
            "rows": len(data),
            "calibration_id": run.calibration_id,
        },
    )
    return run
