"""What every session kind's last step (``SessionKind.finish``, :mod:`service.kinds`) shares:
the session's measurements as calibration's arrays, the model that guides the instruments, the
way a result is stored, and the error that says the measurements cannot give one."""

from __future__ import annotations

from collections.abc import Callable

from sqlmodel import Session

from calibration.errors import RecalError
from calibration.identification import Measurements
from calibration.model import KinematicModel, model_to_dict

from . import records
from .devices import InstrumentSigma, instrument_sigma
from .models import Calibration, Cell, Measurement, RunSession
from .records import NoMeasurementsError, current_model
from .store import activate_calibration, current_calibration


class AnalysisError(RecalError, RuntimeError):
    """The measurements cannot give a result (the reason is for the technician)."""


def session_sigma(run: RunSession, cell: Cell, role: str) -> InstrumentSigma:
    """The per-axis standard uncertainty the session's instrument (of ``role``) declared when the
    session was planned (stored with its plan), else what the cell's instrument declares now (a
    session imported from a file, or planned before the figure was stored)."""
    return run.session_plan().instrument_sigma or instrument_sigma(cell.devices, role)


def guide_model(db: Session, cell: Cell) -> KinematicModel:
    return current_model(db, cell)[0]


def session_measurements(db: Session, run: RunSession) -> tuple[Measurements, list[Measurement]]:
    """As :func:`records.session_measurements`, with "no measurements" as the session's reason."""
    try:
        return records.session_measurements(db, run)
    except NoMeasurementsError as exc:
        raise AnalysisError(str(exc)) from None


# Session.info key: {session id: Measurements} the caller has just stored (records.as_stored),
# given to the analysis instead of read back (an import of 100,000 rows: a second and 100 MB).
HANDED_OVER = "recal.measurements_handed_over"


def session_data(db: Session, run: RunSession) -> Measurements:
    """As :func:`records.session_data` (arrays only, read as plain columns), with "no
    measurements" as the session's reason; the arrays handed over in ``db.info`` when the caller
    has just stored them (:data:`HANDED_OVER`)."""
    handed = db.info.get(HANDED_OVER, {}).get(run.id)
    if handed is not None:
        return handed
    try:
        return records.session_data(db, run)
    except NoMeasurementsError as exc:
        raise AnalysisError(str(exc)) from None


def store_calibration(
    db: Session,
    cell: Cell,
    run: RunSession,
    kind: str,
    model: KinematicModel,
    report: dict,
    rms: float | None,
    extra: dict | None = None,
    predict: Callable[[Calibration], dict | None] | None = None,
) -> Calibration:
    """Store what a session gave as a calibration of ``kind`` of ``cell``, committed once;
    ``extra`` goes into the stored model document beside the model (an identified model's
    ``identification`` block: its parameters' covariance is stored there, once). ``predict``:
    its predicted accuracy (``Calibration.predicted``) from the calibration as stored, with its
    id (the workspace's samples are drawn from it, as the result page draws them)."""
    assert cell.id is not None  # a stored cell
    doc = model_to_dict(model)
    if extra:
        doc.update(extra)
    cal = Calibration(
        cell_id=cell.id,
        session_id=run.id,
        kind=kind,
        model=doc,
        report=report,
        rms=rms,
        nominal_version=cell.model_version,
    )
    first = kind == "pose" and current_calibration(db, cell) is None
    if kind != "pose":  # only pose calibrations serve as the cell's model: nothing to protect
        cal.activated_at, cal.activated_by = cal.created_at, run.created_by
    db.add(cal)
    if predict is not None:
        db.flush()  # its id, in this transaction
        cal.predicted = predict(cal)
    db.commit()
    db.refresh(cal)
    if first:  # a cell with no current calibration has nothing to protect: this one is current at once
        activate_calibration(
            db, cal, actor=run.created_by or "recal", why=f"the cell's first calibration (session {run.id})"
        )
    return cal
