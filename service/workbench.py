"""What the technician's web page reads beyond the core resources, apart from HTTP: the overview
of the cells (last accuracy and its trend, without loading reports), one cell's summary, its
calibration history and sessions page by page, the connection test of its devices, and the
robot library. Columns only where a page lists many rows (bench/service.py measures these)."""

from __future__ import annotations

from sqlalchemy import func
from sqlmodel import Session, select

from calibration import robots

from .devices import describe
from .devicetest import test_cell_devices
from .models import Calibration, Cell, RunSession, Token, identified_calibration_kinds
from .problems import NotFound
from .sessions import driving_session, public_session
from .store import as_utc, audit, candidate_calibration, current_calibration, measured_count, verifications

TREND = 30  # calibrations and verifications in a cell's trend


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
        .where(Calibration.cell_id == cell_id, Calibration.kind.in_(identified_calibration_kinds()))  # type: ignore[attr-defined]
        .order_by(Calibration.id.desc())
        .limit(limit)
    ).all()
    return [{"id": i, "rms": r, "created_at": as_utc(t).isoformat()} for i, r, t in reversed(rows)]


def _brief(cal: Calibration | None) -> dict | None:
    if cal is None:
        return None
    return {"id": cal.id, "rms": cal.rms, "created_at": as_utc(cal.created_at).isoformat()}


def _verified(db, cell_id: int, limit: int = TREND) -> list[dict]:
    """The cell's verified accuracy over time, oldest first: each completed verify session of
    one of its calibrations (not of the nominal model) among the last ``limit`` verify
    sessions, with the calibration it checked and its RMS and max error on fresh
    configurations. This, not a calibration's residual (how well the model fits the data it was
    identified from), is the cell's accuracy."""
    out = []
    for sid, t, v in reversed(verifications(db, cell_id, limit=limit)):
        if v.calibration_id is None or v.rms is None:
            continue
        out.append(
            {
                "session_id": sid,
                "calibration_id": v.calibration_id,
                "rms": v.rms,
                "max": v.max,
                "n": v.n,
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


def summary(db, cell: Cell) -> dict:
    trend = _trend(db, cell.id)
    verified = _verified(db, cell.id)
    unit = (cell.model.get("units") or {}).get("length")
    last = trend[-1] if trend else None
    kinds, devices_error = describe(cell.devices)
    current, candidate = current_calibration(db, cell), candidate_calibration(db, cell)
    # the cell's accuracy: the last verification of its current calibration (None until verified)
    accuracy = verified[-1] if verified and current and verified[-1]["calibration_id"] == current.id else None
    return {
        "id": cell.id,
        "name": cell.name,
        "site": cell.site,
        "robot": _robot(cell.model),
        "devices": kinds,
        "devices_error": devices_error,
        "unit": unit,
        "drift_threshold": cell.drift_threshold,
        "last": last,  # the newest pose calibration, current or not
        "current": _brief(current),  # the cell's model (issue 27: activated, not overwritten)
        "candidate": _brief(candidate),  # made later, waits for a verify session or an activation
        "trend": trend,
        "verified": verified,
        "accuracy": accuracy,
        "active_session": _active(db, cell.id),
    }


def overview(db: Session, tok: Token, site: str | None, limit: int, offset: int) -> dict:
    """Every cell (a page of them, ``site``'s only if given) as :func:`summary`, and who is asking."""
    q = select(Cell).order_by(Cell.id)
    if site is not None:
        q = q.where(Cell.site == site)
    total = db.exec(select(func.count()).select_from(q.subquery())).one()
    cells = db.exec(q.offset(max(0, offset)).limit(max(1, min(limit, 500)))).all()
    return {"me": {"name": tok.name, "role": tok.role}, "total": int(total), "cells": [summary(db, c) for c in cells]}


def cell_summary(db: Session, cell: Cell) -> dict:
    """One cell as on the overview, with its devices document, allowed region, nominal model and
    the controller's own kinematics (a UR cell)."""
    from .controller import controller_summary

    return {
        **summary(db, cell),
        "devices_doc": cell.devices,
        "allowed_region": cell.allowed_region,
        "created_at": as_utc(cell.created_at).isoformat(),
        "model": cell.model,
        "controller_model": controller_summary(db, cell),
    }


def calibration_page(db: Session, cell_id: int, kind: str | None, limit: int, offset: int) -> dict:
    """A page of the cell's calibrations, newest first (without their reports)."""
    where = [Calibration.cell_id == cell_id] + ([Calibration.kind == kind] if kind else [])
    total = db.exec(select(func.count(Calibration.id)).where(*where)).one()
    rows = db.exec(
        select(Calibration.id, Calibration.kind, Calibration.session_id, Calibration.rms, Calibration.created_at)
        .where(*where)
        .order_by(Calibration.id.desc())
        .offset(max(0, offset))
        .limit(max(1, min(limit, 200)))
    ).all()
    status = _statuses(db, cell_id, [r[0] for r in rows])
    return {
        "total": int(total),
        "offset": offset,
        "items": [
            {
                "id": i,
                "kind": k,
                "session_id": s,
                "rms": r,
                "created_at": as_utc(t).isoformat(),
                "status": status.get(i),
            }
            for i, k, s, r, t in rows
        ],
    }


def session_page(db: Session, cell_id: int, limit: int, offset: int, dry_runs: bool, *, max_limit: int = 200) -> dict:
    """A page of the cell's sessions, newest first (dry runs left out unless asked for), at most
    ``max_limit`` of them."""
    where = [RunSession.cell_id == cell_id] + ([] if dry_runs else [RunSession.dry_run == False])  # noqa: E712 (SQL)
    total = db.exec(select(func.count(RunSession.id)).where(*where)).one()
    rows = db.exec(
        select(RunSession)
        .where(*where)
        .order_by(RunSession.id.desc())
        .offset(max(0, offset))
        .limit(max(1, min(limit, max_limit)))
    ).all()
    return {"total": int(total), "offset": offset, "items": [public_session(db, r) for r in rows]}


def calibration_list(db: Session, cell_id: int, kind: str | None, limit: int) -> list[dict]:
    """The cell's calibrations, newest first (at most ``limit``, 5000), without models and
    reports: residual RMS, predicted accuracy and the nominal model version of each."""
    q = select(
        Calibration.id,
        Calibration.kind,
        Calibration.session_id,
        Calibration.rms,
        Calibration.created_at,
        Calibration.nominal_version,
        Calibration.predicted,
    ).where(Calibration.cell_id == cell_id)
    if kind:
        q = q.where(Calibration.kind == kind)
    rows = db.exec(q.order_by(Calibration.id.desc()).limit(max(1, min(limit, 5000)))).all()
    status = _statuses(db, cell_id, [r[0] for r in rows])
    return [
        {
            "id": i,
            "kind": k,
            "session_id": s,
            "rms": r,
            "created_at": t,
            "nominal_version": v,
            "predicted": p,
            "status": status.get(i),
        }
        for i, k, s, r, t, v, p in rows
    ]


def _statuses(db: Session, cell_id: int, ids: list[int]) -> dict[int, str]:
    """Each listed calibration's status (``store.calibration_status``) from columns only."""
    cell = db.get(Cell, cell_id)
    if cell is None or not ids:
        return {}
    cur = current_calibration(db, cell)
    rows = db.exec(
        select(
            Calibration.id,
            Calibration.kind,
            Calibration.nominal_version,
            Calibration.activated_at,
            Calibration.retired_at,
        ).where(Calibration.id.in_(ids))  # type: ignore[union-attr]
    ).all()
    out = {}
    for i, kind, version, activated, retired in rows:
        if retired is not None:
            out[i] = "retired"
        elif kind != "pose":  # never a cell's model
            continue
        elif cur is not None and i == cur.id:
            out[i] = "current"
        elif activated is None and version == cell.model_version:
            out[i] = "candidate"
        else:
            out[i] = "superseded"
    return out


def test_devices(db: Session, cell: Cell, tok: Token, timeout_s: float) -> dict:
    """Open each device of the cell, ask it something harmless (nothing moves), each within
    ``timeout_s`` (0.5 to 30 s); not while a session drives the cell. Kept in the audit log (the
    certificate quotes the instrument's identity from it)."""
    busy = driving_session(db, cell.id)
    reason = f"session {busy.id} is driving this cell ({busy.state}); test when it has stopped" if busy else None
    results = test_cell_devices(cell.devices, timeout_s=max(0.5, min(float(timeout_s), 30.0)), busy=reason)
    ok = all(r.get("ok") for r in results)
    audit(db, actor=tok.name, action="test devices", subject=f"cell {cell.id}", detail={"ok": ok, "results": results})
    return {"cell_id": cell.id, "ok": ok, "results": results}


def library() -> list[dict]:
    """The nominal robots Recal knows (name, joints, convention, source)."""
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


def library_robot(name: str) -> dict:
    """A library robot's nominal ``recal.model/1`` document."""
    try:
        return robots.nominal_document(name)
    except KeyError as exc:
        raise NotFound(str(exc).strip("'\"")) from None
