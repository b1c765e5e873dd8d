"""What every residual-correction family shares (the smooth map, :mod:`calibration.residual_map`;
the joint transmission, :mod:`calibration.transmission`; the trees, :mod:`calibration.trees`):
the joint-space embedding, squared distances in it, and the error a malformed section raises.
Apart so that the families import it and :mod:`calibration.residual_map`, which loads any family
from a model file, imports them: one direction, no circle."""

from __future__ import annotations

import numpy as np

from .errors import RecalError


class ResidualMapError(RecalError, ValueError):
    """A model's ``residual_map`` section is malformed; ``field`` is the JSON path at fault."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


def features(q: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """The embedding φ(q) (N, F): (cos, sin) of each revolute joint, q / 1 m of each prismatic one."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    rev = np.asarray(revolute, dtype=bool)
    return np.hstack([np.cos(q[:, rev]), np.sin(q[:, rev]), q[:, ~rev]])


def sqdist(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances (N, M) between the rows of ``A`` (N, F) and ``B`` (M, F)."""
    d = np.sum(A**2, axis=1)[:, None] + np.sum(B**2, axis=1)[None, :] - 2.0 * A @ B.T
    return np.maximum(d, 0.0)


def corrected_model_sigma(sq_sum_m2: float, noise_sq_sum_m2: float, rows: int) -> float:
    """Per-axis standard uncertainty (m) of the corrected model's position inside its region,
    from cross-validation: ``sq_sum_m2`` the sum over ``rows`` held-out rows inside the region of
    the squared error (3 axes) of the geometric model plus the correction, ``noise_sq_sum_m2`` the
    sum of what the instrument's stated noise gives there (3 σ² a row). The held-out error is the
    model's plus the instrument's, so the model's variance is the difference; when the data cannot
    resolve it (the difference is within the sampling scatter of the noise's own sum of squares,
    ``σ² √(6/n)`` per row), it is taken as that scatter: a bound the data support, never zero.
    Why the held-out rows and not the fit's: the correction was fitted to the others (issue 28:
    "the correction's CV error enters u95")."""
    if rows <= 0:
        return 0.0
    noise_per_row = noise_sq_sum_m2 / rows  # 3 σ² (m²)
    excess = sq_sum_m2 / rows - noise_per_row
    resolution = (noise_per_row / 3.0) * np.sqrt(6.0 / rows)  # scatter of the mean of |noise|²: σ² √(6/n)
    return float(np.sqrt(max(excess, resolution) / 3.0))


def quantile_model_sigma(norms_m: np.ndarray, noise_sigma_m: float, chi2_95: float, floor_m: float) -> float:
    """Per-axis σ (m) of the corrected model inside its region whose 95 % radius (``√χ²₃(0.95)``
    times it, with the instrument's noise ``noise_sigma_m`` per axis added back) equals the 95 %
    quantile of the cross-validated held-out errors ``norms_m`` (N,) there: the split-conformal
    quantile, the ⌈0.95 (N + 1)⌉-th smallest (the largest when N is under 19). Never below
    ``floor_m`` (:func:`corrected_model_sigma`: the RMS's σ). Why not the RMS's σ alone: the error
    left depends on the configuration, so the held-out errors are a mixture, longer-tailed than
    one Gaussian (on a measured UR5 their 95 % quantile was 1.67 RMS against a Gaussian's 1.61),
    and a Gaussian bound from the RMS covered 92.4 % of hold-out errors instead of 95 %; the
    quantile covers 95 % of exchangeable held-out errors whatever their distribution."""
    e = np.sort(np.asarray(norms_m, dtype=float))
    if len(e) == 0:
        return float(floor_m)
    k = min(int(np.ceil(0.95 * (len(e) + 1))), len(e))
    q95 = float(e[k - 1])
    excess = q95**2 / chi2_95 - float(noise_sigma_m) ** 2
    return float(max(np.sqrt(max(excess, 0.0)), floor_m))
