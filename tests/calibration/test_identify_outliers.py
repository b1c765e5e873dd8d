"""Outliers are judged against the noise the residuals show (issue 25, case 4): when the model
structure cannot explain the data (a rigid model of an arm that sags), every row is many
instrument sigmas off, and flagging nearly all of them (293 of 300 before) named nothing; a
reflector that was bumped must still stand out."""

from __future__ import annotations

import dataclasses

import numpy as np

from calibration.identify import identify
from calibration.robots import nominal
from calibration.simulate import SAGGING_ARMS, perturbed, random_configurations, sagging, simulate_measurements

SIGMA_M = 20e-6


def _sagging_cobot_data(n, seed):
    rng = np.random.default_rng(seed)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = sagging(perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3), "cobot", frames_of=nom)
    q = random_configurations(nom, n, rng)
    pay = np.array([[0.0, 0, 0, 0], SAGGING_ARMS["cobot"]["payload"]] * (n // 2), dtype=float)
    return nom, simulate_measurements(truth, q, rng, sigma_m=SIGMA_M, targets=("smr",), payload=pay)


def test_an_incomplete_model_does_not_flag_every_row_and_still_finds_a_bumped_reflector():
    nom, data = _sagging_cobot_data(300, seed=11)
    bumped = np.array([17, 140, 251])
    p = data.p_world.copy()
    p[bumped, 2] += 5e-3  # 5 mm: a reflector knocked out of its nest (the sag leaves ~0.6 mm RMS)
    data = dataclasses.replace(data, p_world=p)
    result = identify(nom, data, sigma_m=SIGMA_M)
    # the rigid model cannot explain the sag, and says so
    assert not result.consistency["consistent"]
    assert result.sigma_scale > 3.0
    flagged = set(result.outliers)
    assert set(bumped.tolist()) <= flagged, sorted(flagged)
    # against the instrument's 0.02 mm alone 290+ rows were outliers; against the scaled noise
    # only the bumped rows and a few of the sag's largest remain
    assert len(flagged) <= len(bumped) + 0.03 * len(data), len(flagged)


def test_a_complete_model_flags_only_the_bumped_rows():
    rng = np.random.default_rng(3)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3)
    data = simulate_measurements(truth, random_configurations(nom, 300, rng), rng, sigma_m=SIGMA_M, targets=("smr",))
    p = data.p_world.copy()
    p[[5, 77], 0] -= 0.5e-3  # 0.5 mm: 25 sigmas
    result = identify(nom, dataclasses.replace(data, p_world=p), sigma_m=SIGMA_M)
    assert set(result.outliers) == {5, 77}
