"""A cell's records as an operator handles them: a session's measurements as the CSV that
``recal identify`` reads, externally measured CSVs imported into a cell's history, and the
admin's deletion of sessions and cells (audited; what is kept is in docs/service.md, "Backup
and retention")."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse

from ... import external, retention
from ...kinds import KINDS
from ...models import SessionPublic
from ...records import session_measurements_csv
from ...sessions import get_cell, get_run, public_session
from ..deps import Admin, CellEditor, DbSession, Reader

router = APIRouter(tags=["records"])

IMPORT_KINDS = [k.name for k in KINDS.values() if k.rules.importable]  # each kind says (service/kinds/)


# --------------------------------------------------------------------------- measurements as CSV


@router.get("/sessions/{session_id}/measurements.csv", response_class=PlainTextResponse)
def read_measurements_csv(session_id: int, db: DbSession, tok: Reader) -> PlainTextResponse:
    """The session's measurements as the CSV that ``recal identify`` reads (contracts §3), in the
    units of the cell's nominal model."""
    run = get_run(db, session_id)
    text = session_measurements_csv(db, run, get_cell(db, run.cell_id))
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
        db, get_cell(db, cell_id), body, kind=kind, name=name, actor=tok.name, settings=settings
    )
    return public_session(db, run)


# --------------------------------------------------------------------------- deletion (admin)


@router.delete("/sessions/{session_id}")
def delete_session(session_id: int, db: DbSession, tok: Admin) -> dict:
    """Delete a session and its measurements (admin). A running or planned session cannot be
    deleted (abort it first), nor one a calibration was identified from: the calibration's
    measurements are its evidence and are kept as long as it is (docs/service.md)."""
    return retention.delete_session(db, get_run(db, session_id), tok)


@router.delete("/cells/{cell_id}")
def delete_cell(cell_id: int, db: DbSession, tok: Admin) -> dict:
    """Delete a cell with everything recorded of it (admin): its sessions and their
    measurements, its calibrations and their compensations, its task files. Refused (409)
    while one of its sessions is planned or running. The audit entry keeps the counts."""
    return retention.delete_cell(db, get_cell(db, cell_id), tok)


@router.delete("/cells/{cell_id}/tasks/{task_id}")
def delete_task_file(cell_id: int, task_id: int, db: DbSession, tok: CellEditor) -> dict:
    """Delete a task file registered with the cell (technician or admin, who register them; audited):
    ``/cells/{id}/tasks/compensate`` and the nightly job no longer compensate it. Its stored
    compensations are kept (delete them one by one, or with the cell)."""
    get_cell(db, cell_id)
    return retention.delete_task_file(db, cell_id, task_id, tok)


@router.delete("/compensations/{compensation_id}")
def delete_compensation(compensation_id: int, db: DbSession, tok: Admin) -> dict:
    """Delete a stored compensation, its compensated file and report (admin; audited). Its
    calibration is untouched: the task can be compensated again."""
    return retention.delete_compensation(db, compensation_id, tok)
