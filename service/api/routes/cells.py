"""Cells: register, list, edit; their sessions, calibrations, drift and task files."""

from __future__ import annotations

import logging
from typing import Literal

from fastapi import APIRouter, Request
from pydantic import Field
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ... import cells, tasks, workbench
from ...controller import controller_document, store_controller_document
from ...device_config import devices_json_schema
from ...drift import cell_drift
from ...models import (
    CellCreate,
    CellPublic,
    CellUpdate,
    SessionCreate,
    SessionPublic,
    _In,
)
from ...sessions import get_cell, start_session
from ...store import audit
from ..deps import CellEditor, Compensator, DbSession, Reader, SessionOperator, SessionRunnerDep
from ..schemas import CalibrationListItem, Drift, JsonSchema, TaskFileContent, TaskFileInfo, TasksCompensated

log = logging.getLogger("recal.api")

router = APIRouter(tags=["cells"])


@router.get("/schemas/devices", response_model=JsonSchema)
def devices_schema(tok: Reader) -> dict:
    """The JSON Schema of a cell's ``devices`` document (the fake cell's endpoint line, contracts
    §7, or the same shape for real equipment): every key, its type, pattern and range. A cell
    registered or edited with a document it refuses gets 422 naming the field."""
    return devices_json_schema()


@router.post("/cells", status_code=201, response_model=CellPublic)
def create_cell(body: CellCreate, db: DbSession, tok: CellEditor):
    """Register a cell: its nominal model, allowed region and devices (each checked, a refusal
    naming the field)."""
    return cells.register_cell(db, body, tok)


@router.get("/cells", response_model=list[CellPublic])
def list_cells(db: DbSession, tok: Reader, site: str | None = None):
    return cells.list_cells(db, site)


@router.get("/cells/{cell_id}", response_model=CellPublic)
def read_cell(cell_id: int, db: DbSession, tok: Reader):
    return cells.public_cell(db, get_cell(db, cell_id))


@router.patch("/cells/{cell_id}", response_model=CellPublic)
def update_cell(cell_id: int, body: CellUpdate, db: DbSession, tok: CellEditor):
    """Change some of a cell's fields. A new ``model`` (the nominal model) is validated as at
    registration, refused while a session drives the cell, and counted (``model_version``; each
    calibration says which it was identified from); the old one is kept in the audit log.
    Calibrations of an earlier nominal no longer serve as the cell's current model or prior."""
    return cells.edit_cell(db, get_cell(db, cell_id), body, tok)


@router.post("/cells/{cell_id}/sessions", status_code=201, response_model=SessionPublic)
def create_session(cell_id: int, body: SessionCreate, db: DbSession, tok: SessionOperator, runner: SessionRunnerDep):
    cell = get_cell(db, cell_id)
    return start_session(db, cell, body, tok, runner)


@router.get("/cells/{cell_id}/sessions", response_model=list[SessionPublic])
def list_sessions(cell_id: int, db: DbSession, tok: Reader, limit: int = 50, dry_runs: bool = False):
    """The cell's sessions, newest first; dry runs (plans shown, nothing measured) only if asked."""
    get_cell(db, cell_id)
    return workbench.session_page(db, cell_id, limit, 0, dry_runs, max_limit=1000)["items"]


@router.get("/cells/{cell_id}/calibrations", response_model=list[CalibrationListItem])
def list_calibrations(
    cell_id: int, db: DbSession, tok: Reader, kind: str | None = None, limit: int = 100
) -> list[dict]:
    """The cell's calibrations, newest first (``limit`` of them, at most 5000), without models
    and reports: the residual RMS, the predicted accuracy (``predicted``: 95 % radius over the
    workspace) and the nominal model version each was identified from."""
    get_cell(db, cell_id)
    return workbench.calibration_list(db, cell_id, kind, limit)


@router.get("/cells/{cell_id}/drift", response_model=Drift, response_model_exclude_unset=True)
def drift(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """How the cell's robot changed over time, oldest first:

    - ``calibrations``: each pose calibration's time, residual RMS, predicted accuracy over the
      workspace (``predicted``: the 95 % radius statistics stored with it) and the nominal model
      version it was identified from;
    - ``parameters``: each identified parameter over those calibrations, with its change from the
      previous calibration of the same nominal model in units of their combined standard
      uncertainty (|Δ| / sqrt(σ₁² + σ₂²) > 2: moved beyond its uncertainty);
    - ``verify``: each completed verify session's measured accuracy (RMS, max, 95th percentile,
      and ISO 9283 pose accuracy and repeatability when it repeated its configurations) with its
      time and the calibration it checked.
    """
    get_cell(db, cell_id)
    return cell_drift(db, cell_id)


_ENCODING = (
    "utf-8, or iso-8859-1 for a program that is not UTF-8 (a KRL or RAPID file in Windows-1252): "
    "a character per byte, `content.encode(encoding)` is the file's bytes, kept as they are"
)


class TaskFilePart(_In):
    name: str = Field(min_length=1, max_length=200)
    content: str = Field(min_length=1)
    encoding: Literal["utf-8", "iso-8859-1"] = Field(default="utf-8", description=_ENCODING)


class TaskFileCreate(_In):
    name: str = Field(min_length=1, max_length=200)
    content: str = Field(min_length=1)
    mode: str = Field(default="joints", pattern="^(joints|targets)$")
    encoding: Literal["utf-8", "iso-8859-1"] = Field(default="utf-8", description=_ENCODING)
    files: list[TaskFilePart] = Field(
        default=[],
        description="a KRL .src's other files: its .dat (one; a .src alone is taken too), and $config.dat",
        max_length=2,
    )


@router.post("/cells/{cell_id}/tasks", status_code=201, response_model=TaskFileInfo, response_model_exclude_unset=True)
def register_task(cell_id: int, body: TaskFileCreate, db: DbSession, tok: CellEditor) -> dict:
    """Register a task file (a task CSV or a robot program: URScript, RAPID, TP, a KRL ``.src``
    with its ``.dat`` in ``files``), compensated again by ``/cells/{id}/tasks/compensate``. A
    program that is not UTF-8 is sent as the compensation route answers one: its text read as
    ISO-8859-1 and ``"encoding": "iso-8859-1"``; its bytes are kept, and its compensations served
    in them."""
    return tasks.register_task(
        db,
        get_cell(db, cell_id),
        name=body.name,
        content=body.content,
        mode=body.mode,
        actor=tok.name,
        encoding=body.encoding,
        files=[f.model_dump() for f in body.files],
    )


@router.get("/cells/{cell_id}/tasks", response_model=list[TaskFileInfo])
def list_tasks(cell_id: int, db: DbSession, tok: Reader) -> list[dict]:
    get_cell(db, cell_id)
    return tasks.list_tasks(db, cell_id)


@router.get("/cells/{cell_id}/tasks/{task_id}", response_model=TaskFileContent)
def read_task(cell_id: int, task_id: int, db: DbSession, tok: Reader) -> dict:
    return tasks.read_task(db, cell_id, task_id)


def _tasks_to_compensate(engine, cell_id: int, calibration_id: int | None) -> tuple[int, list[tuple]]:
    with Session(engine) as db:
        return tasks.tasks_to_compensate(db, get_cell(db, cell_id), calibration_id)


def _task_input(engine, task_id: int) -> dict:
    with Session(engine) as db:
        return tasks.task_input(db, task_id)


def _audit(engine, **kw) -> None:
    with Session(engine) as db:
        audit(db, **kw)


@router.post("/cells/{cell_id}/tasks/compensate", response_model=TasksCompensated, response_model_exclude_unset=True)
async def compensate_tasks(cell_id: int, request: Request, tok: Compensator, calibration_id: int | None = None):
    """Compensate every task file registered with the cell, with ``calibration_id`` (default the
    cell's last pose calibration); each result is stored. Each file is compensated on its own:
    one that fails is answered with its ``error`` beside the others' results. Each is computed and stored in a
    worker process (service.heavy), awaited: no request thread is held meanwhile."""
    from ...stored_compensation import CompensationInputError, compensate_and_store

    engine, heavy = request.app.state.engine, request.app.state.heavy
    cal_id, todo = await run_in_threadpool(_tasks_to_compensate, engine, cell_id, calibration_id)
    url = request.app.state.settings.effective_database_url
    results = []
    for task_id, name, mode in todo:
        # each file on its own: one that fails is reported with its reason, the others still done
        try:
            task = await run_in_threadpool(_task_input, engine, task_id)
            rec_id, _, summary, _ = await heavy.run(
                compensate_and_store,
                url,
                cal_id,
                task["text"],
                name=name,
                mode=mode,
                actor=tok.name,
                audited=False,
                companions=task["companions"],
                encodings=task["encodings"],
            )
        except CompensationInputError as exc:
            results.append({"task_id": task_id, "name": name, "error": str(exc)})
            continue
        except Exception as exc:  # not the file's known fault: logged in full, named in the answer
            log.error("compensating task file %s (%s) of cell %s failed", task_id, name, cell_id, exc_info=exc)
            results.append({"task_id": task_id, "name": name, "error": f"internal error: {type(exc).__name__}: {exc}"})
            continue
        results.append({"task_id": task_id, "name": name, "compensation_id": rec_id, "summary": summary})
    await run_in_threadpool(
        _audit,
        engine,
        actor=tok.name,
        action="compensate tasks",
        subject=f"cell {cell_id}",
        detail={"calibration": cal_id, "tasks": len(results)},
    )
    return {"calibration_id": cal_id, "tasks": results}


# --------------------------------------------------------------------------- the controller's model


@router.get("/cells/{cell_id}/controller-model")
def read_controller_model(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """The UR controller's own kinematics the cell keeps (newest version, ``recal.model/1`` with
    its ``controller`` block) and every version's summary; 404 when none was read."""
    return controller_document(db, get_cell(db, cell_id))


@router.put("/cells/{cell_id}/controller-model")
def upload_controller_model(cell_id: int, body: dict, db: DbSession, tok: CellEditor) -> dict:
    """Store a controller model written by ``recal controller-model`` as the cell's newest
    version (its ``controller`` block, the check figures, is required)."""
    return store_controller_document(db, get_cell(db, cell_id), body, actor=tok.name)
