"""What the technician's web page needs beyond the core resources: an overview of the cells
(last accuracy and its trend, without loading reports), a cell's calibration history page by
page, the connection test of a cell's devices, the robot library, a session's plan before
anything moves and running exactly that plan, and a running session's residuals and pace."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request
from sqlalchemy import func
from sqlmodel import select

from ...devices import describe
from ...devicetest import test_cell_devices
from ...models import Calibration, Cell, RunSession, SessionPublic
from ...results import plan_preview, session_live
from ...sessions import ACTIVE, public_session, run_dry_plan
from ...store import as_utc, audit, measured_count
from ..deps import DbSession, Orchestrator, Reader, Runner
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

TREND = 30


def _cell(db, cell_id: int) -> Cell:
    cell = db.get(Cell, cell_id)
    if cell is None:
        raise HTTPException(404, f"no cell {cell_id}")
    return cell


def _run(db, session_id: int) -> RunSession:
    run = db.get(RunSession, session_id)
    if run is None:
        raise HTTPException(404, f"no session {session_id}")
    return run


def _robot(model_doc: dict) -> dict:
    joints = model_doc.get("joints") or []
    return {
        "name": model_doc.get("name") or "?",
        "convention": model_doc.get("convention"),
        "joints": len(joints),
        "units": model_doc.get("units"),
        "targets": sorted((model_doc.get("targets") or {}).keys()),
    }


def _trend(db, cell_id: int, limit: int = TREND) -> list[dict]:
    """The last ``limit`` pose calibrations' RMS, oldest first (columns only, no reports)."""
    rows = db.exec(
        select(Calibration.id, Calibration.rms, Calibration.created_at)
        .where(Calibration.cell_id == cell_id, Calibration.kind == "pose")
        .order_by(Calibration.id.desc())
        .limit(limit)
    ).all()
    return [{"id": i, "rms": r, "created_at": as_utc(t).isoformat()} for i, r, t in reversed(rows)]


def _verified(db, cell_id: int, limit: int = TREND) -> list[dict]:
    """The cell's verified accuracy over time, oldest first: each completed verify session of
    one of its calibrations (not of the nominal model) among the last ``limit`` verify
    sessions, with the calibration it checked and its RMS and max error on fresh
    configurations. This, not a calibration's residual (how well the model fits the data it was
    identified from), is the cell's accuracy."""
    rows = db.exec(
        select(RunSession.id, RunSession.plan_info, RunSession.updated_at)
        .where(
            RunSession.cell_id == cell_id,
            RunSession.kind == "verify",
            RunSession.state == "completed",
            RunSession.dry_run == False,  # noqa: E712 (SQL)
        )
        .order_by(RunSession.id.desc())
        .limit(limit)
    ).all()
    out = []
    for sid, info, t in reversed(rows):
        v = (info or {}).get("verify") or {}
        if v.get("calibration_id") is None or v.get("rms") is None:
            continue
        out.append(
            {
                "session_id": sid,
                "calibration_id": v["calibration_id"],
                "rms": v["rms"],
                "max": v.get("max"),
                "n": v.get("n"),
                "created_at": as_utc(t).isoformat(),
            }
        )
    return out


def _active(db, cell_id: int) -> dict | None:
    run = db.exec(
        select(RunSession)
        .where(
            RunSession.cell_id == cell_id,
            RunSession.dry_run == False,  # noqa: E712
            RunSession.state.in_(("planned", "running", "paused", "interrupted")),
        )
        .order_by(RunSession.id.desc())
    ).first()
    if run is None:
        return None
    return {
        "id": run.id,
        "kind": run.kind,
        "state": run.state,
        "planned": run.planned,
        "measured": measured_count(db, run.id),
        "reason": run.reason,
    }


def _summary(db, cell: Cell) -> dict:
    trend = _trend(db, cell.id)
    verified = _verified(db, cell.id)
    unit = (cell.model.get("units") or {}).get("length")
    last = trend[-1] if trend else None
    # the cell's accuracy: the last verification of its current calibration (None until verified)
    accuracy = verified[-1] if verified and last and verified[-1]["calibration_id"] == last["id"] else None
    return {
        "id": cell.id,
        "name": cell.name,
        "site": cell.site,
        "robot": _robot(cell.model),
        "devices": describe(cell.devices or {}),
        "unit": unit,
        "drift_threshold": cell.drift_threshold,
        "last": last,
        "trend": trend,
        "verified": verified,
        "accuracy": accuracy,
        "active_session": _active(db, cell.id),
    }


@router.get("/overview", response_model=Overview)
def overview(db: DbSession, tok: Reader, site: str | None = None, limit: int = 200, offset: int = 0) -> dict:
    """Every cell (a page of them) with its robot, devices, last pose calibration's RMS, the
    trend of the last 30, and the session driving it if any; and who is asking."""
    q = select(Cell).order_by(Cell.id)
    if site is not None:
        q = q.where(Cell.site == site)
    total = db.exec(select(func.count()).select_from(q.subquery())).one()
    cells = db.exec(q.offset(max(0, offset)).limit(max(1, min(limit, 500)))).all()
    return {"me": {"name": tok.name, "role": tok.role}, "total": int(total), "cells": [_summary(db, c) for c in cells]}


@router.get("/cells/{cell_id}/summary", response_model=CellSummary)
def cell_summary(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """One cell as on the overview, with its devices document and allowed region."""
    cell = _cell(db, cell_id)
    from ...controller import controller_summary

    return {
        **_summary(db, cell),
        "devices_doc": cell.devices,
        "allowed_region": cell.allowed_region,
        "created_at": as_utc(cell.created_at).isoformat(),
        "model": cell.model,
        "controller_model": controller_summary(db, cell),
    }


@router.get("/cells/{cell_id}/history", response_model=History)
def history(
    cell_id: int, db: DbSession, tok: Reader, kind: str | None = None, limit: int = 20, offset: int = 0
) -> dict:
    """A page of the cell's calibrations, newest first (without their reports)."""
    _cell(db, cell_id)
    where = [Calibration.cell_id == cell_id] + ([Calibration.kind == kind] if kind else [])
    total = db.exec(select(func.count(Calibration.id)).where(*where)).one()
    rows = db.exec(
        select(Calibration.id, Calibration.kind, Calibration.session_id, Calibration.rms, Calibration.created_at)
        .where(*where)
        .order_by(Calibration.id.desc())
        .offset(max(0, offset))
        .limit(max(1, min(limit, 200)))
    ).all()
    return {
        "total": int(total),
        "offset": offset,
        "items": [
            {"id": i, "kind": k, "session_id": s, "rms": r, "created_at": as_utc(t).isoformat()}
            for i, k, s, r, t in rows
        ],
    }


@router.get("/cells/{cell_id}/session-list", response_model=SessionPage)
def session_list(
    cell_id: int, db: DbSession, tok: Reader, limit: int = 20, offset: int = 0, dry_runs: bool = False
) -> dict:
    """A page of the cell's sessions, newest first (dry runs left out unless asked for)."""
    _cell(db, cell_id)
    where = [RunSession.cell_id == cell_id] + ([] if dry_runs else [RunSession.dry_run == False])  # noqa: E712
    total = db.exec(select(func.count(RunSession.id)).where(*where)).one()
    rows = db.exec(
        select(RunSession)
        .where(*where)
        .order_by(RunSession.id.desc())
        .offset(max(0, offset))
        .limit(max(1, min(limit, 200)))
    ).all()
    return {"total": int(total), "offset": offset, "items": [public_session(db, r) for r in rows]}


# --------------------------------------------------------------------------- devices


@router.post("/cells/{cell_id}/devices/test", response_model=DeviceTest)
def test_connections(cell_id: int, request: Request, db: DbSession, tok: Runner, timeout_s: float = 8.0) -> dict:
    """Open each device of the cell, ask it something harmless (nothing moves) and report what
    it answered, or the error, each within ``timeout_s``: the robot, the instrument, and each
    reference encoder and resolver reader on its own (a joint may have both). While a session
    drives the cell its devices are not opened. The result is kept in the audit log (the
    certificate quotes the instrument's identity from it)."""
    cell = _cell(db, cell_id)
    busy = db.exec(
        select(RunSession).where(
            RunSession.cell_id == cell_id,
            RunSession.state.in_(ACTIVE),
            RunSession.dry_run == False,  # noqa: E712 (SQL)
        )
    ).first()  # noqa: E712
    reason = f"session {busy.id} is driving this cell ({busy.state}); test when it has stopped" if busy else None
    results = test_cell_devices(cell.devices or {}, timeout_s=max(0.5, min(float(timeout_s), 30.0)), busy=reason)
    ok = all(r.get("ok") for r in results)
    audit(db, actor=tok.name, action="test devices", subject=f"cell {cell_id}", detail={"ok": ok, "results": results})
    return {"cell_id": cell_id, "ok": ok, "results": results}


@router.get("/cells/{cell_id}/devices/test", response_model=LastDeviceTest)
def last_test(cell_id: int, db: DbSession, tok: Reader) -> dict:
    """The last connection test of the cell's devices (``null`` results when none was run)."""
    from ...certificate import last_device_test

    _cell(db, cell_id)
    return {"cell_id": cell_id, "last": last_device_test(db, cell_id)}


# --------------------------------------------------------------------------- robot library


@router.get("/library/robots", response_model=list[LibraryRobot])
def library(tok: Reader) -> list[dict]:
    """The nominal robots Recal knows (name, joints, convention)."""
    from calibration import robots

    out = []
    for name in robots.names():
        doc = robots.nominal_document(name)
        out.append(
            {
                **_robot(doc),
                "name": name,
                "model_name": doc.get("name"),
                "description": doc.get("description"),
                "source": doc.get("source"),
            }
        )
    return out


@router.get(
    "/library/robots/{name}",
    response_model=dict[str, Any],
    responses={200: {"description": "a recal.model/1 document (docs/formats.md)"}},
)
def library_robot(name: str, tok: Reader) -> dict:
    """A library robot's nominal ``recal.model/1`` document."""
    from calibration import robots

    try:
        return robots.nominal_document(name)
    except KeyError as exc:
        raise HTTPException(404, str(exc).strip("'\"")) from None


# --------------------------------------------------------------------------- plans


@router.get("/sessions/{session_id}/plan", response_model=PlanPreview)
def plan(session_id: int, request: Request, db: DbSession, tok: Reader) -> dict:
    """A session's plan, for confirmation before anything moves: configurations, the joint
    ranges they use against the allowed limits, the limit check, the accuracy identification
    from them is predicted to give, the estimated motion time."""
    run = _run(db, session_id)
    return plan_preview(db, run, _cell(db, run.cell_id), request.app.state.settings)


@router.post("/sessions/{session_id}/run", status_code=201, response_model=SessionPublic)
def run_plan(session_id: int, db: DbSession, tok: Runner, orchestrator: Orchestrator):
    """Run the plan of a completed dry-run session for real: a new session measuring exactly
    the configurations that were shown and checked."""
    dry = _run(db, session_id)
    return run_dry_plan(db, dry, _cell(db, dry.cell_id), tok, orchestrator)


@router.get("/sessions/{session_id}/live", response_model=LiveSession)
def live(session_id: int, db: DbSession, tok: Reader) -> dict:
    """A session's residuals so far (per pose, against the cell's current model), the last
    reading, seconds per pose and the time remaining."""
    run = _run(db, session_id)
    return session_live(db, run, _cell(db, run.cell_id))
