""" "Before" is the starting model placed where it fits the data best, its base and its common
target offset registered (issue 25, case 1): a reflector mounted 50 mm from where the nominal
model says must not read as 50 mm of robot error. Reference: the registration written here as a
plain least-squares problem (scipy), independent of calibration.registration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.identify import identify
from calibration.kinematics import fk
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.uncertainty import validate

SIGMA_M = 20e-6


def _reference_registered_rms(model, q, p_world, p_tool):
    """min over (rotation vector, translation, common tool-frame offset) of the RMS error."""
    T = fk(dataclasses.replace(model, base=np.zeros(6)), q)

    def residual(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        pts = T[:, :3, 3] + np.einsum("nij,j->ni", T[:, :3, :3], p_tool + x[6:9])
        return (pts @ R.T + x[3:6] - p_world).ravel()

    # start from the identity placement; the instrument sits about a metre off in these cells
    sol = least_squares(residual, np.zeros(9), x_scale=np.r_[np.ones(3), np.ones(3), 0.1 * np.ones(3)])
    e = sol.fun.reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.mark.parametrize("offset_m", [0.0, 0.016, 0.05])
def test_a_mounting_offset_of_the_target_does_not_inflate_before(offset_m):
    rng = np.random.default_rng(7)
    smr = np.array([0.0, 0.0, 0.05])
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": smr})
    truth = perturbed(nom, rng, base_length_m=0.05, base_angle_rad=0.05)
    # the reflector really sits offset_m further along z than the nominal model says
    truth = dataclasses.replace(truth, targets={"smr": smr + [0.0, 0.0, offset_m]})
    train = simulate_measurements(truth, random_configurations(nom, 60, rng), rng, sigma_m=SIGMA_M, targets=("smr",))
    hold = simulate_measurements(truth, random_configurations(nom, 200, rng), rng, sigma_m=SIGMA_M, targets=("smr",))
    result = identify(nom, train, sigma_m=SIGMA_M)
    v = validate(result, hold)
    reference = _reference_registered_rms(result.start_model, hold.q, hold.p_world, smr)
    assert v.before_rms_m == pytest.approx(reference, rel=1e-3, abs=1e-7)
    # the robot's own error (links and joints, a few millimetres), not the reflector's mounting
    assert v.before_rms_m < 0.5 * max(offset_m, 0.01) or offset_m == 0.0
    # the registration's figure includes the offset it estimated, as the reference does
    train_ref = _reference_registered_rms(result.start_model, train.q, train.p_world, smr)
    assert result.registration["rms_after_m"] == pytest.approx(train_ref, rel=1e-3, abs=1e-7)
