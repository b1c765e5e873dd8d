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
   order of preference; a column that adds (numerically) nothing to the columns before it is
   not freed, and the report names what it duplicates.
5. Levenberg–Marquardt with Marquardt's scaling (the damping is proportional to diag(JᵀWJ)),
   analytic Jacobian (:mod:`calibration.jacobian`), optional robust loss by iteratively
   reweighted rows (a bumped reflector does not ruin the fit; the rows it down-weights are
   named).
6. Covariance ``s²(JᵀWJ)⁻¹`` (book eq. 4.54/4.70 with W = Σ⁻¹), ``s² = max(1, χ²/dof)``: if the
   residuals are larger than the stated uncertainty, the stated uncertainty was optimistic and
   the covariance grows accordingly; it never shrinks below what the instrument states.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .conventions import hayati_for_parallel_axes, mdh_to_dh
from .jacobian import Prediction, jacobian_from_walk, record_keys, world_points
from .kinematics import walk
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
    ``row`` (N,) row numbers in the source file, for reports."""

    q: np.ndarray
    p_world: np.ndarray
    quat: np.ndarray | None = None
    target: np.ndarray | None = None
    sigma: np.ndarray | None = None
    pose_id: np.ndarray | None = None
    row: np.ndarray | None = None

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
                            pick(self.pose_id), self.row[idx])


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior knowledge of parameters (book §4.3.2, minimum-variance estimation): the model passed
    to :func:`identify` is the prior mean, and ``covariance`` (P, P) SI the uncertainty of the
    parameters ``names`` about it (typically the previous calibration's covariance, inflated for
    drift). Parameters without a prior are unconstrained."""

    names: tuple[str, ...]
    covariance: np.ndarray

    def information(self, params: list["Parameter"]) -> np.ndarray:
        """The prior information matrix (inverse covariance) over ``params`` (zero rows and
        columns for parameters without a prior)."""
        idx = {n: i for i, n in enumerate(self.names)}
        have = [k for k, p in enumerate(params) if p.name in idx]
        info = np.zeros((len(params), len(params)))
        if have:
            sub = np.asarray(self.covariance)[np.ix_([idx[params[k].name] for k in have], [idx[params[k].name] for k in have])]
            info[np.ix_(have, have)] = np.linalg.pinv(sub, hermitian=True)
        return info


@dataclass(frozen=True, slots=True)
class Unidentifiable:
    """A parameter the data cannot determine: ``reason`` in words, ``relation`` the freed
    parameters whose motion it duplicates, with coefficients (SI)."""

    name: str
    reason: str
    relation: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True, eq=False)
class IdentificationResult:
    """Everything :func:`identify` did. Arrays over the freed parameters are (P,) / (P, P), SI.

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
    w = walk(model, prob.data.q, record)
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
    the Jacobian (M, P) is a Fortran-ordered array made without a transposing copy."""
    wp = 1.0 / prob.sigma_pos
    r = [(rp.T * wp).reshape(-1)]
    Jt = None if Jp is None else [(Jp.transpose(2, 1, 0) * wp).reshape(Jp.shape[2], -1)]  # (P, 3N)
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


def _describe(name: str) -> str:
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


def _reason(p: Parameter, relation: list[tuple[str, float]], position_only: bool, multi_target: bool) -> str:
    n = p.name
    if not relation:
        if n.startswith("tool.r") and position_only:
            return "tool orientation is unobservable from position-only data"
        if n.startswith("target."):
            return f"{_describe(n)} has no effect on these measurements"
        return f"{_describe(n)} has no effect on these measurements"
    if n.startswith(("tool.", "home.")) and all(r[0].startswith(("target.", "tool.", "home.")) for r in relation):
        if position_only and n.startswith("tool.r"):
            return "tool orientation is unobservable from position-only data (it only moves the targets, whose offsets are identified)"
        return f"{_describe(n)} moves the measured points exactly as the target offsets do"
    top = relation[0]
    if len(relation) == 1 or abs(relation[1][1]) < 0.05 * abs(top[1]):
        return f"{_describe(n)} and {_describe(top[0])} are the same motion"
    combo = " + ".join(f"{c:+.3g}·{r}" for r, c in relation[:4])
    return f"{_describe(n)} is a combination of other parameters ({combo})"


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


def select_identifiable(
    J: np.ndarray, params: list[Parameter], *, rtol: float = 1e-6, position_only: bool, multi_target: bool = False
) -> tuple[list[int], list[Unidentifiable]]:
    """Choose the columns of the weighted Jacobian ``J`` (M, P) the data determine.

    Columns are scaled to unit norm and orthogonalised in the order given (the order of
    preference), Gram–Schmidt with re-orthogonalisation: column k is kept if its component
    orthogonal to the KEPT columns before it is at least ``rtol`` of its norm (a QR with column
    pivoting restricted to a fixed order; dropped columns never enter the basis). A dropped
    column's relation to the kept ones is solved from the triangular factor of the kept columns.
    Returns the kept indices and, for the others, the reasons.
    """
    M, P = J.shape
    if M > P:
        # Everything below works in the column space through inner products, so the triangular
        # factor R of J = QR (same Gram matrix JᵀJ = RᵀR) gives the same result at O(P³) cost.
        J = _r_factor(J)
        M = P
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    Jn = J / scale
    zero = norms <= 1e-12 * max(norms.max(initial=0.0), 1e-300)
    basis = np.zeros((M, min(M, P)))
    kept: list[int] = []
    pending: list[tuple[int, np.ndarray]] = []
    for k in range(P):
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
    dropped: list[Unidentifiable] = []
    for k, proj in pending:
        relation: list[tuple[str, float]] = []
        if proj.size:
            n_at = proj.size  # kept columns that were in the basis when k was tested
            coef = np.linalg.solve(Rk[:n_at, :n_at], proj) if n_at else np.zeros(0)
            # column_k ≈ Σ coef_j column_j (unit-scaled) -> d(param_k) ≡ Σ c_j d(param_j)
            c_si = coef * norms[k] / scale[kept[:n_at]]
            order = np.argsort(-np.abs(coef))
            relation = [(params[kept[i]].name, float(c_si[i])) for i in order if abs(coef[i]) > 1e-3]
        dropped.append(Unidentifiable(params[k].name, _reason(params[k], relation, position_only, multi_target),
                                      tuple(relation)))
    dropped.sort(key=lambda u: [p.name for p in params].index(u.name))
    return kept, dropped


# --------------------------------------------------------------------------- registration


def _register(model: KinematicModel, prob: _Problem) -> tuple[KinematicModel, dict]:
    """Try a rigid registration of the model's predictions onto the data; keep it if it fits
    better than the model's own base."""
    data = prob.data
    local = dataclasses.replace(model, base=np.zeros(6))
    w = walk(local, data.q)  # the chain in the model's base frame; one walk serves every base

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
    return (candidate if after < before else model), info


# --------------------------------------------------------------------------- the solver


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
    ``½ sᵀ Σp⁻¹ s`` for the step ``s`` away from ``model``, parameters with a prior are freed even
    where the data alone cannot determine them, and no registration is done (the prior knows
    the base).

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
    has_rot = data.has_orientation
    R_meas = quat_to_matrix(np.where(np.isfinite(data.quat), data.quat, [1, 0, 0, 0])) if data.quat is not None else None
    sigma_pos = np.where(np.isfinite(data.sigma) & (data.sigma > 0), data.sigma, sigma_m)
    sigma_rot = float(sigma_rad) if sigma_rad is not None else sigma_m / 0.1
    prob = _Problem(data, data.target, has_rot, R_meas, sigma_pos, sigma_rot, _target_rows(data.target))

    registration = None
    if register != "never" and prior is None:
        cand, registration = _register(start, prob)
        if register == "always" or registration["applied"]:
            start = cand
            registration["applied"] = True

    used_targets = tuple(sorted(set(data.target) - {None}))
    cands = candidate_parameters(start, targets=used_targets, gains=gains)
    cands = [p for p in cands if not _matches(p.name, fixed)]
    pred, rp, rr = _evaluate(start, prob, cands)
    r_start, J_cands = _stack(prob, rp, rr, pred.Jp, pred.Jr)
    position_only = not np.any(has_rot)
    kept, dropped = select_identifiable(J_cands, cands, rtol=rank_rtol, position_only=position_only,
                                        multi_target=len(used_targets) > 1)
    if prior is not None:  # a prior determines what the data alone cannot
        with_prior = set(prior.names)
        kept = sorted(set(kept) | {k for k, p in enumerate(cands) if p.name in with_prior})
        dropped = [u for u in dropped if u.name not in with_prior]
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
    if P:
        r, J = r_start, J_cands[:, kept]  # the Jacobian at the start, already computed
        del J_cands
        fresh = True  # r, J, rp, rr are those of `current`
        keys = record_keys(params)  # trials record what the Jacobian needs: if accepted, no second walk
        w_row = _robust_weights(_row_norms(prob, r), loss, f_scale)
        w = _expand_rows(prob, w_row)
        cost = 0.5 * float(np.sum(w * r**2))
        history.append(cost)
        for it in range(1, max_iter + 1):
            if np.all(w == 1.0):  # unit weights (linear loss): skip the copies
                Jw, rw = J, r
            else:
                Jw, rw = J * np.sqrt(w)[:, None], r * np.sqrt(w)
            A = Jw.T @ Jw + info
            gram = (J, w, A)  # A and what it was computed from, for the statistics
            g = Jw.T @ rw - info @ steps
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
    chi2 = float(np.sum(w * r**2))
    dof = max(n_res - P, 1)
    sigma_scale = math.sqrt(max(1.0, chi2 / dof))
    cov = np.zeros((P, P))
    sv = np.zeros(0)
    cond = float("inf") if P == 0 else 0.0
    obs: dict = {}
    if P:
        unit = bool(np.all(w == 1.0))
        Jw = J if unit else J * np.sqrt(w)[:, None]
        # The triangular factor of Jw = QR has the same singular values and Gram matrix: one QR
        # of the tall matrix, then small P x P decompositions.
        Rw = _r_factor(Jw) if Jw.shape[0] > P else Jw
        sv = np.linalg.svd(Rw, compute_uv=False)
        # Σ = s² (JᵀWJ + Σp⁻¹)⁻¹ (book eq. 4.54 / 4.70); pseudo-inverse on the column-scaled
        # matrix for numerical safety.
        if gram is not None and gram[0] is J and unit and np.all(gram[1] == 1.0):
            A = gram[2]  # the last iteration's: the same Jacobian, unit weights, the same prior
        else:
            A = Jw.T @ Jw + info
        dscale = np.sqrt(np.maximum(np.diag(A), 1e-300))
        cov = np.linalg.pinv(A / np.outer(dscale, dscale), rcond=1e-14, hermitian=True) / np.outer(dscale, dscale)
        cov *= sigma_scale**2
        norms = np.linalg.norm(Jw, axis=0)
        svn = np.linalg.svd(Rw / np.where(norms > 0, norms, 1.0), compute_uv=False)
        cond = float(svn[0] / svn[-1]) if svn[-1] > 0 else float("inf")
        obs = observability_indices(Rw, params, n_poses=len(data), reach_m=_reach(start))
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    rn = np.linalg.norm(rp, axis=1)
    outliers = tuple(int(i) for i in np.nonzero((z > outlier_sigma) | (w_row < 0.5))[0])
    success = status > 0
    return IdentificationResult(
        model=dataclasses.replace(current, metadata={}),
        start_model=start,
        params=tuple(params),
        values=parameter_values(current, params),
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
    )


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
