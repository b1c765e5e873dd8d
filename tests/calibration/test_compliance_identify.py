"""Identification with joint compliance under gravity, on simulated arms that sag (a 10 kg-class
cobot and a 165 kg-payload arm, calibration.simulate.SAGGING_ARMS): the compliant model explains
the data down to the instrument's noise where the rigid one cannot, its 95 % bounds are honest,
cross-validation leaves a rigid arm rigid, and two payloads separate the arm's weight from the
payload's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration import compliance as C
from calibration import compliance_fit
from calibration.identify import identify
from calibration.robots import nominal
from calibration.simulate import (
    SAGGING_ARMS,
    heavy_arm_nominal,
    perturbed,
    random_configurations,
    sagging,
    simulate_measurements,
)
from calibration.uncertainty import validate

SIGMA = {"cobot": 20e-6, "arm165": 30e-6}  # tracker noise per axis: a cobot near, a big arm farther away


def _nominal(arm):
    m = nominal("ur10e") if arm == "cobot" else heavy_arm_nominal()
    return dataclasses.replace(m, targets={"smr": np.array([0.0, 0.0, 0.05])})


def _cell(arm, seed, *, sag=True):
    rng = np.random.default_rng(seed)
    nom = _nominal(arm)
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3)
    if sag:
        truth = sagging(truth, arm, frames_of=nom)
    return nom, truth, rng


def _measure(nom, truth, rng, n, payloads, sigma):
    """``n`` random configurations, the payloads taken in turn (kg, x, y, z)."""
    q = random_configurations(nom, n, rng)
    pay = np.array([payloads[i % len(payloads)] for i in range(n)], dtype=float)
    return simulate_measurements(truth, q, rng, sigma_m=sigma, targets=("smr",), payload=pay)


@pytest.mark.parametrize("arm", ["cobot", "arm165"])
def test_compliant_model_reaches_the_noise_floor_and_its_bounds_are_honest(arm):
    nom, truth, rng = _cell(arm, seed=11)
    sigma = SIGMA[arm]
    payloads = [(0.0, 0, 0, 0), SAGGING_ARMS[arm]["payload"]]
    train = _measure(nom, truth, rng, 200, payloads, sigma)
    holdout = _measure(nom, truth, rng, 2000, payloads, sigma)
    floor = np.sqrt(3.0) * sigma  # RMS length of the instrument's noise alone
    rigid_result = identify(nom, train, sigma_m=sigma)
    rigid = validate(rigid_result, holdout)
    result = identify(C.with_section(nom, C.default_section(nom)), train, sigma_m=sigma)
    compliant = validate(result, holdout)
    assert compliant.rms_m <= 1.10 * floor, (compliant.rms_m, floor)
    assert rigid.rms_m > 3.0 * floor, (rigid.rms_m, floor)
    assert 0.93 <= compliant.coverage_95 <= 0.97, compliant.coverage_95
    # the rigid model cannot explain the data (the sag is not in it) and says so: its residuals
    # fail the chi-squared test against the instrument's sigma (issue 14; its bounds grow by the
    # residuals' own scale instead of staying at the instrument's, so they are no longer too
    # narrow), while the compliant model's pass with a scale near 1
    assert not rigid_result.consistency["consistent"], rigid_result.consistency
    assert rigid_result.sigma_scale > 3.0, rigid_result.sigma_scale
    assert result.consistency["consistent"], result.consistency
    assert result.sigma_scale < 1.2, result.sigma_scale
    # the joints' compliance (rad per N·m) is recovered, within its stated uncertainty
    names = list(result.param_names)
    for joint, c_true in SAGGING_ARMS[arm]["compliance"].items():
        k = names.index(f"compliance.{joint}.k")
        assert abs(result.values[k] - c_true) < 4 * result.std_errors[k] + 1e-3 * c_true, joint
        assert result.std_errors[k] < 0.1 * c_true


@pytest.mark.parametrize("arm", ["cobot", "arm165"])
def test_the_compliant_models_95_percent_bounds_cover_93_to_97_percent_on_every_seed(arm):
    """Issue 17's criterion, seed by seed. The bounds use the stated sigma unless the residuals
    show it too small (identify.excess_scale): with a complete model that is most data sets, and
    the bounds covered up to 97.7 % when every chance excess of chi-squared widened them."""
    sigma = SIGMA[arm]
    payloads = [(0.0, 0, 0, 0), SAGGING_ARMS[arm]["payload"]]
    inside = n = 0.0
    for seed in range(6):
        nom, truth, rng = _cell(arm, seed)
        train = _measure(nom, truth, rng, 200, payloads, sigma)
        holdout = _measure(nom, truth, rng, 2000, payloads, sigma)
        v = validate(identify(C.with_section(nom, C.default_section(nom)), train, sigma_m=sigma), holdout)
        assert 0.93 <= v.coverage_95 <= 0.97, (seed, v.coverage_95)
        inside, n = inside + v.coverage_95 * v.n, n + v.n
    assert 0.94 <= inside / n <= 0.96, inside / n


def test_two_payloads_separate_the_arm_weight_from_the_payload():
    nom, truth, rng = _cell("cobot", seed=5)
    sigma = SIGMA["cobot"]
    start = C.with_section(nom, C.default_section(nom))
    # one payload throughout: its torque is indistinguishable from a heavier wrist
    one = identify(start, _measure(nom, truth, rng, 150, [SAGGING_ARMS["cobot"]["payload"]], sigma), sigma_m=sigma)
    held = {u.name: u for u in one.unidentifiable}
    assert {"compliance.j2.k", "compliance.j3.k"} <= set(held)
    assert held["compliance.j2.k"].category == "combination"
    assert any(n.startswith("compliance.j2.j6.") for n, _ in held["compliance.j2.k"].relation)
    # two payloads: the compliance itself is determined
    two = identify(
        start, _measure(nom, truth, rng, 150, [(0.0, 0, 0, 0), (10.0, 0.0, 0.02, 0.1)], sigma), sigma_m=sigma
    )
    assert "compliance.j2.k" in two.param_names and "compliance.j3.k" in two.param_names
    k = two.param_names.index("compliance.j2.k")
    assert abs(two.values[k] / SAGGING_ARMS["cobot"]["compliance"]["j2"] - 1.0) < 0.05


def test_identifiability_names_terms_the_arm_cannot_show():
    """The selection names each compliance term it drops and why, as for a geometric parameter:
    joints 2 and 3 of a UR are parallel, so a lump's moment along link 2's z (joint 3's axis)
    gives no torque about joint 2."""
    nom, truth, rng = _cell("cobot", seed=3)
    data = _measure(nom, truth, rng, 120, [(0.0, 0, 0, 0), SAGGING_ARMS["cobot"]["payload"]], SIGMA["cobot"])
    result = identify(C.with_section(nom, C.default_section(nom)), data, sigma_m=SIGMA["cobot"])
    dropped = {u.name: u for u in result.unidentifiable if u.name.startswith("compliance.")}
    # link 2's DH z axis is joint 3's axis, parallel to joint 2's: a moment along it has no torque.
    # At the nominal geometry exactly (no effect); identification decides at the identified
    # geometry (issue 14), where the identified Hayati tilt between the axes leaves it a sliver
    # of the link's mass and y moment: a combination with tiny coefficients, still dropped
    u = dropped["compliance.j2.j2.z"]
    assert u.category in ("no_effect", "combination"), u
    if u.category == "no_effect":
        assert "has no effect" in u.reason
    else:
        assert u.relation and all(abs(c) < 0.01 for _, c in u.relation), u.relation
    for u in dropped.values():
        assert u.reason and "compliance" in u.reason
    # every kept compliance term has a finite standard error in its own unit kind
    for p, s in zip(result.params, result.std_errors):
        if p.name.startswith("compliance."):
            assert np.isfinite(s) and s > 0


@pytest.mark.parametrize("arm", ["cobot", "arm165"])
def test_auto_leaves_a_rigid_arm_rigid_and_adds_compliance_to_a_sagging_one(arm):
    sigma = SIGMA[arm]
    payloads = [(0.0, 0, 0, 0), SAGGING_ARMS[arm]["payload"]]
    nom, truth, rng = _cell(arm, seed=21, sag=False)
    cv = compliance_fit.choose_compliance(
        nom, _measure(nom, truth, rng, 120, payloads, sigma), identify_kw={"sigma_m": sigma}
    )
    assert cv.joints == () and cv.section is None
    assert cv.rms_compliant_m > (1.0 - compliance_fit.MIN_CV_GAIN) * cv.rms_rigid_m  # the figures are there either way
    nom, truth, rng = _cell(arm, seed=21)
    cv = compliance_fit.choose_compliance(
        nom, _measure(nom, truth, rng, 120, payloads, sigma), identify_kw={"sigma_m": sigma}
    )
    assert cv.joints == ("j2", "j3")
    assert cv.rms_chosen_m < 0.5 * cv.rms_rigid_m
    assert next(j for j, _ in cv.tried) == ()


def test_folds_keep_a_configuration_together():
    nom, truth, rng = _cell("cobot", seed=2, sag=False)
    q = random_configurations(nom, 20, rng)
    data = simulate_measurements(truth, q, rng, targets=("smr", None))  # two rows per configuration
    folds = compliance_fit.fold_indices(data, 5)
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(data)))
    for f in folds:
        others = np.setdiff1d(np.arange(len(data)), f)
        assert not set(data.pose_id[f].tolist()) & set(data.pose_id[others].tolist())


def test_planning_for_compliance_chooses_configurations_that_excite_the_gravity_torques():
    """A compliant nominal model plans for its compliance terms too: the poses it chooses
    determine them better than poses planned for geometry alone (smaller predicted standard
    errors of the same compliant identification)."""
    from calibration import planning

    nom, _, rng = _cell("cobot", seed=13)
    compliant = C.with_section(nom, C.default_section(nom))
    cand = random_configurations(nom, 400, rng)
    kw = dict(targets=("smr",), n_evaluation=50, rng=np.random.default_rng(0))
    for_compliance = planning.plan(compliant, cand, 30, **kw)
    for_geometry = planning.plan(nom, cand, 30, **kw)
    assert any(p.name.startswith("compliance.") for p in for_compliance.params)
    # the same compliant identification predicted from each design: the compliance terms' errors
    geometry_design = planning.plan(compliant, cand[for_geometry.indices], 30, exchange=False, **kw)
    names = [p.name for p in for_compliance.params]
    other = {p.name: s for p, s in zip(geometry_design.params, geometry_design.std_errors)}
    shared = [n for n in names if n.startswith("compliance.") and n in other]
    assert shared
    ratio = np.median([other[n] / for_compliance.std_errors[names.index(n)] for n in shared])
    assert ratio > 1.2, ratio
