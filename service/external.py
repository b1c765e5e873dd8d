"""Measurements taken elsewhere (another instrument, another program) stored in a cell's history
as if a session had taken them, and concluded as that kind of session concludes."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from sqlmodel import Session

from calibration.model import model_from_dict

from . import records
from .analysis import AnalysisError
from .kinds import finish_session
from .models import Cell, RunSession
from .problems import Invalid
from .store import audit, delete_session_rows


def import_measurements(
    db: Session, cell: Cell, body: bytes, *, kind: str, name: str, actor: str, settings
) -> RunSession:
    """Externally measured data (a measurement CSV, contracts §3, in the units of the cell's
    nominal model) stored as a completed session of ``kind`` (``pose``: identified as a pose
    session is; ``verify``: the cell's current model checked against it). Nothing is kept when
    the data cannot conclude. Bad rows: :class:`~service.problems.Invalid` naming row and column."""
    from .files import InputError, read_measurements

    model = model_from_dict(cell.model)
    safe_name = Path(name).name or "measurements.csv"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / safe_name
        path.write_bytes(body)
        try:
            data = read_measurements(path, model)
        except InputError as exc:
            raise Invalid("body", str(exc).replace(str(path), safe_name)) from None
    device = "cmm" if data.quat is not None and not np.all(np.isnan(data.quat)) else "tracker"
    run = RunSession(
        cell_id=cell.id,
        kind=kind,
        state="completed",
        planned=len(data),
        device=device,
        target=None,
        plan=data.q.tolist(),
        created_by=actor,
        plan_info={"imported": {"name": safe_name, "rows": len(data)}, "nominal_version": cell.model_version},
    )
    db.add(run)
    db.flush()
    db.add_all(records.measurement_rows(run.id, data))
    db.commit()
    db.refresh(run)
    try:
        finish_session(db, run, cell, settings)
    except (AnalysisError, ValueError, np.linalg.LinAlgError) as exc:  # the data cannot conclude
        db.rollback()
        delete_session_rows(db, run.id)
        db.commit()
        raise Invalid("body", f"{safe_name}: {exc}") from None
    db.refresh(run)
    audit(
        db,
        actor=actor,
        action="import measurements",
        subject=f"session {run.id}",
        detail={
            "cell": cell.id,
            "kind": kind,
            "name": safe_name,
            "rows": len(data),
            "calibration_id": run.calibration_id,
        },
    )
    return run
