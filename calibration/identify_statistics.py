"""What the identification's answer is worth (:func:`calibration.identify.identify`, step 5):
the covariance ``s²(JᵀWJ + MᵀΣp⁻¹M)⁻¹`` and its growth (:func:`excess_scale`), the χ² test
(:func:`_consistency`), the linearised cross-validation, conditioning and observability
indices, the held parameters' covariance at their prior width (:func:`held_covariance`), and
what a prior made from a result needs (:func:`held_relations`, :func:`drift_scale`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .identification import (
    INSTRUMENT_SIGMA_M,
    IdentificationResult,
    Measurements,
    Prior,
)
from .identify_problem import _evaluate, _Linearisation, _linearise, _Problem, _problem, _sample, _stack
from .identify_selection import (
    DETERMINED_M,
    DETERMINED_RAD,
    RESELECT_ROWS,
    _Selection,
    _sqrt_psd,
    _weak_bound,
    select_identifiable,
)
from .model import KinematicModel
from .parameters import Parameter, candidate_parameters


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


# How far a held parameter is taken to be from the model's value, for what it moves that the
# data did not see (the tool's orientation after a position-only fit, issue 25): held is not
# known to be zero. A parameter held as ``weak`` at the weak threshold: the data could not
# determine it better than that, and the bound does not claim to. One the data cannot see at all
# (a tool's rotation on its flange, the last joint's zero under a reflector on its axis, a length
# another parameter moves the same way) at what a robot and its tool's mounting are taken to
# deviate from their drawing: 1 mm, 0.2 deg (a joint mastered to about 0.1 deg; the simulated
# arms' joint offsets are drawn at 0.1 deg). The weak threshold for those too made a UR10's
# orientation bound 11 deg where the errors were 0.3-0.7 deg (27 times): right, and useless.
HELD_SD_M = 1e-3
HELD_SD_RAD = math.radians(0.2)


def _held_sd(p: Parameter, category: str) -> float:
    """The prior standard deviation (SI) of held parameter ``p`` (:data:`HELD_SD_M`,
    :data:`HELD_SD_RAD`; a ``weak`` one's, the weak threshold)."""
    if category == "weak":
        return DETERMINED_M if p.kind == "length" else DETERMINED_RAD
    return HELD_SD_M if p.kind == "length" else HELD_SD_RAD


def held_covariance(
    current: KinematicModel, prob: _Problem, cands: list[Parameter], sel: _Selection, scale: float
) -> dict | None:
    """The covariance over the freed parameters and the held geometric ones, each held one with a
    prior of :data:`HELD_SD_M` / :data:`HELD_SD_RAD` about the model's value: ``((JᵀWJ) / scale²
    + Σh⁻¹)⁻¹``, ``scale`` the growth of the freed ones' covariance (``sigma_scale`` times
    ``model_error_scale``). Along what the data see it is the freed parameters' covariance; along
    what they do not (a held tool rotation, a joint offset on the reflector's axis) the prior's
    width, moved into whatever the data see with it. ``{"names", "prior_sd", "matrix"}`` SI, for
    the uncertainty of what the data did not measure (:func:`calibration.uncertainty.
    orientation_covariance`); None when nothing geometric is held."""
    category = {u.name: u.category for u in sel.dropped}
    held = [k for k, p in enumerate(cands) if p.name in category and _weak_bound(p) is not None]
    if not held:
        return None
    idx = list(sel.kept) + held
    sub, share = _sample(prob, RESELECT_ROWS)
    G = _linearise(current, sub, [cands[k] for k in idx]).gram / share / scale**2
    prior_sd = np.array([np.inf] * len(sel.kept) + [_held_sd(cands[k], category[cands[k].name]) for k in held])
    A = G + np.diag(1.0 / prior_sd**2)
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    cov = np.linalg.pinv(A / np.outer(d, d), rcond=1e-14, hermitian=True) / np.outer(d, d)
    return {"names": [cands[k].name for k in idx], "prior_sd": prior_sd.tolist(), "matrix": cov}


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


def chi2_upper_tail(chi2: float, dof: float) -> float:
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
    out: dict[str, Any] = {
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
        assert Rw is not None  # asked for (factor), and there are parameters
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


def _conditioning(R: np.ndarray, params: list[Parameter], *, n_poses: int, reach_m: float) -> tuple:
    """Singular values, condition number (columns scaled to unit norm) and observability indices
    of a factor ``R`` whose Gram matrix is the estimate's information (up to the noise scale)."""
    sv = np.linalg.svd(R, compute_uv=False)
    norms = np.linalg.norm(R, axis=0)
    svn = np.linalg.svd(R / np.where(norms > 0, norms, 1.0), compute_uv=False)
    cond = float(svn[0] / svn[-1]) if svn[-1] > 0 else float("inf")
    return sv, cond, observability_indices(R, params, n_poses=n_poses, reach_m=reach_m)


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
