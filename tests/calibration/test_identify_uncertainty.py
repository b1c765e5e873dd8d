"""Honest uncertainty (issue 14): the predicted 95 % bounds cover about 95 % of hold-out errors on
random arms, also with the reflector nominally on the last axis; a noisier instrument than
stated, or an unmodelled sag, shows in the residuals (scaled sigma, cross-validation) and in the
χ² test, not as a bound that covers a few percent.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from complete_reference import random_case

from calibration.identification import Measurements
from calibration.identify import identify
from calibration.kinematics import target_positions
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.uncertainty import (
    chi2_quantile,
    position_covariance,
    predicted_uncertainty,
    structure_sigma,
    validate,
)

SIGMA = 20e-6


# a series of random 6R arms, the even ones with the reflector nominally on the last axis
# (complete_reference.random_case): enough of them that the pooled coverage of the true errors,
# which varies from arm to arm by several percent (one arm's errors all come from one draw of
# its parameters' errors), is known to about ±1 %
ARMS = 40


@pytest.mark.slow  # forty identifications and their covariance at 800 configurations: several seconds
def test_the_95_percent_bounds_cover_95_percent_on_random_arms():
    """Over random arms, half with the reflector nominally on the last axis: identified from 150
    rows with the stated noise and checked at 800 other configurations, the predicted 95 %
    regions hold 93-97 % of (a) the model's true errors (against the true robot, no noise: the
    covariance for predictions, a χ²₃ ellipsoid; the issue's u95 covered as little as 8 % of
    them with a reflector on the flange axis) and (b) the measured hold-out errors
    (``inside_predicted_95``: the covariance plus the scaled noise); the reported u95 radius
    (the largest principal axis) covers at least 95 % of the true errors."""
    q95 = chi2_quantile(0.95, 3)
    true_in = measured_in = radius_in = 0.0
    n = 0
    for seed in range(ARMS):
        nom, truth, rng = random_case(seed)
        data = simulate_measurements(truth, random_configurations(nom, 150, rng), rng, sigma_m=SIGMA, targets=("smr",))
        hold = simulate_measurements(truth, random_configurations(nom, 800, rng), rng, sigma_m=SIGMA, targets=("smr",))
        result = identify(nom, data, sigma_m=SIGMA)
        e = target_positions(result.model, hold.q, "smr") - target_positions(truth, hold.q, "smr")
        C = position_covariance(result, hold.q, "smr")
        d2 = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
        inside = float(np.mean(d2 <= q95))
        assert inside > 0.6, (seed, inside, result.warnings)  # no arm's bound far off (was 12 %, 18 %, 54 %)
        v = validate(result, hold)
        assert 0.9 < v.coverage_95 < 0.99, (seed, v.coverage_95)
        true_in += inside * len(e)
        measured_in += v.coverage_95 * v.n
        radius_in += float(np.mean(np.linalg.norm(e, axis=1) <= predicted_uncertainty(result, hold.q, "smr"))) * len(e)
        n += len(e)
    assert 0.93 <= true_in / n <= 0.97, true_in / n
    assert 0.93 <= measured_in / n <= 0.97, measured_in / n
    assert radius_in / n >= 0.95, radius_in / n


def _ur10e_case(rng, *, noise_m=SIGMA, sag_deg=0.0, n=200):
    """Measurements of a perturbed UR10e's reflector, with ``noise_m`` per axis and a sag of
    joints 2 and 3 (an error of ``sag_deg`` times the cosine of the arm's angle to the horizon):
    the nominal, ``n`` rows, 1,000 hold-out rows, and where the real reflector is (no noise)."""
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.03, 0.0, 0.05])})
    truth = perturbed(nom, rng)

    def real(q):
        bent = q.copy()
        bent[:, 1] += np.deg2rad(sag_deg) * np.cos(q[:, 1])
        bent[:, 2] += np.deg2rad(sag_deg) * np.cos(q[:, 1] + q[:, 2])
        return target_positions(truth, bent, "smr")

    def measure(count):
        q = random_configurations(nom, count, rng)
        p = real(q) + rng.normal(0, noise_m, (count, 3))
        return Measurements(q, p, target=np.array(["smr"] * count, dtype=object))

    return nom, measure(n), measure(1000), real


def _inside_95(result, q, real_p):
    """The share of the model's true errors at ``q`` inside its predicted 95 % region."""
    e = target_positions(result.model, q, "smr") - real_p
    C = position_covariance(result, q, "smr")
    return float(
        np.mean(np.einsum("ni,ni->n", e, np.linalg.solve(C, e[:, :, None])[:, :, 0]) <= chi2_quantile(0.95, 3))
    )


def test_a_right_model_is_consistent_and_cross_validates_at_the_noise():
    nom, data, _, _ = _ur10e_case(np.random.default_rng(1))
    result = identify(nom, data, sigma_m=SIGMA)
    assert result.consistency["consistent"] and result.consistency["p_value"] > 0.001
    cv = result.cross_validation
    assert cv["folds"] == 5 and 0.85 < cv["scale"] < 1.15, cv
    assert result.rms_m < cv["rms_m"] < 1.3 * result.rms_m
    assert result.model_error_scale < 1.1


def test_a_noisier_instrument_than_stated_widens_the_bound_it_is_checked_with():
    """Twice the stated noise: the covariance grows by sigma_scale, and the hold-out check's
    region with it (inside_predicted_95 about 95 %, not 51 %); the χ² test flags it. The data
    cannot tell this excess from an unmodelled effect (below), so the model's own bound takes it
    for one and covers the model's true errors more than 95 % (conservative, not too narrow)."""
    nom, data, hold, real = _ur10e_case(np.random.default_rng(2), noise_m=2 * SIGMA)
    result = identify(nom, data, sigma_m=SIGMA)
    assert 1.8 < result.sigma_scale < 2.2
    assert not result.consistency["consistent"]
    assert 0.92 < validate(result, hold).coverage_95 < 0.98
    assert _inside_95(result, hold.q, real(hold.q)) >= 0.95


def test_an_unmodelled_sag_is_not_hidden():
    """A sag of 0.005° the rigid model cannot describe, on six arms: the residuals and the
    cross-validated error exceed the stated noise, the χ² test says so, and the model's predicted
    95 % region (parameters and the model-structure error the residuals show) holds about 90 % of
    its true errors (the issue's u95 held 12 %, and 10-18 % here before the structure term: the
    parameters' covariance, however scaled, cannot describe an error of the model's form; the
    in-sample excess slightly underestimates it at new configurations), and the hold-out check
    (inside_predicted_95) about as many of the measured errors."""
    inside = measured = 0.0
    for seed in range(3, 9):
        nom, data, hold, real = _ur10e_case(np.random.default_rng(seed), sag_deg=0.005)
        result = identify(nom, data, sigma_m=SIGMA)
        assert not result.consistency["consistent"] and result.sigma_scale > 1.3
        assert result.cross_validation["rms_m"] > result.rms_m
        assert structure_sigma(result) > SIGMA, structure_sigma(result)  # the sag's error is larger than the noise
        share = _inside_95(result, hold.q, real(hold.q))
        assert share > 0.8, (seed, share)
        inside += share / 6
        measured += validate(result, hold).coverage_95 / 6
    assert inside > 0.87 and measured > 0.87, (inside, measured)


def test_the_stored_covariance_grows_as_the_cross_validation_says():
    """The model file keeps model_error_scale beside the covariance; what `recal predict
    --uncertainty` propagates (covariance_from_block) is the covariance times its square, plus
    the stored model-structure error (structure_sigma_from_block)."""
    from calibration.model import Units
    from calibration.report import identification_block
    from calibration.uncertainty import (
        CovarianceError,
        covariance_from_block,
        prediction_covariance,
        propagate,
        stored_position_covariance,
        structure_sigma_from_block,
    )

    nom, data, _, _ = _ur10e_case(np.random.default_rng(3), sag_deg=0.005)
    result = identify(nom, data, sigma_m=SIGMA)
    block = identification_block(result, Units("mm", "deg"))
    block["covariance"]["model_error_scale"] = 1.7  # as if the cross-validation had said so
    model = dataclasses.replace(result.model, metadata={"identification": block})
    names, matrix = covariance_from_block(model)
    assert [p.name for p in names] == list(result.param_names)
    np.testing.assert_allclose(matrix, result.covariance * 1.7**2, rtol=1e-12)
    np.testing.assert_allclose(prediction_covariance(dataclasses.replace(result, model_error_scale=1.7)), matrix)
    # and the model-structure error the sag's residuals showed, which predictions add
    assert block["covariance"]["structure_sigma_m"] == pytest.approx(structure_sigma(result))
    assert structure_sigma(result) > SIGMA
    assert structure_sigma_from_block(model) == block["covariance"]["structure_sigma_m"]
    q = data.q[:5]
    C = position_covariance(result, q, "smr") - propagate(
        result.model, list(result.params), prediction_covariance(result), q, np.array(["smr"] * 5, dtype=object)
    )
    np.testing.assert_allclose(C, np.broadcast_to(structure_sigma(result) ** 2 * np.eye(3), (5, 3, 3)), atol=1e-24)
    # what a model read from a file or the store predicts (recal predict, the result page) is the
    # identification's own position covariance, the stored scale included
    as_written = dataclasses.replace(
        result.model, metadata={"identification": identification_block(result, Units("mm", "deg"))}
    )
    np.testing.assert_allclose(
        stored_position_covariance(as_written, q, "smr"), position_covariance(result, q, "smr"), rtol=1e-9, atol=1e-24
    )
    block["covariance"]["model_error_scale"] = 0.5
    with pytest.raises(CovarianceError, match="expected a number >= 1") as exc:
        covariance_from_block(dataclasses.replace(result.model, metadata={"identification": block}))
    assert exc.value.field == "identification.covariance.model_error_scale"
    block["covariance"]["structure_sigma_m"] = -1.0
    with pytest.raises(CovarianceError, match="expected a number >= 0") as exc:
        structure_sigma_from_block(dataclasses.replace(result.model, metadata={"identification": block}))
    assert exc.value.field == "identification.covariance.structure_sigma_m"
