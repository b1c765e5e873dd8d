"""Cells: register, list, edit; their sessions, calibrations, drift and task files."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from pydantic import Field
from sqlmodel import Session, select
from starlette.concurrency import run_in_threadpool

from calibration.model import ModelFormatError, model_from_dict

from ... import tasks, workbench
from ...controller import controller_document, store_controller_document
from ...device_config import DeviceConfigError, devices_json_schema, parse_devices
from ...drift import cell_drift
from ...models import (
    Cell,
    CellCreate,
    CellPublic,
    CellUpdate,
    RunSession,
    SessionCreate,
    SessionPublic,
    _In,
)
from ...plans import RegionError, check_region
from ...problems import Invalid
from ...sessions import ACTIVE, get_cell, start_session
from ...store import audit, current_calibration
from ..deps import CellEditor, Compensator, DbSession, Orchestrator, Reader, Runner
from ..schemas import CalibrationListItem, Drift, JsonSchema, TaskFileContent, TaskFileInfo, TasksCompensated

router = APIRouter(tags=["cells"])


def _public(db, cell: Cell) -> CellPublic:
    last = current_calibration(db, cell)
    return CellPublic(**cell.model_dump(), last_calibration_id=None if last is None else last.id)


def _check_model(doc: dict):
    """The parsed model, or 422 naming the field of ``body.model`` at fault."""
    try:
        return model_from_dict(doc)
    except ModelFormatError as exc:
        field = f"body.model.{exc.field}" if exc.field else "body.model"
        raise HTTPException(422, {"field": field, "message": str(exc).split(": ", 1)[-1]}) from None


def _check_region(model, region: list | None, *, sent: bool = True) -> None:
    """422 naming the row of ``body.allowed_region`` at fault (``sent``: the region came with
    this request; else it is the cell's, checked against a new model)."""
    try:
        check_region(model, region)
    except RegionError as exc:
        field = "body.allowed_region" + (f"[{exc.row}]" if exc.row is not None else "")
        message = (
            str(exc)
            if sent
            else f"the cell's allowed region does not fit the new model: {exc}; send an "
            f"allowed_region for it with the model"
        )
        raise HTTPException(422, {"field": field, "message": message}) from None


def _check_devices(devices: dict | None) -> None:
    """422 naming the field of ``body.devices`` at fault (an unknown key with the nearest known
    one); the document is stored as it was sent."""
    if devices is None:
        return
    try:
        parse_devices(devices)
    except DeviceConfigError as exc:
        raise Invalid(f"body.{exc.field}", exc.message) from None


def _name_free(db, name: str, cell_id: int | None = None) -> None:
    other = db.exec(select(Cell.id).where(Cell.name == name)).first()
    if other is not None and other != cell_id:
        raise HTTPException(409, f"a cell named {name!r} exists already")


@router.get("/schemas/devices", response_model=JsonSchema)
def devices_schema(tok: Reader) -> dict:
    """The JSON Schema of a cell's ``devices`` document (the fake cell's endpoint line, contracts
    §7, or the same shape for real equipment): every key, its type, pattern and range. A cell
    registered or edited with a document it refuses gets 422 naming the field."""
    return devices_json_schema()


@router.post("/cells", status_code=201, response_model=CellPublic)
def create_cell(body: CellCreate, db: DbSession, tok: CellEditor):
    _check_region(_check_model(body.model), body.allowed_region)
    _check_devices(body.devices)
    _name_free(db, body.name)
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
    """Change some of a cell's fields. A new ``model`` (the nominal model) is validated as at
    registration, refused while a session drives the cell, and counted (``model_version``; each
    calibration says which it was identified from); the old one is kept in the audit log.
    Calibrations of an earlier nominal no longer serve as the cell's current model or prior."""
    cell = get_cell(db, cell_id)
    changes = body.model_dump(exclude_unset=True)
    if "name" in changes:
        _name_free(db, changes["name"], cell_id)
    _check_devices(changes.get("devices"))
    detail: dict = {"fields": sorted(changes)}
    if "model" in changes and changes["model"] == cell.model:
        del changes["model"]
    if "model" in changes:
        model = _check_model(changes["model"])
        _check_region(model, changes.get("allowed_region", cell.allowed_region), sent="allowed_region" in changes)
        busy = db.exec(select(RunSession).where(RunSession.cell_id == cell_id, RunSession.state.in_(ACTIVE))).first()
        if busy is not None:
            raise HTTPException(
                409, f"session {busy.id} is driving this cell ({busy.state}); replace the model when it has stopped"
            )
        detail.update(
            {"old_model": cell.model, "old_model_version": cell.model_version, "model_version": cell.model_version + 1}
        )
        cell.model_version += 1
    elif changes.get("allowed_region") is not None:
        _check_region(model_from_dict(cell.model), changes["allowed_region"])
    for k, v in changes.items():
        setattr(cell, k, v)
    db.add(cell)
    db.commit()
    db.refresh(cell)
    audit(db, actor=tok.name, action="edit cell", subject=f"cell {cell_id}", detail=detail)
    return _public(db, cell)


@router.post("/cells/{cell_id}/sessions", status_code=201, response_model=SessionPublic)
def create_session(cell_id: int, body: SessionCreate, db: DbSession, tok: Runner, orchestrator: Orchestrator):
    cell = get_cell(db, cell_id)
    return start_session(db, cell, body, tok, orchestrator)


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


class TaskFileCreate(_In):
    name: str = Field(min_length=1, max_length=200)
    content: str = Field(min_length=1)
    mode: str = Field(default="joints", pattern="^(joints|targets)$")


@router.post("/cells/{cell_id}/tasks", status_code=201, response_model=TaskFileInfo, response_model_exclude_unset=True)
def register_task(cell_id: int, body: TaskFileCreate, db: DbSession, tok: CellEditor) -> dict:
    return tasks.register_task(
        db, get_cell(db, cell_id), name=body.name, content=body.content, mode=body.mode, actor=tok.name
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


def _task_content(engine, task_id: int) -> str:
    with Session(engine) as db:
        return tasks.task_content(db, task_id)


def _audit(engine, **kw) -> None:
    with Session(engine) as db:
        audit(db, **kw)


@router.post("/cells/{cell_id}/tasks/compensate", response_model=TasksCompensated, response_model_exclude_unset=True)
async def compensate_tasks(cell_id: int, request: Request, tok: Compensator, calibration_id: int | None = None):
    """Compensate every task file registered with the cell, with ``calibration_id`` (default the
    cell's last pose calibration); each result is stored. Each is computed and stored in a
    worker process (service.heavy), awaited: no request thread is held meanwhile."""
    from ...compensate import CompensationInputError, compensate_and_store

    engine, heavy = request.app.state.engine, request.app.state.heavy
    cal_id, todo = await run_in_threadpool(_tasks_to_compensate, engine, cell_id, calibration_id)
    url = request.app.state.settings.effective_database_url
    results = []
    for task_id, name, mode in todo:
        content = await run_in_threadpool(_task_content, engine, task_id)
        try:
            rec_id, _, summary, _ = await heavy.run(
                compensate_and_store, url, cal_id, content, name=name, mode=mode, actor=tok.name, audited=False
            )
        except CompensationInputError as exc:
            results.append({"task_id": task_id, "name": name, "error": str(exc)})
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
