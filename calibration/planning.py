"""Observation planning: which configurations to measure, and how many (book §4.5).

The book leaves the synthesis of an optimal observation strategy open (§4.5, "as yet an
unanswered research issue") and offers only measures of a strategy's quality: the condition
number (eq. 4.174), the observability index O1 of Borm & Menq (eq. 4.193-4.194) and, in the
literature it cites, O3 (minimum singular value) and O4 (noise amplification). Since then the
field plans poses as an *optimal experiment design*: choose, from many feasible candidate
configurations, the K that maximise a scalar function of the information matrix
``M = Σ_k J_kᵀ W J_k`` of the identifiable parameters (Daney et al. 2005; Sun & Hollerbach
2008). This module does that:

1. Candidates: given, or drawn uniformly within the joint limits and kept when the measured
   target lies in the instrument's volume (:class:`Volume`) and can be seen
   (:class:`LineOfSight`).
2. The identifiable parameters: the same candidate set and the same selection as
   :func:`calibration.identify.identify` (:func:`calibration.identify.select_identifiable`),
   applied to the Jacobian stacked over all candidates.
3. A greedy start (D-optimal, the determinant lemma ``det(M + JᵢᵀJᵢ) = det M · det(I + Jᵢ M⁻¹ Jᵢᵀ)``
   scores every candidate with a 3×3 determinant), then an exchange (Fedorov's, one design
   point at a time): remove a chosen pose (Woodbury: ``(M − JⱼᵀJⱼ)⁻¹`` from ``M⁻¹``) and put in
   the candidate that improves the criterion most, until no swap helps.
4. The predicted accuracy: the parameters' covariance ``Σ = (JᵀWJ)⁻¹ = σ²(JᵀJ)⁻¹`` (book eq.
   4.54 with W = I/σ²) propagated to evaluation configurations, ``C_e = J_e Σ J_eᵀ``.

Criteria (all on the information matrix with angle columns scaled by 1/reach, as
:func:`calibration.identify.observability_indices` does, so that they do not depend on units):

- ``I`` (default): minimise the mean predicted position variance over the evaluation
  configurations, ``trace(M⁻¹ W_e)`` (I- or V-optimal design): directly the predicted RMS
  accuracy where the robot will work, which is what a calibration is for.
- ``D``: ``log det M``. Invariant to any rescaling of the parameters, and it minimises the
  volume of the parameters' confidence ellipsoid; it weighs every parameter direction alike,
  also those that hardly move the measured point in the working space.
- ``O1``: Borm & Menq's index ``det(M)^(1/2L) / √m``. At a fixed number of poses it is a monotone
  function of ``det M``, so maximising it is the D-optimal design; its value is reported as O1.
- ``O3``: the minimum singular value ``√λmin`` (E-optimal).
- ``O4``: the noise amplification index ``λmin / √λmax``.
- ``condition``: minimise ``√(λmax/λmin)``.

The greedy start is D-optimal for every criterion (the eigenvalue criteria cannot rank
candidates while the design is still rank deficient); the exchange then optimises the chosen
criterion. D, O1 and I score every possible swap exactly (rank-3 updates of ``M⁻¹``); for the
eigenvalue criteria each exchange screens the candidates by their D gain and by how much they
add along the weakest direction of the design, and accepts a swap on the exact criterion.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .identification import INSTRUMENT_SIGMA_M
from .identify import Unidentifiable, _reach, complete_form, observability_indices, select_identifiable
from .jacobian import predict
from .kinematics import program, walk
from .model import KinematicModel
from .parameters import Parameter, candidate_parameters
from .simulate import random_configurations

CRITERIA = ("D", "O1", "O3", "O4", "condition", "I")
STATISTICS = ("rms", "p95")


# --------------------------------------------------------------------------- where and what can be measured


@dataclass(frozen=True, eq=False)
class Volume:
    """Where the instrument can measure, in the world (instrument) frame, m: a box ``lo``..``hi``
    or a spherical shell ``inner_radius <= |p - center| <= radius`` (a laser tracker has a
    minimum range). Build with :meth:`box` or :meth:`sphere`."""

    kind: str
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    center: np.ndarray | None = None
    radius: float = 0.0
    inner_radius: float = 0.0

    def __post_init__(self):
        if self.kind == "box":
            lo, hi = np.asarray(self.lo, float).reshape(3), np.asarray(self.hi, float).reshape(3)
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
                raise ValueError(f"a box volume needs finite corners with lo < hi on every axis; got {lo}, {hi}")
            object.__setattr__(self, "lo", lo)
            object.__setattr__(self, "hi", hi)
        elif self.kind == "sphere":
            c = np.asarray(self.center, float).reshape(3)
            if not (np.all(np.isfinite(c)) and self.radius > 0 and 0 <= self.inner_radius < self.radius):
                raise ValueError(
                    "a sphere volume needs a finite center and 0 <= inner_radius < radius; "
                    f"got {c}, {self.inner_radius}, {self.radius}"
                )
            object.__setattr__(self, "center", c)
        else:
            raise ValueError(f"`kind` must be box or sphere; got {self.kind!r}")

    @classmethod
    def box(cls, lo, hi) -> Volume:
        return cls("box", lo=lo, hi=hi)

    @classmethod
    def sphere(cls, center, radius: float, inner_radius: float = 0.0) -> Volume:
        return cls("sphere", center=center, radius=float(radius), inner_radius=float(inner_radius))

    def contains(self, p_world: np.ndarray) -> np.ndarray:
        """(N,) True where the points ``p_world`` (N, 3) m lie inside."""
        p = np.atleast_2d(np.asarray(p_world, float))
        if self.kind == "box":
            return np.all((p >= self.lo) & (p <= self.hi), axis=1)
        r = np.linalg.norm(p - self.center, axis=1)
        return (r <= self.radius) & (r >= self.inner_radius)


@dataclass(frozen=True, eq=False)
class LineOfSight:
    """When the instrument can see a target (world frame, m and rad).

    - Orientation: the target's normal ``normal_tool`` (tool frame; a reflector faces along the
      tool z axis by default) must point towards the instrument at ``instrument_m`` within the
      acceptance half-angle ``cone_rad`` (about 30° for a 1.5" SMR). ``None``: not tested.
    - Occlusion: the beam from the instrument to the target must stay ``clearance_m`` away from
      the robot, modelled as its kinematic stick figure (the polyline through the origins of the
      chain's elementary frames, from the base to the flange: for ``dh`` models the physical link
      lengths and offsets), except for the last ``near_target_m`` of the beam, where the beam
      reaches the target carried by the flange. ``None``: not tested.
    """

    instrument_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    normal_tool: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    cone_rad: float | None = None
    clearance_m: float | None = None
    near_target_m: float = 0.1

    def __post_init__(self):
        inst = np.asarray(self.instrument_m, float).reshape(3)
        n = np.asarray(self.normal_tool, float).reshape(3)
        if not (np.all(np.isfinite(inst)) and np.all(np.isfinite(n)) and np.linalg.norm(n) > 0):
            raise ValueError("`instrument_m` must be finite and `normal_tool` a finite non-zero vector")
        if self.cone_rad is not None and not 0 < self.cone_rad <= math.pi:
            raise ValueError(f"`cone_rad` must be in (0, pi]; got {self.cone_rad}")
        if self.clearance_m is not None and not self.clearance_m >= 0:
            raise ValueError(f"`clearance_m` must be >= 0; got {self.clearance_m}")
        if not self.near_target_m >= 0:
            raise ValueError(f"`near_target_m` must be >= 0; got {self.near_target_m}")
        object.__setattr__(self, "instrument_m", inst)
        object.__setattr__(self, "normal_tool", n / np.linalg.norm(n))


def stick_figure(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """World positions (N, S, 3) m of the origins of the chain's elementary frames, base to flange
    (the tool transform excluded), at readings ``q`` (N, n): consecutive points are the links."""
    ops = program(model)
    # the ".link" marks (where compliance's lumped masses sit) repeat an origin already listed
    keys = [op.key for op in ops if op.key is not None and op.key != "tool" and not op.key.endswith(".link")]
    w = walk(model, q, set(keys))
    pts = [w.axes[k][1] if k in w.axes else w.frames[k][1] for k in keys]
    return np.stack(pts, axis=1)


def segment_distance(
    a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray, *, eps: float = 1e-18, parallel_rtol: float = 1e-12
) -> np.ndarray:
    """Shortest distance between segments ``a0-a1`` and ``b0-b1`` (..., 3), broadcast: (...,).

    The closest points of two segments (Ericson, *Real-Time Collision Detection*, §5.1.9),
    clamped to both segments; segments shorter than √eps count as points, and (nearly) parallel
    ones (``sin² < parallel_rtol``) start from s = 0, which is as good as any point there."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a = np.sum(d1 * d1, axis=-1)
    e = np.sum(d2 * d2, axis=-1)
    f = np.sum(d2 * r, axis=-1)
    c = np.sum(d1 * r, axis=-1)
    b = np.sum(d1 * d2, axis=-1)
    a_ok, e_ok = a > eps, e > eps
    sa, se = np.where(a_ok, a, 1.0), np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    general = denom > parallel_rtol * a * e
    s = np.where(general, np.clip((b * f - c * e) / np.where(general, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / se
    s = np.where(t < 0, np.clip(-c / sa, 0, 1), np.where(t > 1, np.clip((b - c) / sa, 0, 1), s))
    t = np.clip(t, 0, 1)
    # one or both segments degenerate to a point
    s = np.where(~a_ok, 0.0, np.where(~e_ok, np.clip(-c / sa, 0, 1), s))
    t = np.where(~e_ok, 0.0, np.where(~a_ok, np.clip(f / se, 0, 1), t))
    return np.linalg.norm((a0 + d1 * s[..., None]) - (b0 + d2 * t[..., None]), axis=-1)


def visible(model: KinematicModel, q: np.ndarray, sight: LineOfSight, target: str | None = None) -> np.ndarray:
    """(N,) True where the instrument sees ``target`` at readings ``q`` (N, n) (see :class:`LineOfSight`)."""
    w = walk(model, q)
    p = w.p + w.R @ model.target(target)
    beam = sight.instrument_m - p
    length = np.linalg.norm(beam, axis=1)
    ok = length > 0
    if sight.cone_rad is not None:
        n_world = w.R @ sight.normal_tool
        cos = np.sum(n_world * beam, axis=1) / np.where(ok, length, 1.0)
        ok &= cos >= math.cos(sight.cone_rad)
    if sight.clearance_m is not None:
        u = beam / np.where(length > 0, length, 1.0)[:, None]
        end = p + u * np.minimum(sight.near_target_m, length)[:, None]  # the beam stops short of the target
        pts = stick_figure(model, q)
        d = segment_distance(sight.instrument_m[None, None, :], end[:, None, :], pts[:, :-1], pts[:, 1:])
        ok &= np.all(d >= sight.clearance_m, axis=1)
    return ok


def feasible(
    model: KinematicModel,
    q: np.ndarray,
    *,
    targets: tuple[str | None, ...] = (None,),
    volume: Volume | None = None,
    sight: LineOfSight | None = None,
) -> np.ndarray:
    """(N,) True where every target lies in ``volume`` and is ``visible``, and ``q`` is within the
    joint limits."""
    q = np.atleast_2d(np.asarray(q, float))
    lim = model.joint_limits
    ok = np.all((q >= lim[:, 0]) & (q <= lim[:, 1]), axis=1)
    for t in targets:
        if volume is not None:
            w = walk(model, q)
            ok &= volume.contains(w.p + w.R @ model.target(t))
        if sight is not None:
            ok &= visible(model, q, sight, t)
    return ok


def generate_candidates(
    model: KinematicModel,
    count: int,
    rng: np.random.Generator,
    *,
    targets: tuple[str | None, ...] = (None,),
    volume: Volume | None = None,
    sight: LineOfSight | None = None,
    limits: np.ndarray | None = None,
    max_draws: int | None = None,
) -> np.ndarray:
    """Up to ``count`` candidate readings (M, n): uniform within ``limits`` (default the joint
    limits, revolute joints within ±π; :func:`calibration.simulate.random_configurations`), kept
    when :func:`feasible`. Draws at most ``max_draws`` (default ``200·count``) configurations;
    returns fewer than ``count`` when the constraints accept too few of them, and raises
    ``ValueError`` when they accept none."""
    if count < 1:
        raise ValueError(f"`count` must be at least 1; got {count}")
    max_draws = 200 * count if max_draws is None else int(max_draws)
    batch = max(1000, 2 * count)
    kept: list[np.ndarray] = []
    n_kept = drawn = 0
    while n_kept < count and drawn < max_draws:
        n = min(batch, max_draws - drawn)
        q = random_configurations(model, n, rng, limits=limits)
        drawn += n
        q = q[feasible(model, q, targets=targets, volume=volume, sight=sight)]
        kept.append(q)
        n_kept += len(q)
    out = np.concatenate(kept)[:count] if kept else np.zeros((0, model.n_joints))
    if len(out) == 0:
        raise ValueError(
            f"none of {drawn} random configurations puts the target(s) inside the volume and in sight "
            "of the instrument: check the volume, the instrument position and the acceptance cone"
        )
    return out


# --------------------------------------------------------------------------- the information of one pose


@dataclass(frozen=True, eq=False)
class _Design:
    """The planning problem in the working space: ``J`` (C, r, P) = ``J_SI · S / σ`` per candidate
    (r = 3 per target), ``S`` (P,) the column scaling (1/reach for angles)."""

    model: KinematicModel
    q: np.ndarray
    params: tuple[Parameter, ...]
    unidentifiable: tuple[Unidentifiable, ...]
    J: np.ndarray
    S: np.ndarray
    sigma_m: float
    targets: tuple[str | None, ...]
    reach_m: float


def identification_form(model: KinematicModel, *, hayati: bool = True) -> KinematicModel:
    """The model in the form :func:`calibration.identify.identify` identifies it
    (:func:`calibration.identify.complete_form`: ``mdh`` as ``dh``, parallel-axis ``dh`` links in
    Hayati's form, ``poe`` where ``dh`` cannot be complete): the plan predicts the accuracy of the
    model identification will fit."""
    return complete_form(model, hayati=hayati)[0]


def _jacobians(model: KinematicModel, q: np.ndarray, params: list[Parameter], targets) -> np.ndarray:
    """SI position Jacobians (N, 3·T, P) of every target at readings ``q``."""
    blocks = []
    for t in targets:
        names = np.array([t] * len(q), dtype=object)
        Jp = predict(model, q, model.target(t), params, names).Jp
        assert Jp is not None  # asked with params
        blocks.append(Jp)
    return np.concatenate(blocks, axis=1)


def _prepare(model, candidates, *, targets, sigma_m, gains, fixed, rank_rtol, hayati) -> _Design:
    if not sigma_m > 0:
        raise ValueError(f"`sigma_m` must be positive; got {sigma_m}")
    targets = tuple(targets) if targets else (None,)
    for t in targets:
        model.target(t)  # KeyError naming an unknown target
    work = identification_form(model, hayati=hayati)
    q = np.atleast_2d(np.asarray(candidates, float))
    if q.ndim != 2 or q.shape[1] != model.n_joints or len(q) == 0:
        raise ValueError(f"`candidates` must have shape (C, {model.n_joints}) with C >= 1; got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("`candidates` must be finite")
    used = tuple(sorted({t for t in targets if t is not None}))
    cands = candidate_parameters(work, targets=used, gains=gains)
    cands = [p for p in cands if not any(p.name == f or (f.endswith("*") and p.name.startswith(f[:-1])) for f in fixed)]
    J_si = _jacobians(work, q, cands, targets)
    C, r, _ = J_si.shape
    kept, dropped = select_identifiable(
        (J_si / sigma_m).reshape(C * r, -1), cands, rtol=rank_rtol, position_only=True, multi_target=len(used) > 1
    )
    params = tuple(cands[k] for k in kept)
    reach = _reach(work)
    S = np.array([1.0 / reach if p.kind == "angle" else 1.0 for p in params])
    J = J_si[:, :, kept] * S / sigma_m
    return _Design(work, q, params, tuple(dropped), J, S, float(sigma_m), targets, reach)


# --------------------------------------------------------------------------- criteria


def _logdet(M: np.ndarray) -> np.ndarray:
    """log det of a stack of symmetric matrices (..., k, k); -inf where not positive definite.
    3x3 blocks (one target per pose) by the closed form, which is much faster than LAPACK."""
    if M.shape[-1] == 3:
        d = (
            M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
            - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
            + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0])
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(d > 0, np.log(np.where(d > 0, d, 1.0)), -np.inf)
    sign, ld = np.linalg.slogdet(M)
    return np.where(sign > 0, ld, -np.inf)


def _top(values: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
    """The (at most) ``n`` entries of ``idx`` with the largest ``values``, unordered."""
    if len(idx) <= n:
        return idx
    return idx[np.argpartition(-values[idx], n)[:n]]


def _scores(Ms: np.ndarray, criterion: str, W: np.ndarray | None) -> np.ndarray:
    """The criterion to MAXIMISE for a stack of information matrices (..., P, P)."""
    if criterion in ("D", "O1"):
        return _logdet(Ms)
    if criterion == "I":
        assert W is not None, "criterion I weighs by W"
        tr = np.trace(np.linalg.solve(Ms, np.broadcast_to(W, Ms.shape)), axis1=-2, axis2=-1)
        return np.where(np.isfinite(tr) & (tr > 0), -tr, -np.inf)
    lam = np.linalg.eigvalsh(Ms)
    lmin, lmax = np.maximum(lam[..., 0], 0.0), lam[..., -1]
    if criterion == "O3":
        return np.sqrt(lmin)
    if criterion == "O4":
        return lmin / np.sqrt(np.maximum(lmax, 1e-300))
    return np.where(lmin > 0, -np.sqrt(lmax / np.where(lmin > 0, lmin, 1.0)), -np.inf)  # condition


def criterion_value(M: np.ndarray, criterion: str, *, n_rows: int, W: np.ndarray | None = None) -> float:
    """The criterion's value as reported (not negated): ``D`` log det M; ``O1`` det(M)^(1/2P)/√m
    (book eq. 4.194, m = ``n_rows`` measured points); ``O3`` √λmin; ``O4`` λmin/√λmax;
    ``condition`` √(λmax/λmin); ``I`` √trace(M⁻¹W) m, the predicted RMS position error."""
    P = M.shape[0]
    if criterion == "D":
        return float(_logdet(M))
    if criterion == "O1":
        ld = float(_logdet(M))
        return 0.0 if not math.isfinite(ld) else math.exp(ld / (2 * P)) / math.sqrt(n_rows)
    if criterion == "I":
        assert W is not None, "criterion I weighs by W"
        try:
            return math.sqrt(max(float(np.trace(np.linalg.solve(M, W))), 0.0))
        except np.linalg.LinAlgError:
            return float("inf")
    s = float(_scores(M, criterion, W))
    return -s if criterion == "condition" else s


# --------------------------------------------------------------------------- greedy and exchange


def _inv(M: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.diag(M))
    return np.linalg.inv(M / np.outer(d, d)) / np.outer(d, d)


def _add_gain(J: np.ndarray, Mi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every candidate: ``G = J M⁻¹`` (C, r, P), ``A = J M⁻¹ Jᵀ`` (C, r, r) and the D gain of
    adding it, ``log det(I + A)`` (the matrix determinant lemma)."""
    C, r, P = J.shape
    G = (J.reshape(C * r, P) @ Mi).reshape(C, r, P)
    A = G @ np.swapaxes(J, 1, 2)
    return G, A, _logdet(np.eye(r) + A)


def _greedy(J: np.ndarray, k: int, ridge: np.ndarray, on_step=None) -> tuple[list[int], np.ndarray]:
    """D-optimal greedy: add, k times, the candidate with the largest ``log det(I + Jᵢ M⁻¹ Jᵢᵀ)``.
    ``M`` starts at ``diag(ridge)``, a tiny regularisation that lets the first picks be ranked.
    ``on_step(chosen, M)`` is called after each pick; when it returns True the greedy stops early.
    Returns the picks and ``M`` (ridge included)."""
    M = np.diag(ridge)
    free = np.ones(len(J), bool)
    chosen: list[int] = []
    for _ in range(k):
        _, _, gain = _add_gain(J, _inv(M))
        gain[~free] = -np.inf
        i = int(np.argmax(gain))
        chosen.append(i)
        free[i] = False
        M = M + J[i].T @ J[i]
        if on_step is not None and on_step(chosen, M):
            break
    return chosen, M


def _exchange(
    J: np.ndarray,
    chosen: list[int],
    ridge: np.ndarray,
    criterion: str,
    W: np.ndarray | None,
    *,
    max_sweeps: int,
    screen: int,
    tol: float,
) -> tuple[list[int], int, int]:
    """Exchange (Fedorov; one design point at a time): for each chosen pose j, the best candidate
    to replace it; swap when the criterion improves by more than ``tol`` (log det units for D and
    O1, relative for the others). Sweeps until a sweep swaps nothing. Returns the design, the
    number of swaps and of sweeps.

    D, O1 and I score every candidate exactly by rank-3 updates (:func:`_downdate`,
    :func:`_swap_trace`); the eigenvalue criteria screen ``screen`` candidates by their D gain and
    ``screen`` by what they add along the design's weakest direction, then score those exactly."""
    chosen = list(chosen)
    C, r, _ = J.shape
    in_design = np.zeros(C, bool)
    in_design[chosen] = True
    M = np.diag(ridge) + sum(J[i].T @ J[i] for i in chosen)
    swaps = sweeps = 0
    eye = np.eye(r)
    use_trace = criterion == "I"
    st = _exchange_state(J, M, W, use_trace)
    for sweeps in range(1, max_sweeps + 1):
        swapped = False
        for pos in range(len(chosen)):
            j = chosen[pos]
            Sj = eye - st.A[j]
            if np.linalg.det(Sj) <= 1e-12:
                continue  # j alone carries a direction: removing it would lose rank
            Sji = np.linalg.inv(Sj)
            allowed = ~in_design
            if not np.any(allowed):
                return chosen, swaps, sweeps
            i, better = _best_swap(J, st, j, Sj, Sji, allowed, criterion, W, screen=screen, tol=tol)
            if better:
                chosen[pos] = i
                in_design[j], in_design[i] = False, True
                st = _exchange_state(J, st.M - J[j].T @ J[j] + J[i].T @ J[i], W, use_trace)
                swaps += 1
                swapped = True
        if not swapped:
            break
    return chosen, swaps, sweeps


@dataclass(frozen=True, eq=False)
class _ExchangeState:
    """The design's information ``M`` (P, P) during :func:`_exchange`, its inverse ``Mi``, and per
    candidate i ``Gᵢ = Jᵢ M⁻¹`` (C, r, P) and ``Aᵢ = Jᵢ M⁻¹ Jᵢᵀ`` (C, r, r); for the I criterion
    also ``GWᵢ = Gᵢ W`` and ``Hᵢ = Gᵢ W Gᵢᵀ`` (else None)."""

    M: np.ndarray
    Mi: np.ndarray
    G: np.ndarray
    A: np.ndarray
    GW: np.ndarray | None
    H: np.ndarray | None


def _exchange_state(J: np.ndarray, M: np.ndarray, W: np.ndarray | None, use_trace: bool) -> _ExchangeState:
    """:class:`_ExchangeState` of the design ``M``: recomputed exactly after each accepted swap
    only (no drift)."""
    C, r, P = J.shape
    Mi = _inv(M)
    G, A, _ = _add_gain(J, Mi)
    if not use_trace:
        return _ExchangeState(M, Mi, G, A, None, None)
    assert W is not None  # the I criterion's weight
    GW = (G.reshape(C * r, P) @ W).reshape(C, r, P)
    return _ExchangeState(M, Mi, G, A, GW, GW @ np.swapaxes(G, 1, 2))


def _best_swap(
    J: np.ndarray,
    st: _ExchangeState,
    j: int,
    Sj: np.ndarray,
    Sji: np.ndarray,
    allowed: np.ndarray,
    criterion: str,
    W: np.ndarray | None,
    *,
    screen: int,
    tol: float,
) -> tuple[int, bool]:
    """The best candidate i (among ``allowed``) to replace the design's pose j, and whether the
    swap improves the criterion by more than ``tol``. D and O1: the D gain ``log det(I + Aᵢ⁻ʲ)``
    of i in against j's (Aᵢ⁻ʲ from :func:`_downdate`); I: ``trace(M'⁻¹W)`` with j out and i in
    (:func:`_swap_trace`); the eigenvalue criteria: ``screen`` candidates by their D gain and
    ``screen`` by what they add along the weakest direction of ``M − JⱼᵀJⱼ``, scored exactly."""
    eye = np.eye(J.shape[1])
    B, A_minus = _downdate(st.G, st.A, J[j], Sji)
    if criterion in ("D", "O1"):
        gain = _logdet(eye + A_minus)  # the D gain of i in, relative to j out
        cand = np.where(allowed, gain, -np.inf)
        i = int(np.argmax(cand))
        return i, bool(cand[i] > gain[j] + tol)
    if criterion == "I":
        assert st.GW is not None and st.H is not None and W is not None  # kept for the I criterion
        after = _swap_trace(B, A_minus, st.GW, st.H, J[j], Sj, Sji, st.Mi, W)  # trace(M'⁻¹W), j out, i in
        cand = np.where(allowed, after, np.inf)
        i = int(np.argmin(cand))
        return i, bool(cand[i] < after[j] * (1.0 - tol))
    gain = _logdet(eye + A_minus)
    M_minus = st.M - J[j].T @ J[j]
    _, V = np.linalg.eigh(M_minus)
    weak = np.sum((J @ V[:, 0]) ** 2, axis=1)
    idx = np.nonzero(allowed)[0]
    pool = np.unique(np.concatenate([_top(gain, idx, screen), _top(weak, idx, screen)]))
    s = _scores(M_minus + np.swapaxes(J[pool], 1, 2) @ J[pool], criterion, W)
    now = float(_scores(st.M, criterion, W))
    k = int(np.argmax(s))
    return int(pool[k]), bool(s[k] > now + tol * max(abs(now), 1e-300))


def _downdate(G: np.ndarray, A: np.ndarray, Jj: np.ndarray, Sji: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose j removed from the design M: for every candidate i, ``Bᵢ = Jᵢ M⁻¹ Jⱼᵀ = Gᵢ Jⱼᵀ`` and
    ``Jᵢ N⁻¹ Jᵢᵀ = Aᵢ + Bᵢ Sⱼ⁻¹ Bᵢᵀ`` (both (C, r, r)) with ``N = M − JⱼᵀJⱼ``, by Woodbury:
    ``N⁻¹ = M⁻¹ + M⁻¹Jⱼᵀ Sⱼ⁻¹ Jⱼ M⁻¹``, ``Sⱼ = I − Jⱼ M⁻¹ Jⱼᵀ``. The D gain of putting i in
    j's place is then ``log det(I + Jᵢ N⁻¹ Jᵢᵀ)`` (the matrix determinant lemma)."""
    B = G @ Jj.T
    return B, A + B @ Sji @ np.swapaxes(B, 1, 2)


def _swap_trace(B, A_minus, GW, H, Jj, Sj, Sji, Mi, W) -> np.ndarray:
    """For every candidate i: ``trace((M − JⱼᵀJⱼ + JᵢᵀJᵢ)⁻¹ W)`` (C,), the I criterion of the design
    with pose j exchanged for candidate i, exactly, by two rank-r updates (``B``, ``A_minus``
    from :func:`_downdate`; ``GW = G W`` (C, r, P) and ``H = G W Gᵀ`` (C, r, r) cached with
    ``G = J M⁻¹``).

    Removing j, with ``K = Sⱼ⁻¹ Jⱼ M⁻¹``: ``N⁻¹ = M⁻¹ + M⁻¹JⱼᵀK``, so
    ``trace(N⁻¹W) = trace(M⁻¹W) + trace(K W Kᵀ Sⱼ)`` and ``Jᵢ N⁻¹ = Gᵢ + Bᵢ K``. Adding i:
    ``trace((N + JᵢᵀJᵢ)⁻¹W) = trace(N⁻¹W) − trace((I + Jᵢ N⁻¹ Jᵢᵀ)⁻¹ Jᵢ N⁻¹ W N⁻¹ Jᵢᵀ)`` with
    ``Jᵢ N⁻¹ W N⁻¹ Jᵢᵀ = Hᵢ + Qᵢ Bᵢᵀ + Bᵢ Qᵢᵀ + Bᵢ (K W Kᵀ) Bᵢᵀ``, ``Qᵢ = GWᵢ Kᵀ``.
    Cost O(C·r²·P) per j, where scoring each swap by a solve would cost O(C·P³)."""
    K = Sji @ Jj @ Mi  # (r, P)
    KWK = K @ W @ K.T
    Q = GW @ K.T  # (C, r, r)
    Bt = np.swapaxes(B, 1, 2)
    H_minus = H + Q @ Bt + B @ np.swapaxes(Q, 1, 2) + B @ KWK @ Bt
    t_minus = float(np.trace(Mi @ W) + np.trace(KWK @ Sj))
    reduction = np.trace(np.linalg.solve(np.eye(len(Sj)) + A_minus, H_minus), axis1=1, axis2=2)
    return t_minus - reduction


# --------------------------------------------------------------------------- predicted accuracy


@dataclass(frozen=True, eq=False)
class _Evaluation:
    q: np.ndarray  # (E, n)
    Je: np.ndarray  # (E, 3T, P) SI Jacobian times S (no 1/σ)
    W: np.ndarray  # (P, P) mean over evaluation points of JeᵀJe per target


def _evaluation(design: _Design, q: np.ndarray) -> _Evaluation:
    Je = _jacobians(design.model, q, list(design.params), design.targets) * design.S
    E, r, _P = Je.shape
    W = np.einsum("erp,erq->pq", Je, Je) / (E * (r // 3))
    return _Evaluation(q, Je, W)


def _uncertainty(ev: _Evaluation, Mi: np.ndarray) -> np.ndarray:
    """Per evaluation point and target, ``√trace(J_e Σ J_eᵀ)`` (m): the RMS 3-D position error the
    model is predicted to have there. (E·T,)"""
    E, r, P = ev.Je.shape
    var = np.sum((ev.Je.reshape(E * r, P) @ Mi) * ev.Je.reshape(E * r, P), axis=1)
    return np.sqrt(np.maximum(var.reshape(E, r // 3, 3).sum(axis=2).reshape(-1), 0.0))


def _full_rank(M: np.ndarray, rtol: float = 1e-12) -> bool:
    d = np.sqrt(np.maximum(np.diag(M), 1e-300))
    lam = np.linalg.eigvalsh(M / np.outer(d, d))
    return bool(lam[0] > rtol * lam[-1])


def _stats(u: np.ndarray) -> tuple[float, float, float]:
    return float(np.sqrt(np.mean(u**2))), float(np.percentile(u, 95)), float(np.max(u))


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class PlanResult:
    """What :func:`plan` chose and what it predicts.

    ``indices`` (K,) rows of the candidates chosen, ``q`` (K, n) those readings (SI);
    ``criterion`` and its ``value`` (see :func:`criterion_value`), ``greedy_value`` before the
    exchange; ``observability``: :func:`calibration.identify.observability_indices` of the chosen
    design (what :func:`~calibration.identify.identify` will report for noise-free data there);
    ``params`` the identifiable parameters, ``unidentifiable`` the others and why;
    ``covariance`` (P, P) SI the predicted ``σ²(JᵀJ)⁻¹``; ``uncertainty_m`` (E·T,) the predicted
    RMS position error at each evaluation configuration (and target) and its ``predicted_rms_m``
    (root mean square over them), ``predicted_p95_m`` (95th percentile) and ``predicted_max_m``.
    """

    indices: np.ndarray
    q: np.ndarray
    criterion: str
    value: float
    greedy_value: float
    log_det: float
    observability: dict
    params: tuple[Parameter, ...]
    unidentifiable: tuple[Unidentifiable, ...]
    covariance: np.ndarray
    std_errors: np.ndarray
    evaluation_q: np.ndarray
    uncertainty_m: np.ndarray
    predicted_rms_m: float
    predicted_p95_m: float
    predicted_max_m: float
    sigma_m: float
    targets: tuple[str | None, ...]
    n_candidates: int
    swaps: int
    sweeps: int
    success: bool
    message: str

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)


def _ridge(J: np.ndarray, rel: float) -> np.ndarray:
    """Per-parameter regularisation: ``rel`` times the mean information one candidate carries."""
    d = np.einsum("crp,crp->p", J, J) / len(J)
    return rel * np.maximum(d, 1e-300)


def _check_count(design: _Design, count: int) -> None:
    C, r, P = design.J.shape
    k_min = max(1, math.ceil(P / r))
    if count < k_min:
        raise ValueError(
            f"`count` must be at least {k_min}: {P} identifiable parameters need {P} equations and each pose gives {r}"
        )
    if count > C:
        raise ValueError(f"`count` ({count}) exceeds the number of candidates ({C})")


def _evaluation_q(model, evaluation, n_evaluation, rng, volume, targets) -> np.ndarray:
    if evaluation is not None:
        q = np.atleast_2d(np.asarray(evaluation, float))
        if q.ndim != 2 or q.shape[1] != model.n_joints or len(q) == 0:
            raise ValueError(f"`evaluation` must have shape (E, {model.n_joints}); got {q.shape}")
        return q
    if volume is None:
        return random_configurations(model, n_evaluation, rng)
    return generate_candidates(model, n_evaluation, rng, targets=targets, volume=volume)


def _finish(design, ev, chosen, criterion, greedy_value, swaps, sweeps) -> PlanResult:
    idx = np.array(chosen, dtype=int)
    C, r, P = design.J.shape
    M = np.einsum("krp,krq->pq", design.J[idx], design.J[idx])
    n_rows = len(idx) * (r // 3)
    ok = _full_rank(M)
    if ok:
        Mi = _inv(M)
        u = _uncertainty(ev, Mi)
        cov = Mi * np.outer(design.S, design.S)
        rms, p95, mx = _stats(u)
        msg = f"{len(idx)} poses determine the {P} identifiable parameters"
    else:
        u = np.full(len(ev.q) * (r // 3), np.inf)
        cov = np.full((P, P), np.inf)
        rms = p95 = mx = float("inf")
        msg = f"the {len(idx)} poses chosen do not determine all {P} identifiable parameters; choose more poses"
    Jw = design.J[idx].reshape(-1, P) / design.S  # σ-weighted SI Jacobian, as identify builds it
    return PlanResult(
        indices=idx,
        q=design.q[idx],
        criterion=criterion,
        value=criterion_value(M, criterion, n_rows=n_rows, W=ev.W),
        greedy_value=greedy_value,
        log_det=float(_logdet(M)),
        observability=observability_indices(Jw, list(design.params), n_poses=n_rows, reach_m=design.reach_m),
        params=design.params,
        unidentifiable=design.unidentifiable,
        covariance=cov,
        std_errors=np.sqrt(np.maximum(np.diag(cov), 0.0)) if ok else np.full(P, np.inf),
        evaluation_q=ev.q,
        uncertainty_m=u,
        predicted_rms_m=rms,
        predicted_p95_m=p95,
        predicted_max_m=mx,
        sigma_m=design.sigma_m,
        targets=design.targets,
        n_candidates=C,
        swaps=swaps,
        sweeps=sweeps,
        success=ok,
        message=msg,
    )


@dataclass(frozen=True, eq=False)
class PlanOptions:
    """How :func:`plan` and :func:`poses_for_accuracy` choose poses (one definition of the
    defaults for both).

    ``targets``: the targets measured at each pose; ``criterion``: one of :data:`CRITERIA`
    (default D, the issue's choice and the fastest; I, the least predicted mean position error
    over the evaluation configurations, is 4–5 % better on average accuracy at 3–7 times the
    planning time, docs/benchmarks.md); ``sigma_m``: the instrument's per-axis standard
    uncertainty (m), which scales the predicted accuracy; ``evaluation`` (E, n): where the
    predicted accuracy is evaluated and what the I criterion minimises (default ``n_evaluation``
    random readings within the joint limits, and within ``volume`` when given, drawn with
    ``rng``, default seed 0); ``gains``, ``fixed``, ``hayati``, ``rank_rtol``: as for
    :func:`calibration.identify.identify`; ``exchange``: improve the greedy start by exchanges, at
    most ``max_sweeps`` sweeps, each screening ``screen`` candidates per pose for the eigenvalue
    criteria; ``ridge``: the start-up regularisation relative to one candidate's information;
    ``tol``: the smallest improvement a swap must bring (log det units for D/O1, relative for the
    others)."""

    targets: tuple[str | None, ...] = (None,)
    criterion: str = "D"
    sigma_m: float = INSTRUMENT_SIGMA_M
    evaluation: np.ndarray | None = None
    n_evaluation: int = 300
    volume: Volume | None = None
    rng: np.random.Generator | None = None
    gains: bool = False
    fixed: tuple[str, ...] = ()
    hayati: bool = True
    rank_rtol: float = 1e-6
    exchange: bool = True
    max_sweeps: int = 20
    screen: int = 24
    ridge: float = 1e-8
    tol: float = 1e-9


def _options(options: PlanOptions | None, overrides: dict) -> PlanOptions:
    """``options`` (default :class:`PlanOptions`) with the keyword ``overrides`` applied; checks the
    criterion."""
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(PlanOptions)})
    if unknown:
        raise TypeError(f"unknown planning option(s): {', '.join(unknown)}")
    o = dataclasses.replace(options or PlanOptions(), **overrides)
    if o.criterion not in CRITERIA:
        raise ValueError(f"`criterion` must be one of {', '.join(CRITERIA)}; got {o.criterion!r}")
    return o


def _design(model: KinematicModel, candidates: np.ndarray, o: PlanOptions):
    """:func:`_prepare` with the options' targets, noise, gains, fixed parameters and rank rule."""
    return _prepare(
        model,
        candidates,
        targets=o.targets,
        sigma_m=o.sigma_m,
        gains=o.gains,
        fixed=tuple(o.fixed),
        rank_rtol=o.rank_rtol,
        hayati=o.hayati,
    )


def plan(
    model: KinematicModel, candidates: np.ndarray, count: int, options: PlanOptions | None = None, **overrides
) -> PlanResult:
    """Choose ``count`` of the ``candidates`` (C, n) readings (SI) to measure at, for the best
    identification of ``model`` (see the module docstring for the method), as ``options`` say
    (:class:`PlanOptions`; keyword arguments override single fields).

    Raises ``ValueError`` for inconsistent input (shapes, ``count`` below the number of poses
    the identifiable parameters need or above the number of candidates, unknown criterion)."""
    o = _options(options, overrides)
    rng = np.random.default_rng(0) if o.rng is None else o.rng
    design = _design(model, candidates, o)
    _check_count(design, count)
    ev = _evaluation(design, _evaluation_q(model, o.evaluation, o.n_evaluation, rng, o.volume, design.targets))
    return _plan(
        design,
        ev,
        count,
        o.criterion,
        exchange=o.exchange,
        max_sweeps=o.max_sweeps,
        screen=o.screen,
        ridge=o.ridge,
        tol=o.tol,
    )


def _plan(
    design: _Design, ev: _Evaluation, count: int, criterion: str, *, exchange, max_sweeps, screen, ridge, tol
) -> PlanResult:
    rdiag = _ridge(design.J, ridge)
    chosen, M = _greedy(design.J, count, rdiag)
    r = design.J.shape[1]
    greedy_value = criterion_value(M - np.diag(rdiag), criterion, n_rows=count * (r // 3), W=ev.W)
    swaps = sweeps = 0
    if exchange:
        chosen, swaps, sweeps = _exchange(
            design.J, chosen, rdiag, criterion, ev.W, max_sweeps=max_sweeps, screen=screen, tol=tol
        )
    return _finish(design, ev, chosen, criterion, greedy_value, swaps, sweeps)


@dataclass(frozen=True, eq=False)
class AccuracyPlan:
    """How many poses a wanted accuracy needs (:func:`poses_for_accuracy`).

    ``count``: the fewest poses whose planned design is predicted to meet ``accuracy_m`` in
    ``statistic`` (``rms`` or ``p95`` of :class:`PlanResult`), ``None`` when even ``k_max`` poses
    do not; ``plan``: the design at ``count`` (at ``k_max`` when unmet); ``counts`` and
    ``predicted_m``: the predicted statistic along the greedy sequence, pose by pose (the curve
    accuracy against number of poses, book §4.5 step 2)."""

    count: int | None
    plan: PlanResult
    accuracy_m: float
    statistic: str
    counts: np.ndarray
    predicted_m: np.ndarray
    success: bool
    message: str


def poses_for_accuracy(
    model: KinematicModel,
    candidates: np.ndarray,
    accuracy_m: float,
    *,
    statistic: str = "rms",
    k_max: int | None = None,
    options: PlanOptions | None = None,
    **overrides,
) -> AccuracyPlan:
    """The fewest poses (from ``candidates``) whose plan is predicted to reach ``accuracy_m`` (m) in
    ``statistic`` (``rms`` or ``p95`` of the predicted position error over the evaluation
    configurations), and that plan.

    The D-optimal greedy sequence is nested, so one greedy run up to ``k_max`` (default
    ``min(C, 400)``) gives the predicted accuracy for every K; the first K that meets the
    accuracy is then planned in full (greedy and exchange) and checked, K growing until the full
    plan meets it too. Other arguments as for :func:`plan`."""
    if statistic not in STATISTICS:
        raise ValueError(f"`statistic` must be one of {', '.join(STATISTICS)}; got {statistic!r}")
    if not (accuracy_m > 0 and math.isfinite(accuracy_m)):
        raise ValueError(f"`accuracy_m` must be a positive number; got {accuracy_m}")
    o = _options(options, overrides)
    rng = np.random.default_rng(0) if o.rng is None else o.rng
    design = _design(model, candidates, o)
    criterion = o.criterion
    C, r, P = design.J.shape
    k_min = max(1, math.ceil(P / r))
    k_max = min(C, 400) if k_max is None else min(int(k_max), C)
    if k_max < k_min:
        raise ValueError(
            f"`k_max` ({k_max}) is below the {k_min} poses the {P} identifiable parameters need "
            f"(or there are too few candidates)"
        )
    ev = _evaluation(design, _evaluation_q(model, o.evaluation, o.n_evaluation, rng, o.volume, design.targets))
    rdiag = _ridge(design.J, o.ridge)
    pick = 0 if statistic == "rms" else 1
    counts: list[int] = []
    values: list[float] = []

    def on_step(chosen, M) -> bool:
        k = len(chosen)
        if k < k_min:
            return False
        M0 = M - np.diag(rdiag)
        v = _stats(_uncertainty(ev, _inv(M0)))[pick] if _full_rank(M0) else float("inf")
        counts.append(k)
        values.append(v)
        return v <= accuracy_m

    _greedy(design.J, k_max, rdiag, on_step)
    opts = dict(exchange=True, max_sweeps=o.max_sweeps, screen=o.screen, ridge=o.ridge, tol=o.tol)
    curve = (np.array(counts), np.array(values))
    if not values or values[-1] > accuracy_m:
        return _at_most(design, ev, k_max, criterion, opts, accuracy_m, statistic, curve)
    return _growing(design, ev, counts[-1], k_max, criterion, opts, accuracy_m, statistic, curve)


def _statistic_name(statistic: str) -> str:
    return "RMS" if statistic == "rms" else "95th percentile"


def _at_most(
    design,
    ev,
    k_max: int,
    criterion,
    opts: dict,
    accuracy_m: float,
    statistic: str,
    curve: tuple[np.ndarray, np.ndarray],
) -> AccuracyPlan:
    """:func:`poses_for_accuracy` when the greedy sequence did not reach ``accuracy_m`` by
    ``k_max`` poses: the full plan of ``k_max`` poses, which may still reach it."""
    name = _statistic_name(statistic)
    result = _plan(design, ev, k_max, criterion, **opts)
    got = result.predicted_rms_m if statistic == "rms" else result.predicted_p95_m
    if got <= accuracy_m:
        return AccuracyPlan(
            k_max,
            result,
            accuracy_m,
            statistic,
            *curve,
            True,
            f"{k_max} poses are predicted to give a {name} error of {got:.3g} m",
        )
    return AccuracyPlan(
        None,
        result,
        accuracy_m,
        statistic,
        *curve,
        False,
        f"even {k_max} poses are predicted to give a {name} error of {got:.3g} m, above the "
        f"{accuracy_m:.3g} m wanted: allow more poses or candidates, or use a better instrument",
    )


def _growing(
    design,
    ev,
    k: int,
    k_max: int,
    criterion,
    opts: dict,
    accuracy_m: float,
    statistic: str,
    curve: tuple[np.ndarray, np.ndarray],
) -> AccuracyPlan:
    """:func:`poses_for_accuracy` from the first ``k`` the greedy sequence predicts to reach
    ``accuracy_m``: planned in full, ``k`` growing until the full plan reaches it too."""
    name = _statistic_name(statistic)
    while True:
        result = _plan(design, ev, k, criterion, **opts)
        got = result.predicted_rms_m if statistic == "rms" else result.predicted_p95_m
        if got <= accuracy_m or k >= k_max:
            ok = got <= accuracy_m
            msg = (
                f"{k} poses are predicted to give a {name} error of {got:.3g} m (wanted {accuracy_m:.3g} m)"
                if ok
                else f"even {k} poses are predicted to give a {name} error of {got:.3g} m, above the "
                f"{accuracy_m:.3g} m wanted"
            )
            return AccuracyPlan(k if ok else None, result, accuracy_m, statistic, *curve, ok, msg)
        k += 1


def measurement_order(q: np.ndarray) -> np.ndarray:
    """An order (K,) to measure the poses ``q`` (K, n) in: a nearest-neighbour tour in joint space
    (distance: the largest joint move, which sets the travel time of a joint move), starting from
    the pose nearest the centre of the set. Short moves save time and keep the robot warm."""
    q = np.atleast_2d(np.asarray(q, float))
    K = len(q)
    if K == 0:
        return np.zeros(0, dtype=int)
    # the distances from the last pose, row by row: a dense session's K x K matrix would not fit
    start = int(np.argmin(np.max(np.abs(q - np.median(q, axis=0)), axis=1)))
    order = [start]
    left = np.ones(K, bool)
    left[start] = False
    for _ in range(K - 1):
        d = np.where(left, np.max(np.abs(q - q[order[-1]]), axis=1), np.inf)
        nxt = int(np.argmin(d))
        order.append(nxt)
        left[nxt] = False
    return np.array(order, dtype=int)


# --------------------------------------------------------------------------- what a plan cannot determine

# What would determine a parameter that more poses of the same kind never will, by the category
# of :class:`calibration.identification.Unidentifiable` (issue 27: "a plan that cannot determine
# everything says how many more poses, or which kind, would").
WHAT_WOULD_DETERMINE = {
    "tool_orientation": "orientation measurements (a 6-D probe) or two more targets on the tool, not on one "
    "line with the first",
    "last_joint_offset": "orientation measurements (a 6-D probe) or a second target elsewhere on the tool",
    "no_effect": "a target away from the axis that hides it (e.g. 20 mm or more off the last joint's axis), or "
    "orientation measurements",
    "weak": "a target 20 mm or more off the joint axis it sits on",
    "same_motion": "nothing: it is the same motion as another parameter, which carries it; predictions do not "
    "depend on it",
    "combination": "nothing: other parameters' motions together make it; predictions do not depend on it",
    "target_offsets": "nothing: the target offsets carry it; predictions do not depend on it",
}
NEEDS_NOTHING = ("same_motion", "combination", "target_offsets")


@dataclass(frozen=True, eq=False)
class Shortfall:
    """What a plan of ``count`` poses leaves undetermined, and what would determine it.

    ``poses_needed``: the fewest poses, planned from the same candidates (the D-optimal greedy
    sequence), that determine every parameter poses of this kind can determine (None when even
    ``k_max`` do not); ``more_poses``: how many that is beyond ``count`` (0 when ``count``
    suffices); ``identifiable``: how many parameters that is; ``by_kind``: the parameters no
    number of such poses determines, grouped by what would (:data:`WHAT_WOULD_DETERMINE`), each
    ``{"category", "needs", "parameters", "harmless"}``; ``message``: one line saying all this."""

    count: int
    poses_needed: int | None
    more_poses: int | None
    identifiable: int
    by_kind: tuple[dict, ...]
    message: str

    def as_dict(self) -> dict:
        return {
            "count": self.count,
            "poses_needed": self.poses_needed,
            "more_poses": self.more_poses,
            "identifiable": self.identifiable,
            "by_kind": [dict(k) for k in self.by_kind],
            "message": self.message,
        }


def shortfall(
    model: KinematicModel,
    candidates: np.ndarray,
    count: int,
    options: PlanOptions | None = None,
    *,
    k_max: int = 400,
    **overrides,
) -> Shortfall:
    """How many poses (from ``candidates``, planned) would determine every parameter poses of
    this kind can, against the ``count`` a plan has; and, for the parameters no number of such
    poses determines, which kind of measurement would (:data:`WHAT_WOULD_DETERMINE`). Other
    arguments as for :func:`plan`."""
    o = _options(options, overrides)
    design = _design(model, candidates, o)
    needed = _poses_needed(design, min(int(k_max), len(design.J)))
    more = None if needed is None else max(needed - int(count), 0)
    groups: dict[str, list[str]] = {}
    for u in design.unidentifiable:
        groups.setdefault(u.category if u.category in WHAT_WOULD_DETERMINE else "no_effect", []).append(u.name)
    by_kind = tuple(
        {
            "category": c,
            "needs": WHAT_WOULD_DETERMINE[c],
            "parameters": names,
            "harmless": c in NEEDS_NOTHING,
        }
        for c, names in groups.items()
    )
    return Shortfall(
        int(count), needed, more, len(design.params), by_kind, _shortfall_message(design, count, needed, by_kind)
    )


def _poses_needed(design: _Design, k_max: int) -> int | None:
    """The fewest poses of the D-optimal greedy sequence that determine every identifiable
    parameter (full rank), or None when ``k_max`` do not."""
    _C, r, P = design.J.shape
    k_min = max(1, math.ceil(P / r))
    rdiag = _ridge(design.J, PlanOptions.ridge)
    found: list[int] = []

    def on_step(chosen, M) -> bool:
        if len(chosen) >= k_min and _full_rank(M - np.diag(rdiag)):
            found.append(len(chosen))
            return True
        return False

    _greedy(design.J, k_max, rdiag, on_step)
    return found[0] if found else None


def _shortfall_message(design: _Design, count: int, needed: int | None, by_kind: tuple[dict, ...]) -> str:
    P = len(design.params)
    if needed is None:
        first = f"no plan of up to the candidates' poses determines all {P} parameters poses of this kind can"
    elif needed > count:
        first = (
            f"{needed} planned poses would determine the {P} parameters poses of this kind can ({needed - count} "
            "more; identification wants a few beyond that to check the fit)"
        )
    else:
        first = f"{count} poses determine the {P} parameters poses of this kind can (planned, {needed} would)"
    parts = [first]
    for k in by_kind:
        names = k["parameters"]
        shown = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
        if k["harmless"]:
            parts.append(f"{len(names)} need no measurement ({shown}): {k['needs'].split(': ', 1)[-1]}")
        else:
            parts.append(f"{len(names)} no number of these poses determines ({shown}): {k['needs']} would")
    return "; ".join(parts)
