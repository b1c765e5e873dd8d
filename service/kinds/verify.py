"""``verify``: the current calibration's errors on fresh random configurations (not the planned
ones); the model is not changed. With ``repeats`` > 1 each configuration is visited that many
times in a row, every visit from the same approach configuration: ISO 9283 pose accuracy and
repeatability (§7.2.1-7.2.2)."""

from __future__ import annotations

import functools

import numpy as np

from calibration import metrics
from calibration.identification import Measurements
from calibration.model import KinematicModel, model_from_dict

from ..analysis import session_data
from ..models import KindRules, VerifyResult
from ..plans import Plan, PlanRequest, random_inside, repeated
from ..records import corrected_errors, current_model, position_errors, registered_errors
from ..results import position_residuals
from ..store import activate_calibration, candidate_calibration
from ..task_compensation import calibrated_range_of
from .positions import PositionKind


class Verify(PositionKind):
    name = "verify"
    order = 20
    title = "Verify"
    summary = "measure fresh poses and report how accurate the current model is (changes nothing)"
    heading = "Verification session"
    default_count = 20
    rules = KindRules(
        max_count=500,
        carries_payloads=True,
        repeats=True,
        stores="verification",
        importable=True,
        live_residuals=functools.partial(position_residuals, checks=True),
    )

    def plan(self, req: PlanRequest) -> Plan:
        return repeated(random_inside(req.lim, req.count, req.rng, req.model), req.repeats)

    def finish(self, db, run, cell, settings) -> None:
        run.record_verify(verify_session(db, run, cell))


def verify_session(db, run, cell) -> VerifyResult:
    """The current model's position errors on the session's measurements (statistics in the
    model's length unit), also with the base placed where it fits best, and the ISO 9283 figures
    of a repeated session."""
    data = session_data(db, run)
    model, cal = current_model(db, cell)
    candidate = candidate_calibration(db, cell, made_by=run.created_at)
    before = None
    if candidate is not None:  # a new calibration waits: this session checks it against the current model
        before = _errors(model, data, cal)
        model, cal = model_from_dict(candidate.model), candidate
    e_xyz, inside = corrected_errors(model, data)  # with the model's residual correction, as compensation uses it
    e = np.linalg.norm(e_xyz, axis=1)
    L = model.units.length_m
    st = metrics.norm_statistics(e / L)
    out: dict = {}  # the parts that apply
    if inside is not None:
        # where the correction did not apply the geometric model alone was judged: counted, flagged
        out["residual_correction"] = {
            "family": (model.metadata.get("residual_map") or {}).get("family", "map"),
            "outside_mapped_region": int(np.count_nonzero(~inside)),
        }
    if len(e) >= 3:
        # Also with the base placed where it fits best (book Table 1.1 does the same): the robot's
        # own inaccuracy, apart from where the instrument stands; the same figure as the result
        # page's "before" (one definition, calibration.metrics.registered_errors).
        reg = metrics.norm_statistics(np.linalg.norm(registered_errors(model, data), axis=1) / L)
        out["registered"] = {"rms": reg.rms, "max": reg.max}
    if cal is not None:
        # configurations outside the joint ranges the calibration's data covered are an
        # extrapolation of it: counted, so that a figure measured there is read as such
        ranges = calibrated_range_of(model)
        if ranges is not None:
            out["outside_calibrated_region"] = int(np.count_nonzero(metrics.outside_joint_ranges(data.q, ranges)))
    repeats = run.session_plan().visits
    if repeats > 1:
        out["iso9283"] = pose_repeatability(model, data, repeats)
    if candidate is not None and before is not None:
        out["candidate"] = _judge(db, run, candidate, st.rms, before)
    calibration_id = None if cal is None else cal.id
    return VerifyResult(calibration_id, st.n, st.rms, st.max, st.p95, st.mean, model.units.length, **out)


def _errors(model: KinematicModel, data: Measurements, cal) -> dict:
    """The RMS and max position error of ``model`` (calibration ``cal``, None: the nominal model)
    on the session's measurements, in the model's length unit, its residual correction applied
    as for the candidate (one comparison, one definition)."""
    st = metrics.norm_statistics(np.linalg.norm(corrected_errors(model, data)[0], axis=1) / model.units.length_m)
    return {"calibration_id": None if cal is None else cal.id, "rms": st.rms, "max": st.max}


def _judge(db, run, candidate, rms: float, before: dict) -> dict:
    """A candidate passes when its RMS error on these fresh configurations is no larger than the
    current model's on the same measurements (both in the model's length unit); it then becomes
    the cell's current calibration, activated by whoever started the session."""
    passed = bool(rms <= before["rms"])
    if passed:
        activate_calibration(db, candidate, actor=run.created_by or "recal", why=f"verify session {run.id} passed it")
    return {"calibration_id": candidate.id, "passed": passed, "activated": passed, "against": before}


def pose_repeatability(model: KinematicModel, data: Measurements, repeats: int) -> dict:
    """ISO 9283 pose accuracy AP and repeatability RP (§7.2.1-7.2.2, ``calibration.metrics``) of
    a verify session that visited each configuration ``repeats`` times (step ``s`` visits
    configuration ``s // repeats``); the command is where the current model puts the target."""
    assert data.pose_id is not None  # a session's measurements carry their pose numbers (records.session_data)
    p_cmd = data.p_world - position_errors(model, data)
    st = metrics.pose_statistics(p_cmd, data.p_world, data.pose_id // repeats)
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


KIND = Verify()
