"""Identification (calibration.identify) on simulated robots: accuracy against the truth,
registration, several targets, robust losses, parallel axes, identifiability reasons,
uncertainty, gains, prismatic joints and bad input.

"Noise floor": the hold-out error of the identified model against the noise-free truth, compared
with what identifying in the truth's own parameterisation (``poe``, from ``to_poe`` of the
nominal) achieves on the same data (the issue's target: ratio < 1.2).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from sample_models import fanuc_r2000ic_doc, stanford_5r1p_doc

from calibration.conventions import to_poe
from calibration.identification import IdentificationResult, Measurements
from calibration.identify import identify
from calibration.kinematics import fk, target_positions
from calibration.model import model_from_dict
from calibration.parameters import apply_step, candidate_parameters
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.transforms import matrix_to_rotvec
from calibration.uncertainty import position_covariance, predicted_uncertainty, validate

SIGMA = 20e-6  # m, per axis
# The hold-out RMS 3D error of a model identified to the noise floor: about SIGMA·sqrt(3P/M)
# (P parameters, M residuals), 0.6-1.0 SIGMA with the data sets below.
FLOOR = 1.5 * SIGMA
FAR_BASE = np.array([3.0, -2.0, 0.5, 0.02, -0.03, 2.5])  # instrument metres away, yaw 143 deg


def _far(truth, base=FAR_BASE, tool=None):
    return dataclasses.replace(truth, base=np.asarray(base, float), **({} if tool is None else {"tool": tool}))


def _holdout_rms(model, truth, q, target=None):
    """RMS (m) of the 3D position error against the noise-free truth."""
    e = target_positions(model, q, target) - target_positions(truth, q, target)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.fixture(scope="module")
def ur10e():
    return nominal("ur10e")


@pytest.fixture(scope="module")
def far_case(ur10e):
    """A perturbed UR10e seen from an instrument metres away; 50 poses; identified from the
    nominal DH model and from its poe form."""
    rng = np.random.default_rng(0)
    truth = _far(perturbed(ur10e, rng))
    data = simulate_measurements(truth, random_configurations(ur10e, 50, rng), rng, sigma_m=SIGMA)
    q_hold = random_configurations(ur10e, 300, rng)
    return truth, data, q_hold, identify(ur10e, data), identify(to_poe(ur10e), data)


# --------------------------------------------------------------------------- (a) far base


def test_far_base_identified_to_the_noise_floor(far_case):
    truth, data, q_hold, result, result_poe = far_case
    assert isinstance(result, IdentificationResult)
    assert result.success and result.status > 0
    # the instrument frame was found by registration first
    assert result.registration["applied"] and "Kabsch" in result.registration["method"]
    assert result.registration["rms_before_m"] > 1.0 and result.registration["rms_after_m"] < 0.01
    # training residuals: 3D RMS of noise with 3(1 - P/M) degrees of freedom per row
    P, M = len(result.params), 3 * len(data)
    expected = SIGMA * math.sqrt(3 * (1 - P / M))
    assert 0.8 * expected < result.rms_m < 1.2 * expected
    assert result.sigma_scale < 1.2
    hold = _holdout_rms(result.model, truth, q_hold)
    hold_poe = _holdout_rms(result_poe.model, truth, q_hold)
    assert hold < FLOOR
    assert hold / hold_poe < 1.2
    # and the nominal was millimetres off (after registration)
    assert _holdout_rms(result.start_model, truth, q_hold) > 50 * hold


def test_result_is_a_frozen_record(far_case):
    result = far_case[3]
    P = len(result.params)
    assert result.values.shape == result.steps.shape == result.std_errors.shape == (P,)
    assert result.covariance.shape == result.correlation.shape == (P, P)
    np.testing.assert_allclose(np.diag(result.correlation), 1.0)
    assert result.residuals_m.shape == (len(far_case[1]), 3)
    assert result.param_names == tuple(p.name for p in result.params)
    assert result.iterations >= 1 and result.nfev >= result.iterations
    assert list(result.cost_history) == sorted(result.cost_history, reverse=True)
    assert "converged" in result.message
    assert math.isfinite(result.condition_number) and result.condition_number >= 1
    assert set(result.observability) >= {"O1_borm_menq", "O2_inverse_condition", "O3_min_singular"}
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.success = False  # type: ignore[misc]
    # the identified model is in the units of the nominal and carries no stale metadata
    assert result.model.units == nominal("ur10e").units and dict(result.model.metadata) == {}


# --------------------------------------------------------------------------- (b) full pose


def test_full_pose_base_and_tool_far_off(ur10e):
    """Full-pose data with base AND tool far off: robot-world/hand-eye registration gives both,
    then the refinement reaches the noise floor in position and orientation."""
    rng = np.random.default_rng(1)
    truth = _far(
        perturbed(ur10e, rng),
        base=[2.5, 1.5, -0.3, 0.1, -0.05, -2.0],
        tool=np.array([0.05, -0.08, 0.15, 1.2, -0.4, 2.2]),
    )
    sigma_rad = 2e-4
    data = simulate_measurements(
        truth, random_configurations(ur10e, 40, rng), rng, sigma_m=SIGMA, full_pose=True, sigma_rad=sigma_rad
    )
    result = identify(ur10e, data, sigma_rad=sigma_rad)
    assert result.success
    assert "hand-eye" in result.registration["method"] and result.registration["applied"]
    assert result.registration["rms_before_m"] > 1.0
    assert len(result.params) == 30  # complete: 4R + 6 with the base, full-pose data
    assert result.rms_rad < 2 * sigma_rad * math.sqrt(3)
    q = random_configurations(ur10e, 200, rng)
    Ti, Tt = fk(result.model, q), fk(truth, q)
    pos = np.sqrt(np.mean(np.sum((Ti[:, :3, 3] - Tt[:, :3, 3]) ** 2, axis=1)))
    rot = np.sqrt(np.mean(np.sum(matrix_to_rotvec(Ti[:, :3, :3] @ np.swapaxes(Tt[:, :3, :3], 1, 2)) ** 2, axis=1)))
    assert pos < FLOOR and rot < 1.5 * sigma_rad


@pytest.mark.parametrize("seed", [3, 4])
def test_full_pose_tool_aligned_with_the_last_link_is_well_conditioned(ur10e, seed):
    """Regression: a tool without rotation (the common case) is, after hand-eye registration,
    nearly but not exactly aligned with link 6. The last link's a, d, alpha must not be freed next
    to the tool's six motions (they span the same rigid motions): with both, the problem was
    ill-conditioned (cond 1e6), j6.a and tool.tx drifted to ±tens of metres and LM ran out of
    iterations."""
    rng = np.random.default_rng(seed)
    truth = _far(perturbed(ur10e, rng), tool=np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))
    data = simulate_measurements(
        truth, random_configurations(ur10e, 40, rng), rng, sigma_m=SIGMA, full_pose=True, sigma_rad=1e-4
    )
    result = identify(ur10e, data, sigma_rad=1e-4)
    assert result.success and result.iterations < 20
    assert result.condition_number < 1e3
    assert np.max(np.abs(result.steps)) < 0.05  # no parameter wandered off
    assert {"j6.d", "j6.a", "j6.alpha"} <= {u.name for u in result.unidentifiable}
    assert _holdout_rms(result.model, truth, random_configurations(ur10e, 100, rng)) < FLOOR


def test_rows_without_orientation_are_position_rows(ur10e):
    rng = np.random.default_rng(2)
    truth = _far(perturbed(ur10e, rng), tool=np.array([0.0, 0.0, 0.1, 0.3, 0.0, 0.0]))
    data = simulate_measurements(
        truth, random_configurations(ur10e, 40, rng), rng, sigma_m=SIGMA, full_pose=True, sigma_rad=1e-4
    )
    quat = data.quat.copy()
    quat[::2] = np.nan  # every other row has no orientation
    data = dataclasses.replace(data, quat=quat)
    assert data.has_orientation.sum() == 20
    result = identify(ur10e, data, sigma_rad=1e-4)
    assert result.success and not np.any(result.residuals_rad[::2])
    q = random_configurations(ur10e, 100, rng)
    assert _holdout_rms(result.model, truth, q) < FLOOR


# --------------------------------------------------------------------------- (c) three reflectors


def test_three_reflectors_with_their_own_offsets(ur10e):
    """Three reflectors measured at every configuration, each mounted a millimetre or so away
    from where the nominal says: their offsets are identified together with the robot."""
    design = {"r1": [0.06, 0.0, 0.04], "r2": [-0.03, 0.052, 0.04], "r3": [-0.03, -0.052, 0.04]}
    nom = dataclasses.replace(ur10e, targets=design)
    rng = np.random.default_rng(7)
    true_targets = {k: np.asarray(v) + rng.normal(0, 1e-3, 3) for k, v in design.items()}
    truth = dataclasses.replace(_far(perturbed(nom, rng)), targets=true_targets)
    data = simulate_measurements(
        truth, random_configurations(nom, 40, rng), rng, sigma_m=SIGMA, targets=("r1", "r2", "r3")
    )
    assert len(data) == 120 and list(data.target[:3]) == ["r1", "r2", "r3"]
    result = identify(nom, data)
    assert result.success
    assert {f"target.{t}.{s}" for t in ("r1", "r2") for s in "xyz"} <= set(result.param_names)
    # complete: 30 for the chain + 9 target coordinates - 6 for the tool frame they share
    assert len(result.params) == 33
    # the reflectors' distances from each other (independent of how the tool frame is chosen)
    for a, b in (("r1", "r2"), ("r2", "r3"), ("r1", "r3")):
        d_id = np.linalg.norm(result.model.targets[a] - result.model.targets[b])
        d_true = np.linalg.norm(true_targets[a] - true_targets[b])
        assert abs(d_id - d_true) < 3e-5
    q = random_configurations(nom, 100, rng)
    poe = identify(to_poe(nom), data)
    for t in ("r1", "r2", "r3"):
        hold = _holdout_rms(result.model, truth, q, t)
        assert hold < FLOOR and hold / _holdout_rms(poe.model, truth, q, t) < 1.2
        assert _holdout_rms(nom, truth, q, t) > 1e-3  # the nominal (in the registered frame) is not


# --------------------------------------------------------------------------- (d) robust loss


@pytest.fixture(scope="module")
def bumped_case(ur10e):
    rng = np.random.default_rng(2)
    truth = _far(perturbed(ur10e, rng), base=[2.0, -1.0, 0.2, 0.0, 0.0, 1.0])
    data = simulate_measurements(truth, random_configurations(ur10e, 60, rng), rng, sigma_m=SIGMA)
    bumped = np.array([5, 17, 33, 48])
    p = data.p_world.copy()
    direction = rng.normal(size=(4, 3))
    p[bumped] += 4e-3 * direction / np.linalg.norm(direction, axis=1, keepdims=True)  # a reflector knocked 4 mm
    return truth, dataclasses.replace(data, p_world=p), bumped, random_configurations(ur10e, 200, rng)


@pytest.mark.parametrize("loss", ["soft_l1", "huber", "cauchy"])
def test_robust_loss_names_the_bumped_rows(ur10e, bumped_case, loss):
    truth, data, bumped, q_hold = bumped_case
    robust = identify(ur10e, data, loss=loss)
    assert robust.success
    assert set(bumped) <= set(robust.outliers)
    assert len(robust.outliers) <= len(bumped) + 0.1 * len(data)  # few ordinary rows
    assert np.all(robust.row_weights[bumped] < 0.1)
    clean = np.setdiff1d(np.arange(len(data)), bumped)
    assert np.median(robust.row_weights[clean]) > 0.7  # cauchy down-weights even ordinary rows a little
    assert _holdout_rms(robust.model, truth, q_hold) < FLOOR


def test_linear_loss_is_ruined_by_the_bumped_rows(ur10e, bumped_case):
    truth, data, _bumped, q_hold = bumped_case
    linear = identify(ur10e, data, loss="linear")
    robust = identify(ur10e, data, loss="soft_l1")
    assert _holdout_rms(linear.model, truth, q_hold) > 5 * _holdout_rms(robust.model, truth, q_hold)
    assert np.all(linear.row_weights == 1.0)
    assert linear.sigma_scale > 5  # the misfit shows in the residuals


# --------------------------------------------------------------------------- (e) parallel axes


@pytest.fixture(scope="module")
def parallel_case(ur10e):
    """Axes 2-3-4 of a UR10e out of parallel by about 0.05 deg in both directions."""
    rng = np.random.default_rng(10)
    poe = perturbed(ur10e, rng, angle_rad=0.0)  # offsets and shifts only
    params = candidate_parameters(poe)
    idx = {p.name: k for k, p in enumerate(params)}
    step = np.zeros(len(params))
    for name, deg in (("j3.tilt_x", 0.05), ("j3.tilt_y", 0.05), ("j4.tilt_x", -0.05), ("j4.tilt_y", 0.03)):
        step[idx[name]] = math.radians(deg)
    truth = _far(apply_step(poe, params, step), base=[1.5, 0.5, 0.0, 0.0, 0.0, 0.7])
    data = simulate_measurements(truth, random_configurations(ur10e, 60, rng), rng, sigma_m=SIGMA)
    return truth, data, random_configurations(ur10e, 200, rng)


def test_nearly_parallel_axes_identified_through_hayati(ur10e, parallel_case):
    truth, data, q_hold = parallel_case
    result = identify(ur10e, data)
    assert any("Hayati" in n and "j2" in n for n in result.notes)
    assert any("Hayati" in n and "j3" in n for n in result.notes)
    assert {"j2.beta", "j3.beta"} <= set(result.param_names)
    betas = [abs(math.degrees(result.model.joints[k].beta)) for k in (1, 2)]
    assert max(betas) > 0.01  # the tilt was found (it is not in the nominal)
    hold = _holdout_rms(result.model, truth, q_hold)
    hold_poe = _holdout_rms(identify(to_poe(ur10e), data).model, truth, q_hold)
    assert hold < FLOOR and hold / hold_poe < 1.2


def test_plain_dh_cannot_follow_the_tilt(ur10e, parallel_case):
    """Without Hayati's beta (book §2.6), plain DH cannot describe the tilt: the fit is far worse
    and its residuals say so (sigma_scale, the ratio of the residuals to the stated noise)."""
    truth, data, q_hold = parallel_case
    plain = identify(ur10e, data, hayati=False)
    hayati = identify(ur10e, data)
    assert not any(j.hayati for j in plain.model.joints)
    assert _holdout_rms(plain.model, truth, q_hold) > 5 * _holdout_rms(hayati.model, truth, q_hold)
    assert plain.sigma_scale > 3 and hayati.sigma_scale < 1.3


# --------------------------------------------------------------------------- (f) reasons


def test_unidentifiable_reasons(far_case):
    result = far_case[3]
    why = {u.name: u for u in result.unidentifiable}
    for r in ("tool.rx", "tool.ry", "tool.rz"):
        assert "tool orientation is unobservable from position-only data" in why[r].reason
    j1 = why["j1.theta"]
    assert "same motion" in j1.reason and "base.rz" in j1.reason
    assert j1.relation[0][0] == "base.rz" and abs(j1.relation[0][1]) == pytest.approx(1.0, abs=1e-6)
    assert why["j1.d"].relation[0][0] == "base.tz"
    # nothing is both freed and reported unidentifiable
    assert not set(why) & set(result.param_names)


def test_fixed_parameters_are_not_freed(ur10e, far_case):
    _truth, data, _q_hold, *_ = far_case
    result = identify(ur10e, data, fixed=("j2.a", "j3.*"))
    assert "j2.a" not in result.param_names
    assert not any(n.startswith("j3.") for n in result.param_names)
    assert result.model.joints[1].a == pytest.approx(ur10e.joints[1].a)


# --------------------------------------------------------------------------- (g) uncertainty


def test_predicted_uncertainty_is_honest(ur10e, far_case):
    """Hold-out coverage of the predicted 95 % region is close to 95 %."""
    truth, _data, q_hold, result, _ = far_case
    holdout = simulate_measurements(truth, q_hold, np.random.default_rng(40), sigma_m=SIGMA)
    v = validate(result, holdout)
    assert v.n == 300
    assert 0.88 <= v.coverage_95 <= 0.99
    assert v.rms_m < 2 * SIGMA * math.sqrt(3) and v.before_rms_m > 10 * v.rms_m
    C = position_covariance(result, q_hold[:10])
    assert C.shape == (10, 3, 3) and np.all(np.linalg.eigvalsh(C) > -1e-20)
    u = predicted_uncertainty(result, q_hold[:10])
    assert u.shape == (10,) and np.all((u > 0) & (u < 5 * SIGMA))


def test_standard_errors_shrink_as_one_over_sqrt_n(ur10e):
    rng = np.random.default_rng(41)
    truth = _far(perturbed(ur10e, rng))
    small = identify(ur10e, simulate_measurements(truth, random_configurations(ur10e, 50, rng), rng, sigma_m=SIGMA))
    large = identify(ur10e, simulate_measurements(truth, random_configurations(ur10e, 200, rng), rng, sigma_m=SIGMA))
    assert small.param_names == large.param_names
    # the information part only: sigma_scale >= 1 inflates small data sets a little more
    ratio = (small.std_errors / small.sigma_scale) / (large.std_errors / large.sigma_scale)
    assert 1.7 < np.median(ratio) < 2.3


# --------------------------------------------------------------------------- (h) gains


def test_gains_identified(ur10e):
    rng = np.random.default_rng(5)
    true_gains = np.array([1.0008, 0.9994, 1.0005, 0.9990, 1.0012, 0.9997])
    truth = _far(perturbed(ur10e, rng))
    truth = dataclasses.replace(
        truth, joints=tuple(dataclasses.replace(j, gain=g) for j, g in zip(truth.joints, true_gains))
    )
    data = simulate_measurements(truth, random_configurations(ur10e, 80, rng), rng, sigma_m=SIGMA)
    q = random_configurations(ur10e, 200, rng)
    with_gains = identify(ur10e, data, gains=True)
    without = identify(ur10e, data)
    names = with_gains.param_names
    for i in range(5):  # j6's gain does not move a point on its own axis
        k = names.index(f"j{i + 1}.gain")
        err = with_gains.values[k] - true_gains[i]
        assert abs(err) < 5 * with_gains.std_errors[k] and abs(err) < 1e-4  # true errors up to 1.2e-3
    assert "j6.gain" in {u.name for u in with_gains.unidentifiable}
    assert _holdout_rms(with_gains.model, truth, q) < FLOOR
    assert _holdout_rms(without.model, truth, q) > 20 * _holdout_rms(with_gains.model, truth, q)
    assert not any(n.endswith(".gain") for n in without.param_names)


# --------------------------------------------------------------------------- (i) prismatic joint


def test_prismatic_robot(ur10e):
    """The 5R1P of the book's Table 4.1 (inches, degrees), base far off."""
    nom = model_from_dict(stanford_5r1p_doc(5.0))
    rng = np.random.default_rng(6)
    truth = _far(perturbed(nom, rng), base=[1.0, 2.0, 0.3, 0.0, 0.0, 2.0])
    data = simulate_measurements(truth, random_configurations(nom, 60, rng), rng, sigma_m=SIGMA)
    result = identify(nom, data)
    assert result.success
    assert result.model.joints[2].type == "prismatic" and "j3.d" in result.param_names
    # the book's l_3 and r_4 are not free (the prismatic axis may pass through frame 3)
    assert {"j3.a", "j4.d"} <= {u.name for u in result.unidentifiable}
    q = random_configurations(nom, 200, rng)
    hold = _holdout_rms(result.model, truth, q)
    hold_poe = _holdout_rms(identify(to_poe(nom), data).model, truth, q)
    assert hold < FLOOR and hold / hold_poe < 1.2
    assert result.model.units == nom.units


def test_coupled_robot():
    """The Fanuc coupling of contracts §2 travels through perturbation and identification: the
    data hold the controller's readings (J3 relative to the horizon)."""
    nom = model_from_dict(fanuc_r2000ic_doc())
    rng = np.random.default_rng(3)
    truth = _far(perturbed(nom, rng), base=[2.0, 3.0, -0.4, 0.0, 0.0, -2.0])
    assert truth.coupling is not None
    data = simulate_measurements(truth, random_configurations(nom, 50, rng), rng, sigma_m=SIGMA, targets=("smr1",))
    result = identify(nom, data)
    assert result.success
    np.testing.assert_array_equal(result.model.coupling, nom.coupling)
    q = random_configurations(nom, 200, rng)
    hold = _holdout_rms(result.model, truth, q, "smr1")
    hold_poe = _holdout_rms(identify(to_poe(nom), data).model, truth, q, "smr1")
    assert hold < FLOOR and hold / hold_poe < 1.2


# --------------------------------------------------------------------------- (j) bad input


def test_bad_input_raises_clear_errors(ur10e, far_case):
    data = far_case[1]
    with pytest.raises(ValueError, match="5 joint columns but the model has 6 joints"):
        identify(ur10e, Measurements(data.q[:, :5], data.p_world))
    with pytest.raises(KeyError, match="unknown target 'smr9'"):
        identify(ur10e, dataclasses.replace(data, target=np.array(["smr9"] * len(data), dtype=object)))
    q = data.q.copy()
    q[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        identify(ur10e, Measurements(q, data.p_world))
    p = data.p_world.copy()
    p[7, 0] = np.inf
    with pytest.raises(ValueError, match="finite"):
        identify(ur10e, Measurements(data.q, p))
    with pytest.raises(ValueError, match="`loss` must be one of"):
        identify(ur10e, data, loss="l1")
    with pytest.raises(ValueError, match="`register` must be"):
        identify(ur10e, data, register="sometimes")


def test_measurement_shapes_are_checked(far_case):
    data = far_case[1]
    with pytest.raises(ValueError):
        Measurements(data.q, data.p_world[:-1])
    m = Measurements(data.q[0], data.p_world[0])  # a single row
    assert len(m) == 1 and m.q.shape == (1, 6)
    sub = data.subset(np.arange(10))
    assert len(sub) == 10 and list(sub.row) == list(range(1, 11))


def test_row_sigma_weights_the_rows(ur10e):
    """Rows with a stated larger uncertainty count less: a noisy half with sigma says so and the
    fit follows the good half."""
    rng = np.random.default_rng(9)
    truth = _far(perturbed(ur10e, rng))
    q = random_configurations(ur10e, 80, rng)
    data = simulate_measurements(truth, q, rng, sigma_m=SIGMA)
    p = data.p_world.copy()
    noisy = np.arange(len(data)) % 2 == 1
    p[noisy] += rng.normal(0, 1e-3, (noisy.sum(), 3))
    sigma = np.where(noisy, 1e-3, SIGMA)
    weighted = identify(ur10e, dataclasses.replace(data, p_world=p, sigma=sigma))
    unweighted = identify(ur10e, dataclasses.replace(data, p_world=p))
    q_hold = random_configurations(ur10e, 200, rng)
    assert _holdout_rms(weighted.model, truth, q_hold) < 0.5 * _holdout_rms(unweighted.model, truth, q_hold)
