"""What the technician's web page needs beyond the core resources: an overview of the cells
(last accuracy and its trend, without loading reports), a cell's calibration history page by
page, the connection test of a cell's devices, the robot library, a session's plan before
anything moves and running exactly that plan, and a running session's residuals and pace.
HTTP only: the use cases are ``service.workbench``, ``service.results`` and ``service.sessions``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from ... import workbench
from ...models import SessionPublic
from ...results import plan_preview, session_live
from ...sessions import get_cell, get_run, run_dry_plan
from ..deps import DbSession, Reader, SessionOperator, SessionRunnerDep
from ..schemas import (
    CellSummary,
    DeviceTest,
    History,
    LastDeviceTest,
    LibraryRobot,
    LiveSession,
    Overview,
    PlanPreview,
    SessionPage,
)

router = APIRouter(tags=["workbench"])


@router.get("/overview", response_model=Overview)
def overview(db: DbSession, tok: Reader, site: str | None = None, limit: int = 200, offset: int = 0) -> dict:
    """Every cell (a page of them) with its robot, devices, last pose calibration's RMS, the
    trend of the last 30, and the session driving it if any; and who is asking."""
    return workbench.overview(db, tok, site, limit, offset)


@router.get("/cells/{cell_id}/summary", response_model=CellSummary)
def cell_summary(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """One cell as on the overview, with its devices document and allowed region."""
    return workbench.cell_summary(db, get_cell(db, cell_id))


@router.get("/cells/{cell_id}/history", response_model=History)
def history(
    cell_id: int, db: DbSession, tok: Reader, kind: str | None = None, limit: int = 20, offset: int = 0
) -> dict:
    """A page of the cell's calibrations, newest first (without their reports)."""
    get_cell(db, cell_id)
    return workbench.calibration_page(db, cell_id, kind, limit, offset)


@router.get("/cells/{cell_id}/session-list", response_model=SessionPage)
def session_list(
    cell_id: int, db: DbSession, tok: Reader, limit: int = 20, offset: int = 0, dry_runs: bool = False
) -> dict:
    """A page of the cell's sessions, newest first (dry runs left out unless asked for)."""
    get_cell(db, cell_id)
    return workbench.session_page(db, cell_id, limit, offset, dry_runs)


# --------------------------------------------------------------------------- devices


@router.post("/cells/{cell_id}/devices/test", response_model=DeviceTest)
def test_connections(
    cell_id: int, request: Request, db: DbSession, tok: SessionOperator, timeout_s: float = 8.0
) -> dict:
    """Open each device of the cell, ask it something harmless (nothing moves) and report what
    it answered, or the error, each within ``timeout_s``: the robot, the instrument, and each
    reference encoder and resolver reader on its own (a joint may have both). While a session
    drives the cell its devices are not opened. The result is kept in the audit log (the
    certificate quotes the instrument's identity from it)."""
    return workbench.test_devices(db, get_cell(db, cell_id), tok, timeout_s)


@router.get("/cells/{cell_id}/devices/test", response_model=LastDeviceTest)
def last_test(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """The last connection test of the cell's devices (``null`` results when none was run)."""
    from ...certificate import last_device_test

    get_cell(db, cell_id)
    return {"cell_id": cell_id, "last": last_device_test(db, cell_id)}


# --------------------------------------------------------------------------- robot library


@router.get("/library/robots", response_model=list[LibraryRobot])
def library(tok: Reader) -> list[dict]:
    """The nominal robots Recal knows (name, joints, convention)."""
    return workbench.library()


@router.get(
    "/library/robots/{name}",
    response_model=dict[str, Any],
    responses={200: {"description": "a recal.model/1 document (docs/formats.md)"}},
)
def library_robot(name: str, tok: Reader) -> dict:
    """A library robot's nominal ``recal.model/1`` document."""
    return workbench.library_robot(name)


# --------------------------------------------------------------------------- plans


@router.get("/sessions/{session_id}/plan", response_model=PlanPreview)
def plan(session_id: int, request: Request, db: DbSession, tok: Reader) -> dict:
    """A session's plan, for confirmation before anything moves: configurations, the joint
    ranges they use against the allowed limits, the limit check, the accuracy identification
    from them is predicted to give, the estimated motion time."""
    run = get_run(db, session_id)
    return plan_preview(db, run, get_cell(db, run.cell_id), request.app.state.settings)


@router.post("/sessions/{session_id}/run", status_code=201, response_model=SessionPublic)
def run_plan(session_id: int, db: DbSession, tok: SessionOperator, runner: SessionRunnerDep):
    """Run the plan of a completed dry-run session for real: a new session measuring exactly
    the configurations that were shown and checked."""
    dry = get_run(db, session_id)
    return run_dry_plan(db, dry, get_cell(db, dry.cell_id), tok, runner)


@router.get("/sessions/{session_id}/live", response_model=LiveSession)
def live(session_id: int, db: DbSession, tok: Reader) -> dict:
    """A session's residuals so far (per pose, against the cell's current model), the last
    reading, seconds per pose and the time remaining."""
    run = get_run(db, session_id)
    return session_live(db, run, get_cell(db, run.cell_id))
