"""Identification: the kinematic parameters that best explain measured positions (and poses).

One call, one frozen result (after scipy's ``least_squares``): :func:`identify` returns an
:class:`IdentificationResult` that says everything that happened — the identified model, the
parameters freed with their standard errors and correlations, the ones the data cannot
determine and why, conditioning and observability indices, residual statistics, rows
down-weighted as outliers, and how the solver ended.

Method (book §4.4.2, §4.3.3, §4.5.3):

1. Parallel consecutive axes in ``dh`` links become Hayati links (§2.6, §2.8.1.1); ``mdh`` is
   converted to ``dh`` first (exact).
2. When the base is unknown or far off, start from a rigid registration of the nominal
   predictions onto the measurements (full-pose data: base and tool together, the
   robot-world/hand-eye problem).
3. Rows are weighted by their uncertainty (``sigma`` per row, or the instrument's).
4. The identifiable set: a QR factorisation of the column-scaled, weighted Jacobian, in a fixed
   order of preference (:func:`preference_order`); a column that adds (numerically) nothing to
   the columns before it is not freed, keeps the model's value, and the report names what it
   duplicates, compared in that dimensionless scaling (:func:`select_identifiable`).
5. Levenberg–Marquardt with Marquardt's scaling (the damping is proportional to diag(JᵀWJ)),
   analytic Jacobian (:mod:`calibration.jacobian`), optional robust loss by iteratively
   reweighted rows (a bumped reflector does not ruin the fit; the rows it down-weights are
   named).
6. Covariance ``s²(JᵀWJ)⁻¹`` (book eq. 4.54/4.70 with W = Σ⁻¹), ``s² = max(1, χ²/dof)``: if the
   residuals are larger than the stated uncertainty, the stated uncertainty was optimistic and
   the covariance grows accordingly; it never shrinks below what the instrument states. With a
   :class:`Prior` (book §4.3.2): ``s²(JᵀWJ + MᵀΣp⁻¹M)⁻¹`` (``M`` the combinations the prior
   describes, :meth:`Prior.combinations`), the prior's term counted in χ².
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .conventions import hayati_for_parallel_axes, mdh_to_dh
from .jacobian import Prediction, jacobian_from_walk, record_keys, world_points
from .kinematics import Walk, walk
from .model import KinematicModel
from .parameters import Parameter, apply_step, candidate_parameters, parameter_values
from .registration import register_points, register_poses
from .transforms import homogeneous, invert, matrix_to_pose, matrix_to_rotvec, pose_to_matrix, quat_to_matrix

LOSSES = ("linear", "huber", "soft_l1", "cauchy")

TERMINATION_MESSAGES = {
    -1: "the data cannot determine any parameter",
    0: "the maximum number of iterations was reached before convergence",
    1: "converged: the relative reduction of the cost fell below ftol",
    2: "converged: the parameter step fell below xtol",
    3: "converged: the gradient fell below gtol",
}


@dataclass(frozen=True, eq=False)
class Measurements:
    """Measured data, SI. ``q`` (N, n) joint readings; ``p_world`` (N, 3) measured target
    positions; ``quat`` (N, 4) tool orientation ``(qw, qx, qy, qz)`` or NaN where a row has
    none (``None``: position-only data); ``target`` (N,) target names (``None``: tool origin);
    ``sigma`` (N,) m per-axis standard uncertainty or NaN for the instrument's; ``pose_id`` (N,);
    ``row`` (N,) row numbers in the source file, for reports; ``payload`` (N, 4) kg and centre of
    gravity in the tool frame (m) per row, for a compliant model (``None``: the model's own)."""

    q: np.ndarray
    p_world: np.ndarray
    quat: np.ndarray | None = None
    target: np.ndarray | None = None
    sigma: np.ndarray | None = None
    pose_id: np.ndarray | None = None
    row: np.ndarray | None = None
    payload: np.ndarray | None = None

    def __post_init__(self):
        q = np.atleast_2d(np.asarray(self.q, dtype=float))
        N = q.shape[0]
        object.__setattr__(self, "q", q)
        p = np.asarray(self.p_world, dtype=float).reshape(N, 3)
        object.__setattr__(self, "p_world", p)
        if self.quat is not None:
            object.__setattr__(self, "quat", np.asarray(self.quat, dtype=float).reshape(N, 4))
        t = np.full(N, None, dtype=object) if self.target is None else np.asarray(self.target, dtype=object).reshape(N)
        t = np.array([None if (x is None or x == "") else str(x) for x in t], dtype=object)
        object.__setattr__(self, "target", t)
        s = np.full(N, np.nan) if self.sigma is None else np.asarray(self.sigma, dtype=float).reshape(N)
        object.__setattr__(self, "sigma", s)
        if self.row is None:
            object.__setattr__(self, "row", np.arange(1, N + 1))
        if self.payload is not None:
            object.__setattr__(self, "payload", np.asarray(self.payload, dtype=float).reshape(N, 4))

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def has_orientation(self) -> np.ndarray:
        """(N,) True where the row carries a measured orientation."""
        if self.quat is None:
            return np.zeros(len(self), bool)
        return np.all(np.isfinite(self.quat), axis=1)

    def subset(self, idx) -> "Measurements":
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return Measurements(self.q[idx], self.p_world[idx], pick(self.quat), self.target[idx], self.sigma[idx],
                            pick(self.pose_id), self.row[idx], pick(self.payload))


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior knowledge of parameters (book §4.3.2, minimum-variance estimation): the model passed
    to :func:`identify` is the prior mean, and ``covariance`` (P, P) SI the uncertainty of the
    parameters ``names`` about it (typically the previous calibration's covariance, inflated for
    drift). Parameters without a prior are unconstrained.

    ``held``: the parameters the previous calibration kept at the model's value because its data
    could not tell them from a combination of the ones it estimated, each with that relation
    (:attr:`Unidentifiable.relation`, SI: a unit change of it moves the measured points as
    changes ``c`` of those do; :func:`held_relations`). Its data then determined each estimated
    ``p`` only together with them, ``p + Σ c·u``, and that combination is what ``covariance``
    describes: a held parameter that new data determine (a tool orientation measured at last)
    moves the parameters it was confused with instead of being held by their prior."""

    names: tuple[str, ...]
    covariance: np.ndarray
    held: dict = field(default_factory=dict)

    def _block(self, params: list["Parameter"]) -> tuple[list[int], np.ndarray]:
        idx = {n: i for i, n in enumerate(self.names)}
        have = [k for k, p in enumerate(params) if p.name in idx]
        rows = [idx[params[k].name] for k in have]
        return have, np.asarray(self.covariance, dtype=float)[np.ix_(rows, rows)]

    def combinations(self, params: list["Parameter"]) -> np.ndarray:
        """The matrix M (H, P) of the combinations the prior describes, one row per parameter of
        ``params`` with a prior (in the order of ``params``): ``M·s`` for a step ``s`` (P,) over
        ``params``, the held ones of ``params`` entering by their relation."""
        have, _ = self._block(params)
        row = {params[k].name: i for i, k in enumerate(have)}
        M = np.zeros((len(have), len(params)))
        M[np.arange(len(have)), have] = 1.0
        for k, p in enumerate(params):
            for name, c in self.held.get(p.name, ()):
                if name in row:
                    M[row[name], k] += c
        return M

    def information(self, params: list["Parameter"]) -> np.ndarray:
        """The prior information matrix ``Mᵀ Σ⁻¹ M`` over ``params`` (:meth:`combinations`, Σ the
        marginal covariance of the parameters of ``params`` with a prior; zero rows and columns
        for parameters neither with a prior nor held)."""
        have, sub = self._block(params)
        if not have:
            return np.zeros((len(params), len(params)))
        M = self.combinations(params)
        return M.T @ np.linalg.pinv(sub, hermitian=True) @ M

    def covariance_of(self, params: list["Parameter"]) -> np.ndarray:
        """The prior covariance (P, P) over ``params`` (NaN rows and columns for parameters without
        a prior)."""
        have, sub = self._block(params)
        cov = np.full((len(params), len(params)), np.nan)
        cov[np.ix_(have, have)] = sub
        return cov


def held_relations(result: "IdentificationResult") -> dict:
    """What a :class:`Prior` made from ``result`` needs to know of the parameters it held at the
    model's value: ``{name: ((estimated name, coefficient SI), ...)}`` for those related to the
    estimated ones."""
    return {u.name: tuple(u.relation) for u in result.unidentifiable if u.relation}


def drift_scale(model: KinematicModel, data: Measurements, names: tuple[str, ...], covariance: np.ndarray,
                drift: np.ndarray, *, sigma_m: float = 20e-6, sigma_rad: float | None = None,
                scales: np.ndarray | None = None, held: dict | None = None) -> float:
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
        U, sv, _ = np.linalg.svd(J_all[:, free] - J @ M[:, len(cols):], full_matrices=False)
        basis = U[:, sv > 1e-9 * max(sv[0], 1e-300)]
        r = r - basis @ (basis.T @ r)
        J = J - basis @ (basis.T @ J)
    G, b = J.T @ J, J.T @ r
    best = (math.inf, 0.0)
    for s in (np.concatenate([[0.0], np.geomspace(0.01, 100.0, 41)]) if scales is None else scales):
        # -log evidence, up to a constant, in the parameters' space (determinant lemma, Woodbury):
        # C = I + J Q Jᵀ, Q = L Lᵀ: log det C = log det K, rᵀC⁻¹r = rᵀr - cᵀK⁻¹c, K = I + LᵀGL, c = Lᵀb
        L = _sqrt_psd(cov + s * s * np.diag(d2)).T
        K = np.eye(len(keep)) + L.T @ G @ L
        c = L.T @ b
        nll = 0.5 * (np.linalg.slogdet(K)[1] + r @ r - c @ np.linalg.solve(K, c))
        if nll < best[0]:
            best = (nll, float(s))
    return best[1]


@dataclass(frozen=True, eq=False)
class IdentificationResult:
    """Everything :func:`identify` did. Arrays over the parameters with an estimate are (P,) /
    (P, P), SI.

    ``sources`` (P,) says what determined each: ``"data"``, ``"data + prior"`` (minimum-variance
    estimation with a :class:`Prior`) or ``"prior"`` (the data cannot see it: it keeps the
    prior's value and uncertainty and was not estimated); ``prior_std_errors`` (P,) the prior's
    standard errors (NaN without one). ``singular_values``, ``condition_number`` and
    ``observability`` are those of what was estimated (with a prior: data and prior together);
    ``data_only`` (with a prior) the same statistics for the parameters the data alone determine.
    ``chi2`` is the weighted residuals' (plus, with a prior, the prior term ``chi2_prior``) and
    ``dof`` its degrees of freedom (residuals, plus prior constraints, minus estimated
    parameters).

    Residuals are measured minus predicted: ``residuals_m`` (N, 3) position, ``residuals_rad``
    (N, 3) orientation (zeros for position-only rows).
    """

    model: KinematicModel
    start_model: KinematicModel
    params: tuple[Parameter, ...]
    values: np.ndarray
    steps: np.ndarray
    std_errors: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    unidentifiable: tuple[Unidentifiable, ...]
    singular_values: np.ndarray
    condition_number: float
    observability: dict
    residuals_m: np.ndarray
    residuals_rad: np.ndarray
    rms_m: float
    max_m: float
    rms_rad: float
    chi2: float
    dof: int
    sigma_scale: float
    row_weights: np.ndarray
    outliers: tuple[int, ...]
    success: bool
    status: int
    message: str
    iterations: int
    nfev: int
    cost_history: tuple[float, ...]
    registration: dict | None
    notes: tuple[str, ...] = ()
    settings: dict = field(default_factory=dict)
    sources: tuple[str, ...] = ()
    prior_std_errors: np.ndarray | None = None
    chi2_prior: float = 0.0
    data_only: dict | None = None

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def n_rows(self) -> int:
        return len(self.residuals_m)


# --------------------------------------------------------------------------- residuals


@dataclass(frozen=True, eq=False)
class _Problem:
    data: Measurements
    p_tool_names: np.ndarray  # (N,) object
    has_rot: np.ndarray  # (N,) bool
    R_meas: np.ndarray | None  # (N, 3, 3)
    sigma_pos: np.ndarray  # (N,) m
    sigma_rot: float  # rad
    target_rows: dict = field(default_factory=dict)  # target name -> (N,) bool, the rows that measure it
    trig: dict = field(default_factory=dict)  # the joints' cos and sin over the data, for every walk (kinematics.walk)


def _problem(data: Measurements, sigma_m: float, sigma_rad: float | None) -> _Problem:
    """The data with their weights: ``sigma_m`` for rows without their own ``sigma``, ``sigma_rad``
    for orientations (default ``sigma_m`` over 0.1 m)."""
    has_rot = data.has_orientation
    R_meas = quat_to_matrix(np.where(np.isfinite(data.quat), data.quat, [1, 0, 0, 0])) if data.quat is not None else None
    sigma_pos = np.where(np.isfinite(data.sigma) & (data.sigma > 0), data.sigma, sigma_m)
    sigma_rot = float(sigma_rad) if sigma_rad is not None else sigma_m / 0.1
    return _Problem(data, data.target, has_rot, R_meas, sigma_pos, sigma_rot, _target_rows(data.target))


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
    Jp, Jr = jacobian_from_walk(w, pt, params, prob.data.q, prob.p_tool_names,
                                orientation=bool(np.any(prob.has_rot)))
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


def _row_norms(prob: _Problem, r: np.ndarray) -> np.ndarray:
    """Per-measurement-row norm of the weighted residual (position and orientation together)."""
    N = len(prob.data)
    pos = r[: 3 * N].reshape(3, N)
    sq = pos[0] ** 2 + pos[1] ** 2 + pos[2] ** 2
    if np.any(prob.has_rot):
        rot = r[3 * N:].reshape(3, -1)
        sq[prob.has_rot] += rot[0] ** 2 + rot[1] ** 2 + rot[2] ** 2
    return np.sqrt(sq)


def _expand_rows(prob: _Problem, w_row: np.ndarray) -> np.ndarray:
    """Per-row weights -> per-residual weights, in the order of :func:`_stack`."""
    parts = [np.tile(w_row, 3)]
    if np.any(prob.has_rot):
        parts.append(np.tile(w_row[prob.has_rot], 3))
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


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


# --------------------------------------------------------------------------- parameter selection

# How a parameter the data cannot determine relates to the freed ones (``Unidentifiable.category``).
CATEGORIES = ("no_effect", "same_motion", "combination", "target_offsets", "tool_orientation", "last_joint_offset")


def _describe(name: str) -> str:
    if name.startswith("compliance."):  # joint compliance under gravity (calibration.compliance)
        from .compliance import describe_term

        return describe_term(name)
    head, _, f = name.rpartition(".")
    words = {"theta": "offset", "d": "d", "a": "a", "alpha": "twist alpha", "beta": "Hayati beta",
             "gain": "gain", "tilt_x": "axis tilt x", "tilt_y": "axis tilt y", "shift_x": "axis shift x",
             "shift_y": "axis shift y"}
    if head in ("base", "tool", "home"):
        kind = "translation" if f.startswith("t") else "rotation"
        return f"{head} {kind} {f[1]} ({name})"
    if head.startswith("target."):
        return f"target {head[7:]} {f} ({name})"
    return f"joint {head} {words.get(f, f)} ({name})"


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


@dataclass(frozen=True, slots=True)
class Unidentifiable:
    """A parameter the data cannot determine; it keeps the model's value.

    ``reason`` in words (SI units); ``category`` one of :data:`CATEGORIES`; ``relation`` the
    freed parameters whose combined motion it duplicates: a unit change of ``name`` moves the
    measured points as changes ``coefficient`` of those do (SI: m or rad of each per m or rad of
    ``name``), largest first in the scaled (dimensionless) parameterisation the selection uses;
    ``kinds`` the kinds (``length``, ``angle``, ``scale``) of ``name`` and of each related
    parameter, for writing the coefficients in other units (:func:`explain`).
    """

    name: str
    reason: str
    relation: tuple[tuple[str, float], ...] = ()
    category: str = "no_effect"
    kinds: tuple[str, ...] = ()


def _unit_name(kind: str, units) -> tuple[str, float]:
    """(unit, SI per unit) of a parameter kind; ``units`` None: SI."""
    if kind == "length":
        return ("m", 1.0) if units is None else (units.length, units.length_m)
    if kind == "angle":
        return ("rad", 1.0) if units is None else (units.angle, units.angle_rad)
    if kind == "angle_per_length":  # compliance x mass terms (calibration.compliance)
        return ("rad/m", 1.0) if units is None else (f"{units.angle}/{units.length}", units.angle_rad / units.length_m)
    if kind == "angle_per_torque":  # a joint's compliance
        return ("rad/(N·m)", 1.0) if units is None else (f"{units.angle}/(N·m)", units.angle_rad)
    return ("", 1.0)


def relation_coefficients(u: Unidentifiable, units=None) -> list[tuple[str, float, str]]:
    """``u.relation`` in ``units`` (a :class:`calibration.model.Units`; None: SI): (name,
    coefficient, unit of the coefficient such as ``mm/deg``) per related parameter."""
    out = []
    kinds = u.kinds or ("",) * (len(u.relation) + 1)
    un, sn = _unit_name(kinds[0], units)
    for (name, c), kind in zip(u.relation, kinds[1:]):
        uj, sj = _unit_name(kind, units)
        unit = uj if not un else (f"{uj}/{un}" if uj else f"1/{un}")
        out.append((name, c * sn / sj, "1" if uj == un else unit))
    return out


def relation_text(u: Unidentifiable, units=None, *, terms: int = 6) -> str:
    """The relation in words: ``1 mm of tool.ty ≡ +1.43 deg of j6.theta +1 mm of target.smr1.x``."""
    kinds = u.kinds or ("",) * (len(u.relation) + 1)
    un, _ = _unit_name(kinds[0], units)
    parts = []
    for (name, c, _), kind in zip(relation_coefficients(u, units)[:terms], kinds[1:]):
        uj, _ = _unit_name(kind, units)
        parts.append(f"{c:+.3g}{' ' + uj if uj else ''} of {name}")
    more = " + …" if len(u.relation) > terms else ""
    return f"1{' ' + un if un else ''} of {u.name} ≡ {' '.join(parts)}{more}"


def explain(u: Unidentifiable, units=None) -> str:
    """Why ``u`` is not identified, in words, with the relation's coefficients in ``units``
    (a :class:`calibration.model.Units`; None: SI)."""
    d = _describe(u.name)
    rel = relation_text(u, units) if u.relation else ""
    if u.category == "tool_orientation":
        return "tool orientation is unobservable from position-only data" + (f" ({rel})" if rel else "")
    if u.category == "target_offsets":
        return f"{d} moves the measured points exactly as the target offsets do ({rel})"
    if u.category == "last_joint_offset":
        joint = u.name.rpartition(".")[0]
        what = ("the target offsets already describe" if any(n.startswith("target.") for n, _ in u.relation)
                else "the tool translation already describes")
        return (f"{d} only turns the measured points about the axis of joint {joint}, which {what}: "
                f"position-only data cannot tell the two apart, so it keeps the model's value ({rel})")
    if u.category == "same_motion":
        return f"{d} and {_describe(u.relation[0][0])} are the same motion ({rel})"
    if u.category == "combination":
        return f"{d} moves the measured points as a combination of freed parameters does: {rel}"
    return f"{d} has no effect on these measurements"


def _category(p: Parameter, relation: list[tuple[str, float]], pair: bool, position_only: bool,
              last_offset: bool) -> str:
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
        u = Unidentifiable(params[k].name, "", tuple(relation),
                           _category(params[k], relation, pair, position_only, k == last), tuple(kinds))
        dropped.append(dataclasses.replace(u, reason=explain(u)))
    dropped.sort(key=lambda u: [p.name for p in params].index(u.name))
    return sorted(kept), dropped, factor


# --------------------------------------------------------------------------- registration


def _register(model: KinematicModel, prob: _Problem, record=frozenset()) -> tuple[KinematicModel, dict, Walk]:
    """Try a rigid registration of the model's predictions onto the data; keep it if it fits
    better than the model's own base. Also returns the walk of the chain in its base frame
    (recording ``record``): one walk serves every base (:func:`_linearise_in_base_frame`)."""
    data = prob.data
    local = dataclasses.replace(model, base=np.zeros(6))
    w = walk(local, data.q, record, prob.trig, data.payload)

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
    info["rms_after_m"] = after
    info["applied"] = bool(after < before)
    return (candidate if after < before else model), info, w


def _linearise_in_base_frame(model: KinematicModel, prob: _Problem, params: list[Parameter], w_base: Walk):
    """Position-only data: the weighted residuals and Jacobian of ``params`` at ``model`` from a
    walk ``w_base`` of the same chain with the base frame at the identity (so no second walk
    after the registration), and the residuals (N, 3) in the world frame.

    With ``B = (R, t)`` the model's base, a predicted point is ``R·p + t`` and every Jacobian
    block ``R·J_i``: the measured points brought into the base frame, ``Rᵀ(m − t)``, give the
    same residuals and Jacobian turned row by row by ``Rᵀ``, which changes no row norm, no
    inner product JᵀJ or Jᵀr and no triangular factor: what the selection and the solver use."""
    B = pose_to_matrix(model.base)
    R, t = B[:3, :3], B[:3, 3]
    pt = world_points(w_base, _p_tool(model, prob.p_tool_names, prob.target_rows))
    rp_base = (prob.data.p_world - t) @ R - pt
    Jp, _ = jacobian_from_walk(w_base, pt, params, prob.data.q, prob.p_tool_names, orientation=False)
    r, J = _stack(prob, rp_base, None, Jp)
    return r, J, rp_base @ R.T


# --------------------------------------------------------------------------- the solver

_START = object()  # marks a Gram matrix computed from the start's Jacobian (never taken as an array)


def identify(
    model: KinematicModel,
    data: Measurements,
    *,
    sigma_m: float = 20e-6,
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
    also free the joint gains; ``hayati``: rewrite parallel-axis ``dh`` links in Hayati's form;
    ``prior``: minimum-variance estimation about ``model`` (book eq. 4.69-4.70): the cost gains
    ``½ (Ms)ᵀ Σp⁻¹ (Ms)`` for the step ``s`` away from ``model`` (``M``: :meth:`Prior.combinations`,
    the identity but for the prior's held parameters); parameters with a prior that the data see
    are estimated (source ``data + prior``) even where the data alone cannot determine them, those
    the data cannot see (:data:`SEEN_BY_DATA`) keep the prior's value and covariance (source
    ``prior``) unless a held parameter the data determine was confused with them (a reflector's
    offset and the tool orientation): then they move with it (source ``data + prior``); no
    registration is done (the prior knows the base).

    Raises ``ValueError`` for inconsistent input (shapes, unknown targets, non-finite values).
    """
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
    notes: list[str] = []
    start = model
    if start.convention == "mdh":
        start = mdh_to_dh(start) if not any(j.hayati for j in start.joints) else start
        notes.append("mdh model converted to dh (exact) for identification")
    if hayati and start.convention == "dh":
        start, hn = hayati_for_parallel_axes(start)
        notes += hn
    if start is not model and model.compliance is not None:  # compliance (issue 17): lumps sit in link frames
        from .compliance import reexpress

        start = reexpress(start, model)
    prob = _problem(data, sigma_m, sigma_rad)
    has_rot, sigma_rot = prob.has_rot, prob.sigma_rot

    used_targets = tuple(sorted(set(data.target) - {None}))
    prior_targets = () if prior is None else tuple(sorted(
        {n.split(".")[1] for n in prior.names if n.startswith("target.")} & set(start.targets) - set(used_targets)))
    with_gains = gains or (prior is not None and any(n.endswith(".gain") for n in prior.names))
    # the candidates depend on the model's structure, not on its base: the same after registration
    cands = candidate_parameters(start, targets=used_targets + prior_targets, gains=with_gains)
    cands = [p for p in cands if not _matches(p.name, fixed)]
    position_only = not np.any(has_rot)

    registration = None
    w_base = None
    if register != "never" and prior is None:
        cand, registration, w_base = _register(start, prob, record_keys(cands) if position_only else frozenset())
        if register == "always" or registration["applied"]:
            start = cand
            registration["applied"] = True

    if w_base is not None and position_only:
        r_start, J_cands, rp = _linearise_in_base_frame(start, prob, cands, w_base)
        rr = np.zeros_like(rp)
    else:
        pred, rp, rr = _evaluate(start, prob, cands)
        r_start, J_cands = _stack(prob, rp, rr, pred.Jp, pred.Jr)
    del w_base
    kept, dropped, R_cands = _select(J_cands, cands, rtol=rank_rtol, position_only=position_only)
    by_data = set(kept)  # what the data alone determine
    from_prior: list[int] = []
    sd_prior = np.full(len(cands), np.nan)
    if prior is not None:  # a prior determines what the data alone cannot
        sd_prior = np.sqrt(np.maximum(np.diag(prior.covariance_of(cands)), 0.0))
        has_prior = [k for k in range(len(cands)) if np.isfinite(sd_prior[k])]
        seen = _seen_by_data(J_cands, sd_prior)
        # a held parameter the data determine moves those it was confused with: estimated too
        released = {n for k in kept for n, _ in prior.held.get(cands[k].name, ())}
        from_prior = [k for k in has_prior if not seen[k] and cands[k].name not in released]
        kept = sorted((set(kept) | set(has_prior)) - set(from_prior))
        named = {cands[k].name for k in has_prior}
        dropped = [u for u in dropped if u.name not in named]
    params = [cands[k] for k in kept]
    info = prior.information(params) if prior is not None else np.zeros((len(params), len(params)))

    # ---- Levenberg–Marquardt with Marquardt scaling and IRLS robust weights
    current = start
    P = len(params)
    steps = np.zeros(P)
    lam = 1e-3
    status = 0 if P else -1
    nfev = 1
    it = 0
    history: list[float] = []
    gram = None
    w_row = np.ones(len(data))
    J = None  # the Jacobian over `params` at `current`; at the start: columns `kept` of J_cands, taken when needed
    if P:
        r = r_start
        R_start = R_cands[:, kept]  # RᵀR = the start's JᵀJ: the selection's factor gives it without J
        fresh = True  # r, J, rp, rr are those of `current`
        keys = record_keys(params)  # trials record what the Jacobian needs: if accepted, no second walk
        w_row = _robust_weights(_row_norms(prob, r), loss, f_scale)
        w = _expand_rows(prob, w_row)
        cost = 0.5 * float(np.sum(w * r**2))
        history.append(cost)
        for it in range(1, max_iter + 1):
            unit = bool(np.all(w == 1.0))
            if J is None and unit:  # the start, unit weights: JᵀJ and Jᵀr without taking J's columns
                G, g = R_start.T @ R_start, (r @ J_cands)[kept]
            else:
                if J is None:
                    J = J_cands[:, kept]
                Jw, rw = (J, r) if unit else (J * np.sqrt(w)[:, None], r * np.sqrt(w))  # unit: skip the copies
                G, g = Jw.T @ Jw, Jw.T @ rw
            A = G + info
            gram = (_START if J is None else J, w, G)  # G and what it was computed from, for the statistics
            g = g - info @ steps
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
                if lam <= 1e-3 and float(delta @ g - 0.5 * delta @ A @ delta) <= ftol * cost:
                    # the (nearly Gauss-Newton) model predicts no relative reduction beyond ftol:
                    # converged, without spending a trial evaluation to confirm it
                    break
                trial = apply_step(current, params, delta)
                nfev += 1
                t_walk, t_pt, trp, trr = _residuals(trial, prob, keys)
                tr, _ = _stack(prob, trp, trr)
                tw_row = _robust_weights(_row_norms(prob, tr), loss, f_scale)
                tw = _expand_rows(prob, tw_row)
                prior_cost = 0.5 * float((steps + delta) @ info @ (steps + delta))
                tcost = 0.5 * float(np.sum(tw * tr**2)) + prior_cost
                # compare with the cost of the current point under the same weights (IRLS)
                ref = 0.5 * float(np.sum(tw * r**2)) + 0.5 * float(steps @ info @ steps)
                if tcost < ref or tcost <= cost:
                    improved = True
                    break
                # at the rounding floor: neither the actual nor the predicted reduction exceeds
                # ftol (MINPACK's test), so no damping will find a better point
                predicted = float(delta @ g - 0.5 * delta @ A @ delta)
                if abs(cost - tcost) <= ftol * cost and predicted <= ftol * cost:
                    break
                lam *= 10
            if not improved:
                status = 1
                break
            step_norm = float(np.linalg.norm(delta * np.sqrt(D)))
            rel = (cost - tcost) / max(cost, 1e-300)
            current, r, w, w_row, cost = trial, tr, tw, tw_row, tcost
            fresh = False
            steps += delta
            history.append(cost)
            lam = max(lam / 10, 1e-12)
            if 0 <= rel < ftol:
                status = 1
                break
            if step_norm < xtol * (1.0 + float(np.linalg.norm(steps * np.sqrt(D)))):
                status = 2
                break
            # the Jacobian only at accepted points, from the trial's own walk
            rp, rr = trp, trr
            r, J = _stack(prob, rp, rr, *jacobian_from_walk(t_walk, t_pt, params, data.q, prob.p_tool_names,
                                                            orientation=bool(np.any(has_rot))))
            J_cands = R_start = None  # only the start needed them
            fresh = True
        else:
            status = 0

    # ---- statistics at the solution (the last Jacobian, when it was computed there)
    if not (P and fresh):
        pred, rp, rr = _evaluate(current, prob, params if P else None)
        r, J = _stack(prob, rp, rr, pred.Jp, pred.Jr) if P else (_stack(prob, rp, rr)[0], None)
    z = _row_norms(prob, r)
    w_row = _robust_weights(z, loss, f_scale)
    w = _expand_rows(prob, w_row)
    n_res = r.size
    chi2_prior = float(steps @ info @ steps)
    n_prior = int(np.count_nonzero(np.isfinite(sd_prior[kept])))  # estimated parameters with a prior
    chi2 = float(np.sum(w * r**2)) + chi2_prior
    dof = max(n_res + n_prior - P, 1)
    sigma_scale = math.sqrt(max(1.0, chi2 / dof))
    cov = np.zeros((P, P))
    sv = np.zeros(0)
    cond = float("inf") if P == 0 else 0.0
    obs: dict = {}
    data_only = None
    reach = _reach(start)
    if P:
        unit = bool(np.all(w == 1.0))
        if gram is not None and gram[0] is (_START if J is None else J) and unit and np.all(gram[1] == 1.0):
            G = gram[2]  # the last iteration's: the same Jacobian, unit weights
        else:
            if J is None:
                J = J_cands[:, kept]
            Jw = J if unit else J * np.sqrt(w)[:, None]
            G = Jw.T @ Jw
        # Σ = s² (JᵀWJ + MᵀΣp⁻¹M)⁻¹ (book eq. 4.54 / 4.70); pseudo-inverse on the column-scaled
        # matrix for numerical safety.
        A = G + info
        dscale = np.sqrt(np.maximum(np.diag(A), 1e-300))
        cov = np.linalg.pinv(A / np.outer(dscale, dscale), rcond=1e-14, hermitian=True) / np.outer(dscale, dscale)
        cov *= sigma_scale**2
        # A factor with the data's singular values and Gram matrix (RᵀR = JᵀWJ): from G when it
        # is well conditioned, else the triangular factor of Jw = QR
        Rw = _gram_factor(G)
        if Rw is None:
            if J is None:
                J = J_cands[:, kept]
            Jw = J if unit else J * np.sqrt(w)[:, None]
            Rw = _r_factor(Jw) if Jw.shape[0] > P else Jw
        # conditioning of what was estimated: with a prior, data and prior together (a factor
        # whose Gram matrix is JᵀWJ + MᵀΣp⁻¹M)
        Ra = Rw if prior is None else np.vstack([Rw, _sqrt_psd(info)])
        sv, cond, obs = _conditioning(Ra, params, n_poses=len(data), reach_m=reach)
        if prior is not None:
            alone = [i for i, k in enumerate(kept) if k in by_data]
            if alone:
                _, c_data, o_data = _conditioning(Rw[:, alone], [params[i] for i in alone], n_poses=len(data),
                                                  reach_m=reach)
                data_only = {"parameters": [params[i].name for i in alone], "condition_number": c_data,
                             "observability": o_data}
    sources = ["data" if np.isnan(sd_prior[k]) else "data + prior" for k in kept]
    values = parameter_values(current, params)
    if from_prior:  # not estimated: the prior's value (the model's) and the prior's covariance
        order = sorted(kept + from_prior)
        pos = {k: i for i, k in enumerate(order)}
        full = np.zeros((len(order), len(order)))
        est = [pos[k] for k in kept]
        full[np.ix_(est, est)] = cov
        fp = [pos[k] for k in from_prior]
        full[np.ix_(fp, fp)] = prior.covariance_of([cands[k] for k in from_prior])
        cov = full
        params = [cands[k] for k in order]
        sources = ["prior" if k in from_prior else sources[kept.index(k)] for k in order]
        steps = np.array([0.0 if k in from_prior else steps[kept.index(k)] for k in order])
        values = parameter_values(current, params)
        kept = order
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    rn = np.linalg.norm(rp, axis=1)
    outliers = tuple(int(i) for i in np.nonzero((z > outlier_sigma) | (w_row < 0.5))[0])
    success = status > 0
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
        singular_values=sv,
        condition_number=cond,
        observability=obs,
        residuals_m=rp,
        residuals_rad=rr,
        rms_m=float(np.sqrt(np.mean(rn**2))),
        max_m=float(rn.max(initial=0.0)),
        rms_rad=float(np.sqrt(np.mean(np.sum(rr[has_rot] ** 2, axis=1)))) if np.any(has_rot) else 0.0,
        chi2=chi2,
        dof=dof,
        sigma_scale=sigma_scale,
        row_weights=w_row,
        outliers=outliers,
        success=success,
        status=status,
        message=TERMINATION_MESSAGES[status],
        iterations=it,
        nfev=nfev,
        cost_history=tuple(history),
        registration=registration,
        notes=tuple(notes),
        settings=dict(sigma_m=sigma_m, sigma_rad=sigma_rot, loss=loss, f_scale=f_scale, gains=gains,
                      rank_rtol=rank_rtol, fixed=list(fixed)),
        sources=tuple(sources),
        prior_std_errors=None if prior is None else np.array([sd_prior[k] for k in kept]),
        chi2_prior=chi2_prior,
        data_only=data_only,
    )


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
        pts = [j.point for j in model.joints] + [model.home[:3]]
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
        return {"O1_borm_menq": 0.0, "O2_inverse_condition": 0.0, "O3_min_singular": 0.0,
                "O4_noise_amplification": 0.0, "condition_number_physical": float("inf")}
    return {
        "O1_borm_menq": float(np.exp(np.mean(np.log(s))) / math.sqrt(n_poses)),
        "O2_inverse_condition": float(s[-1] / s[0]),
        "O3_min_singular": float(s[-1]),
        "O4_noise_amplification": float(s[-1] ** 2 / s[0]),
        "condition_number_physical": float(s[0] / s[-1]),
    }
