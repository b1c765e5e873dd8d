"""Which parameters the data determine (:func:`calibration.identify.identify`, steps 3 and 6):
the candidates (:func:`_candidates`), the Gram-Schmidt selection in an order of preference
(:func:`select_identifiable`, :func:`_choose`), the parameters held as ``weak``
(:func:`_hold_weak`), the selection again at the answer (:func:`_reselect`), and the merging of
the parameters a prior alone determines (:func:`_merge_prior`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from .identification import (
    Measurements,
    Prior,
    Unidentifiable,
)
from .identify_problem import _linearise, _Problem, _sample
from .model import KinematicModel
from .parameters import Parameter, candidate_parameters
from .report import explain

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
    # numpy's stubs type every mode's answer as the (Q, R) pair; mode "r" returns R alone
    if M <= 2 * block_rows:
        return cast(np.ndarray, np.linalg.qr(J, mode="r"))
    blocks = [cast(np.ndarray, np.linalg.qr(J[a : a + block_rows], mode="r")) for a in range(0, M, block_rows)]
    return cast(np.ndarray, np.linalg.qr(np.vstack(blocks), mode="r"))


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
    held_anyway: Sequence[int] = (),
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
        assert prior is not None  # only a prior gives parameters to take from it
        full[np.ix_(fp, fp)] = prior.covariance_of([cands[k] for k in sel.from_prior])
        cov = full
        params = [cands[k] for k in order]
        sources = ["prior" if k in sel.from_prior else sources[kept.index(k)] for k in order]
        steps = np.array([0.0 if k in sel.from_prior else steps[kept.index(k)] for k in order])
        kept = order
    prior_sd = None if prior is None else np.array([sel.sd_prior[k] for k in kept])
    return params, steps, cov, sources, prior_sd


# A parameter with a prior is "seen" by the data when its prior standard error, as a change of the
# parameter, moves the measurements by at least this much (root sum of squares over all residuals,
# in noise standard deviations): below it, the data would shrink its variance by less than 1 %.
SEEN_BY_DATA = 0.1


def _seen_by_data(J: np.ndarray, sd_prior: np.ndarray) -> np.ndarray:
    """(P,) True where the weighted Jacobian's column times the prior standard error reaches
    :data:`SEEN_BY_DATA` (False where there is no prior)."""
    with np.errstate(invalid="ignore"):
        return np.nan_to_num(np.linalg.norm(J, axis=0) * sd_prior) >= SEEN_BY_DATA


def _sqrt_psd(M: np.ndarray) -> np.ndarray:
    """A factor F with FᵀF = M for a symmetric positive semi-definite M."""
    e, V = np.linalg.eigh(M)
    return np.sqrt(np.maximum(e, 0.0))[:, None] * V.T


def _matches(name: str, patterns) -> bool:
    return any(name == p or (p.endswith("*") and name.startswith(p[:-1])) for p in patterns)
