"""What a session will do, before anything moves: its joint configurations, and the safety
check of every one of them against the model's joint limits and the cell's allowed region.

- ``pose``: observation planning (``calibration.planning``, its default criterion) over
  candidates drawn inside the allowed region;
- ``verify``: fresh random configurations inside the allowed region (not the planned ones); with
  ``repeats`` > 1 each is visited that many times in a row, every visit approached from the same
  direction through the same nearby configuration (ISO 9283 pose repeatability, §7.2.2);
- ``circle``: each joint swept over as much of its allowed range as it has (up to 300 deg),
  the others held at a signature configuration (book §4.6.3, sequence A);
- ``joint``: each joint with a reference encoder swept over its allowed range.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calibration.errors import RecalError
from calibration.model import KinematicModel

# How far (rad, or m for a prismatic joint, per joint) a repeated verify visit backs away before it
# approaches its configuration again: well beyond any backlash, small enough to stay near the pose.
APPROACH_OFFSET_RAD = np.deg2rad(5.0)
APPROACH_OFFSET_M = 0.02
POLL_S = 0.1  # s: how often a stop is looked for while observation planning computes


@dataclass(frozen=True)
class Plan:
    """``q`` (K, n) readings, SI; ``joint`` (K,) the swept joint (1-based) of circle/joint steps,
    0 otherwise; ``info`` what the planner predicts (JSON-ready)."""

    q: np.ndarray
    joint: np.ndarray
    info: dict


class UnsafePlan(RecalError, ValueError):
    """A configuration is outside the joint limits or the cell's allowed region."""


class RegionError(RecalError, ValueError):
    """An allowed region that cannot be used: ``row`` (0-based, or None for the whole region)."""

    def __init__(self, message: str, row: int | None = None):
        self.row = row
        super().__init__(message)


def check_region(model: KinematicModel, region: list | None) -> None:
    """Raise ``RegionError`` unless ``region`` (per joint ``[lower, upper]``, model units) has one
    row per joint, each two finite numbers with lower < upper, overlapping the joint's limits."""
    if region is None:
        return
    if len(region) != model.n_joints:
        raise RegionError(f"expected one [lower, upper] row per joint ({model.n_joints}), got {len(region)} rows")
    lim = model.joint_limits
    for i, (row, j) in enumerate(zip(region, model.joints)):
        unit = model.units.angle if j.revolute else model.units.length
        if len(row) != 2 or not all(np.isfinite(v) for v in row):
            raise RegionError(f"expected [lower, upper] in {unit}, two finite numbers; got {row}", i)
        if not row[0] < row[1]:
            raise RegionError(f"lower ({row[0]:g}) must be below upper ({row[1]:g})", i)
        s = model.units.angle_rad if j.revolute else model.units.length_m
        if row[1] * s <= lim[i, 0] or row[0] * s >= lim[i, 1]:
            raise RegionError(
                f"[{row[0]:g}, {row[1]:g}] {unit} leaves joint {i + 1} no motion within its limits "
                f"[{lim[i, 0] / s:.6g}, {lim[i, 1] / s:.6g}] {unit}",
                i,
            )


def allowed_limits(model: KinematicModel, region: list | None) -> np.ndarray:
    """(n, 2) SI: the model's joint limits intersected with the cell's allowed region (given in
    the model's units)."""
    lim = model.joint_limits.copy()
    if region is not None:
        if len(region) != model.n_joints:
            raise UnsafePlan(f"allowed_region has {len(region)} rows but the model has {model.n_joints} joints")
        for i, (row, j) in enumerate(zip(region, model.joints)):
            s = model.units.angle_rad if j.revolute else model.units.length_m
            lo, hi = float(row[0]) * s, float(row[1]) * s
            lim[i, 0], lim[i, 1] = max(lim[i, 0], lo), min(lim[i, 1], hi)
            if lim[i, 0] >= lim[i, 1]:
                raise UnsafePlan(f"allowed_region row {i + 1} leaves no motion for joint {i + 1}")
    return lim


def check_configurations(model: KinematicModel, q: np.ndarray, region: list | None) -> None:
    """Raise ``UnsafePlan`` naming the first configuration and joint outside the allowed limits."""
    lim = allowed_limits(model, region)
    bad = (q < lim[:, 0] - 1e-12) | (q > lim[:, 1] + 1e-12)
    if np.any(bad):
        k, i = map(int, np.argwhere(bad)[0])
        j = model.joints[i]
        s = model.units.angle_rad if j.revolute else model.units.length_m
        unit = model.units.angle if j.revolute else model.units.length
        raise UnsafePlan(
            f"configuration {k + 1}: joint {i + 1} at {q[k, i] / s:.4g} {unit} is outside the allowed range "
            f"[{lim[i, 0] / s:.4g}, {lim[i, 1] / s:.4g}] {unit}"
        )


@dataclass(frozen=True)
class PlanRequest:
    """What a session kind plans from (``SessionKind.plan``): ``count`` configurations inside
    ``lim`` (n, 2) (the joint limits and the cell's allowed region, SI), the session's
    instrument's per-axis standard uncertainty ``sigma_m`` (m, what the predictions assume:
    ``service.devices.instrument_sigma``), with the session's ``target``, ``joints`` (1-based)
    and ``repeats``; ``between()`` is called between the phases of a long planning (it raises to
    stop it: an abort, a pause, the process stopping)."""

    model: KinematicModel
    lim: np.ndarray
    count: int
    rng: np.random.Generator
    sigma_m: float
    target: str | None = None
    joints: list[int] | None = None
    repeats: int = 1
    between: Callable[[], None] = lambda: None


def plan_session(
    plan_kind: Callable[[PlanRequest], Plan],
    model: KinematicModel,
    count: int,
    *,
    region: list | None = None,
    target: str | None = None,
    joints: list[int] | None = None,
    seed: int = 0,
    sigma_m: float,
    repeats: int = 1,
    between: Callable[[], None] | None = None,
) -> Plan:
    """The configurations of a session, planned by its kind (``plan_kind``, the kind's
    ``SessionKind.plan``: see the module docstring), checked against the joint limits and the
    allowed ``region``, with what they span; ``sigma_m``: the instrument's per-axis standard
    uncertainty (m). ``between()``: as :class:`PlanRequest`."""
    between = between or (lambda: None)
    lim = allowed_limits(model, region)
    n = model.n_joints
    req = PlanRequest(model, lim, count, np.random.default_rng(seed), sigma_m, target, joints, repeats, between)
    plan = plan_kind(req)
    between()
    check_configurations(model, plan.q, region)
    if repeats > 1:
        check_configurations(model, approach_configurations(model, region, plan.q), region)
    span = np.rad2deg(plan.q.max(axis=0) - plan.q.min(axis=0)) if len(plan.q) else np.zeros(n)
    info = dict(plan.info)
    info.update(
        {
            "configurations": int(len(plan.q)),
            "joint_ranges_deg": [
                [float(np.rad2deg(a)), float(np.rad2deg(b))] for a, b in zip(plan.q.min(axis=0), plan.q.max(axis=0))
            ],
            "joint_spans_deg": [float(s) for s in span],
            "limits_checked": True,
        }
    )
    return Plan(plan.q, plan.joint, info)


def joint_sweeps(req: PlanRequest, method: str) -> Plan:
    """Each of ``req.joints`` (default: every joint) swept over as much of its allowed range as
    it has (up to 300 deg), ``req.count`` points (at least 3), the others held at a signature
    configuration (zero, or the middle of a range that excludes it): book §4.6.3, sequence A."""
    model, lim = req.model, req.lim
    n = model.n_joints
    which = req.joints or list(range(1, n + 1))
    for j in which:
        if not 1 <= j <= n:
            raise UnsafePlan(f"joints: {j} is not a joint of this {n}-joint model")
    mid = 0.5 * (lim[:, 0] + lim[:, 1])
    signature = np.clip(np.zeros(n), lim[:, 0], lim[:, 1])
    signature = np.where((signature <= lim[:, 0]) | (signature >= lim[:, 1]), mid, signature)
    rows, swept = [], []
    per_joint = max(int(req.count), 3)
    for j in which:
        i = j - 1
        span = min(lim[i, 1] - lim[i, 0], np.deg2rad(300.0)) if model.joints[i].revolute else lim[i, 1] - lim[i, 0]
        centre = np.clip(signature[i], lim[i, 0] + span / 2, lim[i, 1] - span / 2)
        for v in np.linspace(centre - span / 2, centre + span / 2, per_joint):
            q = signature.copy()
            q[i] = v
            rows.append(q)
            swept.append(j)
    return Plan(np.array(rows), np.array(swept), {"method": method, "points_per_joint": per_joint, "joints": which})


def random_inside(lim: np.ndarray, count: int, rng: np.random.Generator, model: KinematicModel) -> np.ndarray:
    """(count, n) configurations drawn uniformly inside ``lim``, revolute joints within one turn."""
    lo, hi = lim[:, 0].copy(), lim[:, 1].copy()
    for i, j in enumerate(model.joints):  # one turn either way is enough for measuring
        if j.revolute:
            lo[i], hi[i] = max(lo[i], -np.pi), min(hi[i], np.pi)
    return rng.uniform(lo, hi, size=(count, model.n_joints))


def repeated(q: np.ndarray, repeats: int) -> Plan:
    """Verify configurations ``q`` (K, n), each visited ``repeats`` times in a row: step ``s``
    visits configuration ``s // repeats`` (see :func:`approach_configurations`)."""
    steps = np.repeat(np.arange(len(q)), max(int(repeats), 1))
    info: dict[str, object] = {"method": "random"}
    if repeats > 1:
        info.update(
            {
                "repeats": int(repeats),
                "poses": int(len(q)),
                "approach": "every visit from the same approach configuration (ISO 9283)",
            }
        )
    return Plan(q[steps], np.zeros(len(steps), int), info)


def approach_configurations(model: KinematicModel, region: list | None, q: np.ndarray) -> np.ndarray:
    """(K, n): where the robot goes just before each of the configurations ``q`` (K, n) of a
    session that repeats them, so that every visit approaches from the same direction (ISO 9283
    §7.2.2): a few degrees (``APPROACH_OFFSET_*``) below the configuration on every joint, or
    above it for a joint too near its lower allowed limit."""
    lim = allowed_limits(model, region)
    step = np.array([APPROACH_OFFSET_RAD if j.revolute else APPROACH_OFFSET_M for j in model.joints])
    return np.where(q - step >= lim[:, 0], q - step, np.minimum(q + step, lim[:, 1]))


def planned_poses(req: PlanRequest) -> Plan:
    """Planned poses (``calibration.planning``: greedy start and exchange) from random
    candidates inside the allowed region, in a short measurement order, with the accuracy
    they are predicted to give. (The line-of-sight test of the planner needs to know where the
    instrument stands relative to the robot, which a first calibration does not: the session
    relies on the retry policy for the occasional blocked beam.)"""
    from calibration import planning

    model, count, rng, between = req.model, req.count, req.rng, req.between
    target, sigma_m = req.target, req.sigma_m
    if count > DENSE_FROM:
        return dense_poses(req)
    candidates = random_inside(req.lim, max(20 * count, 1000), rng, model)
    between()
    try:
        res = _checking(
            lambda: planning.plan(model, candidates, count, targets=(target,), sigma_m=sigma_m, rng=rng), between
        )
    except ValueError as exc:
        # Too few poses to determine every parameter from the data alone: a short session that
        # updates a previous calibration (its prior) needs no more. Spread them at random, and say
        # how many planned poses would determine them (issue 27).
        return Plan(
            candidates[:count],
            np.zeros(count, int),
            {
                "method": "random (too few poses to plan for a full identification)",
                "note": str(exc),
                "shortfall": _shortfall(model, candidates, count, target, sigma_m),
            },
        )
    between()
    q = res.q[planning.measurement_order(res.q)]
    info = {
        "method": f"{res.criterion}-optimal (greedy + exchange) from {len(candidates)} candidates",
        "predicted_rms_m": float(res.predicted_rms_m),
        "predicted_p95_m": float(res.predicted_p95_m),
        "predicted_max_m": float(res.predicted_max_m),
        "unidentifiable": [u.name for u in res.unidentifiable],
    }
    if res.unidentifiable or not res.success:
        info["shortfall"] = _shortfall(model, candidates, count, target, sigma_m)
    return Plan(q, np.zeros(len(q), int), info)


# A pose session of more configurations than this is a dense set for a learned residual correction
# (issue 28): this many are planned D-optimally for the geometric model, the rest fill the region.
DENSE_FROM = 200


def dense_poses(req: PlanRequest) -> Plan:
    """A dense set of ``req.count`` configurations over the allowed region (the task's region, as
    the cell's allowed region says it): :data:`DENSE_FROM` planned D-optimally (what the geometric
    identification needs, :func:`planned_poses`), the rest a Latin hypercube of the region (every
    joint's range cut in as many strata as configurations, one in each, shuffled per joint), so
    that a learned correction sees the whole region evenly; in a short measurement order."""
    from calibration import planning

    core = planned_poses(
        PlanRequest(req.model, req.lim, DENSE_FROM, req.rng, req.sigma_m, req.target, None, 1, req.between)
    )
    req.between()
    fill = latin_hypercube(req.lim, req.count - len(core.q), req.rng, req.model)
    q = np.vstack([core.q, fill])
    q = q[planning.measurement_order(q)]
    info = {
        **{k: v for k, v in core.info.items() if k != "method"},
        "method": f"dense: {len(core.q)} poses {core.info.get('method')}, {len(fill)} filling the region "
        "(Latin hypercube)",
        "dense": {"planned": int(len(core.q)), "filling": int(len(fill))},
    }
    return Plan(q, np.zeros(len(q), int), info)


def latin_hypercube(lim: np.ndarray, count: int, rng: np.random.Generator, model: KinematicModel) -> np.ndarray:
    """(count, n) configurations inside ``lim`` (revolute joints within one turn, as
    :func:`random_inside`), each joint's range cut in ``count`` equal strata with one
    configuration in each, the strata shuffled independently per joint."""
    lo, hi = lim[:, 0].copy(), lim[:, 1].copy()
    for i, j in enumerate(model.joints):
        if j.revolute:
            lo[i], hi[i] = max(lo[i], -np.pi), min(hi[i], np.pi)
    n = model.n_joints
    u = (np.argsort(rng.random((count, n)), axis=0) + rng.random((count, n))) / max(count, 1)
    return lo + u * (hi - lo)


def _shortfall(model: KinematicModel, candidates: np.ndarray, count: int, target, sigma_m: float) -> dict | None:
    """What ``count`` poses of this kind leave undetermined and what would determine it
    (``calibration.planning.shortfall``), JSON-ready; None when the candidates say nothing."""
    from calibration import planning

    try:
        return planning.shortfall(model, candidates, count, targets=(target,), sigma_m=sigma_m).as_dict()
    except ValueError:
        return None


def _checking(compute: Callable, between: Callable[[], None]):
    """``compute()`` (pure, seconds long: observation planning) in a helper thread, calling
    ``between()`` every ``POLL_S`` while it runs, so that a stop takes effect at once; a stopped
    computation is abandoned (it ends on its own, bounded by the session's count cap)."""
    box: dict = {}
    done = threading.Event()

    def run():
        try:
            box["value"] = compute()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            box["error"] = exc
        finally:
            done.set()

    threading.Thread(target=run, name="planning", daemon=True).start()
    while not done.wait(POLL_S):
        between()
    if "error" in box:
        raise box["error"]
    return box["value"]
