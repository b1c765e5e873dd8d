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
