"""Joint transmission errors: a joint's true angle differs from its reading by a periodic
function of the reading, at the harmonics of its gear (the book's joint-level errors, eq. 2.4,
carried past the one eccentricity term of :attr:`calibration.model.Joint.harmonic`; issue 28).

A harmonic drive's transmission error repeats once and twice per turn of the output (the
circular spline's and the flexspline's eccentricity and ellipticity) and twice per turn of its
wave generator, which turns ``N`` times (the gear ratio) per output turn:

    δq_i(q_i) = Σ_k a_ik cos(r_k q_i) + b_ik sin(r_k q_i),   r_k ∈ {1, 2, 2N, ...}      (2.4')

The position a joint error moves the tool by is that of the geometric model at ``q + δq``: for
small δq, ``Σ_i J_i(q) δq_i`` with ``J_i`` the model's position Jacobian column of joint ``i``.
The coefficients are then a linear least-squares fit of the geometric model's residuals (the
"physical" family of the residual correction). The wave generator's ratio can be given (the
robot's gear ratios) or found: each joint's best of :data:`GEAR_RATIOS_SEARCHED`, kept only
where it explains far more of the residuals than the best of as many random sinusoids would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .model import KinematicModel

FORMAT = "recal.residual_transmission/1"
OUTPUT_HARMONICS = (1.0, 2.0)  # once and twice per output turn: always tried
GEAR_RATIOS_SEARCHED = tuple(range(30, 201))  # harmonic-drive ratios of industrial and cobot arms
# a found wave-generator ratio must lower the residual sum of squares by this many times what the
# best of len(GEAR_RATIOS_SEARCHED) sinusoids of pure noise would (about 2 ln(K) σ² for K tried)
FIND_MARGIN = 4.0
# A joint whose axis passes within this of the measured points (RMS over the data, m) moves them
# too little for its transmission error to be seen in position residuals: a 0.01° error there
# moves them under 1 µm. Its terms are left out; fitted, they grow without bound (a real UR10's
# T-Mac 0.09 mm off the last axis gave that joint 10-19° amplitudes and made the correction
# 5.6 times worse than none on held-out poses).
MIN_LEVER_M = 0.005
RIDGE = 1e-9  # relative to the normal matrix's mean diagonal: only for terms the data cannot see
JACOBIAN_STEP_RAD = 1e-6


@dataclass(frozen=True, eq=False)
class JointTransmission:
    """Per joint ``i``: ``ratios[i]`` (K_i,) cycles per output turn (per metre for a prismatic
    joint, which is not expected to have any) and ``coefficients[i]`` (K_i, 2) rad, the cosine and
    sine amplitudes of eq. 2.4'. ``lower``/``upper`` (n,) the joint ranges it was fitted in (None:
    everywhere, e.g. a simulated truth); ``cv`` the figures that chose it."""

    ratios: tuple[np.ndarray, ...]
    coefficients: tuple[np.ndarray, ...]
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    cv: dict = field(default_factory=dict)

    def joint_errors(self, q: np.ndarray) -> np.ndarray:
        """δq (N, n): true joint angle minus reading, at readings ``q`` (N, n)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        out = np.zeros_like(q)
        for i, (r, c) in enumerate(zip(self.ratios, self.coefficients)):
            if len(r):
                ph = q[:, i, None] * np.asarray(r)[None, :]
                out[:, i] = np.cos(ph) @ c[:, 0] + np.sin(ph) @ c[:, 1]
        return out

    def inside(self, q: np.ndarray) -> np.ndarray:
        """(N,) whether each configuration lies within the joint ranges it was fitted in."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if self.lower is None or self.upper is None:
            return np.ones(len(q), dtype=bool)
        return np.all((q >= self.lower) & (q <= self.upper), axis=1)


@dataclass(frozen=True, eq=False)
class TransmissionCorrection:
    """A fitted :class:`JointTransmission` and the geometric model identified on the readings it
    corrects (``corrected``), as a correction of the model file's own geometric model (``base``):
    inside the fitted region the position is ``corrected`` at ``q + δq(q)``; outside, ``base``
    alone. The same ``evaluate`` as a residual map."""

    base: KinematicModel
    corrected: KinematicModel
    transmission: JointTransmission

    @property
    def cv(self) -> dict:
        return self.transmission.cv

    def evaluate(self, q: np.ndarray, p_tool: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The correction (N, 3) m of the position of tool-frame point ``p_tool`` ((3,) or (N, 3);
        default the tool origin) at readings ``q``, and (N,) whether each is inside the fitted
        region (the correction is zero outside)."""
        from .jacobian import predict

        q = np.atleast_2d(np.asarray(q, dtype=float))
        p = np.broadcast_to(np.zeros(3) if p_tool is None else np.asarray(p_tool, dtype=float), (len(q), 3))
        inside = self.transmission.inside(q)
        corr = np.zeros((len(q), 3))
        if inside.any():
            qi, pi = q[inside], p[inside]
            dq = self.transmission.joint_errors(qi)
            corr[inside] = predict(self.corrected, qi + dq, pi).p_world - predict(self.base, qi, pi).p_world
        return corr, inside


def position_jacobian(model: KinematicModel, q: np.ndarray, p_tool: np.ndarray, payload=None) -> np.ndarray:
    """∂p/∂q (N, 3, n) of the world position of tool-frame points ``p_tool`` (N, 3) with respect
    to the readings, by central differences (the transmission error adds to the reading)."""
    from .jacobian import predict

    q = np.atleast_2d(np.asarray(q, dtype=float))
    J = np.empty((len(q), 3, q.shape[1]))
    h = JACOBIAN_STEP_RAD
    for i in range(q.shape[1]):
        e = np.zeros(q.shape[1])
        e[i] = h
        plus = predict(model, q + e, p_tool, payload=payload).p_world
        minus = predict(model, q - e, p_tool, payload=payload).p_world
        J[:, :, i] = (plus - minus) / (2 * h)
    return J


def _columns(J: np.ndarray, q: np.ndarray, joint: int, ratio: float) -> np.ndarray:
    """The two design columns (3N, 2) of one term: cos and sin of ``ratio·q_joint`` times the
    joint's Jacobian column, rows flattened (x, y, z of each configuration)."""
    ph = ratio * q[:, joint]
    Ji = J[:, :, joint]
    return np.stack([(Ji * np.cos(ph)[:, None]).ravel(), (Ji * np.sin(ph)[:, None]).ravel()], axis=1)


def _solve(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    N = A.T @ A
    lam = RIDGE * max(float(np.trace(N)) / max(len(N), 1), 1e-300)
    return np.linalg.solve(N + lam * np.eye(len(N)), A.T @ y)


def find_gear_ratios(
    J: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    revolute: np.ndarray,
    base: list[list[float]],
    G: np.ndarray | None = None,
) -> list[float | None]:
    """Per revolute joint, the gear ratio ``N`` of :data:`GEAR_RATIOS_SEARCHED` whose wave
    generator term (2N per output turn) lowers the residuals' sum of squares most once the
    ``base`` terms (and the geometric columns ``G``) are fitted, when that drop exceeds :data:`FIND_MARGIN` times what chance gives;
    else None."""
    y = np.asarray(r, dtype=float).ravel()
    blocks = [_columns(J, q, i, k) for i, ks in enumerate(base) for k in ks] + ([G] if G is not None else [])
    A0 = np.hstack(blocks) if blocks else None
    e = y - A0 @ _solve(A0, y) if A0 is not None else y
    dof = max(len(y) - (0 if A0 is None else A0.shape[1]), 1)
    sigma2 = float(e @ e) / dof
    chance = 2.0 * math.log(len(GEAR_RATIOS_SEARCHED)) * sigma2  # the best of K chi2(2)/2 draws
    found: list[float | None] = []
    for i in range(q.shape[1]):
        best, best_drop = None, 0.0
        if revolute[i]:
            for N in GEAR_RATIOS_SEARCHED:
                A = _columns(J, q, i, 2.0 * N)
                c = A.T @ e
                drop = float(c @ np.linalg.solve(A.T @ A + 1e-30 * np.eye(2), c))
                if drop > best_drop:
                    best, best_drop = float(N), drop
        found.append(best if best is not None and best_drop > FIND_MARGIN * chance else None)
    return found


def geometry_columns(model: KinematicModel, q: np.ndarray, p_tool: np.ndarray, target_names=None, payload=None):
    """The design columns (3N, P) of every parameter of ``model`` a complete identification may
    free (base, joints, tool, the rows' targets), each scaled to unit norm."""
    from .jacobian import predict
    from .parameters import candidate_parameters

    names = tuple(sorted({t for t in (target_names if target_names is not None else []) if t is not None}))
    params = candidate_parameters(model, targets=names, gains=False)
    Jp = predict(model, q, p_tool, params, target_names=target_names, payload=payload).Jp
    assert Jp is not None  # asked for with parameters
    G = Jp.reshape(-1, Jp.shape[2])
    norm = np.linalg.norm(G, axis=0)
    return G[:, norm > 0] / norm[norm > 0]


def fit_transmission(
    model: KinematicModel,
    q: np.ndarray,
    residuals: np.ndarray,
    p_tool: np.ndarray,
    *,
    target_names=None,
    payload: np.ndarray | None = None,
    gear_ratios: list[float | None] | None = None,
    find: bool = True,
) -> JointTransmission:
    """Eq. 2.4' fitted by linear least squares to the position ``residuals`` (N, 3) m (measured −
    ``model``) at readings ``q`` (N, n) of tool-frame points ``p_tool`` (N, 3): per revolute joint
    the once- and twice-per-turn terms, and the wave generator's term at ``2N`` where the joint's
    gear ratio ``N`` is given (``gear_ratios``) or, with ``find``, found in the data. Its region:
    the joint ranges of ``q``.

    The geometric model was identified without these terms and has absorbed the part of each that
    its parameters can mimic (a once-per-turn term over a joint's range looks much like an offset
    and a tilt): what it leaves is the terms projected away from the geometric parameters', which
    the terms alone do not fit (half the error stayed on the simulated arm). So the fit is joint,
    geometric columns and transmission columns together; the transmission part is returned, and
    the geometric model is to be identified again on the corrected readings ``q + δq(q)``
    (:func:`corrected_readings`)."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    revolute = np.array([j.revolute for j in model.joints])
    J = position_jacobian(model, q, p_tool, payload)
    G = geometry_columns(model, q, p_tool, target_names, payload)
    lever_m = np.sqrt(np.mean(np.sum(J**2, axis=1), axis=0))  # (n,) RMS |dp/dq_i|
    seen = revolute & (lever_m >= MIN_LEVER_M)
    terms: list[list[float]] = [list(OUTPUT_HARMONICS) if seen[i] else [] for i in range(q.shape[1])]
    given = list(gear_ratios) if gear_ratios is not None else [None] * q.shape[1]
    if find:
        found = find_gear_ratios(J, q, residuals, seen, terms, G)
        given = [g if g is not None else f for g, f in zip(given, found)]
    for i, g in enumerate(given):
        if g is not None and seen[i]:
            terms[i].append(2.0 * float(g))
    cols = [(i, k) for i, ks in enumerate(terms) for k in ks]
    A = np.hstack([_columns(J, q, i, k) for i, k in cols])
    x = _solve(np.hstack([A, G]), np.asarray(residuals, dtype=float).ravel())[: A.shape[1]]
    ratios, coefs = [], []
    for i, ks in enumerate(terms):
        idx = [c for c, (j, _) in enumerate(cols) if j == i]
        ratios.append(np.array(ks, dtype=float))
        coefs.append(np.array([[x[2 * c], x[2 * c + 1]] for c in idx]).reshape(-1, 2))
    return JointTransmission(tuple(ratios), tuple(coefs), q.min(axis=0), q.max(axis=0))


def corrected_readings(data, t: JointTransmission):
    """``data`` with each reading ``q`` replaced by the joint angle ``q + δq(q)`` the transmission
    says the joint stood at (for identifying the geometric model without the transmission error)."""
    import dataclasses

    return dataclasses.replace(data, q=data.q + t.joint_errors(data.q))


# ----------------------------------------------------------------------------- the file section


def to_dict(c: TransmissionCorrection, model: KinematicModel) -> dict:
    """The model file's ``residual_map`` section for the transmission family: per joint its ratios
    (cycles per output turn) and cosine/sine amplitudes in the model's angle unit; the region in
    the model's joint units; the geometric model identified with the correction (a model
    document, in ``model``'s units)."""
    from .model import model_to_dict

    t = c.transmission
    u = model.units
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    return {
        "format": FORMAT,
        "family": "transmission",
        "joints": [
            {
                "name": j.name,
                "ratios": [float(v) for v in r],
                "cos": [float(v) / scale[i] for v in c[:, 0]],
                "sin": [float(v) / scale[i] for v in c[:, 1]],
            }
            for i, (j, r, c) in enumerate(zip(model.joints, t.ratios, t.coefficients))
        ],
        "geometric_model": model_to_dict(c.corrected, units=u),
        "lower": [float(v) for v in t.lower / scale],
        "upper": [float(v) for v in t.upper / scale],
        "cross_validation": {k: (v / u.length_m if k.endswith("_m") else v) for k, v in t.cv.items()},
    }


def from_dict(d: dict, model: KinematicModel) -> TransmissionCorrection:
    """The correction a model file's ``residual_map`` section of :data:`FORMAT` describes."""
    from .residual_base import ResidualMapError

    u = model.units
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    joints = d.get("joints")
    if not isinstance(joints, list) or len(joints) != model.n_joints:
        raise ResidualMapError("residual_map.joints", f"expected a list of {model.n_joints} joints")
    ratios, coefs = [], []
    for i, jd in enumerate(joints):
        try:
            r = np.array(jd["ratios"], dtype=float)
            c = np.stack([np.array(jd["cos"], dtype=float), np.array(jd["sin"], dtype=float)], axis=1)
        except (KeyError, TypeError, ValueError):
            raise ResidualMapError(
                f"residual_map.joints[{i}]", "expected ratios, cos and sin: lists of numbers of one length"
            ) from None
        if r.ndim != 1 or c.shape != (len(r), 2) or not (np.all(np.isfinite(r)) and np.all(np.isfinite(c))):
            raise ResidualMapError(
                f"residual_map.joints[{i}]", "expected ratios, cos and sin: lists of finite numbers of one length"
            )
        ratios.append(r)
        coefs.append(c * scale[i])
    try:
        lo = np.array(d["lower"], dtype=float) * scale
        hi = np.array(d["upper"], dtype=float) * scale
    except (KeyError, TypeError, ValueError):
        raise ResidualMapError(
            "residual_map.lower", f"expected lower and upper: {model.n_joints} numbers each"
        ) from None
    if lo.shape != (model.n_joints,) or hi.shape != (model.n_joints,):
        raise ResidualMapError("residual_map.lower", f"expected lower and upper: {model.n_joints} numbers each")
    try:
        from .model import model_from_dict

        corrected = model_from_dict(d["geometric_model"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ResidualMapError("residual_map.geometric_model", f"expected a model document ({exc})") from None
    if corrected.n_joints != model.n_joints:
        raise ResidualMapError("residual_map.geometric_model", f"expected a model of {model.n_joints} joints")
    t = JointTransmission(tuple(ratios), tuple(coefs), lo, hi, dict(d.get("cross_validation") or {}))
    return TransmissionCorrection(model, corrected, t)
