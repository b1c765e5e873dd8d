"""Identification: the kinematic parameters that best explain measured positions (and poses).

One call, one frozen result (after scipy's ``least_squares``): :func:`identify` returns an
:class:`IdentificationResult` that says everything that happened — the identified model, the
parameters freed with their standard errors and correlations, the ones the data cannot
determine and why, conditioning and observability indices, residual statistics, rows
down-weighted as outliers, and how the solver ended.

Method (book §4.4.2, §4.3.3, §4.5.3), in named steps (:func:`identify` calls them in order):

1. Validation (:func:`_check_input`).
2. Convention rewrite (:func:`complete_form`): a complete, proportional parameterisation (book
   §2.7): ``mdh`` -> ``dh`` (exact); parallel consecutive axes in Hayati links (§2.6,
   §2.8.1.1), prismatic joints too; ``poe`` (§2.8.2) where ``dh`` cannot be complete (collinear
   axes: the rank at generic configurations falls short of the ``poe`` form's) or
   proportional. :func:`completeness` counts N = 4R + 2P + 6 (eq. 2.63) and what the
   measurement can see.
3. The candidates (:func:`_candidates`: THE place where the parameter list is assembled; their
   Jacobian columns in :func:`_linearise`), a rigid registration of the nominal predictions onto
   the measurements when the base is unknown or far off (full-pose data: base and tool, the
   robot-world/hand-eye problem), and the identifiable set (:func:`_choose`): a Gram–Schmidt
   selection on the column-scaled, weighted normal equations, in a fixed order of preference
   (:func:`preference_order`); a column that adds (numerically) nothing to those before it is
   not freed, keeps the model's value, and the report names what it duplicates
   (:func:`select_identifiable`); with a :class:`Prior`, its share (§4.3.2). Too few equations
   to check the fit: :class:`NotEnoughData`.
4. Levenberg–Marquardt (:func:`_levenberg_marquardt`) with Marquardt's scaling, the analytic
   Jacobian (:mod:`calibration.jacobian`), an optional robust loss by iteratively reweighted
   rows (a bumped reflector does not ruin the fit; the rows it down-weights are named). Then the
   selection again at the answer (:func:`_reselect`: parameters redundant only at the nominal
   geometry, a target on an axis, are freed where the data determine them), until the freed
   set is stable.
5. Statistics (:func:`_statistics`): covariance ``s²(JᵀWJ)⁻¹`` (book eq. 4.54/4.70 with W =
   Σ⁻¹), ``s² = χ²/dof`` when the residuals are significantly larger than the stated uncertainty
   (:func:`excess_scale`), else 1: the covariance grows when the data show the instrument, the
   fixturing or the model worse than stated, never for a chance excess of χ², and it never
   shrinks below what the instrument states. With a
   :class:`Prior`: ``s²(JᵀWJ + MᵀΣp⁻¹M)⁻¹`` (``M`` the combinations the prior describes,
   :meth:`Prior.combinations`), the prior's term counted in χ². A linearised k-fold
   cross-validation (:func:`_cross_validation`) says whether the covariance predicts the
   hold-out error (``model_error_scale``), and a χ² test (:func:`_consistency`) whether the
   model explains the data at all.
6. Merging (:func:`_merge_prior`): the parameters only the prior determines join the result.

Rows are processed in chunks (:data:`CHUNK_ROWS`): the normal equations are accumulated per
cross-validation fold, and no array of the size of the whole Jacobian is ever made.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .conventions import hayati_for_parallel_axes, mdh_to_dh, to_poe
from .errors import RecalError
from .identification import (  # re-exported
    INSTRUMENT_SIGMA_M,
    IdentificationResult,
    Measurements,
    Prior,
    Unidentifiable,
)
from .jacobian import Prediction, jacobian_from_walk, predict, record_keys, world_points
from .kinematics import program, walk
from .model import KinematicModel
from .parameters import Parameter, apply_step, candidate_parameters, parameter_values
from .registration import register_points, register_poses
from .report import describe, explain, relation_coefficients, relation_text, unit_name  # noqa: F401 (re-exported)
from .transforms import homogeneous, invert, matrix_to_pose, matrix_to_rotvec, pose_to_matrix, quat_to_matrix

LOSSES = ("linear", "huber", "soft_l1", "cauchy")

TERMINATION_MESSAGES = {
    -1: "the data cannot determine any parameter",
    0: "the maximum number of iterations was reached before convergence",
    1: "converged: the relative reduction of the cost fell below ftol",
    2: "converged: the parameter step fell below xtol",
    3: "converged: the gradient fell below gtol",
}


def held_relations(result: IdentificationResult) -> dict:
    """What a :class:`Prior` made from ``result`` needs to know of the parameters it held at the
    model's value: ``{name: ((estimated name, coefficient SI), ...)}`` for those related to the
    estimated ones."""
    return {u.name: tuple(u.relation) for u in result.unidentifiable if u.relation}


def drift_scale(
    model: KinematicModel,
    data: Measurements,
    names: tuple[str, ...],
    covariance: np.ndarray,
    drift: np.ndarray,
    *,
    sigma_m: float = INSTRUMENT_SIGMA_M,
    sigma_rad: float | None = None,
    scales: np.ndarray | None = None,
    held: dict | None = None,
) -> float:
    """How much drift the new ``data`` show since the calibration that gave ``model`` and the
    ``covariance`` (P, P) SI of its parameters ``names``: the scale ``s`` of a drift allowance
    ``drift`` (P,) (1σ per parameter, SI) that makes the data most likely (type-II maximum
    likelihood, the evidence of the linearised model): the data's residuals at ``model``
    (weighted as :func:`identify` weighs them, ``sigma_m`` and ``sigma_rad`` as there) are
    ``r = J δ + ε`` with ``δ ~ N(0, Σ + s² diag(drift²))`` and ``ε`` the instrument's noise. 0
    when the data fit the previous model within its own uncertainty; about 1 when the parameters
    moved by the allowance. ``scales``: the values tried (default 0 and 41 from 0.01 to 100).

    The parameters without a prior that the data determine (:func:`identify` frees them: a tool
    frame the previous data could not see) explain what they can first, with no prior (the
    restricted likelihood, of the residuals' part they cannot explain), so that they are not
    taken for drift; ``held``: :attr:`Prior.held`, the prior's held parameters, which enter
    with the prior's combinations kept."""
    gains = any(n.endswith(".gain") for n in names)
    cands = candidate_parameters(model, targets=tuple(model.targets), gains=gains)
    index = {p.name: k for k, p in enumerate(cands)}
    keep = [i for i, n in enumerate(names) if n in index]
    if not keep:
        return 0.0
    cols = [index[names[i]] for i in keep]
    cov = np.asarray(covariance, dtype=float)[np.ix_(keep, keep)]
    d2 = np.asarray(drift, dtype=float)[keep] ** 2
    prob = _problem(data, sigma_m, sigma_rad)
    pred, rp, rr = _evaluate(model, prob, cands)
    r, J_all = _stack(prob, rp, rr, pred.Jp, pred.Jr)
    J = J_all[:, cols]
    with_prior = {names[i] for i in keep}
    kept, _ = select_identifiable(J_all, cands, position_only=not np.any(prob.has_rot))
    free = [k for k in kept if cands[k].name not in with_prior]
    if free:
        # with the prior on z = s_p + H s_u (H: the held ones' relations), a step (s_p, s_u)
        # moves the points by J_p z + (J_u - J_p H) s_u: project the columns of the latter out
        M = Prior(tuple(names[i] for i in keep), cov, held or {}).combinations([cands[k] for k in cols + free])
        U, sv, _ = np.linalg.svd(J_all[:, free] - J @ M[:, len(cols) :], full_matrices=False)
        basis = U[:, sv > 1e-9 * max(sv[0], 1e-300)]
        r = r - basis @ (basis.T @ r)
        J = J - basis @ (basis.T @ J)
    G, b = J.T @ J, J.T @ r
    best = (math.inf, 0.0)
    for s in np.concatenate([[0.0], np.geomspace(0.01, 100.0, 41)]) if scales is None else scales:
        # -log evidence, up to a constant, in the parameters' space (determinant lemma, Woodbury):
        # C = I + J Q Jᵀ, Q = L Lᵀ: log det C = log det K, rᵀC⁻¹r = rᵀr - cᵀK⁻¹c, K = I + LᵀGL, c = Lᵀb
        L = _sqrt_psd(cov + s * s * np.diag(d2)).T
        K = np.eye(len(keep)) + L.T @ G @ L
        c = L.T @ b
        nll = 0.5 * (np.linalg.slogdet(K)[1] + r @ r - c @ np.linalg.solve(K, c))
        if nll < best[0]:
            best = (nll, float(s))
    return best[1]


CHUNK_ROWS = 8192

# k of the k-fold cross-validation (:func:`_cross_validation`); data with fewer than 2k poses are
# not cross-validated.
CV_FOLDS = 5


@dataclass(frozen=True, slots=True)
class _Chunk:
    a: int  # rows [a, b) of the (fold-ordered) data
    b: int
    fold: int
    targets: dict  # target name -> (b - a,) bool, the rows of the chunk that measure it
    rot: bool  # some row of the chunk carries an orientation


@dataclass(frozen=True, eq=False)
class _Problem:
    """The data with their weights, in fold order: ``data`` is the caller's data with its rows
    reordered by ``order`` (so that each cross-validation fold is a contiguous block of rows,
    processed in ``chunks``)."""

    data: Measurements
    p_tool_names: np.ndarray  # (N,) object
    has_rot: np.ndarray  # (N,) bool
    R_meas: np.ndarray | None  # (N, 3, 3)
    sigma_pos: np.ndarray  # (N,) m
    sigma_rot: float  # rad
    target_rows: dict = field(default_factory=dict)  # target name -> (N,) bool, the rows that measure it
    trig: dict = field(default_factory=dict)  # the joints' cos and sin over the data, for every walk (kinematics.walk)
    order: np.ndarray | None = None  # (N,) the caller's row of each row here
    chunks: tuple = ()
    n_folds: int = 1

    def original(self, a: np.ndarray) -> np.ndarray:
        """Per-row values (N, ...) in this problem's order -> in the caller's order."""
        if self.order is None:
            return a
        out = np.empty_like(a)
        out[self.order] = a
        return out


def _problem(data: Measurements, sigma_m: float, sigma_rad: float | None, *, folds: int = CV_FOLDS) -> _Problem:
    """The data with their weights: ``sigma_m`` for rows without their own ``sigma``, ``sigma_rad``
    for orientations (default ``sigma_m`` over 0.1 m); rows grouped into ``folds`` folds by pose
    (every ``folds``-th pose in one fold), each fold cut into chunks of :data:`CHUNK_ROWS`."""
    N = len(data)
    key = data.pose_id if data.pose_id is not None else np.arange(N)
    pose = np.unique(np.asarray(key), return_inverse=True)[1].reshape(N) if N else np.zeros(0, int)
    k = folds if N and pose.max() + 1 >= 2 * folds else 1
    fold = pose % k
    order = None
    if k > 1:
        order = np.argsort(fold, kind="stable")
        data = data.subset(order)
        fold = fold[order]
    has_rot = data.has_orientation
    R_meas = (
        quat_to_matrix(np.where(np.isfinite(data.quat), data.quat, [1, 0, 0, 0])) if data.quat is not None else None
    )
    sigma_pos = np.where(np.isfinite(data.sigma) & (data.sigma > 0), data.sigma, sigma_m)
    sigma_rot = float(sigma_rad) if sigma_rad is not None else sigma_m / 0.1
    bounds = np.searchsorted(fold, np.arange(k + 1))
    chunks = []
    for f in range(k):
        for a in range(int(bounds[f]), int(bounds[f + 1]), CHUNK_ROWS):
            b = min(a + CHUNK_ROWS, int(bounds[f + 1]))
            chunks.append(_Chunk(a, b, f, _target_rows(data.target[a:b]), bool(np.any(has_rot[a:b]))))
    return _Problem(
        data,
        data.target,
        has_rot,
        R_meas,
        sigma_pos,
        sigma_rot,
        _target_rows(data.target),
        order=order,
        chunks=tuple(chunks),
        n_folds=k,
    )


def _target_rows(names: np.ndarray) -> dict:
    return {name: names == name for name in sorted(set(names) - {None})}


def _p_tool(model: KinematicModel, names: np.ndarray, rows: dict | None = None) -> np.ndarray:
    """Each row's target point in the tool frame (N, 3); ``rows``: :func:`_target_rows` of
    ``names``, when already known."""
    out = np.zeros((len(names), 3))
    for name, mask in (_target_rows(names) if rows is None else rows).items():
        out[mask] = model.targets[name]
    return out


def _residuals(model, prob: _Problem, record=frozenset()):
    """Walk ``model`` over the data (recording ``record``): the walk, the predicted points and the
    residuals, measured minus predicted (position (N, 3), orientation (N, 3))."""
    w = walk(model, prob.data.q, record, prob.trig, prob.data.payload)
    pt = world_points(w, _p_tool(model, prob.p_tool_names, prob.target_rows))
    rp = prob.data.p_world - pt
    rr = np.zeros_like(rp)
    if prob.R_meas is not None and np.any(prob.has_rot):
        m = prob.has_rot
        rr[m] = matrix_to_rotvec(prob.R_meas[m] @ np.swapaxes(w.R[m], 1, 2))
    return w, pt, rp, rr


def _evaluate(model, prob: _Problem, params=None) -> tuple[Prediction, np.ndarray, np.ndarray]:
    w, pt, rp, rr = _residuals(model, prob, record_keys(params))
    if not params:
        return Prediction(pt, w.R), rp, rr
    Jp, Jr = jacobian_from_walk(w, pt, params, prob.data.q, prob.p_tool_names, orientation=bool(np.any(prob.has_rot)))
    return Prediction(pt, w.R, Jp, Jr), rp, rr


def _stack(prob: _Problem, rp, rr, Jp=None, Jr=None):
    """Weighted residual vector (and Jacobian): position rows / sigma_pos, orientation rows /
    sigma_rot (book §4.3.3: scale rows to equal variance).

    Component-major order: the x residuals of all rows, then y, then z, then the orientation
    rows likewise. :func:`calibration.jacobian.predict` computes its columns in that order, so
    the Jacobian (M, P) is a Fortran-ordered array made without a transposing copy: ``Jp`` (from
    :func:`~calibration.jacobian.jacobian_from_walk`, used for nothing else) is weighted in place."""
    wp = 1.0 / prob.sigma_pos
    r = [(rp.T * wp).reshape(-1)]
    Jt = None
    if Jp is not None:
        JpT = Jp.transpose(2, 1, 0)  # (P, 3, N), contiguous
        JpT = np.multiply(JpT, wp, out=JpT) if JpT.flags.c_contiguous and JpT.flags.writeable else JpT * wp
        Jt = [JpT.reshape(Jp.shape[2], -1)]  # (P, 3N)
    if np.any(prob.has_rot):
        m = prob.has_rot
        r.append((rr[m].T / prob.sigma_rot).reshape(-1))
        if Jp is not None:
            Jt.append((Jr.transpose(2, 1, 0)[:, :, m] / prob.sigma_rot).reshape(Jr.shape[2], -1))
    if Jt is not None:
        Jt = Jt[0] if len(Jt) == 1 else np.concatenate(Jt, axis=1)
    return (r[0] if len(r) == 1 else np.concatenate(r)), (None if Jt is None else Jt.T)


def _robust_weights(z: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """IRLS weights rho'(s) for row norms ``z`` (in sigma units); s = (z / f_scale)²."""
    s = (z / f_scale) ** 2
    if loss == "linear":
        return np.ones_like(z)
    if loss == "huber":
        return np.where(s <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(s, 1e-300)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + s)
    if loss == "cauchy":
        return 1.0 / (1.0 + s)
    raise ValueError(f"`loss` must be one of {', '.join(LOSSES)}; got {loss!r}")


@dataclass(frozen=True, eq=False)
class _Linearisation:
    """The weighted least-squares problem at one model, accumulated over the rows chunk by chunk
    (the Jacobian itself is never kept whole). Per fold ``k`` of the cross-validation:
    ``G[k] = JₖᵀWJₖ``, ``g[k] = JₖᵀWrₖ``, ``c[k] = rₖᵀWrₖ`` and ``n[k]`` residuals (W: the rows'
    1/σ² times their robust weights). ``R`` (with ``factor``): a triangular factor of ``ΣG``
    from the rows themselves (better conditioned than a factor of G)."""

    rp: np.ndarray  # (N, 3) m, measured minus predicted
    rr: np.ndarray  # (N, 3) rad, zeros for rows without orientation
    z2: np.ndarray  # (N,) the row's squared residual norm in units of its sigma
    w_row: np.ndarray  # (N,) the robust weight each row carries in G, g, c
    G: np.ndarray  # (K, P, P)
    g: np.ndarray  # (K, P)
    c: np.ndarray  # (K,)
    n: np.ndarray  # (K,)
    R: np.ndarray | None = None

    @property
    def cost(self) -> float:
        return 0.5 * float(self.c.sum())

    def restricted(self, idx: list[int]) -> _Linearisation:
        """The same linearisation for the parameters ``idx`` only (no pass over the data)."""
        return dataclasses.replace(self, G=self.G[:, idx][:, :, idx], g=self.g[:, idx], R=None)

    @property
    def gram(self) -> np.ndarray:
        return self.G.sum(axis=0)

    @property
    def gradient(self) -> np.ndarray:
        return self.g.sum(axis=0)


def _linearise(
    model: KinematicModel,
    prob: _Problem,
    params: list[Parameter],
    *,
    loss: str = "linear",
    f_scale: float = 3.0,
    factor: bool = False,
) -> _Linearisation:
    """Residuals and the normal equations of ``params`` at ``model``, weighted (book §4.3.3: rows
    scaled to equal variance; robust ``loss`` by iteratively reweighted rows), chunk by chunk.

    THE place where the identification's Jacobian columns are assembled: the kinematic
    parameters' columns come from the walk (:func:`calibration.jacobian.jacobian_from_walk`),
    the compliance terms' too (a joint offset's column times the walk's regressor, which a
    compliant model's walk keeps for each chunk's ``payload``); another block of parameters adds
    its columns to ``Jt`` here, and its candidates in :func:`_candidates`.
    """
    N, P, K = len(prob.data), len(params), prob.n_folds
    rp, rr = np.empty((N, 3)), np.zeros((N, 3))
    z2, w_row = np.empty(N), np.ones(N)
    G, g, c, n = np.zeros((K, P, P)), np.zeros((K, P)), np.zeros(K), np.zeros(K, dtype=int)
    R = None
    keys = record_keys(params)
    data = prob.data
    ops = program(model)  # compiled once for every chunk
    for ch in prob.chunks:
        a, b, f = ch.a, ch.b, ch.fold
        q = data.q[a:b]
        payload = None if data.payload is None else data.payload[a:b]  # a compliant model's (issue 17)
        w = walk(model, q, keys, payload=payload, ops=ops)
        pt = world_points(w, _p_tool(model, prob.p_tool_names[a:b], ch.targets))
        rpc = data.p_world[a:b] - pt
        rp[a:b] = rpc
        wp = 1.0 / prob.sigma_pos[a:b]
        zp = rpc * wp[:, None]
        zz = np.einsum("ni,ni->n", zp, zp)
        m = None
        if ch.rot:
            m = prob.has_rot[a:b]
            rrc = matrix_to_rotvec(prob.R_meas[a:b][m] @ np.swapaxes(w.R[m], 1, 2))
            rr[a:b][m] = rrc
            zr = rrc / prob.sigma_rot
            zz[m] += np.einsum("ni,ni->n", zr, zr)
        z2[a:b] = zz
        wr = _robust_weights(np.sqrt(zz), loss, f_scale)
        w_row[a:b] = wr
        c[f] += float(wr @ zz)
        n[f] += 3 * (b - a) + (3 * int(np.count_nonzero(m)) if m is not None else 0)
        if not P:
            continue
        Jp, Jr = jacobian_from_walk(w, pt, params, q, prob.p_tool_names[a:b], orientation=ch.rot)
        sw = np.sqrt(wr)
        JpT = Jp.transpose(2, 1, 0)  # (P, 3, n), contiguous: weighted in place
        JpT *= wp * sw
        cols, res = [JpT.reshape(P, -1)], [(zp.T * sw).reshape(-1)]
        if m is not None:
            cols.append((Jr.transpose(2, 1, 0)[:, :, m] * (sw[m] / prob.sigma_rot)).reshape(P, -1))
            res.append((zr.T * sw[m]).reshape(-1))
        Jt = cols[0] if len(cols) == 1 else np.concatenate(cols, axis=1)  # (P, rows of the chunk)
        rv = res[0] if len(res) == 1 else np.concatenate(res)
        G[f] += Jt @ Jt.T
        g[f] += Jt @ rv
        if factor:
            R = np.linalg.qr(Jt.T if R is None else np.vstack([R, Jt.T]), mode="r")
    return _Linearisation(rp, rr, z2, w_row, G, g, c, n, R)


# --------------------------------------------------------------------------- parameter selection

# How a parameter the data cannot determine relates to the freed ones (``Unidentifiable.category``).
CATEGORIES = (
    "no_effect",
    "same_motion",
    "combination",
    "target_offsets",
    "tool_orientation",
    "last_joint_offset",
    "weak",
)


def _is_joint_parameter(name: str) -> bool:
    head = name.rpartition(".")[0]
    return head not in ("base", "tool", "home") and not head.startswith(("target.", "compliance."))


def _last_joint_offset(params: list[Parameter]) -> int | None:
    """Index of the last joint's offset (its first parameter in the candidate order: ``theta`` of a
    revolute joint, ``d`` of a prismatic one), or None."""
    heads = [p.name.rpartition(".")[0] for p in params if _is_joint_parameter(p.name)]
    if not heads:
        return None
    return next(k for k, p in enumerate(params) if p.name.rpartition(".")[0] == heads[-1])


def _offset_duplicates(name: str) -> bool:
    """Parameters that only move the measured points rigidly with the tool: target offsets and
    tool translations."""
    return name.startswith(("target.", "tool.t"))


def preference_order(params: list[Parameter], *, position_only: bool) -> list[int]:
    """The order in which :func:`select_identifiable` tries to keep ``params`` (indices).

    The candidates' own order (:func:`calibration.parameters.candidate_parameters`), except that
    with position-only data the last joint's offset is tried after the target offsets and the
    tool translations: turning a measured point about the last axis moves it exactly as a change
    of its offset in the tool frame does, so the data can determine one of the two. The offsets
    are what was really measured (where the reflector sits); the joint offset, kept first, would
    absorb them (a reflector 40 mm off the axis and 1 mm off its nominal place is a 1.4° joint
    offset) and the model would turn the tool orientation by that much.
    """
    order = list(range(len(params)))
    last = _last_joint_offset(params) if position_only else None
    if last is None:
        return order
    anchor = max((k for k, p in enumerate(params) if _offset_duplicates(p.name)), default=-1)
    if anchor < last:
        return order
    order.remove(last)
    order.insert(order.index(anchor) + 1, last)
    return order


def _category(
    p: Parameter, relation: list[tuple[str, float]], pair: bool, position_only: bool, last_offset: bool
) -> str:
    n = p.name
    if n.startswith("tool.r") and position_only:
        return "tool_orientation"
    if not relation:
        return "no_effect"
    if n.startswith(("tool.t", "home.t")) and all(r.startswith("target.") for r, _ in relation):
        return "target_offsets"
    if last_offset and all(_offset_duplicates(r) for r, _ in relation):
        return "last_joint_offset"
    return "same_motion" if pair else "combination"


def _r_factor(J: np.ndarray, *, block_rows: int = 2048) -> np.ndarray:
    """The triangular factor R (P, P) of a tall ``J`` (M, P) = QR, by blocks of rows (TSQR: the
    blocks' factors, stacked, are factored again), so that each QR works in cache: about twice
    as fast as one QR of a tall-skinny matrix. ``RᵀR = JᵀJ``; R's rows may differ in sign from
    LAPACK's, which changes no inner product, singular value or Gram matrix computed from it."""
    M = J.shape[0]
    if M <= 2 * block_rows:
        return np.linalg.qr(J, mode="r")
    blocks = [np.linalg.qr(J[a : a + block_rows], mode="r") for a in range(0, M, block_rows)]
    return np.linalg.qr(np.vstack(blocks), mode="r")


# A dropped column is "the same motion" as the kept column it is closest to when the part of it
# that column does not explain is below this (sine of the angle between the two unit columns).
SAME_MOTION_SINE = 1e-3


def select_identifiable(
    J: np.ndarray, params: list[Parameter], *, rtol: float = 1e-6, position_only: bool, multi_target: bool = False
) -> tuple[list[int], list[Unidentifiable]]:
    """Choose the columns of the weighted Jacobian ``J`` (M, P) the data determine.

    Columns are scaled to unit norm (the dimensionless parameterisation: a metre and a radian
    are not compared) and orthogonalised in the order of preference (:func:`preference_order`),
    Gram–Schmidt with re-orthogonalisation: column k is kept if its component orthogonal to the
    KEPT columns before it is at least ``rtol`` of its norm (a QR with column pivoting restricted
    to a fixed order; dropped columns never enter the basis). A dropped column's relation to the
    kept ones is solved from the triangular factor of the kept columns; it is "the same motion"
    as one kept parameter only when that one column alone explains it (:data:`SAME_MOTION_SINE`),
    otherwise the whole combination is named. Returns the kept indices (ascending) and, for the
    others, the reasons. ``multi_target`` is accepted for compatibility and not used.
    """
    kept, dropped, _ = _select(J, params, rtol=rtol, position_only=position_only)
    return kept, dropped


def _select(J: np.ndarray, params: list[Parameter], *, rtol: float, position_only: bool):
    """:func:`select_identifiable`, also returning the factor it worked on (a matrix whose Gram
    matrix is ``JᵀJ``: the triangular factor of a tall ``J``, else ``J``)."""
    M, P = J.shape
    if M > P:
        # Everything below works in the column space through inner products, so the triangular
        # factor R of J = QR (same Gram matrix JᵀJ = RᵀR) gives the same result at O(P³) cost.
        J = _r_factor(J)
        M = P
    factor = J
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    Jn = J / scale
    zero = norms <= 1e-12 * max(norms.max(initial=0.0), 1e-300)
    basis = np.zeros((M, min(M, P)))
    kept: list[int] = []  # in the order tested
    pending: list[tuple[int, np.ndarray]] = []
    for k in preference_order(params, position_only=position_only):
        if zero[k]:
            pending.append((k, np.zeros(0)))
            continue
        c = Jn[:, k]
        Qk = basis[:, : len(kept)]
        proj = Qk.T @ c
        v = c - Qk @ proj
        corr = Qk.T @ v  # re-orthogonalise once: "twice is enough"
        v -= Qk @ corr
        proj += corr
        nv = float(np.linalg.norm(v))
        if nv > rtol and len(kept) < basis.shape[1]:
            basis[:, len(kept)] = v / nv
            kept.append(k)
        else:
            pending.append((k, proj))
    Rk = basis[:, : len(kept)].T @ Jn[:, kept] if kept else np.zeros((0, 0))
    last = _last_joint_offset(params) if position_only else None
    dropped: list[Unidentifiable] = []
    for k, proj in pending:
        relation: list[tuple[str, float]] = []
        kinds = [params[k].kind]
        pair = False
        if proj.size:
            n_at = proj.size  # kept columns that were in the basis when k was tested
            coef = np.linalg.solve(Rk[:n_at, :n_at], proj) if n_at else np.zeros(0)
            # unit column k = Σ coef_j unit column j (dimensionless) -> d(param_k) ≡ Σ c_j d(param_j), SI
            c_si = coef * norms[k] / scale[kept[:n_at]]
            # largest first; equal ones (to rounding) in the order of preference
            order = [i for i in np.argsort(-np.round(np.abs(coef), 9), kind="stable") if abs(coef[i]) > 1e-3]
            relation = [(params[kept[i]].name, float(c_si[i])) for i in order]
            kinds += [params[kept[i]].kind for i in order]
            if order:
                cos = float(Jn[:, k] @ Jn[:, kept[order[0]]])
                pair = math.sqrt(max(0.0, 1.0 - cos * cos)) < SAME_MOTION_SINE
        u = Unidentifiable(
            params[k].name,
            "",
            tuple(relation),
            _category(params[k], relation, pair, position_only, k == last),
            tuple(kinds),
        )
        dropped.append(dataclasses.replace(u, reason=explain(u)))
    dropped.sort(key=lambda u: [p.name for p in params].index(u.name))
    return sorted(kept), dropped, factor


# --------------------------------------------------------------------------- registration


def _register(model: KinematicModel, prob: _Problem) -> tuple[KinematicModel, dict]:
    """Try a rigid registration of the model's predictions onto the data; keep it if it fits
    better than the model's own base."""
    data = prob.data
    local = dataclasses.replace(model, base=np.zeros(6))
    w = walk(local, data.q, payload=data.payload)

    def rms(base: np.ndarray, p_local: np.ndarray) -> float:
        e = data.p_world - (p_local @ base[:3, :3].T + base[:3, 3])
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))

    p_local = world_points(w, _p_tool(model, prob.p_tool_names, prob.target_rows))
    before = rms(pose_to_matrix(model.base), p_local)
    info = {"rms_before_m": before}
    n_rot = int(np.sum(prob.has_rot))
    if n_rot >= 3:
        m = prob.has_rot
        T_pred = homogeneous(w.R[m], w.p[m])  # includes the current tool
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
        p_local = world_points(w, G[:3, 3] + _p_tool(model, prob.p_tool_names, prob.target_rows) @ G[:3, :3].T)
    else:
        X, c = register_points(w.R, w.p, data.p_world, _p_tool(model, prob.p_tool_names, prob.target_rows))
        candidate = dataclasses.replace(model, base=matrix_to_pose(X))
        info["method"] = "rigid point registration (Kabsch)"
        info["point_offset_correction_m"] = c.tolist()
    after = rms(pose_to_matrix(candidate.base), p_local)
    info["applied"] = bool(after < before)
    # the figure reported is the registration as found, the common target offset included: the
    # start keeps its own targets (the fit frees what the data determine of them), but an offset
    # the registration estimated and then dropped inflated "after" (issue 25: a UR10 measured with
    # a T-Mac read 15 mm where the same registration with its offset gave 1 mm; a reflector 50 mm
    # from the nominal's target read 50.7 mm here, tests/calibration/test_before_figure.py)
    if "point_offset_correction_m" in info:
        p_reg = world_points(w, _p_tool(model, prob.p_tool_names, prob.target_rows) + c)
        info["rms_after_m"] = rms(pose_to_matrix(candidate.base), p_reg)
    else:
        info["rms_after_m"] = after
    return (candidate if after < before else model), info


# --------------------------------------------------------------------------- step 1: validation


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


# --------------------------------------------------------------------------- step 2: convention rewrite


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
        blocks.append(pred.Jp.reshape(-1, len(params)))
        if orientation and i == 0:  # the tool's orientation: the same rows for every target
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
        form, notes = complete_form(rigid, hayati=hayati, parallel_tol_rad=parallel_tol_rad)
        if form is rigid:
            return model, notes
        from .compliance import reexpress  # here: compliance imports identify

        return reexpress(form, model), notes
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


# --------------------------------------------------------------------------- step 3: the parameters


def _candidates(
    start: KinematicModel, data: Measurements, prior: Prior | None, gains: bool, fixed: tuple[str, ...]
) -> list[Parameter]:
    """Every parameter the identification may free, in the selection's order of preference: THE
    place where the parameter list is assembled (a block of other parameters joins here, and
    its Jacobian columns in :func:`_linearise`); a compliant model's terms come last
    (:func:`calibration.parameters.candidate_parameters`), so the selection keeps geometry
    first. The candidates depend on the model's structure, not on its base: the same after
    registration."""
    used_targets = tuple(sorted(set(data.target) - {None}))
    prior_targets = (
        ()
        if prior is None
        else tuple(
            sorted(
                {n.split(".")[1] for n in prior.names if n.startswith("target.")}
                & set(start.targets) - set(used_targets)
            )
        )
    )
    with_gains = gains or (prior is not None and any(n.endswith(".gain") for n in prior.names))
    cands = candidate_parameters(start, targets=used_targets + prior_targets, gains=with_gains)
    return [p for p in cands if not _matches(p.name, fixed)]


def _gram_root(G: np.ndarray) -> np.ndarray:
    """A factor F (P, P) with FᵀF = G, from the eigen-decomposition of the column-scaled G. The
    selection works on inner products only, so F serves as well as the Jacobian's own triangular
    factor: column scaling keeps G's rounding near 1e-16 of unit columns, so an independent
    component down to 1e-7 (below the selection's ``rank_rtol``, 1e-6) is still resolved."""
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    s = np.where(d > 0, d, 1.0)
    return _sqrt_psd(G / np.outer(s, s)) * s


@dataclass(frozen=True, eq=False)
class _Selection:
    kept: list  # indices into the candidates: what is estimated
    dropped: list  # Unidentifiable
    from_prior: list  # indices: not estimated, the prior's value and covariance
    by_data: set  # indices the data alone determine
    sd_prior: np.ndarray  # (C,) the prior's standard errors (NaN without one)


def _choose(
    cands: list[Parameter],
    G: np.ndarray,
    prior: Prior | None,
    *,
    rank_rtol: float,
    position_only: bool,
    factor: np.ndarray | None = None,
) -> _Selection:
    """The identifiable set from the candidates' Gram matrix ``G`` (weighted JᵀJ), or from
    ``factor`` (R with RᵀR = G, from the rows themselves) when given: the data's selection
    (:func:`select_identifiable`), then the prior's bookkeeping: parameters with a prior that the
    data see are estimated, those the data cannot see keep the prior."""
    F = _gram_root(G) if factor is None else factor
    kept, dropped, _ = _select(F, cands, rtol=rank_rtol, position_only=position_only)
    by_data = set(kept)
    from_prior: list[int] = []
    sd_prior = np.full(len(cands), np.nan)
    if prior is not None:  # a prior determines what the data alone cannot
        sd_prior = np.sqrt(np.maximum(np.diag(prior.covariance_of(cands)), 0.0))
        has_prior = [k for k in range(len(cands)) if np.isfinite(sd_prior[k])]
        seen = _seen_by_data(F, sd_prior)
        # a held parameter the data determine moves those it was confused with: estimated too
        released = {n for k in kept for n, _ in prior.held.get(cands[k].name, ())}
        from_prior = [k for k in has_prior if not seen[k] and cands[k].name not in released]
        kept = sorted((set(kept) | set(has_prior)) - set(from_prior))
        named = {cands[k].name for k in has_prior}
        dropped = [u for u in dropped if u.name not in named]
    return _Selection(kept, dropped, from_prior, by_data, sd_prior)


# A parameter that only the real geometry determines (redundant at the nominal: a target on an
# axis) is freed at the converged model when the rank says the data determine it, unless its
# standard error is worse than these: then the data hardly determine it, and the fit's
# linearisation does not hold over its uncertainty (an angle's second-order terms reach 0.1 % at
# 0.05 rad; a length the nominal relates to an angle, j5.a to j5.theta at 0.34 deg per mm on a KR
# 16, turns that by 3 deg over 10 mm): it keeps the model's value. The bound is not "what a real
# robot deviates from its drawing" (1 mm, 1 mrad): a parameter held at the model's value biases
# the fit by its real deviation, which the covariance does not show. With that bound, random 6R
# arms with a reflector on the last axis reached up to 75 times the complete fit's hold-out
# error (a tilt the re-parameterised model needed at 1 degree, held at 0), and the 95 % bounds
# covered 88 % of the true errors over 40 arms (54 % on one); with these, every arm reaches the
# complete fit and the bounds cover 95.6 % (tests/calibration/test_identify_uncertainty.py). A
# looser bound freed j5.a of a 165 kg arm's on-axis reflector at ±51 mm from 100 rows, and the
# fit took 94 iterations to settle it.
DETERMINED_RAD = 0.05
DETERMINED_M = 0.01

# The re-selection at the answer works on at most this many rows (evenly spread over the data).
RESELECT_ROWS = 20000


def _sample(prob: _Problem, n: int) -> tuple[_Problem, float]:
    """At most ``n`` rows of ``prob`` evenly spread, as one fold, and the share of the rows taken."""
    N = len(prob.data)
    if N <= n:
        return prob, 1.0
    idx = np.linspace(0, N - 1, n).round().astype(int)
    data = prob.data.subset(idx)
    has_rot = prob.has_rot[idx]
    chunks = tuple(
        _Chunk(
            a,
            min(a + CHUNK_ROWS, n),
            0,
            _target_rows(data.target[a : a + CHUNK_ROWS]),
            bool(np.any(has_rot[a : a + CHUNK_ROWS])),
        )
        for a in range(0, n, CHUNK_ROWS)
    )
    sub = _Problem(
        data,
        data.target,
        has_rot,
        None if prob.R_meas is None else prob.R_meas[idx],
        prob.sigma_pos[idx],
        prob.sigma_rot,
        _target_rows(data.target),
        chunks=chunks,
        n_folds=1,
    )
    return sub, n / N


# Rounds of "select at the answer, solve again" before the freed set is taken as it stands.
MAX_SELECTION_ROUNDS = 4


def _reselect(
    current: KinematicModel,
    prob: _Problem,
    cands: list[Parameter],
    sel: _Selection,
    *,
    rank_rtol: float,
    position_only: bool,
) -> _Selection:
    """The selection again, at the converged model (book L876: the rank decides, and at the
    answer, not at the nominal): parameters redundant only at the nominal geometry are freed
    where the data determine them (:data:`DETERMINED_RAD`, :data:`DETERMINED_M`). Decided on an
    evenly spread sample of :data:`RESELECT_ROWS` rows at most (the information scaled to the whole
    data's): a rank and a standard error need no million rows."""
    sub, share = _sample(prob, RESELECT_ROWS)
    # the triangular factor of the rows themselves, not a root of their Gram matrix: at the
    # answer the candidates are often many and nearly dependent (a SCARA's 32 candidates span 17
    # directions), and the Gram root's rounding (1e-8 per direction, over 15 null directions)
    # let a prismatic joint's offset pass as independent of the base's z, which it was not
    # (freed twice, with standard errors of a micrometre for an undetermined difference)
    lin = _linearise(current, sub, cands, factor=True)
    G = lin.gram / share  # the whole data's information, estimated from the sample
    new = _choose(cands, G, None, rank_rtol=rank_rtol, position_only=position_only, factor=lin.R)
    s2 = max(1.0, lin.c.sum() / max(lin.n.sum() - len(new.kept), 1))
    # only geometric lengths and angles have a scale of what a real robot deviates from its
    # drawing; a gain and a compliance term (issue 17; a lump's moment is of kind ``angle`` too)
    # freed only at the answer stays held: such a term redundant at the nominal (a lump's moment
    # along its link's x, the same motion as its mass) is seen at the answer only through the
    # identified tilts, and freeing it adds variance, not accuracy
    added = [k for k in new.kept if k not in sel.kept]
    # a parameter held keeps the relation the nominal showed (what a prior made from this result needs)
    before = {u.name: u for u in sel.dropped}
    return _hold_weak(cands, G, new, s2, held_anyway=[k for k in added if _weak_bound(cands[k]) is None], before=before)


def _weak_bound(p: Parameter) -> float | None:
    """The standard error beyond which a geometric parameter counts as undetermined (``weak``):
    :data:`DETERMINED_M`, :data:`DETERMINED_RAD`; None for a gain or a compliance term."""
    if p.name.startswith("compliance."):
        return None
    return {"length": DETERMINED_M, "angle": DETERMINED_RAD}.get(p.kind)


def _hold_weak(
    cands: list[Parameter],
    G: np.ndarray,
    sel: _Selection,
    s2: float,
    *,
    held_anyway: list[int] = (),
    before: dict | None = None,
) -> _Selection:
    """``sel`` less the parameters the data cannot determine to :data:`DETERMINED_M` /
    :data:`DETERMINED_RAD` (standard errors from the information ``G`` times ``s2``), held at the
    model's value as ``weak``, wherever the model puts the tool (issue 25: a reflector 0.09 mm
    off the last axis is not on it, so the rank freed j5.a at ±94 mm and j5.theta at ±29 deg,
    and the solver wandered to its iteration limit; the rule held them only on the axis). The
    weakest is held first and the rest judged again: two parameters that are each undetermined
    only as a pair (j5.a with j5.theta) leave one determined once the other is held.
    ``held_anyway``: parameters held whatever their standard error; ``before``: the
    :class:`Unidentifiable` entries of an earlier selection, whose relations a held parameter keeps."""
    kept = [k for k in sel.kept if k not in held_anyway]
    loose = list(held_anyway)
    while kept:
        Gk = G[np.ix_(kept, kept)]
        d = np.sqrt(np.maximum(np.diag(Gk), 1e-300))
        cov = np.linalg.pinv(Gk / np.outer(d, d), rcond=1e-14, hermitian=True) / np.outer(d, d)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0) * s2)
        ratio = [sd[i] / b if (b := _weak_bound(cands[k])) is not None else 0.0 for i, k in enumerate(kept)]
        worst = int(np.argmax(ratio))
        if ratio[worst] <= 1.0:
            break
        loose.append(kept.pop(worst))
    if not loose:
        return sel
    dropped = list(sel.dropped)
    for k in loose:
        u = (before or {}).get(cands[k].name) or Unidentifiable(cands[k].name, "", (), "weak", (cands[k].kind,))
        u = dataclasses.replace(u, category="weak")
        dropped.append(dataclasses.replace(u, reason=explain(u)))
    dropped.sort(key=lambda u: [p.name for p in cands].index(u.name))
    return _Selection(kept, dropped, sel.from_prior, sel.by_data - set(loose), sel.sd_prior)


# --------------------------------------------------------------------------- step 4: the LM loop


@dataclass(frozen=True, eq=False)
class _Solution:
    model: KinematicModel
    lin: _Linearisation
    steps: np.ndarray
    status: int
    iterations: int
    nfev: int
    history: tuple


def _levenberg_marquardt(
    model: KinematicModel,
    prob: _Problem,
    params: list[Parameter],
    lin: _Linearisation,
    info: np.ndarray,
    *,
    loss: str,
    f_scale: float,
    max_iter: int,
    ftol: float,
    xtol: float,
    gtol: float,
    damping: float = 1e-3,
) -> _Solution:
    """Levenberg–Marquardt with Marquardt's scaling (the damping proportional to diag(JᵀWJ + I_p),
    ``I_p`` the prior's information), from ``model`` whose linearisation is ``lin``; robust
    weights recomputed at every trial (IRLS: a trial is compared with the current point under the
    trial's weights). Stops as MINPACK does (``ftol``, ``xtol``, ``gtol``). ``damping``: the
    first step's (grown tenfold at every rejected trial, shrunk tenfold after an accepted one)."""
    P = len(params)
    steps = np.zeros(P)
    if not P:
        return _Solution(model, lin, steps, -1, 0, 1, (lin.cost,))
    lam, nfev, status, it = damping, 1, 0, 0
    cost = lin.cost
    history = [cost]
    for it in range(1, max_iter + 1):  # noqa: B007 (the iterations done, read after the loop)
        A = lin.gram + info
        g = lin.gradient - info @ steps
        D = np.maximum(np.diag(A), 1e-30)
        if np.max(np.abs(g) / np.sqrt(D)) < gtol * max(1.0, math.sqrt(2 * cost)):
            status = 3
            break
        improved = False
        for _ in range(30):
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            predicted = float(delta @ g - 0.5 * delta @ A @ delta)
            if lam <= 1e-3 and predicted <= ftol * cost:
                # the (nearly Gauss-Newton) model predicts no relative reduction beyond ftol:
                # converged, without spending a trial evaluation to confirm it
                break
            trial = apply_step(model, params, delta)
            nfev += 1
            tlin = _linearise(trial, prob, params, loss=loss, f_scale=f_scale)
            tcost = tlin.cost + 0.5 * float((steps + delta) @ info @ (steps + delta))
            # the current point's cost under the trial's weights (IRLS)
            ref = 0.5 * float(tlin.w_row @ lin.z2) + 0.5 * float(steps @ info @ steps)
            if tcost < ref or tcost <= cost:
                improved = True
                break
            # at the rounding floor: neither the actual nor the predicted reduction exceeds
            # ftol (MINPACK's test), so no damping will find a better point
            if abs(cost - tcost) <= ftol * cost and predicted <= ftol * cost:
                break
            lam *= 10
        if not improved:
            status = 1
            break
        step_norm = float(np.linalg.norm(delta * np.sqrt(D)))
        rel = (cost - tcost) / max(cost, 1e-300)
        model, lin, cost = trial, tlin, tcost
        steps = steps + delta
        history.append(cost)
        lam = max(lam / 10, 1e-12)
        if 0 <= rel < ftol:
            status = 1
            break
        if step_norm < xtol * (1.0 + float(np.linalg.norm(steps * np.sqrt(D)))):
            status = 2
            break
    else:
        status = 0
    return _Solution(model, lin, steps, status, it, nfev, tuple(history))


# --------------------------------------------------------------------------- step 5: statistics


def _cross_validation(lin: _Linearisation, A: np.ndarray, rhs: np.ndarray) -> dict | None:
    """k-fold cross-validation of the fit, linearised at the solution: leaving fold k out moves
    the parameters by ``δₖ = (A − Gₖ)⁻¹(rhs − gₖ)`` (one Gauss–Newton step of the fit without
    fold k, exact for a linear model), and fold k's prediction error is then
    ``cₖ − 2δₖᵀgₖ + δₖᵀGₖδₖ`` (weighted). With a right model and the right noise its expectation
    is ``nₖ + tr(Gₖ(A − Gₖ)⁻¹)`` (the noise plus the error of parameters fitted without the fold):
    ``scale`` is the square root of the ratio, 1 when the covariance predicts the hold-out error,
    more when the model's structure misses something the in-sample residuals hide."""
    K = len(lin.c)
    if K < 2 or not A.size:
        return None
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    chi2 = expected = 0.0
    for k in range(K):
        Ak = (A - lin.G[k]) / np.outer(d, d)
        inv = np.linalg.pinv(Ak, rcond=1e-12, hermitian=True) / np.outer(d, d)
        delta = inv @ (rhs - lin.g[k])
        chi2 += float(lin.c[k] - 2 * delta @ lin.g[k] + delta @ lin.G[k] @ delta)
        expected += float(lin.n[k] + np.trace(lin.G[k] @ inv))
    return {
        "folds": K,
        "chi2": chi2,
        "expected_chi2": expected,
        "scale": math.sqrt(max(chi2, 0.0) / expected) if expected > 0 else float("nan"),
    }


# The χ² test of the residuals against the stated uncertainty (:func:`_consistency`): the model is
# said not to explain the data when χ² exceeds its upper CONSISTENCY_LEVEL quantile AND the
# residuals are at least CONSISTENCY_MIN_SCALE times what the stated uncertainty expects (with a
# million rows the test alone would flag a 0.3 % excess nobody should act on).
CONSISTENCY_LEVEL = 0.001
CONSISTENCY_MIN_SCALE = 1.1

# The level at which an excess of χ² over its expectation is taken as evidence that the stated
# uncertainty is too small (:func:`excess_scale`), for the in-sample residuals (``sigma_scale``)
# and for the cross-validated error (``model_error_scale``). χ² of a few hundred degrees of
# freedom fluctuates by ±6-9 % with an honest sigma: growing the bounds by every excess (the
# scale max(1, χ²/dof), and a second max(1, ...) of the cross-validation on top) widened bounds
# that were right in half the data sets, up to 97-98 % coverage where 95 % was due. A smaller
# level would miss a modestly understated noise on a small data set (bounds too narrow).
SCALE_LEVEL = 0.01


def chi2_upper_tail(chi2: float, dof: int) -> float:
    """P(X ≥ ``chi2``) for X ~ χ²(``dof``), by the Wilson–Hilferty cube-root normal approximation
    (absolute error below 1e-3 from 10 degrees of freedom on, which the redundancy check
    guarantees; no scipy import, which costs ~0.2 s)."""
    if dof <= 0:
        return 0.0
    h = 2.0 / (9.0 * dof)
    z = ((max(chi2, 0.0) / dof) ** (1.0 / 3.0) - (1.0 - h)) / math.sqrt(h)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def excess_scale(chi2: float, dof: float) -> float:
    """The factor ``√(χ²/dof)`` by which an uncertainty grows when ``chi2`` is significantly above
    its expectation ``dof`` (upper tail below :data:`SCALE_LEVEL`); else 1: an excess that the
    χ² distribution itself gives that often is no evidence against the stated uncertainty, which
    the instrument's calibration knows better than a few hundred residuals can estimate it."""
    if not (dof > 0 and math.isfinite(chi2)) or chi2 <= dof:
        return 1.0
    return math.sqrt(chi2 / dof) if chi2_upper_tail(chi2, dof) < SCALE_LEVEL else 1.0


def _consistency(chi2: float, dof: int) -> dict:
    ratio = math.sqrt(chi2 / dof) if dof > 0 else float("inf")
    p = chi2_upper_tail(chi2, dof)
    return {
        "test": "chi-squared",
        "level": CONSISTENCY_LEVEL,
        "min_scale": CONSISTENCY_MIN_SCALE,
        "scale_level": SCALE_LEVEL,
        "p_value": p,
        "ratio": ratio,
        "consistent": not (p < CONSISTENCY_LEVEL and ratio > CONSISTENCY_MIN_SCALE),
    }


# --------------------------------------------------------------------------- the solver


@dataclasses.dataclass(frozen=True)
class _Fit:
    """What :func:`_fit_and_reselect` ends with: the model, the final selection, the last
    Levenberg–Marquardt solution, each freed parameter's total step, and the counts."""

    model: KinematicModel
    selection: object
    solution: object
    moved: dict
    iterations: int
    nfev: int
    history: list
    settled: bool = True


def _fit_and_reselect(
    start,
    prob,
    cands,
    sel,
    lin_next,
    prior,
    *,
    loss,
    f_scale,
    max_iter,
    ftol,
    xtol,
    gtol,
    rank_rtol,
    position_only,
    reselect,
) -> _Fit:
    """Levenberg–Marquardt on the selected parameters (``lin_next``: their linearisation at
    ``start`` when it can be reused); then, when ``reselect``, the selection again at the answer
    (a parameter redundant only at the nominal geometry, e.g. on a reflector nominally on the
    flange axis, is freed where the data show it), and again, until the freed set is stable."""
    current = start
    moved: dict[str, float] = {}
    iterations = nfev = 0
    history: list[float] = []
    settled = True
    for _round in range(MAX_SELECTION_ROUNDS):
        params = [cands[k] for k in sel.kept]
        info = prior.information(params) if prior is not None else np.zeros((len(params), len(params)))
        lin_p = lin_next or _linearise(current, prob, params, loss=loss, f_scale=f_scale)
        sol = _levenberg_marquardt(
            current,
            prob,
            params,
            lin_p,
            info,
            loss=loss,
            f_scale=f_scale,
            max_iter=max_iter,
            ftol=ftol,
            xtol=xtol,
            gtol=gtol,
            # after a re-selection the fit starts at the answer: Gauss-Newton's step first. The
            # freed parameters are weakly determined (a reflector near an axis), and a damping
            # of 1e-3 of the diagonal held them back for five passes over the data (at a
            # million rows with the tool on the flange axis, 11 iterations instead of 6)
            damping=1e-3 if _round == 0 else 1e-9,
        )
        current = sol.model
        for p, s in zip(params, sol.steps):
            moved[p.name] = moved.get(p.name, 0.0) + float(s)
        iterations += sol.iterations
        nfev += sol.nfev
        history += list(sol.history)
        if not reselect:
            break
        again = _reselect(current, prob, cands, sel, rank_rtol=rank_rtol, position_only=position_only)
        if again.kept == sel.kept:
            sel = dataclasses.replace(sel, dropped=again.dropped)
            break
        if _round == MAX_SELECTION_ROUNDS - 1:
            # not settled: keep the set the last fit was made with (its solution, linearisation
            # and covariance belong to it), and say so
            settled = False
            break
        sel, lin_next = again, None
    return _Fit(current, sel, sol, moved, iterations, nfev, history, settled)


def identify(
    model: KinematicModel,
    data: Measurements,
    *,
    sigma_m: float = INSTRUMENT_SIGMA_M,
    sigma_rad: float | None = None,
    loss: str = "linear",
    f_scale: float = 3.0,
    register: str = "auto",
    fixed: tuple[str, ...] = (),
    gains: bool = False,
    hayati: bool = True,
    rank_rtol: float = 1e-6,
    max_iter: int = 100,
    ftol: float = 1e-10,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    outlier_sigma: float = 5.0,
    prior: Prior | None = None,
) -> IdentificationResult:
    """Identify the parameters of ``model`` that ``data`` determine.

    ``sigma_m``: the instrument's per-axis standard uncertainty for rows without ``sigma``;
    ``sigma_rad``: orientation uncertainty of full-pose rows (default: ``sigma_m`` over 0.1 m,
    the spacing of tooling balls); ``loss``: ``linear``, ``huber``, ``soft_l1`` or ``cauchy``,
    with ``f_scale`` in units of sigma; ``register``: ``auto`` (when it fits better), ``always``,
    ``never``; ``fixed``: parameter names (or prefixes ending in ``*``) not to free; ``gains``:
    also free the joint gains; ``hayati``: rewrite the model in a complete form
    (:func:`complete_form`: Hayati links for parallel axes, ``poe`` where ``dh`` cannot be
    complete); ``prior``: minimum-variance estimation about ``model`` (book eq. 4.69-4.70): the
    cost gains ``½ (Ms)ᵀ Σp⁻¹ (Ms)`` for the step ``s`` away from ``model`` (``M``:
    :meth:`Prior.combinations`, the identity but for the prior's held parameters); parameters
    with a prior that the data see are estimated (source ``data + prior``) even where the data
    alone cannot determine them, those the data cannot see (:data:`SEEN_BY_DATA`) keep the
    prior's value and covariance (source ``prior``) unless a held parameter the data determine
    was confused with them (a reflector's offset and the tool orientation): then they move with
    it (source ``data + prior``); no registration is done (the prior knows the base).

    Raises ``ValueError`` for inconsistent input (shapes, unknown targets, non-finite values) and
    :class:`NotEnoughData` (a ``ValueError``) when the data leave no redundancy to check the fit.
    """
    # 1. validation
    _check_input(model, data, loss, register)
    position_only = not np.any(data.has_orientation)
    targets = tuple(sorted(set(data.target) - {None}, key=str)) + ((None,) if None in set(data.target) else ())

    # 2. convention rewrite: a complete, proportional parameterisation
    start, notes = complete_form(model, hayati=hayati)
    complete = completeness(start, targets, orientation=not position_only)
    on_axis = _targets_on_last_axis(start, targets)
    prob = _problem(data, sigma_m, sigma_rad)

    # 3. the parameters, the registration, what the data determine (and the prior's share)
    cands = _candidates(start, data, prior, gains, fixed)
    registration = None
    if register != "never" and prior is None:
        cand, registration = _register(start, prob)
        if register == "always" or registration["applied"]:
            start = cand
            registration["applied"] = True
    lin_all = _linearise(start, prob, cands)
    sel = _choose(cands, lin_all.gram, prior, rank_rtol=rank_rtol, position_only=position_only)
    if prior is None:
        # what the data cannot determine is held before the solver starts, not left to wander
        # (the instrument's sigma: at the nominal the residuals are the robot's errors, not noise)
        sel = _hold_weak(cands, lin_all.gram, sel, 1.0)
        _check_redundancy(prob, len(sel.kept), complete)
    at_nominal = set(sel.kept)
    # the candidates' linearisation at the start serves the freed ones' first step when the
    # weights are the same (no robust loss): no second pass over the data
    lin_next = lin_all.restricted(sel.kept) if loss == "linear" else None

    # 4. Levenberg–Marquardt; then the selection again at the answer, until the freed set is stable
    fit = _fit_and_reselect(
        start,
        prob,
        cands,
        sel,
        lin_next,
        prior,
        loss=loss,
        f_scale=f_scale,
        max_iter=max_iter,
        ftol=ftol,
        xtol=xtol,
        gtol=gtol,
        rank_rtol=rank_rtol,
        position_only=position_only,
        reselect=prior is None and hayati,
    )
    current, sel, sol, moved = fit.model, fit.selection, fit.solution, fit.moved
    iterations, nfev, history = fit.iterations, fit.nfev, fit.history
    if not fit.settled:
        notes.append(
            f"the freed set did not settle in {MAX_SELECTION_ROUNDS} selections at the identified model: "
            f"the last fit's set is kept"
        )
    reach = _reach(start)
    kept, dropped = sel.kept, sel.dropped
    params = [cands[k] for k in kept]
    steps = np.array([moved.get(p.name, 0.0) for p in params])
    status = sol.status
    lin = sol.lin
    P = len(params)

    # 5. statistics at the solution
    stats = _statistics(
        current, prob, params, lin, steps, prior, sel, loss=loss, f_scale=f_scale, reach_m=reach, n_poses=len(data)
    )
    answer_sd = np.sqrt(np.maximum(np.diag(stats["covariance"]), 0.0))
    answer_only = [(params[i], float(answer_sd[i])) for i, k in enumerate(kept) if k not in at_nominal]
    warnings = _on_axis_warnings(on_axis, answer_only, dropped)
    cv = stats.pop("cross_validation")
    chi2_data = float(lin.c.sum())
    rp = prob.original(lin.rp)
    rr = prob.original(lin.rr)
    rn = np.linalg.norm(rp, axis=1)
    rms_m = float(np.sqrt(np.mean(rn**2))) if len(rn) else 0.0
    mes = 1.0
    if cv is not None:
        cv["rms_m"] = rms_m * math.sqrt(max(cv["chi2"], 0.0) / chi2_data) if chi2_data > 0 else 0.0
        # the cross-validated χ² against what the covariance (already grown by sigma_scale) predicts
        mes = excess_scale(cv["chi2"] / stats["sigma_scale"] ** 2, cv["expected_chi2"])
        cv["model_error_scale"] = mes
    consistency = _consistency(stats["chi2"], stats["dof"])
    # what the measurement can see, at the identified geometry as the selection is: a target
    # nominally on an axis hides parameters the real one shows
    seen = _jacobian_rank(to_poe(current), targets or (None,), orientation=not position_only)
    if seen != complete["measurable"]:
        complete["measurable_at_nominal"] = complete["measurable"]
        complete["measurable"] = seen
    complete["identified"] = len(sel.by_data)

    # 6. merging: the parameters the prior alone determines join the estimated ones
    params, steps, cov, sources, prior_sd = _merge_prior(cands, sel, stats["covariance"], steps, prior)
    values = parameter_values(current, params)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    z = prob.original(np.sqrt(lin.z2))
    w_row = prob.original(lin.w_row)
    # a row is an outlier against the noise the residuals show, not the instrument's alone: when
    # the model structure cannot explain the data (sigma_scale > 1, the consistency test failed)
    # every row is many instrument sigmas off, and flagging 293 of 300 rows as outliers hides
    # the few that are (issue 25); a gross error still stands out of the scaled noise
    outliers = tuple(int(i) for i in np.nonzero((z > outlier_sigma * stats["sigma_scale"]) | (w_row < 0.5))[0])
    has_rot = data.has_orientation
    return IdentificationResult(
        model=dataclasses.replace(current, metadata={}, name=identified_name(model.name)),
        start_model=start,
        params=tuple(params),
        values=values,
        steps=steps,
        std_errors=std,
        covariance=cov,
        correlation=corr,
        unidentifiable=tuple(dropped),
        singular_values=stats["singular_values"],
        condition_number=stats["condition_number"],
        observability=stats["observability"],
        residuals_m=rp,
        residuals_rad=rr,
        rms_m=rms_m,
        max_m=float(rn.max(initial=0.0)),
        rms_rad=float(np.sqrt(np.mean(np.sum(rr[has_rot] ** 2, axis=1)))) if np.any(has_rot) else 0.0,
        chi2=stats["chi2"],
        dof=stats["dof"],
        sigma_scale=stats["sigma_scale"],
        row_weights=w_row,
        outliers=outliers,
        success=status > 0 if P else False,
        status=status if P else -1,
        message=TERMINATION_MESSAGES[status if P else -1],
        iterations=iterations,
        nfev=nfev,
        cost_history=tuple(history),
        registration=registration,
        notes=tuple(notes),
        settings=dict(
            sigma_m=sigma_m,
            sigma_rad=prob.sigma_rot,
            loss=loss,
            f_scale=f_scale,
            gains=gains,
            rank_rtol=rank_rtol,
            fixed=list(fixed),
        ),
        sources=tuple(sources),
        prior_std_errors=prior_sd,
        chi2_prior=stats["chi2_prior"],
        data_only=stats["data_only"],
        completeness=complete,
        cross_validation=cv,
        consistency=consistency,
        model_error_scale=mes,
        warnings=tuple(warnings),
    )


def _on_axis_warnings(on_axis: list, answer_only: list[tuple[Parameter, float]], dropped: list) -> list[str]:
    """What a target nominally on the last axis cost: the parameters only the identified
    geometry determined, with their standard errors (``answer_only``: (parameter, SI)), and
    those the data could not determine at all (category ``weak``)."""
    held = [u.name for u in dropped if u.category == "weak"]
    freed = ", ".join(f"{p.name} ±{_sd_text(p, sd)}" for p, sd in answer_only)
    out = []
    for t, dist in on_axis:
        what = "the tool origin" if t is None else f"target {t}"
        out.append(
            f"{what} is nominally on the last joint's axis ({dist * 1e3:.2f} mm from it): what the last axes do "
            f"there is seen only through the real offset from the axis"
            + (
                f"; determined only at the identified geometry, to standard errors of {freed} (the predicted "
                f"accuracy includes them; a target 20 mm or more off the axis determines them better)"
                if answer_only
                else ""
            )
            + (
                f"; not determined, kept at the model's value: {', '.join(held)} (the model may be biased "
                f"by them; put the target 20 mm or more off the axis)"
                if held
                else ""
            )
        )
    return out


def _sd_text(p: Parameter, sd_si: float) -> str:
    """A standard error for a warning, in mm or deg (the warnings' fixed units)."""
    if p.kind == "length":
        return f"{sd_si * 1e3:.2g} mm"
    if p.kind == "angle":
        return f"{math.degrees(sd_si):.2g} deg"
    return f"{sd_si:.2g}"


def _statistics(
    current: KinematicModel,
    prob: _Problem,
    params: list[Parameter],
    lin: _Linearisation,
    steps: np.ndarray,
    prior: Prior | None,
    sel: _Selection,
    *,
    loss: str,
    f_scale: float,
    reach_m: float,
    n_poses: int,
) -> dict:
    """χ², the covariance ``s²(JᵀWJ + MᵀΣp⁻¹M)⁻¹`` (book eq. 4.54 / 4.70, ``s``: :func:`excess_scale`),
    conditioning and observability of what was estimated, and the cross-validation."""
    P = len(params)
    info = prior.information(params) if prior is not None else np.zeros((P, P))
    chi2_prior = float(steps @ info @ steps)
    n_prior = int(np.count_nonzero(np.isfinite(sel.sd_prior[sel.kept]))) if P else 0
    chi2 = float(lin.c.sum()) + chi2_prior
    dof = max(int(lin.n.sum()) + n_prior - P, 1)
    sigma_scale = excess_scale(chi2, dof)
    out = {
        "chi2": chi2,
        "dof": dof,
        "sigma_scale": sigma_scale,
        "chi2_prior": chi2_prior,
        "data_only": None,
        "covariance": np.zeros((P, P)),
        "singular_values": np.zeros(0),
        "condition_number": float("inf") if P == 0 else 0.0,
        "observability": {},
        "cross_validation": None,
    }
    if not P:
        return out
    G = lin.gram
    A = G + info
    dscale = np.sqrt(np.maximum(np.diag(A), 1e-300))
    cov = np.linalg.pinv(A / np.outer(dscale, dscale), rcond=1e-14, hermitian=True) / np.outer(dscale, dscale)
    out["covariance"] = cov * sigma_scale**2
    # A factor with the data's singular values (RᵀR = JᵀWJ): from G when it is well conditioned,
    # else the triangular factor of the weighted rows (one more pass over the data)
    Rw = _gram_factor(G)
    if Rw is None:
        Rw = _linearise(current, prob, params, loss=loss, f_scale=f_scale, factor=True).R
    Ra = Rw if prior is None else np.vstack([Rw, _sqrt_psd(info)])
    out["singular_values"], out["condition_number"], out["observability"] = _conditioning(
        Ra, params, n_poses=n_poses, reach_m=reach_m
    )
    if prior is not None:
        alone = [i for i, k in enumerate(sel.kept) if k in sel.by_data]
        if alone:
            _, c_data, o_data = _conditioning(
                Rw[:, alone], [params[i] for i in alone], n_poses=n_poses, reach_m=reach_m
            )
            out["data_only"] = {
                "parameters": [params[i].name for i in alone],
                "condition_number": c_data,
                "observability": o_data,
            }
    out["cross_validation"] = _cross_validation(lin, A, lin.gradient - info @ steps)
    return out


def _merge_prior(cands: list[Parameter], sel: _Selection, cov: np.ndarray, steps: np.ndarray, prior: Prior | None):
    """The estimated parameters and those the prior alone determines (not estimated: the prior's
    value, the model's, and the prior's covariance), in the candidates' order. Returns params,
    steps, covariance, sources and the prior's standard errors (None without a prior)."""
    kept = sel.kept
    sources = ["data" if np.isnan(sel.sd_prior[k]) else "data + prior" for k in kept]
    params = [cands[k] for k in kept]
    if sel.from_prior:
        order = sorted(kept + sel.from_prior)
        pos = {k: i for i, k in enumerate(order)}
        full = np.zeros((len(order), len(order)))
        est = [pos[k] for k in kept]
        full[np.ix_(est, est)] = cov
        fp = [pos[k] for k in sel.from_prior]
        full[np.ix_(fp, fp)] = prior.covariance_of([cands[k] for k in sel.from_prior])
        cov = full
        params = [cands[k] for k in order]
        sources = ["prior" if k in sel.from_prior else sources[kept.index(k)] for k in order]
        steps = np.array([0.0 if k in sel.from_prior else steps[kept.index(k)] for k in order])
        kept = order
    prior_sd = None if prior is None else np.array([sel.sd_prior[k] for k in kept])
    return params, steps, cov, sources, prior_sd


def identified_name(name: str) -> str:
    """The name of a model identified from the model ``name``: ``ur10e-nominal`` ->
    ``ur10e-identified`` (a model identified again keeps its name)."""
    stripped = True
    while stripped:
        stripped = False
        for suffix in ("-nominal", "-identified", "-true"):
            if name.endswith(suffix):
                name, stripped = name[: -len(suffix)], True
    return f"{name or 'robot'}-identified"


# A parameter with a prior is "seen" by the data when its prior standard error, as a change of the
# parameter, moves the measurements by at least this much (root sum of squares over all residuals,
# in noise standard deviations): below it, the data would shrink its variance by less than 1 %.
SEEN_BY_DATA = 0.1


def _seen_by_data(J: np.ndarray, sd_prior: np.ndarray) -> np.ndarray:
    """(P,) True where the weighted Jacobian's column times the prior standard error reaches
    :data:`SEEN_BY_DATA` (False where there is no prior)."""
    with np.errstate(invalid="ignore"):
        return np.nan_to_num(np.linalg.norm(J, axis=0) * sd_prior) >= SEEN_BY_DATA


# Below this condition number (columns scaled to unit norm) the Cholesky factor of JᵀJ gives the
# singular values to ~1e-8 relative (the error grows as the square of the condition number);
# above, the QR of J itself is used.
GRAM_FACTOR_MAX_CONDITION = 1e4


def _gram_factor(G: np.ndarray) -> np.ndarray | None:
    """An upper triangular R with RᵀR = G (P, P), by Cholesky of the column-scaled G, when G is
    well conditioned (:data:`GRAM_FACTOR_MAX_CONDITION`); else None. A P x P factorisation
    instead of a QR of the tall Jacobian."""
    d = np.sqrt(np.diag(G))
    if not np.all(d > 0):
        return None
    try:
        U = np.linalg.cholesky(G / np.outer(d, d)).T
    except np.linalg.LinAlgError:
        return None
    s = np.linalg.svd(U, compute_uv=False)
    if not s[-1] > 0 or s[0] / s[-1] > GRAM_FACTOR_MAX_CONDITION:
        return None
    return U * d


def _sqrt_psd(M: np.ndarray) -> np.ndarray:
    """A factor F with FᵀF = M for a symmetric positive semi-definite M."""
    e, V = np.linalg.eigh(M)
    return np.sqrt(np.maximum(e, 0.0))[:, None] * V.T


def _conditioning(R: np.ndarray, params: list[Parameter], *, n_poses: int, reach_m: float) -> tuple:
    """Singular values, condition number (columns scaled to unit norm) and observability indices
    of a factor ``R`` whose Gram matrix is the estimate's information (up to the noise scale)."""
    sv = np.linalg.svd(R, compute_uv=False)
    norms = np.linalg.norm(R, axis=0)
    svn = np.linalg.svd(R / np.where(norms > 0, norms, 1.0), compute_uv=False)
    cond = float(svn[0] / svn[-1]) if svn[-1] > 0 else float("inf")
    return sv, cond, observability_indices(R, params, n_poses=n_poses, reach_m=reach_m)


def _matches(name: str, patterns) -> bool:
    return any(name == p or (p.endswith("*") and name.startswith(p[:-1])) for p in patterns)


def _reach(model: KinematicModel) -> float:
    """A characteristic length of the robot (m): the sum of its link lengths and offsets."""
    if model.convention == "poe":
        pts = [j.axis_point()[1] for j in model.joints] + [model.poe_home()[:3]]
        return float(max(sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)), 0.1))
    return float(max(sum(abs(j.a) + abs(j.d) for j in model.joints), 0.1))


def observability_indices(Jw: np.ndarray, params: list[Parameter], *, n_poses: int, reach_m: float) -> dict:
    """Observability indices of the weighted Jacobian (book §4.5.3). Only its singular values
    matter, so ``Jw`` may as well be the triangular factor R of ``Jw = QR`` (P x P, far cheaper).

    Angle columns are multiplied by ``1/reach_m`` (an angle error of 1 rad is compared with a
    length error of the robot's reach), so the indices do not depend on the choice of units.
    - ``O1`` Borm & Menq (eq. 4.193-4.194): ``(σ1···σL)^(1/L) / √m``;
    - ``O2`` inverse condition number ``σL/σ1``;
    - ``O3`` the minimum singular value ``σL`` (Nahvi et al.);
    - ``O4`` the noise amplification index ``σL²/σ1`` (Nahvi & Hollerbach).
    """
    scale = np.array([1.0 / reach_m if p.kind == "angle" else 1.0 for p in params])
    s = np.linalg.svd(Jw * scale, compute_uv=False)
    L = len(s)
    if L == 0 or s[-1] <= 0:
        return {
            "O1_borm_menq": 0.0,
            "O2_inverse_condition": 0.0,
            "O3_min_singular": 0.0,
            "O4_noise_amplification": 0.0,
            "condition_number_physical": float("inf"),
        }
    return {
        "O1_borm_menq": float(np.exp(np.mean(np.log(s))) / math.sqrt(n_poses)),
        "O2_inverse_condition": float(s[-1] / s[0]),
        "O3_min_singular": float(s[-1]),
        "O4_noise_amplification": float(s[-1] ** 2 / s[0]),
        "condition_number_physical": float(s[0] / s[-1]),
    }
