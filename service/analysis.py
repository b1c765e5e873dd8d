"""What happens after a session has measured everything.

- ``pose``: identification, with the cell's previous calibration as a prior when it has one
  (minimum-variance estimation, book §4.3.2), so that a short nightly session updates a
  calibration instead of replacing it; stored as a new calibration.
- ``verify``: the current calibration's errors on fresh configurations; the model is not
  changed.
- ``circle``: circle-point analysis (book §4.6); stored as a calibration of kind ``cpa``.
- ``joint``: per joint, the reference reading against the controller's, fitted with book eq. 2.4
  ``θ = k1·q + k2 + k3·sin(k4·q + k5)``; gains and eccentricity harmonics stored as a calibration
  of kind ``joint``.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
from sqlmodel import Session

from calibration import metrics
from calibration.errors import RecalError
from calibration.geometry import fit_joint_harmonic
from calibration.identify import Measurements, NotEnoughData, Prior, drift_scale, held_relations, identify
from calibration.model import KinematicModel, model_from_dict, model_to_dict
from calibration.report import identification_block, identification_report

from . import records
from .models import Calibration, Cell, Measurement, RunSession
from .problems import Invalid
from .records import NoMeasurementsError, current_model, position_errors, registered_errors
from .results import predicted_accuracy
from .settings import Settings
from .store import audit, current_calibration, current_controller_model, delete_session_rows

# Allowance for what may have changed since the previous calibration (per parameter, 1 sigma):
# the prior's covariance is the previous one plus this allowance times a scale the new data show
# (calibration.identify.drift_scale: about 1 when the parameters moved by this much, 0 when the
# data fit the previous model), so the new data can move the model as far as they say it moved,
# and a robot that did not move is not made to look less certain than it was.
DRIFT_LENGTH_M = 0.05e-3
DRIFT_ANGLE_RAD = np.deg2rad(0.005)
# The scale never goes below this: a short session cannot rule out a little drift.
DRIFT_SCALE_MIN = 0.1


class AnalysisError(RecalError, RuntimeError):
    """The measurements cannot give a result (the reason is for the technician)."""


def guide_model(db: Session, cell: Cell) -> KinematicModel:
    return current_model(db, cell)[0]


def session_measurements(db: Session, run: RunSession) -> tuple[Measurements, list[Measurement]]:
    """As :func:`records.session_measurements`, with "no measurements" as the session's reason."""
    try:
        return records.session_measurements(db, run)
    except NoMeasurementsError as exc:
        raise AnalysisError(str(exc)) from None


def finish_session(db: Session, run: RunSession, cell: Cell, settings: Settings) -> None:
    if run.kind == "pose":
        cal = identify_session(db, run, cell)
        cal.predicted = predicted_accuracy(cal, cell, run.target)  # stored with it: drift lists it without reports
        db.add(cal)
        run.calibration_id = cal.id
    elif run.kind == "verify":
        run.plan_info = {**(run.plan_info or {}), "verify": verify_session(db, run, cell)}
    elif run.kind == "joint":
        cal = joint_session(db, run, cell)
        run.calibration_id = cal.id
    elif run.kind == "circle":
        cal = circle_session(db, run, cell)
        run.calibration_id = cal.id
    db.add(run)
    db.commit()
    db.refresh(run)


def _store(
    db: Session,
    cell: Cell,
    run: RunSession,
    kind: str,
    model: KinematicModel,
    report: dict,
    covariance: dict | None,
    rms: float | None,
    extra: dict | None = None,
) -> Calibration:
    doc = model_to_dict(model)
    if extra:
        doc.update(extra)
    cal = Calibration(
        cell_id=cell.id,
        session_id=run.id,
        kind=kind,
        model=doc,
        report=report,
        covariance=covariance,
        rms=rms,
        nominal_version=cell.model_version,
    )
    db.add(cal)
    db.commit()
    db.refresh(cal)
    return cal


def identify_session(db: Session, run: RunSession, cell: Cell) -> Calibration:
    data, _ = session_measurements(db, run)
    nominal = model_from_dict(cell.model)
    prev = current_calibration(db, cell)
    prior = None
    start = nominal
    if prev is not None and prev.covariance:
        start = model_from_dict(prev.model)
        names = tuple(prev.covariance["names"])
        cov = np.array(prev.covariance["matrix"], dtype=float)
        kinds = prev.covariance.get("kinds") or ["length"] * len(names)
        drift = np.array(
            [DRIFT_ANGLE_RAD if k == "angle" else DRIFT_LENGTH_M if k == "length" else 1e-4 for k in kinds]
        )
        # what it held at the model's value, confused with what it estimated (e.g. the tool orientation
        # a tracker cannot see): new data that determine them move the combinations it measured
        held = {n: tuple((m, float(c)) for m, c in rel) for n, rel in (prev.covariance.get("held") or {}).items()}
        scale = max(drift_scale(start, data, names, cov, drift, held=held), DRIFT_SCALE_MIN)
        prior = Prior(names, cov + np.diag((scale * drift) ** 2), held)
    try:
        result = identify(start, data, prior=prior)
    except NotEnoughData as exc:  # too few poses to check the fit: say how many, as the CLI does
        raise AnalysisError(str(exc)) from None
    if not result.success:
        raise AnalysisError(f"identification did not converge: {result.message}")
    units = nominal.units
    report = identification_report(result, units, data_rows=data.row)
    report["prior"] = None if prior is None else _prior_summary(result, prev, prior, scale, units)
    if start.compliance is not None:  # a compliant calibration: rigid against compliant, cross-validated
        from calibration.compliance_fit import compare

        try:
            cmp = compare(start, data)
        except NotEnoughData:  # each fold's share of the poses leaves no redundancy: nothing to compare
            cmp = None
        if cmp is not None:
            report["compliance"] = {
                k.removesuffix("_m"): (v / units.length_m if k.endswith("_m") else v) for k, v in cmp.items()
            }
    cov = {
        "names": list(result.param_names),
        "kinds": [p.kind for p in result.params],
        "matrix": result.covariance.tolist(),
        "held": {n: [[m, c] for m, c in rel] for n, rel in held_relations(result).items()},
    }
    model = dataclasses.replace(result.model, units=units, name=f"{cell.name}-calibrated")
    L = units.length_m
    block = identification_block(result, units, nominal=nominal, q=data.q)
    ctrl = current_controller_model(db, cell.id)
    if ctrl is not None:  # a UR cell: what its controller computes with (targets mode, URScript need it)
        block["controller"] = ctrl.model
    return _store(db, cell, run, "pose", model, report, cov, result.rms_m / L, {"identification": block})


def _prior_summary(result, prev: Calibration, prior: Prior, scale: float, units) -> dict:
    """What the prior (the previous calibration) contributed: how many parameters each source
    determined, the ones the new data cannot see (kept from the prior), the ones it held at the
    model's value that the new data determine (``released``, e.g. a tool orientation a tracker
    could not see, measured by a CMM), and the drift allowance with the scale the data showed."""
    by = {
        s: [n for n, src in zip(result.param_names, result.sources) if src == s]
        for s in ("data", "data + prior", "prior")
    }
    return {
        "calibration_id": prev.id,
        "parameters": len(prior.names),
        "determined_by": {s: len(names) for s, names in by.items()},
        "from_prior": by["prior"],
        "released": [n for n in result.param_names if n in prior.held],
        "drift_allowance": {
            "length": DRIFT_LENGTH_M / units.length_m,
            "angle": DRIFT_ANGLE_RAD / units.angle_rad,
            "scale": scale,
            "note": "per parameter, 1 sigma, times scale (how far the new data show the robot moved; "
            f"at least {DRIFT_SCALE_MIN}), added to the previous calibration's covariance",
        },
    }


def verify_session(db: Session, run: RunSession, cell: Cell) -> dict:
    data, _ = session_measurements(db, run)
    model, cal = current_model(db, cell)
    e = np.linalg.norm(position_errors(model, data), axis=1)
    L = model.units.length_m
    st = metrics.norm_statistics(e / L)
    out = {
        "calibration_id": None if cal is None else cal.id,
        "n": st.n,
        "rms": st.rms,
        "max": st.max,
        "p95": st.p95,
        "mean": st.mean,
        "unit": model.units.length,
    }
    if len(e) >= 3:
        # Also with the base placed where it fits best (book Table 1.1 does the same): the robot's
        # own inaccuracy, apart from where the instrument stands; the same figure as the result
        # page's "before" (one definition, calibration.metrics.registered_errors).
        reg = metrics.norm_statistics(np.linalg.norm(registered_errors(model, data), axis=1) / L)
        out["registered"] = {"rms": reg.rms, "max": reg.max}
    repeats = int((run.plan_info or {}).get("repeats") or 1)
    if repeats > 1:
        out["iso9283"] = pose_repeatability(model, data, repeats)
    return out


def pose_repeatability(model: KinematicModel, data: Measurements, repeats: int) -> dict:
    """ISO 9283 pose accuracy AP and repeatability RP (§7.2.1-7.2.2, ``calibration.metrics``) of
    a verify session that visited each configuration ``repeats`` times (step ``s`` visits
    configuration ``s // repeats``); the command is where the current model puts the target."""
    from calibration.metrics import pose_statistics

    p_cmd = data.p_world - position_errors(model, data)
    st = pose_statistics(p_cmd, data.p_world, data.pose_id // repeats)
    L = model.units.length_m
    return {
        "repeats": repeats,
        "poses": int(len(st.pose_ids)),
        "unit": model.units.length,
        "accuracy": {"mean": float(st.AP_m.mean() / L), "max": float(st.AP_m.max() / L)},
        "repeatability": {"mean": float(st.RP_m.mean() / L), "max": float(st.RP_m.max() / L)},
        "per_pose": [
            {"pose": int(k) + 1, "visits": int(n), "AP": float(ap / L), "RP": float(rp / L)}
            for k, n, ap, rp in zip(st.pose_ids, st.n, st.AP_m, st.RP_m)
        ],
    }


def joint_session(db: Session, run: RunSession, cell: Cell) -> Calibration:
    rows = records.stored_rows(db, run)
    if not rows:
        raise AnalysisError("the session has no measurements")
    model, _ = current_model(db, cell)
    results = {}
    joints = list(model.joints)
    for j in sorted({r.joint for r in rows if r.joint}):
        sel = [r for r in rows if r.joint == j]
        q = np.array([r.q[j - 1] for r in sel])
        ref = np.array([r.reference for r in sel])
        freq = joints[j - 1].harmonic[1] if joints[j - 1].harmonic else None
        fit = dataclasses.asdict(fit_joint_harmonic(q, ref, freq))
        results[str(j)] = fit
        if model.coupling is None:
            joints[j - 1] = dataclasses.replace(
                joints[j - 1],
                gain=fit["gain"],
                harmonic=(fit["amplitude"], fit["frequency"], fit["phase"]) if fit["amplitude"] > 0 else None,
            )
    new = dataclasses.replace(model, joints=tuple(joints))
    report = {
        "joints": results,
        "note": "reference encoder offsets are the encoders' own zeros; joint offsets come from pose calibration",
    }
    return _store(db, cell, run, "joint", new, report, None, None)


def circle_session(db: Session, run: RunSession, cell: Cell) -> Calibration:
    """Circle-point analysis of the session's sweeps (book §4.6); the report is the one
    ``recal cpa`` writes."""
    from calibration.cpa import SweepError, Sweeps, circle_point_analysis
    from calibration.report import cpa_report

    data, rows = session_measurements(db, run)
    nominal = model_from_dict(cell.model)
    sweeps = Sweeps(
        q=data.q,
        p_world=data.p_world,
        joint=np.array([(r.joint or 1) - 1 for r in rows]),
        target=data.target,
        row=data.row,
    )
    try:
        res = circle_point_analysis(nominal, sweeps)
    except (SweepError, ValueError) as exc:
        raise AnalysisError(f"circle-point analysis failed: {exc}") from None
    report = cpa_report(res, nominal, sweeps)
    model = dataclasses.replace(res.model, units=nominal.units, name=f"{cell.name}-cpa")
    return _store(db, cell, run, "cpa", model, report, None, None)


# --------------------------------------------------------------------------- measured elsewhere


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
