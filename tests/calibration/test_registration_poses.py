"""Full-pose registration ``T_meas ≈ X · T_pred · Y`` at the sizes real data sets have.

Found on public measured data (a UR10 with a T-Mac, 2,218 full-pose rows, issue 28's bench):
``recal identify`` peaked at 6.2 GB resident, quadratic in the rows (0.37 GB at 500, 1.3 GB at
1,000), because the registration's SVD built the full 9N x 9N left factor it never used. At
20,000 poses that factor alone is 259 GB: a MemoryError before the fix.
"""

from __future__ import annotations

import numpy as np

from calibration.registration import register_poses
from calibration.transforms import homogeneous, rotvec_to_matrix


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    R = rotvec_to_matrix(rng.normal(size=(n, 3)))
    return homogeneous(R, rng.uniform(-1000.0, 1000.0, size=(n, 3)))


def test_register_poses_recovers_both_frames_from_20000_poses():
    rng = np.random.default_rng(7)
    T_pred = _random_poses(rng, 20_000)
    X = homogeneous(rotvec_to_matrix(np.array([0.3, -1.1, 2.0])), np.array([1800.0, -600.0, 300.0]))
    Y = homogeneous(rotvec_to_matrix(np.array([-0.02, 0.01, 1.5])), np.array([0.1, -0.2, 109.0]))
    T_meas = X @ T_pred @ Y

    X_fit, Y_fit = register_poses(T_pred, T_meas)

    np.testing.assert_allclose(X_fit, X, atol=1e-8)
    np.testing.assert_allclose(Y_fit, Y, atol=1e-8)
