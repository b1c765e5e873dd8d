"""``pose``: observation planning over candidates inside the allowed region, then
identification, with the cell's previous calibration as a prior when it has one
(minimum-variance estimation, book §4.3.2), so that a short nightly session updates a
calibration instead of replacing it; then, as ``recal identify --residual-map auto``, a residual
correction chosen by nested cross-validation among every family (none, the smooth map, the joint
transmission, boosted trees; issue 28), kept where it shows a gain; stored as a new calibration
of kind ``pose``."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from sqlmodel import Session

from calibration.identification import Measurements
from calibration.identify import NotEnoughData, Prior, drift_scale, held_relations, identify
from calibration.model import KinematicModel, model_from_dict
from calibration.report import identification_block, identification_report

from ..analysis import AnalysisError, session_data, session_sigma, store_calibration
from ..models import Calibration, Cell, KindRules, RunSession
from ..plans import Plan, PlanRequest, planned_poses
from ..results import position_residuals, predicted_accuracy
from ..store import current_calibration, current_controller_model
from .positions import PositionKind

# Allowance for what may have changed since the previous calibration (per parameter, 1 sigma):
# the prior's covariance is the previous one plus this allowance times a scale the new data show
# (calibration.identify.drift_scale: about 1 when the parameters moved by this much, 0 when the
# data fit the previous model), so the new data can move the model as far as they say it moved,
# and a robot that did not move is not made to look less certain than it was.
DRIFT_LENGTH_M = 0.05e-3
DRIFT_ANGLE_RAD = np.deg2rad(0.005)
# The scale never goes below this: a short session cannot rule out a little drift.
DRIFT_SCALE_MIN = 0.1


# Calibration.kind of what a pose session stores (named once: its rules and its store)
CALIBRATION_KIND = "pose"


class Pose(PositionKind):
    name = "pose"
    order = 10
    title = "Calibrate"
    summary = "measure the robot at planned poses and identify its true geometry"
    heading = "Calibration (pose) session"
    default_count = 40
    # 200 planned configurations (600 coordinates) are twenty per identified parameter, far past
    # where more poses still improve the geometric model much; a learned residual correction
    # (issue 28) wants a dense set over the task's region (the measured UR10 of issue 28 had 2,773),
    # so a session may ask for 5,000: D-optimal planning chooses at most service.plans.DENSE_FROM
    # of them and the rest fill the region (service.plans.planned_poses).
    rules = KindRules(
        max_count=5000,
        carries_payloads=True,
        calibration_kind=CALIBRATION_KIND,
        current_model=True,
        importable=True,
        predicts_accuracy=True,
        live_residuals=position_residuals,
    )

    def plan(self, req: PlanRequest) -> Plan:
        return planned_poses(req)

    def finish(self, db, run, cell, settings) -> None:
        cal = identify_session(db, run, cell, self.instrument(run))
        run.calibration_id = cal.id


def identify_session(db: Session, run: RunSession, cell: Cell, role: str) -> Calibration:
    """Identify the session's measurements (its ``role``'s instrument's declared sigma weighs the
    rows that carry none, and the orientations of full poses), from the previous calibration as
    the prior when there is one; the calibration stored once, with its predicted accuracy."""
    assert cell.id is not None  # a stored cell
    data = session_data(db, run)
    sigma_m = session_sigma(run, cell, role).sigma_m
    nominal = model_from_dict(cell.model)
    prev = current_calibration(db, cell)
    prior = None
    start = nominal
    stored = None if prev is None else stored_covariance(prev)
    if prev is not None and stored is not None:
        start = model_from_dict(prev.model)
        names, kinds, cov, held = stored
        drift = np.array(
            [DRIFT_ANGLE_RAD if k == "angle" else DRIFT_LENGTH_M if k == "length" else 1e-4 for k in kinds]
        )
        scale = max(drift_scale(start, data, names, cov, drift, sigma_m=sigma_m, held=held), DRIFT_SCALE_MIN)
        prior = Prior(names, cov + np.diag((scale * drift) ** 2), held)
    try:
        result = identify(start, data, prior=prior, sigma_m=sigma_m)
    except NotEnoughData as exc:  # too few poses to check the fit: say how many, as the CLI does
        raise AnalysisError(str(exc)) from None
    if not result.success:
        raise AnalysisError(f"identification did not converge: {result.message}")
    units = nominal.units
    report = identification_report(result, units, data_rows=data.row)
    report["prior"] = None if prior is None or prev is None else _prior_summary(result, prev, prior, scale, units)
    if start.compliance is not None:  # a compliant calibration: rigid against compliant, cross-validated
        from calibration.compliance_fit import compare

        try:
            cmp = compare(start, data, identify_kw={"sigma_m": sigma_m})
        except NotEnoughData:  # each fold's share of the poses leaves no redundancy: nothing to compare
            cmp = None
        if cmp is not None:
            report["compliance"] = {
                k.removesuffix("_m"): (v / units.length_m if k.endswith("_m") else v) for k, v in cmp.items()
            }
    model = dataclasses.replace(result.model, units=units, name=f"{cell.name}-calibrated")
    rmap_doc, report["residual_map"] = _residual_map(start, data, prior, sigma_m, result.model, model)
    L = units.length_m
    block = identification_block(result, units, nominal=nominal, q=data.q, report=report)
    held = held_relations(result)
    if held:  # what the next session's prior needs of the parameters it held (stored_covariance)
        block["covariance"]["held_relations"] = {n: [[m, c] for m, c in rel] for n, rel in held.items()}
    ctrl = current_controller_model(db, cell.id)
    if ctrl is not None:  # a UR cell: what its controller computes with (targets mode, URScript need it)
        block["controller"] = ctrl.model
    extra = {"identification": block, **({"residual_map": rmap_doc} if rmap_doc else {})}
    # its predicted accuracy stored with it (drift lists it without reading reports)
    predict = functools.partial(predicted_accuracy, cell=cell, target=run.target)
    return store_calibration(db, cell, run, CALIBRATION_KIND, model, report, result.rms_m / L, extra, predict)


def stored_covariance(cal: Calibration) -> tuple[tuple[str, ...], list[str], np.ndarray, dict] | None:
    """What a calibration's identification left for the next one's prior, read from the one place
    it is stored (the model's ``identification.covariance``, SI, calibration.report's block):
    the parameters' names and kinds, their covariance (P, P) as identified (not grown by the
    model-error scale: the drift allowance is added to it), and what it held at the model's value,
    confused with what it estimated (e.g. the tool orientation a tracker cannot see): ``{name:
    ((estimated name, coefficient SI), ...)}``, so that new data that determine them move the
    combinations it measured. None when it stores no covariance."""
    block = cal.model.get("identification")
    cov = block.get("covariance") if isinstance(block, dict) else None
    if not isinstance(cov, dict) or not cov.get("names"):
        return None
    names = tuple(cov["names"])
    kinds = list(cov.get("kinds") or ["length"] * len(names))
    held = {n: tuple((m, float(c)) for m, c in rel) for n, rel in (cov.get("held_relations") or {}).items()}
    return names, kinds, np.array(cov["matrix"], dtype=float), held


def _residual_map(
    start: KinematicModel,
    data: Measurements,
    prior: Prior | None,
    sigma_m: float,
    identified: KinematicModel,
    model: KinematicModel,
) -> tuple[dict | None, dict | None]:
    """What ``recal identify --residual-map auto`` does, by the same function
    (``calibration.residual_choice.choose_correction``; a session has no setting for it: it is
    always auto, among every family): a correction of what the identified model leaves, kept
    only where nested cross-validation of the whole procedure (the identification from ``start``,
    with the session's ``prior`` and instrument's ``sigma_m``, then each family) shows a gain.
    Returns the model file's ``residual_map`` section of the chosen family (None when none is
    kept), which every verb applies inside the region it was fitted in, and the CLI report's
    ``residual_map`` figures in ``model``'s units either way (each family's cross-validated RMS,
    the choice, the learning curve; None when the folds leave too few poses to tell)."""
    from calibration import residual_choice as rc

    try:
        choice = rc.choose_correction(start, data, identify_kw={"prior": prior, "sigma_m": sigma_m}, final=identified)
    except NotEnoughData:
        return None, None
    return choice.section(model), choice.report(model)


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


KIND = Pose()
