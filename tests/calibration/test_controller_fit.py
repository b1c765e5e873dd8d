"""calibration.controller: a UR controller's own model fitted exactly from its forward
kinematics. The controller is written out in the test: UR's published DH table plus per-joint
deltas in the "linearised" form of its calibration.conf, composed with plain 4x4 matrices
(not calibration.kinematics), so the fit is checked against a reference of its own."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.controller import fit_controller_model, pose_differences
from calibration.robots import nominal

# UR5e published DH (m, rad) and a factory calibration of the linearised kind: delta_d of the
# parallel joints 2-4 tens of metres with a sum near zero (the values of the reference note),
# small twists between the parallel axes.
D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
DELTA_THETA = (2.1e-4, -3.9e-4, 6.2e-4, -2.8e-4, 1.1e-4, 4.9e-4)
DELTA_A = (1.2e-4, 3.1e-4, -2.2e-4, 5e-5, -1.1e-4, 0.0)
DELTA_D = (0.0005, 11.198, -92.527, 81.328, -0.0002, -0.0001)
DELTA_ALPHA = (-4.6e-4, 1.9e-5, -2.7e-5, 3.8e-4, 2.2e-4, 0.0)


def controller_fk(q: np.ndarray) -> np.ndarray:
    """T_base_flange (N, 4, 4): Rz(theta+q)·Tz(d)·Tx(a)·Rx(alpha) per joint, deltas added."""
    out = []
    for row in q:
        T = np.eye(4)
        for i, qi in enumerate(row):
            th = qi + DELTA_THETA[i]
            d, a, al = D[i] + DELTA_D[i], A[i] + DELTA_A[i], ALPHA[i] + DELTA_ALPHA[i]
            ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
            T = T @ np.array(
                [
                    [ct, -st * ca, st * sa, a * ct],
                    [st, ct * ca, -ct * sa, a * st],
                    [0.0, sa, ca, d],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            )
        out.append(T)
    return np.array(out)


def test_the_fit_reproduces_a_linearised_ur_controller_to_well_below_a_micrometre():
    rng = np.random.default_rng(3)
    q_fit, q_check = rng.uniform(-np.pi, np.pi, (2, 40, 6))
    T_fit = controller_fk(q_fit)
    published = nominal("ur5e")
    # the controller differs from the published table by millimetres: a fit worth doing
    dp0, _ = pose_differences(published, q_check, controller_fk(q_check))
    assert dp0.max() > 1e-3
    fit = fit_controller_model(q_fit, T_fit, published)
    assert fit.position_max_m < 1e-9 and fit.rotation_max_rad < 1e-9 and fit.n_poses == 40
    dp, dr = pose_differences(fit.model, q_check, controller_fk(q_check))
    assert dp.max() < 1e-9 and dr.max() < 1e-9
    assert fit.model.convention == "dh" and fit.model.name == "ur5e-controller"
    assert [j.name for j in fit.model.joints] == [j.name for j in published.joints]
    assert fit.model.units == published.units
    # joints 2-4 come out in Hayati's form (small beta) instead of tens of metres of d
    assert [j.hayati for j in fit.model.joints] == [False, True, True, False, False, False]
    assert max(abs(j.d) for j in fit.model.joints) < 0.5


def test_poses_of_no_serial_chain_leave_large_fit_figures():
    """A controller whose poses carry 0.1 mm of noise (not a kinematic chain) cannot be fitted
    exactly, and the figures say so (the command then refuses)."""
    rng = np.random.default_rng(4)
    q = rng.uniform(-np.pi, np.pi, (40, 6))
    T = controller_fk(q)
    T[:, :3, 3] += rng.normal(0.0, 1e-4, (40, 3))
    fit = fit_controller_model(q, T, nominal("ur5e"))
    assert fit.position_max_m > 1e-5


def test_too_few_poses_or_wrong_shapes_are_refused():
    q = np.zeros((4, 6))
    with pytest.raises(ValueError, match="4 poses give 24 equations for 30 parameters"):
        fit_controller_model(q, controller_fk(q), nominal("ur5e"))
    with pytest.raises(ValueError, match="expected q"):
        fit_controller_model(np.zeros((8, 5)), np.zeros((8, 4, 4)), nominal("ur5e"))
