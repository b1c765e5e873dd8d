"""A cell's registered task files (the programs it runs, compensated again after every
calibration): register, list, read, and what compensating all of them needs. The compensation
itself is :func:`service.compensate.compensate_and_store`, run in the heavy-work pool."""

from __future__ import annotations

from sqlmodel import Session, select

from .models import Calibration, Cell, TaskFile
from .problems import NotFound
from .store import audit, current_calibration


def register_task(db: Session, cell: Cell, *, name: str, content: str, mode: str, actor: str) -> dict:
    t = TaskFile(cell_id=cell.id, name=name, content=content, mode=mode)
    db.add(t)
    db.commit()
    db.refresh(t)
    audit(db, actor=actor, action="register task file", subject=f"cell {cell.id}", detail={"name": name})
    return {"id": t.id, "name": t.name, "mode": t.mode}


def list_tasks(db: Session, cell_id: int) -> list[dict]:
    rows = db.exec(select(TaskFile).where(TaskFile.cell_id == cell_id).order_by(TaskFile.id)).all()
    return [{"id": t.id, "name": t.name, "mode": t.mode, "created_at": t.created_at} for t in rows]


def read_task(db: Session, cell_id: int, task_id: int) -> dict:
    t = db.get(TaskFile, task_id)
    if t is None or t.cell_id != cell_id:
        raise NotFound(f"no task file {task_id} in cell {cell_id}")
    return {"id": t.id, "name": t.name, "mode": t.mode, "content": t.content, "created_at": t.created_at}


def tasks_to_compensate(db: Session, cell: Cell, calibration_id: int | None) -> tuple[int, list[tuple]]:
    """The calibration to compensate with (``calibration_id``, default the cell's current one)
    and the cell's task files ``(id, name, mode)``; :class:`NotFound` without a calibration."""
    cal = db.get(Calibration, calibration_id) if calibration_id is not None else current_calibration(db, cell)
    if cal is None or cal.cell_id != cell.id:
        raise NotFound(
            "no calibration to compensate with"
            if calibration_id is None
            else f"no calibration {calibration_id} in cell {cell.id}"
        )
    tasks = db.exec(
        select(TaskFile.id, TaskFile.name, TaskFile.mode).where(TaskFile.cell_id == cell.id).order_by(TaskFile.id)
    ).all()
    return cal.id, [tuple(t) for t in tasks]


def task_content(db: Session, task_id: int) -> str:
    return db.get(TaskFile, task_id).content
