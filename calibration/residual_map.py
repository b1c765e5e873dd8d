"""Residual maps: a smooth correction of what the parametric model leaves (book §5.4,
nonparametric compensation).

The book fits polynomials in the joint angles to the remaining error (Shamma and Whitney,
§5.4.1) or a CMAC table (§5.4.2). What the field uses now for a smooth function of a handful of
joint angles from a few hundred samples is a kernel method; here kernel ridge regression (the
mean of a Gaussian process) with a Gaussian kernel on the joint configuration: revolute joints
enter as (cos q, sin q), so the map is periodic in them and a distance between configurations
is the chordal distance (≈ the angle, for small ones); prismatic joints enter as q over 1 m.

    correction(q) = Σ_j k(q, q_j) α_j,   k(q, q') = exp(−|φ(q) − φ(q')|² / (2ℓ²)),
    α = (K + λ I)⁻¹ R                                                                  (5.4)

with ``R`` (M, 3) the world-frame position residuals (measured − parametric) at the training
configurations. The smoothness ``ℓ`` and the ridge ``λ`` are chosen on held-out data
(k-fold cross-validation, a configuration's rows together). The map applies only inside the
measured region: within the joint ranges the training configurations span and within ``ℓ`` of
one of them; elsewhere it says so and the parametric model is used alone. A map is a correction of one parametric model: identify that
model again and the map must be fitted again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .model import KinematicModel
from .residual_base import ResidualMapError, features
from .residual_base import sqdist as _sqdist

LENGTH_SCALES = tuple(float(v) for v in np.geomspace(0.25, 4.0, 9))  # chordal units (≈ rad)
RIDGES = (1e-4, 1e-3, 1e-2, 1e-1, 1.0)  # relative to the kernel's unit diagonal
MIN_CV_GAIN = 0.05  # a map must lower the cross-validated RMS by at least this fraction to be kept
# A map is fitted to at most this many configurations (a seeded draw of them when there are
# more): the kernel matrix is M x M and its solve M^3, so without a bound a 30,000-row import
# needed 16 GB; a few hundred samples are what a smooth function of six angles needs.
MAX_MAP_CONFIGURATIONS = 400
# The cross-validation of the whole procedure (identification, then the map) runs on at most this
# many configurations (a seeded draw): its five identifications are then bounded too, and a few
# thousand held-out configurations tell a gain of 5 % as well as a hundred thousand do.
MAX_CV_CONFIGURATIONS = 4000
EVALUATE_CHUNK_ROWS = 4096  # rows evaluated at once: the distance block stays a few MB
FORMAT = "recal.residual_map/1"


@dataclass(frozen=True, eq=False)
class ResidualMap:
    """A fitted map (eq. 5.4). ``q_train`` (M, n) SI readings, ``alpha`` (M, 3) m,
    ``length_scale`` ℓ and ``ridge`` λ, ``revolute`` (n,); ``cv`` the cross-validation figures
    that chose it (m)."""

    q_train: np.ndarray
    alpha: np.ndarray
    length_scale: float
    ridge: float
    revolute: np.ndarray
    cv: dict

    def evaluate(self, q: np.ndarray, p_tool: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The correction (N, 3) m to add to the parametric model's position at readings ``q``
        (N, n), and (N,) whether each is inside the measured region (the correction is zero
        outside). ``p_tool`` is not used: the map corrects whatever point it was fitted to."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        F_train = features(self.q_train, self.revolute)
        lo, hi = self.q_train.min(axis=0), self.q_train.max(axis=0)
        corr = np.zeros((len(q), 3))
        inside = np.zeros(len(q), dtype=bool)
        for start in range(0, len(q), EVALUATE_CHUNK_ROWS):  # bounded memory however many rows
            part = slice(start, start + EVALUATE_CHUNK_ROWS)
            D = _sqdist(features(q[part], self.revolute), F_train)
            in_box = np.all((q[part] >= lo) & (q[part] <= hi), axis=1)
            inside[part] = in_box & (np.sqrt(D.min(axis=1)) <= self.length_scale)
            corr[part] = np.exp(-D / (2.0 * self.length_scale**2)) @ self.alpha
        corr[~inside] = 0.0
        return corr, inside


def fit(
    q: np.ndarray,
    residuals: np.ndarray,
    revolute: np.ndarray,
    length_scale: float,
    ridge: float,
    cv: dict | None = None,
) -> ResidualMap:
    """Kernel ridge regression (eq. 5.4) of ``residuals`` (M, 3) m on readings ``q`` (M, n)."""
    F = features(q, revolute)
    K = np.exp(-_sqdist(F, F) / (2.0 * length_scale**2))
    alpha = np.linalg.solve(K + ridge * np.eye(len(K)), np.asarray(residuals, dtype=float))
    return ResidualMap(
        np.array(q, dtype=float),
        alpha,
        float(length_scale),
        float(ridge),
        np.asarray(revolute, dtype=bool),
        dict(cv or {}),
    )


def select_smoothness(
    q: np.ndarray, residuals: np.ndarray, revolute: np.ndarray, folds: list[np.ndarray]
) -> tuple[float, float, float]:
    """The (ℓ, λ) of :data:`LENGTH_SCALES` x :data:`RIDGES` with the least held-out RMS over
    ``folds`` (row indices), and that RMS (m)."""
    F = features(q, revolute)
    D = _sqdist(F, F)
    R = np.asarray(residuals, dtype=float)
    best = (math.inf, LENGTH_SCALES[0], RIDGES[0])
    for ell in LENGTH_SCALES:
        K = np.exp(-D / (2.0 * ell**2))
        for lam in RIDGES:
            sq = 0.0
            for test in folds:
                train = np.setdiff1d(np.arange(len(R)), test)
                a = np.linalg.solve(K[np.ix_(train, train)] + lam * np.eye(len(train)), R[train])
                sq += float(np.sum((R[test] - K[np.ix_(test, train)] @ a) ** 2))
            rms = math.sqrt(sq / len(R))
            if rms < best[0]:
                best = (rms, ell, lam)
    return best[1], best[2], best[0]


def residuals(model: KinematicModel, data) -> np.ndarray:
    """Measured minus predicted positions (N, 3) m of ``data`` on ``model`` (each row's target and payload)."""
    from .jacobian import predict

    p_tool = np.array([model.target(t) for t in data.target])
    return data.p_world - predict(model, data.q, p_tool, payload=data.payload).p_world


def map_rows(data, max_configurations: int = MAX_MAP_CONFIGURATIONS, seed: int = 0) -> np.ndarray:
    """Row indices a map is fitted to: every row when ``data`` has at most ``max_configurations``
    configurations (``pose_id``), else the rows of a seeded draw of that many (a configuration's
    rows together), in their order."""
    N = len(data)
    groups = np.asarray(data.pose_id) if data.pose_id is not None else np.arange(N)
    keys, label = np.unique(groups.astype(str) if groups.dtype == object else groups, return_inverse=True)
    if len(keys) <= max_configurations:
        return np.arange(N)
    chosen = np.random.default_rng(seed).choice(len(keys), size=max_configurations, replace=False)
    return np.nonzero(np.isin(label, chosen))[0]


# ----------------------------------------------------------------------------- the file section


def to_dict(m: ResidualMap, model: KinematicModel) -> dict:
    """The model file's ``residual_map`` section, in the model's units (configurations in its
    joint units, coefficients in its length unit; ℓ is dimensionless, chordal)."""
    u = model.units
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    return {
        "format": FORMAT,
        "family": "map",
        "kernel": "gaussian on (cos q, sin q) of revolute joints, q / 1 m of prismatic ones",
        "length_scale": m.length_scale,
        "ridge": m.ridge,
        "configurations": [[float(f"{v:.12g}") for v in row] for row in m.q_train / scale],
        "coefficients": [[float(f"{v:.12g}") for v in row] for row in m.alpha / u.length_m],
        "cross_validation": {k: (v / u.length_m if k.endswith("_m") else v) for k, v in m.cv.items()},
    }


def from_model(model: KinematicModel):
    """The correction a model file carries in its top-level ``residual_map`` section, whatever its
    family (the smooth map here, :mod:`calibration.transmission`, :mod:`calibration.trees`), or
    None: an object with ``evaluate(q, p_tool=None) -> (correction (N, 3) m, inside (N,))``, so
    every verb loads and applies it the same way."""
    from . import transmission, trees

    d = model.metadata.get("residual_map")
    if d is None:
        return None
    fmt = d.get("format") if isinstance(d, dict) else None
    if fmt == transmission.FORMAT:
        return transmission.from_dict(d, model)
    if fmt == trees.FORMAT:
        return trees.from_dict(d, model)
    if fmt != FORMAT:
        raise ResidualMapError(
            "residual_map.format", f"expected one of {FORMAT!r}, {transmission.FORMAT!r}, {trees.FORMAT!r}"
        )
    n = model.n_joints
    try:
        Q = np.array(d["configurations"], dtype=float)
        A = np.array(d["coefficients"], dtype=float)
        ell, lam = float(d["length_scale"]), float(d["ridge"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ResidualMapError(
            "residual_map", f"expected configurations, coefficients, length_scale and ridge ({exc})"
        ) from None
    if (
        Q.ndim != 2
        or Q.shape[1] != n
        or A.shape != (len(Q), 3)
        or not (np.all(np.isfinite(Q)) and np.all(np.isfinite(A)))
    ):
        raise ResidualMapError(
            "residual_map.configurations", f"expected M rows of {n} joint values and M rows of 3 coefficients"
        )
    if not ell > 0:
        raise ResidualMapError("residual_map.length_scale", "expected a positive number")
    u = model.units
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    return ResidualMap(
        Q * scale,
        A * u.length_m,
        ell,
        lam,
        np.array([j.revolute for j in model.joints]),
        dict(d.get("cross_validation") or {}),
    )
