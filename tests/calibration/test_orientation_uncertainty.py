"""A position-only fit's orientation comes with its uncertainty (issue 25, case 2, "done when"):
a simulated UR10e with its reflector 0.05, 0.3 and 1 mm off the last axis (50 mm out along it) is
identified from positions alone, and the true orientation errors on fresh configurations stay
within the 95 % bounds predicted for them. The bound takes the held parameters at their prior
width (calibration.identify.held_covariance): from the freed parameters alone it claimed the tool's
rotation and the last joint's zero known to nothing, and covered a fraction of the errors.

The true error is the rotation between the model's and the true robot's tool frames, its angle
taken by scipy's Rotation (not by our transforms)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.identify import DETERMINED_M, DETERMINED_RAD, identify
from calibration.kinematics import fk
from calibration.model import Units
from calibration.report import identification_block
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.uncertainty import (
    CovarianceError,
    orientation_covariance,
    orientation_from_block,
    prediction_covariance,
    radius_95,
    rotation_covariance,
    stored_orientation_covariance,
)

SIGMA_M = 20e-6
OFFSETS_M = (0.05e-3, 0.3e-3, 1e-3)
SEEDS = (0, 1, 2)


def _case(off_m: float, seed: int):
    rng = np.random.default_rng(seed)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([off_m, 0.0, 0.05])})
    # the tool mounted 0.1 deg off its drawing too: a rotation no position measures
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3, tool_angle_rad=np.radians(0.1))
    train = simulate_measurements(truth, random_configurations(nom, 100, rng), rng, sigma_m=SIGMA_M, targets=("smr",))
    fresh = random_configurations(nom, 200, rng)
    return nom, truth, train, fresh


def _angle_errors(model, truth, q) -> np.ndarray:
    """(N,) rad: the angle of the rotation from the model's tool frame to the true one."""
    R_model, R_true = fk(model, q)[:, :3, :3], fk(truth, q)[:, :3, :3]
    return Rotation.from_matrix(np.transpose(R_model, (0, 2, 1)) @ R_true).magnitude()


@pytest.fixture(scope="module")
def cases():
    out = {}
    for off in OFFSETS_M:
        for seed in SEEDS:
            nom, truth, train, q = _case(off, seed)
            result = identify(nom, train, sigma_m=SIGMA_M)
            assert result.success, result.message
            out[off, seed] = (result, truth, q)
    return out


def test_orientation_errors_stay_within_their_predicted_bounds(cases):
    inside, ratio, freed_only = [], [], []
    for (off, seed), (result, truth, q) in cases.items():
        err = _angle_errors(result.model, truth, q)
        bound = radius_95(orientation_covariance(result, q))
        inside.append(np.mean(err <= bound))
        assert inside[-1] >= 0.8, (off, seed, inside[-1])
        # not absurdly loose: the median bound measured 2.0-4.2 times the RMS error
        ratio.append(np.median(bound) / np.sqrt(np.mean(err**2)))
        # what the freed parameters alone said (the orientation bound before the held ones entered)
        alone = radius_95(rotation_covariance(result.model, list(result.params), prediction_covariance(result), q))
        freed_only.append(np.mean(err <= alone))
    assert np.mean(inside) >= 0.9, inside  # measured: 100 % in every case (conservative, as u95)
    assert np.median(ratio) <= 4.0, ratio  # measured 2.37
    assert max(ratio) <= 6.0, ratio  # measured 4.23
    # without the held parameters the bound was dishonestly tight: measured 47-65 % on a third of
    # the cases (74 % pooled), where the weakly determined j5 parameters did not happen to cover it
    assert min(freed_only) < 0.7 and np.mean(freed_only) < 0.85, freed_only


def test_the_held_parameters_enter_at_their_prior_width(cases):
    result, _, _q = cases[OFFSETS_M[0], SEEDS[0]]
    held = result.held_covariance
    assert held is not None
    names = held["names"]
    # the tool's rotation and the last joint's zero, which positions cannot see, are among them
    assert {"tool.rx", "tool.ry", "tool.rz", "j6.theta"} <= set(names)
    sd = np.sqrt(np.diag(held["matrix"]))
    for n, prior in zip(names, held["prior_sd"]):
        if np.isfinite(prior):  # a held parameter: no better than its prior, nor much worse
            assert sd[names.index(n)] <= prior * (1 + 1e-6), n
    # the freed ones keep the covariance the data gave them, to within what the held ones add
    i = [names.index(p.name) for p in result.params]
    assert np.all(np.diag(held["matrix"])[i] >= np.diag(prediction_covariance(result)) * (1 - 1e-6))


def test_a_model_read_from_a_file_gives_the_same_orientation_bound(cases):
    result, _, q = cases[OFFSETS_M[1], SEEDS[1]]
    block = identification_block(result, Units("mm", "deg"))
    model = dataclasses.replace(result.model, metadata={"identification": block})
    np.testing.assert_allclose(
        stored_orientation_covariance(model, q[:20]), orientation_covariance(result, q[:20]), rtol=1e-9, atol=1e-20
    )
    block["covariance"]["held"]["names"][0] = "j9.theta"
    with pytest.raises(CovarianceError, match=r"no parameter 'j9\.theta'") as exc:
        orientation_from_block(dataclasses.replace(result.model, metadata={"identification": block}))
    assert exc.value.field == "identification.covariance.held.names[0]"
    # a file written before the held parameters were stored: the freed ones' covariance
    del block["covariance"]["held"]
    params, _matrix = orientation_from_block(dataclasses.replace(result.model, metadata={"identification": block}))
    assert [p.name for p in params] == list(result.param_names)


def test_a_weak_parameter_enters_at_the_weak_threshold():
    """A parameter held as weak is known no better than the threshold it was held at: a KR 16 with
    its reflector 0.09 mm off the flange axis, 60 positions, holds base.ty and base.tz as weak, and
    what they move with them (the arm's tilts) widens the orientation bound to several degrees:
    honest (the data determine the orientation no better), and loose. Measured: errors 0.45 deg
    RMS, bound median 6.9 deg, every error inside."""
    rng = np.random.default_rng(0)
    nom = dataclasses.replace(nominal("kr16"), targets={"smr": np.array([0.09e-3, 0.0, 0.0])})
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3)
    train = simulate_measurements(truth, random_configurations(nom, 60, rng), rng, sigma_m=30e-6, targets=("smr",))
    result = identify(nom, train, sigma_m=30e-6)
    weak = {u.name for u in result.unidentifiable if u.category == "weak"}
    assert weak
    held = result.held_covariance
    prior = dict(zip(held["names"], held["prior_sd"]))
    assert all(prior[n] in (DETERMINED_M, DETERMINED_RAD) for n in weak), prior
    q = random_configurations(nom, 200, rng)
    err = _angle_errors(result.model, truth, q)
    bound = radius_95(orientation_covariance(result, q))
    assert np.all(err <= bound)
    assert np.median(bound) < 20 * np.sqrt(np.mean(err**2))  # measured 15 times
