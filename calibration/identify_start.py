"""Before the parameters (:func:`calibration.identify.identify`, steps 1-3): the input's
validation (:func:`_check_input`, :class:`NotEnoughData`), the convention rewrite to a complete,
proportional form (:func:`complete_form`, :func:`completeness`), the targets nominally on the last
axis, and the rigid registration of the nominal's predictions onto the measurements
(:func:`_register`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from .conventions import hayati_for_parallel_axes, mdh_to_dh, to_poe
from .errors import RecalError
from .identification import (
    Measurements,
)
from .identify_problem import CHUNK_ROWS, LOSSES, _p_tool, _Problem
from .jacobian import predict, world_points
from .kinematics import program, walk
from .model import KinematicModel
from .parameters import candidate_parameters
from .registration import PointSums, register_poses
from .transforms import homogeneous, invert, matrix_to_pose, pose_to_matrix


def _register(model: KinematicModel, prob: _Problem) -> tuple[KinematicModel, dict]:
    """Try a rigid registration of the model's predictions onto the data; keep it if it fits
    better than the model's own base.

    One pass over the rows, :data:`CHUNK_ROWS` at a time: the points the model predicts are kept
    (N, 3), their tool frames only where a row has a measured orientation; the point
    registration needs only sums (:class:`calibration.registration.PointSums`). Walking all rows
    at once kept every joint's frame of a million rows (issue 25: the identification's peak)."""
    data = prob.data
    local = dataclasses.replace(model, base=np.zeros(6))
    p_tool = _p_tool(model, prob.p_tool_names, prob.target_rows)
    sums, p_local, R_rot, p_rot = _registration_pass(local, prob, p_tool)

    def rms(base: np.ndarray, p_local: np.ndarray) -> float:
        e = data.p_world - (p_local @ base[:3, :3].T + base[:3, 3])
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))

    before = rms(pose_to_matrix(model.base), p_local)
    info: dict[str, Any] = {"rms_before_m": before}
    n_rot = len(R_rot)
    if n_rot >= 3:
        assert prob.R_meas is not None  # rows with an orientation: measured orientations
        m = prob.has_rot
        T_pred = homogeneous(R_rot, p_rot)  # includes the current tool
        T_meas = homogeneous(prob.R_meas[m], np.zeros((n_rot, 3)))
        # the measured position is of the row's target; bring it to the tool origin with the
        # model's target offset as the first guess
        pt = _p_tool(model, prob.p_tool_names[m])
        T_meas[:, :3, 3] = data.p_world[m] - np.einsum("nij,nj->ni", prob.R_meas[m], pt)
        X, Y = register_poses(T_pred, T_meas)
        tool = matrix_to_pose(pose_to_matrix(model.tool) @ Y)
        candidate = dataclasses.replace(model, base=matrix_to_pose(X), tool=tool)
        info["method"] = "robot-world/hand-eye (base and tool from full poses)"
        G = invert(pose_to_matrix(model.tool)) @ pose_to_matrix(candidate.tool)  # old tool -> new tool
        p_local = _registration_pass(local, prob, G[:3, 3] + p_tool @ G[:3, :3].T)[1]
    else:
        X, c = sums.register()
        candidate = dataclasses.replace(model, base=matrix_to_pose(X))
        info["method"] = "rigid point registration (Kabsch)"
        info["point_offset_correction_m"] = c.tolist()
    B = pose_to_matrix(candidate.base)
    after = rms(B, p_local)
    info["applied"] = bool(after < before)
    # the figure reported is the registration as found, the common target offset included: the
    # start keeps its own targets (the fit frees what the data determine of them), but an offset
    # the registration estimated and then dropped inflated "after" (issue 25: a UR10 measured with
    # a T-Mac read 15 mm where the same registration with its offset gave 1 mm; a reflector 50 mm
    # from the nominal's target read 50.7 mm here, tests/calibration/test_before_figure.py)
    if "point_offset_correction_m" in info:
        info["rms_after_m"] = _rms_with_offset(sums, data.p_world, p_local, B, c)
    else:
        info["rms_after_m"] = after
    return (candidate if after < before else model), info


def _registration_pass(model: KinematicModel, prob: _Problem, p_tool: np.ndarray):
    """One chunked walk of every row: the registration's sums, the predicted points (N, 3), and
    the tool frames ``(R, p)`` of the rows with a measured orientation."""
    data = prob.data
    N = len(data)
    sums, points = PointSums(), np.empty((N, 3))
    R_rot, p_rot = [], []
    ops = program(model)
    for a in range(0, N, CHUNK_ROWS):
        b = min(a + CHUNK_ROWS, N)
        payload = None if data.payload is None else data.payload[a:b]
        w = walk(model, data.q[a:b], payload=payload, ops=ops)
        points[a:b] = sums.add(w.R, w.p, data.p_world[a:b], p_tool[a:b])
        m = prob.has_rot[a:b]
        if m.any():
            R_rot.append(w.R[m])
            p_rot.append(w.p[m])
    if R_rot:
        return sums, points, np.concatenate(R_rot), np.concatenate(p_rot)
    return sums, points, np.zeros((0, 3, 3)), np.zeros((0, 3))


def _rms_with_offset(sums: PointSums, m: np.ndarray, a: np.ndarray, B: np.ndarray, c: np.ndarray) -> float:
    """RMS of ``m_i - (B (a_i + R_i c))`` (B (4, 4) rigid) without the rows' frames ``R_i``:
    with ``e_i = m_i - B a_i`` (exact, from the kept points), ``Σ |e_i - B_R R_i c|² = Σ |e_i|²
    - 2 Σ e_iᵀ B_R R_i c + N |c|²``, the middle sum from the registration's sums (it is linear in
    the rows: ``Σ m_iᵀ B_R R_i c - (Σ R_iᵀ a_i)·c - tᵀ B_R (Σ R_i) c``)."""
    BR, t = B[:3, :3], B[:3, 3]
    e = m - (a @ BR.T + t)
    cross = np.einsum("xy,z,zyx->", BR, c, sums.sRm) - sums.sRa @ c - t @ BR @ sums.sR @ c
    total = float(np.sum(e**2)) - 2.0 * float(cross) + sums.n * float(c @ c)
    return float(np.sqrt(max(total, 0.0) / sums.n))


class NotEnoughData(RecalError, ValueError):
    """Too few measurements to identify and check the fit: ``rows_needed`` would do."""

    def __init__(self, message: str, rows_needed: int):
        self.rows_needed = rows_needed
        super().__init__(message)


def _check_input(model: KinematicModel, data: Measurements, loss: str, register: str) -> None:
    if loss not in LOSSES:
        raise ValueError(f"`loss` must be one of {', '.join(LOSSES)}; got {loss!r}")
    if register not in ("auto", "always", "never"):
        raise ValueError(f"`register` must be auto, always or never; got {register!r}")
    if data.q.shape[1] != model.n_joints:
        raise ValueError(f"the data have {data.q.shape[1]} joint columns but the model has {model.n_joints} joints")
    if not (np.all(np.isfinite(data.q)) and np.all(np.isfinite(data.p_world))):
        raise ValueError("joint readings and positions must be finite")
    for t in set(data.target) - {None}:
        model.target(t)  # raises KeyError naming the unknown target


# A fit must have this many more equations than freed parameters (at least
# REDUNDANCY_MIN, and half the parameters): with fewer, the residuals cannot show whether the
# model explains the data (two rows fit six parameters exactly, residual zero).
REDUNDANCY_MIN = 10


def redundancy_margin(n_params: int) -> int:
    """The spare equations a fit of ``n_params`` parameters needs (docs/formats.md §4)."""
    return max(REDUNDANCY_MIN, math.ceil(n_params / 2))


def _check_redundancy(prob: _Problem, n_free: int, completeness: dict) -> None:
    n_eq = 3 * len(prob.data) + 3 * int(np.count_nonzero(prob.has_rot))
    if n_eq >= n_free + redundancy_margin(n_free):
        return
    per_row = 6 if np.all(prob.has_rot) and len(prob.data) else 3
    full = max(completeness["measurable"], n_free)
    need = math.ceil((full + redundancy_margin(full)) / per_row)
    raise NotEnoughData(
        f"{len(prob.data)} rows give {n_eq} equations for {n_free} parameters the data determine: no redundancy to "
        f"check the fit against (at least {redundancy_margin(n_free)} spare equations are needed); measure at least "
        f"{need} rows ({full} parameters of the complete model + {redundancy_margin(full)} spare equations, "
        f"{per_row} per row)",
        need,
    )


def _generic_configurations(model: KinematicModel, n: int = 40) -> np.ndarray:
    """``n`` reproducible configurations spread over the joint limits (revolute ones clipped to
    ±π): a generic place to compute ranks, away from special configurations."""
    lim = model.joint_limits.copy()
    for i, j in enumerate(model.joints):
        if j.revolute:
            lim[i] = np.clip(lim[i], -np.pi, np.pi)
    return np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], size=(n, model.n_joints))


def _rank(J: np.ndarray) -> int:
    """Numerical rank of ``J`` with columns scaled to unit norm (round-off columns dropped)."""
    norms = np.linalg.norm(J, axis=0)
    live = norms > 1e-12 * max(norms.max(initial=0.0), 1e-300)
    if not np.any(live):
        return 0
    s = np.linalg.svd(J[:, live] / norms[live], compute_uv=False)
    return int(np.sum(s > 1e-8 * s[0]))


def _jacobian_rank(model: KinematicModel, targets: tuple, *, orientation: bool) -> int:
    """Rank of the Jacobian of every candidate parameter (base, links, tool, the ``targets``;
    ``None``: the tool origin) at generic configurations: position rows of each target, and the
    tool orientation's rows with ``orientation``."""
    model = dataclasses.replace(model, compliance=None)  # the geometric count (compliance terms apart)
    q = _generic_configurations(model)
    names = tuple(t for t in targets if t is not None)
    params = candidate_parameters(model, targets=names)
    blocks = []
    for i, t in enumerate(targets):
        pred = predict(model, q, model.target(t), params, np.array([t] * len(q), dtype=object))
        assert pred.Jp is not None  # asked for (params)
        blocks.append(pred.Jp.reshape(-1, len(params)))
        if orientation and i == 0:  # the tool's orientation: the same rows for every target
            assert pred.Jr is not None
            blocks.append(pred.Jr.reshape(-1, len(params)))
    return _rank(np.vstack(blocks))


def complete_form(
    model: KinematicModel, *, hayati: bool = True, parallel_tol_rad: float = np.deg2rad(5.0)
) -> tuple[KinematicModel, list[str]]:
    """The model rewritten, exactly, in a complete and proportional parameterisation (book §2.7):
    ``mdh`` becomes ``dh``; in ``dh``, the links whose next axis is (nearly) parallel take Hayati's
    form (§2.8.1.1, :func:`~calibration.conventions.hayati_for_parallel_axes`, prismatic links
    too). Where that is still not complete, or not proportional, the whole model is written in
    ``poe`` (the zero-reference model of §2.8.2, which every serial chain of revolute and
    prismatic joints has): collinear consecutive revolute axes (a Hayati link with a = 0 cannot
    describe a sideways shift of the next axis), a nearly parallel link with a d that cannot move.
    Complete means what the book's independence check says (L876): the rank of the full-pose
    Jacobian at generic configurations equals that of the ``poe`` form, which describes every
    deviation of the axes (4 per revolute joint, 2 per prismatic one) and of the tool (6).
    ``hayati`` False: only ``mdh`` -> ``dh``. Returns the model and notes saying what changed.

    A compliant model (issue 17) is rewritten as its rigid chain; its compliance section is then
    re-expressed in the new link and base frames (:func:`calibration.compliance.reexpress`), so
    the rewritten model sags exactly as the given one."""
    if model.compliance is not None:
        rigid = dataclasses.replace(model, compliance=None)
        form, form_notes = complete_form(rigid, hayati=hayati, parallel_tol_rad=parallel_tol_rad)
        if form is rigid:
            return model, form_notes
        from .compliance import reexpress  # here: compliance imports identify

        return reexpress(form, model), form_notes
    notes: list[str] = []
    start = model
    if start.convention == "mdh" and not any(j.hayati for j in start.joints):
        start = mdh_to_dh(start)
        notes.append("mdh model converted to dh (exact) for identification")
    if not hayati or start.convention != "dh":
        return start, notes
    start, hn = hayati_for_parallel_axes(start, parallel_tol_rad=parallel_tol_rad)
    notes += hn
    stiff = [j.name for j in start.joints[:-1] if not j.hayati and abs(np.sin(j.alpha)) < np.sin(parallel_tol_rad)]
    poe = to_poe(start)  # the complete form: what dh must match
    r_dh, r_poe = (_jacobian_rank(m, (None,), orientation=True) for m in (start, poe))
    if r_dh < r_poe:
        notes.append(
            f"the dh form cannot describe every deviation of this arm (rank {r_dh} of the complete "
            f"{r_poe}: e.g. collinear consecutive axes): identified in poe form (the zero-reference "
            f"model, book §2.8.2), written in poe"
        )
        return poe, notes
    if stiff:
        notes.append(
            f"{', '.join(stiff)}: nearly parallel next axis in plain dh form (not proportional, book "
            f"§2.6): identified in poe form, written in poe"
        )
        return poe, notes
    return start, notes


def completeness(model: KinematicModel, targets: tuple, *, orientation: bool) -> dict:
    """The book's complete count N = 4R + 2P + 6 (eq. 2.63) of ``model``, and how many of those
    parameters the measurement can see (``measurable``: the rank of the complete ``poe``
    model's Jacobian for the measured ``targets``, with orientation rows or not, at generic
    configurations; position-only data of one point, for one, cannot see the tool's orientation;
    several targets add their own offsets)."""
    R = sum(j.revolute for j in model.joints)
    P = model.n_joints - R
    return {
        "rule": "4R + 2P + 6",
        "revolute": R,
        "prismatic": P,
        "count": 4 * R + 2 * P + 6,
        "measurable": _jacobian_rank(to_poe(model), targets or (None,), orientation=orientation),
        "convention": model.convention,
    }


# A target (or the tool origin) closer than this to the last joint's axis in the nominal model is
# "on the axis": what the axis does there is not seen in the nominal, only in the real robot.
ON_AXIS_M = 1e-3


def _targets_on_last_axis(model: KinematicModel, targets: tuple) -> list[tuple[str | None, float]]:
    """(target, distance m) of the measured ``targets`` that the model puts on its last joint's
    axis (a revolute one)."""
    last = model.joints[-1]
    if not last.revolute:
        return []
    key = f"{last.name}.theta"
    w = walk(model, np.zeros((1, model.n_joints)), {key})
    u, o = (a[0] for a in w.axes[key])
    out = []
    for t in targets:
        p = world_points(w, model.target(t))[0]
        dist = float(np.linalg.norm(np.cross(p - o, u)))
        if dist < ON_AXIS_M:
            out.append((t, dist))
    return out
