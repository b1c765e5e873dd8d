"""``kabsch_levelled``: a turn about the vertical and a shift, from one or more points."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from calibration.registration import kabsch_levelled


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_exact_turn_and_shift_from_two_points():
    rng = np.random.default_rng(4)
    for _ in range(10):
        yaw, t = rng.uniform(-np.pi, np.pi), rng.normal(size=3)
        src = rng.normal(size=(2, 3))
        T = kabsch_levelled(src, src @ _rz(yaw).T + t)
        assert np.allclose(T[:3, :3], _rz(yaw)) and np.allclose(T[:3, 3], t)


def test_one_point_is_a_shift():
    T = kabsch_levelled(np.array([1.0, 2.0, 3.0]), np.array([1.5, 1.0, 3.25]))
    assert np.allclose(T[:3, :3], np.eye(3)) and np.allclose(T[:3, 3], [0.5, -1.0, 0.25])


def test_noisy_points_give_the_least_squares_turn():
    """Against a complete reference: the yaw minimising the sum of squared residuals found by a
    1-D search, the shift then the centroids' difference."""
    rng = np.random.default_rng(5)
    src = rng.normal(size=(6, 3))
    dst = src @ _rz(0.7).T + [0.3, -0.2, 0.1] + rng.normal(0, 0.05, (6, 3))

    def cost(yaw):
        R = _rz(yaw)
        t = dst.mean(axis=0) - R @ src.mean(axis=0)
        return float(np.sum((src @ R.T + t - dst) ** 2))

    best = minimize_scalar(cost, bounds=(0.0, 1.4), method="bounded", options={"xatol": 1e-10}).x
    T = kabsch_levelled(src, dst)
    assert np.allclose(T[:3, :3], _rz(best), atol=1e-7)
    assert cost(np.arctan2(T[1, 0], T[0, 0])) <= cost(best) + 1e-12
