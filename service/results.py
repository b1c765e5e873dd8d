"""What the technician's web page shows, computed from the stored records (no new tables):

- :func:`calibration_result`: a calibration's per-pose errors before and after, the predicted
  accuracy over the workspace and its report, for the result page and the certificate;
- :func:`plan_preview`: what a (dry-run) session will do before anything moves: how many
  configurations, the joint ranges they use against the allowed limits, the limit check, the
  accuracy they are predicted to give and how long they will take;
- :func:`session_live`: a running session's residuals so far, its pace and time remaining.

Everything is returned JSON-ready, lengths in the cell model's length unit, angles in degrees
where said. Results of finished calibrations are cached in memory (they never change).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np
from sqlmodel import Session, select

from calibration.kinematics import fk
from calibration.metrics import norm_statistics
from calibration.model import KinematicModel, model_from_dict
from calibration.report import COMPARISON_STATUSES, compare_parameters
from calibration.uncertainty import (
    CovarianceError,
    covariance_from_block,
    orientation_from_block,
    radius_95,
    stored_orientation_covariance,
    stored_position_bound,
)

from .analysis import session_sigma
from .models import KIND_RULES, Calibration, Cell, Measurement, RunSession, identified_calibration_kinds
from .plans import UnsafePlan, allowed_limits, check_configurations
from .records import (
    corrected_errors,
    current_model,
    measurements_of,
    position_errors,
    registered_errors,
    session_measurements,
)
from .store import as_utc, candidate_calibration, current_calibration

WORKSPACE_SAMPLES = 400


def _r(x, digits: int = 6):
    """A float rounded to ``digits`` significant digits (None for NaN/inf)."""
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    return float(f"{x:.{digits}g}")


def _rl(a, digits: int = 6):
    """An array as nested lists of rounded floats."""

    def conv(v):
        return [conv(x) for x in v] if isinstance(v, list) else _r(v, digits)

    return conv(np.asarray(a, dtype=float).tolist())


def _stats(e: np.ndarray) -> dict:
    """The figures of error lengths ``e`` (calibration.metrics.norm_statistics), rounded, JSON-ready."""
    st = norm_statistics(e)
    return {"n": st.n, "rms": _r(st.rms), "mean": _r(st.mean), "max": _r(st.max), "p95": _r(st.p95), "std": _r(st.std)}


# --------------------------------------------------------------------------- calibration result

_cache: OrderedDict[int, dict] = OrderedDict()
_cache_lock = threading.Lock()


def _cached(key, compute) -> dict:
    with _cache_lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    value = compute()
    with _cache_lock:
        _cache[key] = value
        while len(_cache) > 64:
            _cache.popitem(last=False)
    return value


def previous_calibration_id(db: Session, cal: Calibration) -> int | None:
    """The cell's calibration of the same kind just before ``cal`` (id only)."""
    return db.exec(
        select(Calibration.id)
        .where(Calibration.cell_id == cal.cell_id, Calibration.kind == cal.kind, Calibration.id < cal.id)
        .order_by(Calibration.id.desc())
    ).first()


def start_model_of(db: Session, cal: Calibration, cell: Cell) -> tuple[KinematicModel, str]:
    """The model the identification started from: the prior calibration's, else the nominal."""
    prior = (cal.report or {}).get("prior") or {}
    pid = prior.get("calibration_id") if isinstance(prior, dict) else None
    if pid is not None:
        prev = db.get(Calibration, pid)
        if prev is not None:
            return model_from_dict(prev.model), f"calibration {pid} (the prior)"
    if cal.nominal_version not in (None, cell.model_version):  # the cell's nominal was replaced since
        earlier = ((cal.model or {}).get("identification") or {}).get("nominal")
        if earlier:
            return model_from_dict(earlier), f"the nominal model it was identified from (version {cal.nominal_version})"
    return model_from_dict(cell.model), "the nominal model"


def workspace_accuracy(
    cal: Calibration,
    cell: Cell,
    target: str | None,
    *,
    samples: int = WORKSPACE_SAMPLES,
    model: KinematicModel | None = None,
) -> dict:
    """The identified model's predicted position uncertainty (95 % radius, from the parameters'
    covariance, instrument noise not included) at ``samples`` configurations drawn uniformly
    inside the cell's allowed joint ranges; with where the target is there (for a map).
    ``model``: ``cal.model`` already read (``model_from_dict``), else it is read here."""
    model = model_from_dict(cal.model) if model is None else model
    try:  # the model's stored covariance is what `recal predict --uncertainty` reads too
        covariance_from_block(model)
        orientation_from_block(model)
    except CovarianceError as exc:
        return {"available": False, "reason": f"this calibration stored no usable parameter covariance: {exc}"}
    nominal = model_from_dict(cell.model)
    try:
        lim = allowed_limits(nominal, cell.allowed_region)
    except UnsafePlan:
        lim = nominal.joint_limits
    lo, hi = lim[:, 0].copy(), lim[:, 1].copy()
    for i, j in enumerate(model.joints):
        if j.revolute:
            lo[i], hi[i] = max(lo[i], -np.pi), min(hi[i], np.pi)
    rng = np.random.default_rng(1000 + int(cal.id or 0))
    q = rng.uniform(lo, hi, size=(samples, model.n_joints))
    if target is not None and target not in model.targets:
        target = None
    # as `recal predict --uncertainty`: grown by the cross-validation's model_error_scale, plus
    # the model-structure error the residuals showed
    try:
        C, inside = stored_position_bound(model, q, target)
    except CovarianceError as exc:
        return {"available": False, "reason": f"this calibration stored no usable bound: {exc}"}
    T = fk(model, q)
    p_world = T[:, :3, :3] @ model.target(target) + T[:, :3, 3]
    L = model.units.length_m
    radius = radius_95(C) / L
    rms = np.sqrt(np.maximum(np.trace(C, axis1=1, axis2=2), 0.0)) / L
    p = p_world / L
    # the tool orientation's 95 % bound, as `recal predict --uncertainty` gives it (r95): held
    # parameters at their prior width, what a position-only fit's orientation rests on (issue 25)
    angle95 = radius_95(stored_orientation_covariance(model, q)) / model.units.angle_rad
    return {
        "available": True,
        "samples": int(samples),
        "target": target,
        "radius95": _rl(radius, 4),
        "rms": _rl(rms, 4),
        "points": _rl(p, 5),
        "stats95": _stats(radius),
        "stats_rms": _stats(rms),
        "angle95": _stats(angle95),
        "note": "95 % radius of the position the model predicts, from the identified parameters' covariance "
        "and the model-structure error the residuals showed (none when the model explains the data); "
        "the instrument's own noise is not included"
        + (
            ""
            if inside is None
            else "; inside the region its residual correction was fitted in, from the correction's "
            f"cross-validated error ({100 * float(np.mean(inside)):.0f} % of these configurations)"
        )
        + "; angle95: the same for the tool orientation's rotation angle (model angle unit), the "
        "parameters the data could not determine taken at their prior width",
        **({} if inside is None else {"inside_correction_share": float(np.mean(inside))}),
    }


def predicted_accuracy(cal: Calibration, cell: Cell, target: str | None) -> dict | None:
    """The calibration's predicted accuracy over the workspace, compact, to store with it: the
    statistics of the 95 % radius :func:`workspace_accuracy` gives (what /result shows), in the
    model's length unit; None when the calibration has no covariance."""
    model = model_from_dict(cal.model)  # read once
    ws = workspace_accuracy(cal, cell, target, model=model)
    if not ws.get("available"):
        return None
    st = ws["stats95"]
    return {
        "radius95_mean": st["mean"],
        "radius95_p95": st["p95"],
        "radius95_max": st["max"],
        "samples": ws["samples"],
        "target": ws["target"],
        "unit": model.units.length,
    }


def calibration_result(db: Session, cal: Calibration) -> dict:
    """Everything the result page shows about one calibration (cached)."""
    key = (str(db.get_bind().url), int(cal.id), str(cal.created_at))
    return _cached(key, lambda: _calibration_result(db, cal))


# The report's parts the result page shows (the rest stays in the stored report)
RESULT_REPORT_KEYS = (
    "success",
    "message",
    "rows",
    "parameters",
    "unidentifiable",
    "condition_number",
    "observability",
    "residuals",
    "outliers",
    "registration",
    "notes",
    "prior",
    "settings",
    "joints",
    "note",
    "compliance",
    "residual_map",
)


def _calibration_result(db: Session, cal: Calibration) -> dict:
    """The result page's figures of calibration ``cal``: its header, report and, for the kinds
    the robot is known by, the errors before and after on its session's measurements."""
    cell = db.get(Cell, cal.cell_id)
    run = db.get(RunSession, cal.session_id) if cal.session_id is not None else None
    report = cal.report or {}
    model = model_from_dict(cal.model)
    out = _result_header(db, cal, cell, run, model)
    out["report"] = {k: report.get(k) for k in RESULT_REPORT_KEYS}
    out["errors"] = None
    out["workspace"] = None
    # the before/after errors of an identified model (the kinds whose calibration the robot is known by)
    if cal.kind not in identified_calibration_kinds() or run is None:
        return out
    try:
        data, rows = session_measurements(db, run)
    except Exception as exc:  # noqa: BLE001 - a result without its session data still shows its report
        out["errors"] = {"available": False, "reason": str(exc)}
        return out
    out["errors"] = _errors_before_and_after(db, cal, cell, model, data, rows, report)
    out["workspace"] = workspace_accuracy(cal, cell, run.target)
    return out


def _result_header(db: Session, cal: Calibration, cell: Cell, run: RunSession | None, model) -> dict:
    """Which calibration, of which cell and session, in which units."""
    return {
        "id": cal.id,
        "kind": cal.kind,
        "created_at": as_utc(cal.created_at).isoformat(),
        "cell": {"id": cell.id, "name": cell.name, "site": cell.site},
        "robot": model_from_dict(cell.model).name,
        "session": None
        if run is None
        else {
            "id": run.id,
            "kind": run.kind,
            "device": run.device,
            "target": run.target,
            "planned": run.planned,
            "created_by": run.created_by,
            "created_at": as_utc(run.created_at).isoformat(),
            "plan_method": run.session_plan().method,
        },
        "units": {"length": model.units.length, "angle": model.units.angle},
        # a model with joint compliance sags under a task's payload: the page asks for it when compensating
        "compliant": model.compliance is not None,
        "rms": cal.rms,
        "previous_id": previous_calibration_id(db, cal),
    }


def _errors_before_and_after(db: Session, cal: Calibration, cell: Cell, model, data, rows, report: dict) -> dict:
    """The position errors on the session's measurements of the model the robot had before
    (registered to them where there are 3 or more) and of the identified one (with its residual
    correction where it applies), in the model's length unit."""
    L = model.units.length_m
    start, start_name = start_model_of(db, cal, cell)
    e_after, inside = corrected_errors(model, data)  # with its residual correction, as the model is used
    raw_before = np.linalg.norm(position_errors(start, data), axis=1)
    if len(data) >= 3:
        e_before = registered_errors(start, data)
        before_how = f"{start_name} with its base placed where it fits these measurements best"
    else:
        e_before, before_how = position_errors(start, data), start_name
    nb, na = np.linalg.norm(e_before, axis=1), np.linalg.norm(e_after, axis=1)
    return {
        "available": True,
        "pose": [int(r.seq) + 1 for r in rows],
        "target": [r.target or "" for r in rows],
        "q_deg": _rl(np.rad2deg(data.q), 5),
        "before": {
            "norm": _rl(nb / L),
            "xyz": _rl(e_before / L),
            "stats": _stats(nb / L),
            "model": before_how,
            "raw_rms": _r(np.sqrt(np.mean(raw_before**2)) / L),
        },
        "after": {
            "norm": _rl(na / L),
            "xyz": _rl(e_after / L),
            "stats": _stats(na / L),
            "model": "the identified model (in-sample: the same measurements it was fitted to)"
            + (
                ""
                if inside is None
                else f", with its residual correction where it applies ({int(np.count_nonzero(~inside))} "
                "outside its region: the geometric model alone there)"
            ),
            **({} if inside is None else {"outside_mapped_region": int(np.count_nonzero(~inside))}),
        },
        "outlier_poses": [int(o["row"]) for o in report.get("outliers") or []],
    }


def compare_calibrations(a: Calibration, b: Calibration) -> dict:
    """Every parameter of two calibrations of a cell, from ``a`` to ``b``
    (``calibration.report.compare_parameters``), with their ids and residuals."""
    rows = compare_parameters(
        model_from_dict(a.model),
        (a.report or {}).get("parameters") or [],
        model_from_dict(b.model),
        (b.report or {}).get("parameters") or [],
    )
    return {
        "from": a.id,
        "to": b.id,
        "rms_from": a.rms,
        "rms_to": b.rms,
        "parameters": rows,
        "counts": {k: sum(r["status"] == k for r in rows) for k in COMPARISON_STATUSES}
        | {"moved": sum(r["moved"] for r in rows)},
    }


# --------------------------------------------------------------------------- plan preview


def _move_time_s(q: np.ndarray, q0: np.ndarray | None, speed: float, accel: float) -> float:
    """Time of joint moves through ``q`` (K, n) at the capped speed and acceleration
    (trapezoidal profile of the joint that moves furthest)."""
    pts = q if q0 is None else np.vstack([q0[None, :], q])
    total = 0.0
    for d in np.max(np.abs(np.diff(pts, axis=0)), axis=1) if len(pts) > 1 else []:
        t_acc = speed / accel
        if d < speed * t_acc:
            total += 2 * math.sqrt(d / accel)
        else:
            total += d / speed + t_acc
    return total


def plan_preview(db: Session, run: RunSession, cell: Cell, settings) -> dict:
    """A session's plan before anything moves (see the module docstring)."""
    nominal = model_from_dict(cell.model)
    out: dict = {
        "session_id": run.id,
        "state": run.state,
        "reason": run.reason,
        "kind": run.kind,
        "device": run.device,
        "target": run.target,
        "dry_run": run.dry_run,
        "method": run.session_plan().method,
        "configurations": 0,
        "joints": [],
        "check": None,
        "predicted": None,
        "estimated_duration_s": None,
        "units": {"length": nominal.units.length, "angle": "deg"},
    }
    if run.plan is None:
        out["check"] = {"ok": False, "message": run.reason or "not planned yet"}
        return out
    q = np.asarray(run.plan, dtype=float)
    out["configurations"] = int(len(q))
    try:
        lim = allowed_limits(nominal, cell.allowed_region)
    except UnsafePlan as exc:
        out["check"] = {"ok": False, "message": str(exc)}
        return out
    joints = []
    for i, j in enumerate(nominal.joints):
        s = math.pi / 180 if j.revolute else nominal.units.length_m
        unit = "deg" if j.revolute else nominal.units.length
        used = q[:, i] / s if len(q) else np.zeros(1)
        joints.append(
            {
                "name": j.name,
                "unit": unit,
                "limit": [_r(lim[i, 0] / s), _r(lim[i, 1] / s)],
                "model_limit": [_r(j.lower / s), _r(j.upper / s)],
                "used": [_r(used.min()), _r(used.max())],
                "values": _rl(used, 5),
            }
        )
    out["joints"] = joints
    try:
        check_configurations(nominal, q, cell.allowed_region)
        out["check"] = {
            "ok": True,
            "message": f"all {len(q)} configurations are inside the joint limits"
            + (" and the cell's allowed region" if cell.allowed_region else ""),
        }
    except UnsafePlan as exc:
        out["check"] = {"ok": False, "message": str(exc)}
    speed, accel = settings.max_joint_speed_rad_s, settings.max_joint_accel_rad_s2
    out["estimated_duration_s"] = _r(_move_time_s(q, None, speed, accel) + len(q) * (settings.settle_s + 0.05), 3)
    out["speed_caps"] = {
        "joint_speed_deg_s": _r(math.degrees(speed), 4),
        "joint_accel_deg_s2": _r(math.degrees(accel), 4),
    }
    if run.kind in KIND_RULES and KIND_RULES[run.kind].predicts_accuracy:
        out["predicted"] = _predicted_pose_accuracy(db, cell, q, run)
        out["learning_curve"] = learning_curve_prediction(db, cell, len(q))
    return out


def learning_curve_prediction(db: Session, cell: Cell, poses: int) -> dict:
    """The held-out RMS a plan of ``poses`` poses is predicted to reach, from the learning curve
    of the cell's current calibration (the nested cross-validation's held-out RMS of the whole
    procedure, geometric identification and residual correction, against the number of poses),
    extrapolated by a power law of the excess over the instrument's noise
    (``calibration.residual_choice.extrapolate_learning_curve``). Model length unit."""
    from calibration.residual_choice import extrapolate_learning_curve

    _, cal = current_model(db, cell)
    L = model_from_dict(cell.model).units.length_m
    rmap = ((cal.report or {}).get("residual_map") or {}) if cal is not None else {}
    curve = rmap.get("learning_curve") or []
    if not curve or rmap.get("noise_sigma") is None:
        return {
            "available": False,
            "reason": "no earlier learning curve: the cell's current calibration has none (a pose calibration "
            "made by this version records one)",
        }
    pred = extrapolate_learning_curve(
        [{"poses": p["poses"], "rms_m": p["rms"] * L} for p in curve], poses, rmap["noise_sigma"] * L
    )
    if pred is None:
        return {"available": False, "reason": "the earlier learning curve has no point"}
    return {
        "available": True,
        "calibration_id": cal.id if cal is not None else None,
        "poses": int(poses),
        "rms": _r(pred["rms_m"] / L),
        "noise": _r(rmap["noise_sigma"]),
        "exponent": _r(pred["b"], 3),
        "extrapolated": pred["extrapolated"],
        "curve": [{"poses": int(p["poses"]), "rms": _r(p["rms"])} for p in curve],
        "note": f"held-out RMS predicted for {poses} poses from calibration {cal.id if cal else '-'}'s learning "
        f"curve ({len(curve)} points, {min(p['poses'] for p in curve)}-{max(p['poses'] for p in curve)} poses), "
        f"{'extrapolated' if pred['extrapolated'] else 'interpolated'} by a power law: {pred['law']}"
        f" (b = {pred['b']:.2f}); it includes the instrument's noise",
    }


def _predicted_pose_accuracy(db: Session, cell: Cell, q: np.ndarray, run: RunSession) -> dict:
    """What identification from these configurations is predicted to achieve (observation
    planning's covariance σ²(JᵀJ)⁻¹ propagated to random configurations), for the noise the
    session's instrument declares (:func:`service.analysis.session_sigma`)."""
    info = run.session_plan().planner  # what the planner predicted for these configurations
    L = model_from_dict(cell.model).units.length_m
    sigma = session_sigma(run, cell, run.device)
    sigma_m = sigma.sigma_m
    note = (
        f"RMS position error of the identified model over random configurations, predicted for an "
        f"instrument with {sigma_m / L:.3g} {model_from_dict(cell.model).units.length} noise per axis "
        f"({sigma.source})"
    )
    if "dense" in info:  # the planner predicted for the planned core; the filling poses only add to it
        note += (
            f" (from the {info['dense']['planned']} planned poses: the {info['dense']['filling']} filling the "
            "region can only improve it)"
        )
    if "predicted_rms_m" in info:
        un = info.get("unidentifiable")
        return {
            "available": True,
            "rms": _r(info["predicted_rms_m"] / L),
            "p95": _r(info.get("predicted_p95_m", float("nan")) / L),
            "max": _r(info.get("predicted_max_m", float("nan")) / L),
            "sigma": _r(sigma_m / L),
            "sigma_source": sigma.source,
            "unidentifiable": len(un) if isinstance(un, list) else None,
            "unidentifiable_names": un if isinstance(un, list) else None,
            "shortfall": info.get("shortfall"),
            "source": "planner",
            "note": note,
        }
    try:
        from calibration import planning
    except ImportError:  # pragma: no cover
        return {"available": False, "reason": "observation planning is not available in this build"}
    model, _ = session_model(db, run, cell)
    target = run.target if run.device != "cmm" else None
    try:
        res = planning.plan(
            model, q, len(q), targets=(target,), sigma_m=sigma_m, exchange=False, rng=np.random.default_rng(7)
        )
    except ValueError as exc:
        return {"available": False, "reason": str(exc), "shortfall": info.get("shortfall")}
    return {
        "available": bool(res.success),
        # how many more poses, or which kind, would determine what these cannot (issue 27)
        "shortfall": info.get("shortfall"),
        "rms": _r(res.predicted_rms_m / L),
        "p95": _r(res.predicted_p95_m / L),
        "max": _r(res.predicted_max_m / L),
        "sigma": _r(sigma_m / L),
        "sigma_source": sigma.source,
        "identifiable": len(res.params),
        "unidentifiable": len(res.unidentifiable),
        "message": res.message,
        "source": "these configurations",
        "note": note,
    }


# --------------------------------------------------------------------------- live session


def session_model(db: Session, run: RunSession, cell: Cell) -> tuple[KinematicModel, Calibration | None]:
    """The model a session's figures are shown against: only a calibration that existed when
    the session ran. A verify session's is the calibration it checked (None: the nominal model),
    or, until it has finished, the one it will check (the candidate made before it started, else
    the cell's current one then); any other session's is the cell's calibration when it started."""
    verified = run.verify_result()
    if verified is not None:
        cid = verified.calibration_id
        cal = db.get(Calibration, cid) if cid is not None else None
    else:
        cal = candidate_calibration(db, cell, made_by=run.created_at) if run.kind == "verify" else None
        cal = cal or current_calibration(db, cell, at=run.created_at)
    return (model_from_dict(cal.model), cal) if cal is not None else (model_from_dict(cell.model), None)


def session_live(db: Session, run: RunSession, cell: Cell) -> dict:
    """The residuals measured so far and the pace of a session."""
    rows = db.exec(
        select(Measurement).where(Measurement.session_id == run.id).order_by(Measurement.seq, Measurement.id)
    ).all()
    nominal = model_from_dict(cell.model)
    L = nominal.units.length_m
    seqs = sorted({r.seq for r in rows})
    out: dict = {
        "session_id": run.id,
        "state": run.state,
        "reason": run.reason,
        "planned": run.planned,
        "measured": len(seqs),
        "units": {"length": nominal.units.length},
        "residuals": None,
        "elapsed_s": None,
        "seconds_per_pose": None,
        "remaining_s": None,
        "last": None,
    }
    if not rows:
        return out
    times = {}
    for r in rows:
        times.setdefault(r.seq, as_utc(r.created_at))
    t_sorted = sorted(times.values())
    out["elapsed_s"] = _r((t_sorted[-1] - as_utc(run.created_at)).total_seconds(), 4)
    if len(t_sorted) >= 2:
        d = np.diff([t.timestamp() for t in t_sorted[-11:]])
        per = float(np.median(d))
        out["seconds_per_pose"] = _r(per, 3)
        if run.state in ("running", "planned", "paused", "interrupted"):
            out["remaining_s"] = _r(max(run.planned - len(seqs), 0) * per, 3)
    last = rows[-1]
    out["last"] = {
        "pose": int(last.seq) + 1,
        "at": as_utc(last.created_at).isoformat(),
        "q_deg": _rl(np.rad2deg(np.asarray(last.q, dtype=float)), 5),
        "position": [_r(last.x / L), _r(last.y / L), _r(last.z / L)],
        "sigma": _r(last.sigma / L) if last.sigma else None,
        "reference_deg": _r(math.degrees(last.reference)) if last.reference is not None else None,
    }
    view = KIND_RULES[run.kind].live_residuals if run.kind in KIND_RULES else None
    residuals = view(db, run, cell, rows, L) if view is not None else None
    if residuals is not None:
        out["residuals"] = residuals
    return out


# --------------------------------------------------------------------------- the kinds' live residuals
# Each kind names its view (KindRules.live_residuals, service/kinds/); the live page calls it.


def position_residuals(db: Session, run: RunSession, cell: Cell, rows: list, L: float, *, checks: bool = False) -> dict:
    """A session measuring points: each pose's position error so far against the calibration the
    session ran with (``checks``: the one it checks, a verify session's), else the nominal model
    placed where it fits the measurements."""
    # from the rows read by the caller, not read again: the chart, "measured" and "last" count the
    # same poses (a pose stored between two reads made "7 of 60" beside a chart ending at pose 6)
    data = measurements_of(rows, run)
    model, cal = session_model(db, run, cell)
    if cal is not None:
        e = position_errors(model, data)
        how = (
            f"calibration {cal.id}, which this session checks"
            if checks
            else f"calibration {cal.id}, the cell's when this session started"
        )
    elif len(data) >= 4:
        e = registered_errors(model, data)
        how = "the nominal model, its base placed where it fits the measurements so far"
    else:
        e, how = None, "shown from the fourth pose on (the instrument's placement is fitted first)"
    if e is not None:
        n = np.linalg.norm(e, axis=1) / L
        return {
            "pose": [int(s) + 1 for s in data.pose_id],
            "norm": _rl(n),
            "stats": _stats(n),
            "model": how,
        }
    return {"pose": [], "norm": [], "stats": _stats(np.zeros(0)), "model": how}


def joint_residuals(db: Session, run: RunSession, cell: Cell, rows: list, L: float) -> dict | None:
    """A session against reference encoders: reference minus controller reading per point."""
    sel = [r for r in rows if r.joint and r.reference is not None]
    if sel:
        d = np.array([math.degrees(r.reference - r.q[r.joint - 1]) for r in sel])
        d = (d + 180.0) % 360.0 - 180.0
        return {
            "pose": [int(r.seq) + 1 for r in sel],
            "norm": _rl(d - d.mean()),
            "stats": _stats(np.abs(d - d.mean())),
            "unit": "deg",
            "model": "reference encoder minus controller reading (mean removed), deg",
        }
    return None
