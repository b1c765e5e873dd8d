"""Cells: register, list, edit; their sessions, calibrations, drift and task files."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, Field
from sqlmodel import select

from calibration.model import ModelFormatError, model_from_dict

from ...models import (
    Calibration,
    Cell,
    Compensation,
    CellCreate,
    CellPublic,
    CellUpdate,
    RunSession,
    SessionCreate,
    SessionPublic,
    TaskFile,
)
from ...store import audit, last_calibration, measured_count
from ..deps import CellEditor, Compensator, DbSession, Orchestrator, Reader, Runner
from .sessions import public_session, start_session

router = APIRouter(tags=["cells"])


def _public(db, cell: Cell) -> CellPublic:
    last = last_calibration(db, cell.id, kind="pose")
    return CellPublic(**cell.model_dump(), last_calibration_id=None if last is None else last.id)


def get_cell(db, cell_id: int) -> Cell:
    cell = db.get(Cell, cell_id)
    if cell is None:
        raise HTTPException(404, f"no cell {cell_id}")
    return cell


def _check_model(doc: dict) -> None:
    try:
        model_from_dict(doc)
    except ModelFormatError as exc:
        field = f"model.{exc.field}" if exc.field else "model"
        raise HTTPException(422, {"field": field, "message": str(exc).split(": ", 1)[-1]}) from None


@router.post("/cells", status_code=201, response_model=CellPublic)
def create_cell(body: CellCreate, db: DbSession, tok: CellEditor):
    _check_model(body.model)
    if db.exec(select(Cell).where(Cell.name == body.name)).first() is not None:
        raise HTTPException(409, f"a cell named {body.name!r} exists already")
    cell = Cell(**body.model_dump())
    db.add(cell)
    db.commit()
    db.refresh(cell)
    audit(db, actor=tok.name, action="register cell", subject=f"cell {cell.id}", detail={"name": cell.name})
    return _public(db, cell)


@router.get("/cells", response_model=list[CellPublic])
def list_cells(db: DbSession, tok: Reader, site: str | None = None):
    q = select(Cell).order_by(Cell.id)
    if site is not None:
        q = q.where(Cell.site == site)
    return [_public(db, c) for c in db.exec(q).all()]


@router.get("/cells/{cell_id}", response_model=CellPublic)
def read_cell(cell_id: int, db: DbSession, tok: Reader):
    return _public(db, get_cell(db, cell_id))


@router.patch("/cells/{cell_id}", response_model=CellPublic)
def update_cell(cell_id: int, body: CellUpdate, db: DbSession, tok: CellEditor):
    cell = get_cell(db, cell_id)
    changes = body.model_dump(exclude_unset=True)
    for k, v in changes.items():
        setattr(cell, k, v)
    db.add(cell)
    db.commit()
    db.refresh(cell)
    audit(db, actor=tok.name, action="edit cell", subject=f"cell {cell_id}", detail={"fields": sorted(changes)})
    return _public(db, cell)


@router.post("/cells/{cell_id}/sessions", status_code=201, response_model=SessionPublic)
def create_session(cell_id: int, body: SessionCreate, db: DbSession, tok: Runner, orchestrator: Orchestrator):
    cell = get_cell(db, cell_id)
    return start_session(db, cell, body, tok, orchestrator)


@router.get("/cells/{cell_id}/sessions", response_model=list[SessionPublic])
def list_sessions(cell_id: int, db: DbSession, tok: Reader, limit: int = 50):
    get_cell(db, cell_id)
    rows = db.exec(select(RunSession).where(RunSession.cell_id == cell_id).order_by(RunSession.id.desc())
                   .limit(max(1, min(limit, 1000)))).all()
    return [public_session(db, r) for r in rows]


@router.get("/cells/{cell_id}/calibrations")
def list_calibrations(cell_id: int, db: DbSession, tok: Reader, kind: str | None = None, limit: int = 100) -> list[dict]:
    get_cell(db, cell_id)
    q = select(Calibration).where(Calibration.cell_id == cell_id)
    if kind:
        q = q.where(Calibration.kind == kind)
    rows = db.exec(q.order_by(Calibration.id.desc()).limit(max(1, min(limit, 5000)))).all()
    return [{"id": c.id, "kind": c.kind, "session_id": c.session_id, "rms": c.rms, "created_at": c.created_at,
             "success": c.report.get("success")} for c in rows]


@router.get("/cells/{cell_id}/drift")
def drift(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """Each identified parameter and the residual RMS over the cell's pose calibrations, oldest
    first, with each parameter's change from the previous calibration in units of its combined
    standard uncertainty (|Δ| / sqrt(σ₁² + σ₂²) > 2: moved beyond its uncertainty)."""
    get_cell(db, cell_id)
    cals = db.exec(select(Calibration).where(Calibration.cell_id == cell_id, Calibration.kind == "pose")
                   .order_by(Calibration.id)).all()
    series: dict[str, list] = {}
    history = []
    prev: dict[str, dict] = {}
    for c in cals:
        history.append({"id": c.id, "created_at": c.created_at, "rms": c.rms})
        params = {p["name"]: p for p in c.report.get("parameters", [])}
        for name, p in params.items():
            entry = {"calibration_id": c.id, "value": p["value"], "std_error": p["std_error"], "unit": p["unit"]}
            if name in prev and p["value"] is not None and prev[name]["value"] is not None and \
                    not name.startswith(("base.", "tool.", "home.")) and ".tilt_" not in name and ".shift_" not in name:
                d = p["value"] - prev[name]["value"]
                s = float(np.hypot(p["std_error"] or 0.0, prev[name]["std_error"] or 0.0))
                entry["change"] = d
                entry["change_sigmas"] = (abs(d) / s) if s > 0 else None
            series.setdefault(name, []).append(entry)
        prev = params
    return {"calibrations": history, "parameters": series}


class TaskFileCreate(BaseModel):
    name: str = Field(min_length=1, max_length=200)
    content: str = Field(min_length=1)
    mode: str = Field(default="joints", pattern="^(joints|targets)$")


@router.post("/cells/{cell_id}/tasks", status_code=201)
def register_task(cell_id: int, body: TaskFileCreate, db: DbSession, tok: CellEditor) -> dict:
    get_cell(db, cell_id)
    t = TaskFile(cell_id=cell_id, name=body.name, content=body.content, mode=body.mode)
    db.add(t)
    db.commit()
    db.refresh(t)
    audit(db, actor=tok.name, action="register task file", subject=f"cell {cell_id}", detail={"name": body.name})
    return {"id": t.id, "name": t.name, "mode": t.mode}


@router.get("/cells/{cell_id}/tasks")
def list_tasks(cell_id: int, db: DbSession, tok: Reader) -> list[dict]:
    get_cell(db, cell_id)
    return [{"id": t.id, "name": t.name, "mode": t.mode, "created_at": t.created_at}
            for t in db.exec(select(TaskFile).where(TaskFile.cell_id == cell_id).order_by(TaskFile.id)).all()]


@router.get("/cells/{cell_id}/tasks/{task_id}")
def read_task(cell_id: int, task_id: int, db: DbSession, tok: Reader) -> dict:
    t = db.get(TaskFile, task_id)
    if t is None or t.cell_id != cell_id:
        raise HTTPException(404, f"no task file {task_id} in cell {cell_id}")
    return {"id": t.id, "name": t.name, "mode": t.mode, "content": t.content, "created_at": t.created_at}


@router.post("/cells/{cell_id}/tasks/compensate")
def compensate_tasks(cell_id: int, db: DbSession, tok: Compensator, calibration_id: int | None = None) -> dict:
    """Compensate every task file registered with the cell, with ``calibration_id`` (default the
    cell's last pose calibration); each result is stored."""
    from ...compensate import CompensationInputError, compensate_text

    cell = get_cell(db, cell_id)
    cal = db.get(Calibration, calibration_id) if calibration_id is not None else last_calibration(db, cell_id, kind="pose")
    if cal is None or cal.cell_id != cell_id:
        raise HTTPException(404, "no calibration to compensate with" if calibration_id is None
                            else f"no calibration {calibration_id} in cell {cell_id}")
    results = []
    for t in db.exec(select(TaskFile).where(TaskFile.cell_id == cell_id).order_by(TaskFile.id)).all():
        try:
            output, report = compensate_text(t.content, name=t.name, model_doc=cal.model, nominal_doc=cell.model,
                                             mode=t.mode)
        except CompensationInputError as exc:
            results.append({"task_id": t.id, "name": t.name, "error": str(exc)})
            continue
        rec = Compensation(calibration_id=cal.id, name=t.name, mode=t.mode, output=output, report=report,
                           created_by=tok.name)
        db.add(rec)
        db.commit()
        db.refresh(rec)
        results.append({"task_id": t.id, "name": t.name, "compensation_id": rec.id,
                        "summary": (report or {}).get("summary")})
    audit(db, actor=tok.name, action="compensate tasks", subject=f"cell {cell_id}",
          detail={"calibration": cal.id, "tasks": len(results)})
    return {"calibration_id": cal.id, "tasks": results}
