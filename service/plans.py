"""What a session will do, before anything moves: its joint configurations, and the safety
check of every one of them against the model's joint limits and the cell's allowed region.

- ``pose``: observation planning (``calibration.planning``, D-optimal) over candidates drawn
  inside the allowed region;
- ``verify``: fresh random configurations inside the allowed region (not the planned ones);
- ``circle``: each joint swept over as much of its allowed range as it has (up to 300 deg),
  the others held at a signature configuration (book §4.6.3, sequence A);
- ``joint``: each joint with a reference encoder swept over its allowed range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.model import KinematicModel


@dataclass(frozen=True)
class Plan:
    """``q`` (K, n) readings, SI; ``joint`` (K,) the swept joint (1-based) of circle/joint steps,
    0 otherwise; ``info`` what the planner predicts (JSON-ready)."""

    q: np.ndarray
    joint: np.ndarray
    info: dict


class UnsafePlan(ValueError):
    """A configuration is outside the joint limits or the cell's allowed region."""


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


def _random_inside(lim: np.ndarray, count: int, rng: np.random.Generator, model: KinematicModel) -> np.ndarray:
    lo, hi = lim[:, 0].copy(), lim[:, 1].copy()
    for i, j in enumerate(model.joints):  # one turn either way is enough for measuring
        if j.revolute:
            lo[i], hi[i] = max(lo[i], -np.pi), min(hi[i], np.pi)
    return rng.uniform(lo, hi, size=(count, model.n_joints))


def plan_session(kind: str, model: KinematicModel, count: int, *, region: list | None = None,
                 target: str | None = None, joints: list[int] | None = None, seed: int = 0,
                 sigma_m: float = 20e-6) -> Plan:
    """The configurations of a session of ``kind`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    lim = allowed_limits(model, region)
    n = model.n_joints
    if kind in ("pose", "verify"):
        if kind == "pose":
            plan = _planned_poses(model, lim, count, rng, target, sigma_m)
        else:
            plan = Plan(_random_inside(lim, count, rng, model), np.zeros(count, int), {"method": "random"})
    elif kind in ("circle", "joint"):
        which = joints or list(range(1, n + 1))
        for j in which:
            if not 1 <= j <= n:
                raise UnsafePlan(f"joints: {j} is not a joint of this {n}-joint model")
        mid = 0.5 * (lim[:, 0] + lim[:, 1])
        signature = np.clip(np.zeros(n), lim[:, 0], lim[:, 1])
        signature = np.where((signature <= lim[:, 0]) | (signature >= lim[:, 1]), mid, signature)
        rows, swept = [], []
        per_joint = max(int(count), 3)
        for j in which:
            i = j - 1
            span = min(lim[i, 1] - lim[i, 0], np.deg2rad(300.0)) if model.joints[i].revolute else lim[i, 1] - lim[i, 0]
            centre = np.clip(signature[i], lim[i, 0] + span / 2, lim[i, 1] - span / 2)
            for v in np.linspace(centre - span / 2, centre + span / 2, per_joint):
                q = signature.copy()
                q[i] = v
                rows.append(q)
                swept.append(j)
        plan = Plan(np.array(rows), np.array(swept), {"method": f"{kind} sweeps", "points_per_joint": per_joint,
                                                      "joints": which})
    else:
        raise ValueError(f"unknown session kind {kind!r}")
    check_configurations(model, plan.q, region)
    span = np.rad2deg(plan.q.max(axis=0) - plan.q.min(axis=0)) if len(plan.q) else np.zeros(n)
    info = dict(plan.info)
    info.update({"configurations": int(len(plan.q)),
                 "joint_ranges_deg": [[float(np.rad2deg(a)), float(np.rad2deg(b))]
                                      for a, b in zip(plan.q.min(axis=0), plan.q.max(axis=0))],
                 "joint_spans_deg": [float(s) for s in span], "limits_checked": True})
    return Plan(plan.q, plan.joint, info)


def _planned_poses(model, lim, count, rng, target, sigma_m) -> Plan:
    """D-optimal poses (``calibration.planning``: greedy start and exchange) from random
    candidates inside the allowed region, in a short measurement order, with the accuracy
    they are predicted to give. (The line-of-sight test of the planner needs to know where the
    instrument stands relative to the robot, which a first calibration does not: the session
    relies on the retry policy for the occasional blocked beam.)"""
    from calibration import planning

    candidates = _random_inside(lim, max(20 * count, 1000), rng, model)
    try:
        res = planning.plan(model, candidates, count, targets=(target,), sigma_m=sigma_m, rng=rng)
    except ValueError as exc:
        # Too few poses to determine every parameter from the data alone: a short session that
        # updates a previous calibration (its prior) needs no more. Spread them at random.
        return Plan(candidates[:count], np.zeros(count, int),
                    {"method": "random (too few poses to plan for a full identification)", "note": str(exc)})
    q = res.q[planning.measurement_order(res.q)]
    info = {
        "method": f"{res.criterion}-optimal (greedy + exchange) from {len(candidates)} candidates",
        "predicted_rms_m": float(res.predicted_rms_m),
        "predicted_p95_m": float(res.predicted_p95_m),
        "predicted_max_m": float(res.predicted_max_m),
        "unidentifiable": [u.name for u in res.unidentifiable],
    }
    return Plan(q, np.zeros(len(q), int), info)
