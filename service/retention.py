"""Deleting records (the admin's, audited): a session with its measurements, a cell with
everything recorded of it. What is kept and for how long: docs/service.md, "Backup and
retention"."""

from __future__ import annotations

from sqlalchemy import delete, func
from sqlmodel import Session, select

from .models import ACTIVE, Calibration, Cell, Compensation, Measurement, RunSession, TaskFile, Token
from .problems import Conflict, NotFound
from .sessions import driving_session
from .store import audit, delete_session_rows


def delete_session(db: Session, run: RunSession, tok: Token) -> dict:
    """Delete ``run`` and its measurements. Refused (:class:`Conflict`) while it is planned or
    running, and when a calibration was identified from it: the calibration's measurements are
    its evidence and are kept as long as it is."""
    if run.state in ACTIVE:
        raise Conflict(f"session {run.id} is {run.state}: abort it before deleting it")
    cal = db.exec(select(Calibration.id).where(Calibration.session_id == run.id)).first()
    if cal is not None:
        raise Conflict(
            f"calibration {cal} was identified from session {run.id}: its measurements are "
            f"kept as long as the calibration (delete the cell to remove both)"
        )
    detail = {"cell": run.cell_id, "kind": run.kind, "state": run.state, "dry_run": run.dry_run}
    detail["measurements"] = delete_session_rows(db, run.id)
    db.commit()
    audit(db, actor=tok.name, action="delete session", subject=f"session {run.id}", detail=detail)
    return {"deleted": f"session {run.id}", **detail}


def delete_cell(db: Session, cell: Cell, tok: Token) -> dict:
    """Delete ``cell`` with its sessions and their measurements, its calibrations and their
    compensations, its task files. Refused (:class:`Conflict`) while one of its sessions is
    planned or running (a dry run's planning too: it would write to a cell that is gone). The
    audit entry keeps the counts."""
    cell_id = cell.id
    busy = driving_session(db, cell_id, dry_runs=True)
    if busy is not None:
        raise Conflict(f"session {busy.id} is driving cell {cell_id}: abort it before deleting the cell")
    session_ids = list(db.exec(select(RunSession.id).where(RunSession.cell_id == cell_id)).all())
    cal_ids = list(db.exec(select(Calibration.id).where(Calibration.cell_id == cell_id)).all())
    counts = {"sessions": len(session_ids), "calibrations": len(cal_ids)}
    counts["measurements"] = (
        int(db.exec(select(func.count()).select_from(Measurement).where(Measurement.session_id.in_(session_ids))).one())
        if session_ids
        else 0
    )
    if cal_ids:
        db.execute(delete(Compensation).where(Compensation.calibration_id.in_(cal_ids)))
        db.execute(delete(Calibration).where(Calibration.id.in_(cal_ids)))
    if session_ids:
        db.execute(delete(Measurement).where(Measurement.session_id.in_(session_ids)))
        db.execute(delete(RunSession).where(RunSession.id.in_(session_ids)))
    counts["task_files"] = len(db.exec(select(TaskFile.id).where(TaskFile.cell_id == cell_id)).all())
    db.execute(delete(TaskFile).where(TaskFile.cell_id == cell_id))
    name = cell.name
    db.delete(cell)
    db.commit()
    audit(db, actor=tok.name, action="delete cell", subject=f"cell {cell_id}", detail={"name": name, **counts})
    return {"deleted": f"cell {cell_id}", "name": name, **counts}


def delete_task_file(db: Session, cell_id: int, task_id: int, tok: Token) -> dict:
    """Delete task file ``task_id`` of cell ``cell_id`` (a technician's or an admin's, as they
    register them): it is no longer compensated again by ``/cells/{id}/tasks/compensate`` and the
    nightly job. Its compensations already stored are kept (they belong to their calibration)."""
    t = db.get(TaskFile, task_id)
    if t is None or t.cell_id != cell_id:
        raise NotFound(f"no task file {task_id} in cell {cell_id}")
    detail = {"cell": cell_id, "name": t.name, "mode": t.mode, "bytes": len(t.content.encode(t.encoding, "replace"))}
    db.delete(t)
    db.commit()
    audit(db, actor=tok.name, action="delete task file", subject=f"task file {task_id}", detail=detail)
    return {"deleted": f"task file {task_id}", **detail}


def delete_compensation(db: Session, compensation_id: int, tok: Token) -> dict:
    """Delete stored compensation ``compensation_id`` (its compensated file and report; admin).
    Its calibration and the task it came from are untouched: it can be computed again."""
    rec = db.get(Compensation, compensation_id)
    if rec is None:
        raise NotFound(f"no compensation {compensation_id}")
    detail = {"calibration": rec.calibration_id, "name": rec.name, "mode": rec.mode, "created_by": rec.created_by}
    db.delete(rec)
    db.commit()
    audit(db, actor=tok.name, action="delete compensation", subject=f"compensation {compensation_id}", detail=detail)
    return {"deleted": f"compensation {compensation_id}", **detail}
