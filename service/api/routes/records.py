"""A cell's records as an operator handles them: a session's measurements as the CSV that
``recal identify`` reads, externally measured CSVs imported into a cell's history, and the
admin's deletion of sessions and cells (audited; what is kept is in docs/service.md, "Backup
and retention")."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse
from sqlalchemy import delete, func
from sqlmodel import select

from ... import external
from ...models import Calibration, Cell, Compensation, Measurement, RunSession, SessionPublic, TaskFile
from ...records import measurements_csv
from ...sessions import ACTIVE, get_run, public_session
from ...store import audit, delete_session_rows
from ..deps import Admin, CellEditor, DbSession, Reader

router = APIRouter(tags=["records"])

IMPORT_KINDS = ("pose", "verify")


def _cell(db, cell_id: int) -> Cell:
    cell = db.get(Cell, cell_id)
    if cell is None:
        raise HTTPException(404, f"no cell {cell_id}")
    return cell


# --------------------------------------------------------------------------- measurements as CSV


@router.get("/sessions/{session_id}/measurements.csv", response_class=PlainTextResponse)
def read_measurements_csv(session_id: int, db: DbSession, tok: Reader) -> PlainTextResponse:
    """The session's measurements as the CSV that ``recal identify`` reads (contracts §3), in the
    units of the cell's nominal model."""
    from calibration.model import model_from_dict

    run = get_run(db, session_id)
    model = model_from_dict(_cell(db, run.cell_id).model)
    rows = db.exec(
        select(Measurement).where(Measurement.session_id == session_id).order_by(Measurement.seq, Measurement.id)
    ).all()
    text = (
        f"# session {run.id} ({run.kind}, {run.state}) of cell {run.cell_id}, units {model.units.length}/"
        f"{model.units.angle}\n" + measurements_csv(model, rows)
    )
    return PlainTextResponse(
        text,
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="session-{run.id}-measurements.csv"'},
    )


# --------------------------------------------------------------------------- import


@router.post("/cells/{cell_id}/measurements", status_code=201, response_model=SessionPublic)
async def import_measurements(
    cell_id: int, request: Request, db: DbSession, tok: CellEditor, kind: str = "pose", name: str = "measurements.csv"
):
    """Externally measured data (a measurement CSV, contracts §3, in the units of the cell's
    nominal model) into the cell's history, as a completed session: ``kind=pose`` identifies a
    calibration from it (as a pose session does), ``kind=verify`` checks the cell's current
    model against it. Nothing moves. Bad rows: 422 naming the row and column."""
    if kind not in IMPORT_KINDS:
        raise HTTPException(
            422, {"field": "query.kind", "message": f"expected one of {', '.join(IMPORT_KINDS)}, got {kind!r}"}
        )
    body = await request.body()
    if not body.strip():
        raise HTTPException(422, {"field": "body", "message": "expected a measurement CSV, got nothing"})
    from starlette.concurrency import run_in_threadpool

    # identification takes a core for a moment: off the event loop
    return await run_in_threadpool(_import, db, cell_id, body, kind, name, tok, request.app.state.settings)


def _import(db, cell_id: int, body: bytes, kind: str, name: str, tok, settings) -> SessionPublic:
    run = external.import_measurements(
        db, _cell(db, cell_id), body, kind=kind, name=name, actor=tok.name, settings=settings
    )
    return public_session(db, run)


# --------------------------------------------------------------------------- deletion (admin)


@router.delete("/sessions/{session_id}")
def delete_session(session_id: int, db: DbSession, tok: Admin) -> dict:
    """Delete a session and its measurements (admin). A running or planned session cannot be
    deleted (abort it first), nor one a calibration was identified from: the calibration's
    measurements are its evidence and are kept as long as it is (docs/service.md)."""
    run = get_run(db, session_id)
    if run.state in ACTIVE:
        raise HTTPException(409, f"session {session_id} is {run.state}: abort it before deleting it")
    cal = db.exec(select(Calibration.id).where(Calibration.session_id == session_id)).first()
    if cal is not None:
        raise HTTPException(
            409,
            f"calibration {cal} was identified from session {session_id}: its measurements are "
            f"kept as long as the calibration (delete the cell to remove both)",
        )
    detail = {"cell": run.cell_id, "kind": run.kind, "state": run.state, "dry_run": run.dry_run}
    detail["measurements"] = delete_session_rows(db, session_id)
    db.commit()
    audit(db, actor=tok.name, action="delete session", subject=f"session {session_id}", detail=detail)
    return {"deleted": f"session {session_id}", **detail}


@router.delete("/cells/{cell_id}")
def delete_cell(cell_id: int, db: DbSession, tok: Admin) -> dict:
    """Delete a cell with everything recorded of it (admin): its sessions and their
    measurements, its calibrations and their compensations, its task files. Refused (409)
    while one of its sessions is planned or running. The audit entry keeps the counts."""
    cell = _cell(db, cell_id)
    busy = db.exec(select(RunSession.id).where(RunSession.cell_id == cell_id, RunSession.state.in_(ACTIVE))).first()
    if busy is not None:
        raise HTTPException(409, f"session {busy} is driving cell {cell_id}: abort it before deleting the cell")
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
