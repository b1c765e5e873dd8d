"""Identification is right on every serial arm (issue 14): on robots built here (a SCARA, a
Stanford-like arm, a KUKA KR-type 6R with its reflector on the flange axis, a 7-DOF arm, an arm
with two consecutive revolute axes on one line, random 6R arms with the reflector on the last
axis), ``identify`` reaches the hold-out accuracy of a complete reference fit written in
``complete_reference.py``: every link of the nominal DH chain followed by its own 6-DOF error
transform, fitted with ``scipy.optimize.least_squares`` (over-parameterised on purpose: whatever
the real robot's deviations, this model can follow them).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from complete_reference import dh_link, random_case, reference_fit
from sample_models import Rx, Rz, Tx, Tz, stanford_5r1p_doc

from calibration.identify import NotEnoughData, identify
from calibration.kinematics import target_positions
from calibration.model import model_from_dict
from calibration.simulate import perturbed, random_configurations, simulate_measurements

SIGMA = 20e-6
DEG = math.pi / 180


def _doc(rows, *, prismatic=(), limits=None, target=(0.04, 0.0, 0.05), name="arm"):
    """A dh model document in SI: rows of (d, a, alpha deg); ``prismatic``: joint indices."""
    joints = []
    for i, (d, a, alpha) in enumerate(rows):
        lo, hi = (limits or {}).get(i, (0.0, 0.25) if i in prismatic else (-3.0, 3.0))
        joints.append(
            {
                "name": f"j{i + 1}",
                "type": "prismatic" if i in prismatic else "revolute",
                "theta": 0.0,
                "d": d,
                "a": a,
                "alpha": alpha * DEG,
                "lower": lo,
                "upper": hi,
            }
        )
    return {
        "format": "recal.model/1",
        "name": name,
        "units": {"length": "m", "angle": "rad"},
        "convention": "dh",
        "joints": joints,
        "targets": {"smr": list(target)},
    }


ROBOTS = {
    # SCARA: RRPR, every axis vertical, the quill's rotation on the prismatic joint's line
    "scara-rrpr": _doc([(0.40, 0.35, 0.0), (0.0, 0.30, 0.0), (0.0, 0.0, 0.0), (0.05, 0.0, 0.0)], prismatic=(2,)),
    # a KUKA KR 16-like 6R, the reflector on the flange axis (the demo's set-up); the real one is
    # about 1 mm off it (below)
    "kr16-target-on-axis": _doc(
        [
            (0.675, 0.26, -90.0),
            (0.0, 0.68, 0.0),
            (0.0, 0.035, 90.0),
            (0.67, 0.0, -90.0),
            (0.0, 0.0, 90.0),
            (0.158, 0.0, 0.0),
        ],
        target=(0.0, 0.0, 0.05),
    ),
    # a 7-DOF arm (iiwa-like: every pair of consecutive axes intersecting)
    "7dof": _doc(
        [
            (0.34, 0.0, -90.0),
            (0.0, 0.0, 90.0),
            (0.40, 0.0, 90.0),
            (0.0, 0.0, -90.0),
            (0.40, 0.0, -90.0),
            (0.0, 0.0, 90.0),
            (0.126, 0.0, 0.0),
        ]
    ),
    # joints 3 and 4 turn about one line (a = 0, alpha = 0 on link 3)
    "collinear": _doc(
        [(0.30, 0.0, -90.0), (0.0, 0.40, 0.0), (0.0, 0.0, 0.0), (0.0, 0.30, -90.0), (0.0, 0.0, 90.0), (0.10, 0.0, 0.0)]
    ),
}


def _stanford_si():
    """The book's 5R1P (RRPRRR) in SI, with a reflector off the last axis."""
    m = model_from_dict(stanford_5r1p_doc(5.0))
    return dataclasses.replace(m, targets={"smr": np.array([0.03, 0.0, 0.02])})


def _robot(name):
    return _stanford_si() if name == "stanford-rrprrr" else model_from_dict(ROBOTS[name])


# --------------------------------------------------------------------------- the complete reference


def test_the_written_out_link_is_the_product_of_elementary_transforms():
    A = dh_link(np.array([0.3]), np.array([0.2]), 0.1, -0.7)[0]
    np.testing.assert_allclose(A, Rz(0.3) @ Tz(0.2) @ Tx(0.1) @ Rx(-0.7), atol=1e-15)


def _truth(nom, rng, name):
    truth = perturbed(nom, rng)
    off = np.array([0.8e-3, -0.6e-3, 0.0]) if name == "kr16-target-on-axis" else rng.normal(0, 0.5e-3, 3)
    return dataclasses.replace(truth, targets={"smr": nom.targets["smr"] + off})


@pytest.mark.parametrize("name", ["scara-rrpr", "stanford-rrprrr", "kr16-target-on-axis", "7dof", "collinear"])
def test_identification_reaches_the_complete_fit(name):
    nom = _robot(name)
    rng = np.random.default_rng(5)
    truth = _truth(nom, rng, name)
    data = simulate_measurements(truth, random_configurations(nom, 150, rng), rng, sigma_m=SIGMA, targets=("smr",))
    result = identify(nom, data)
    assert result.success, result.message
    q = random_configurations(nom, 500, rng)
    true_p = target_positions(truth, q, "smr")
    ours = np.sqrt(np.mean(np.sum((target_positions(result.model, q, "smr") - true_p) ** 2, axis=1)))
    ref = np.sqrt(np.mean(np.sum((reference_fit(nom, data)(q) - true_p) ** 2, axis=1)))
    assert ours <= 1.05 * ref, (name, ours, ref, result.notes)
    # the model explains the data: residuals at the stated noise, no rows taken for outliers
    assert result.consistency["consistent"] and not result.outliers, (result.sigma_scale, len(result.outliers))
    c = result.completeness
    assert c["count"] == 4 * c["revolute"] + 2 * c["prismatic"] + 6
    # what the measurement can see (one point: no tool orientation, plus the point's own offset),
    # at the identified geometry as the selection decides (the KR 16's reflector on the flange
    # axis hides two at the nominal): no more is freed than that, and the freed set is minimal:
    # no combination of it is undetermined (the SCARA freed its prismatic offset beside the
    # base's z, the collinear arm a dependent tilt: condition numbers of 6e15, 18 and 28 freed)
    assert c["identified"] <= c["measurable"] <= c["count"], c
    assert result.condition_number < 1e6, result.condition_number
    if name == "kr16-target-on-axis":
        assert c["measurable_at_nominal"] < c["measurable"], c


@pytest.mark.slow  # the reference fit of 500 rows: a few seconds
def test_a_reflector_on_the_flange_axis_reaches_the_complete_fit_when_the_noise_is_low():
    """The parameters the nominal's on-axis reflector hides (j5.a, j5.alpha of the KR 16) are
    determined by the real reflector's 1 mm offset once the noise is low enough: selected again
    at the identified model, they are freed, and the fit reaches the complete one (before: 1.8
    times its hold-out error here)."""
    nom = _robot("kr16-target-on-axis")
    rng = np.random.default_rng(5)
    truth = _truth(nom, rng, "kr16-target-on-axis")
    data = simulate_measurements(truth, random_configurations(nom, 500, rng), rng, sigma_m=5e-6, targets=("smr",))
    result = identify(nom, data, sigma_m=5e-6)
    q = random_configurations(nom, 500, rng)
    true_p = target_positions(truth, q, "smr")
    ours = np.sqrt(np.mean(np.sum((target_positions(result.model, q, "smr") - true_p) ** 2, axis=1)))
    ref = np.sqrt(np.mean(np.sum((reference_fit(nom, data)(q) - true_p) ** 2, axis=1)))
    assert ours <= 1.05 * ref, (ours, ref)
    freed_at_the_answer = [w for w in result.warnings if "determined only at the identified geometry" in w]
    assert freed_at_the_answer and "j5" in freed_at_the_answer[0], result.warnings


# random arms with the reflector nominally on the last axis (complete_reference.random_case's even
# seeds); with 2, 16 and 34 the wrist tilt the real reflector's offset determined only to about
# 1 mrad used to be held at the nominal: 1.7, 74 and 7 times the complete fit's hold-out error
ON_AXIS_SEEDS = (0, 2, 4, 6, 8, 16, 20, 34)


@pytest.mark.slow  # eight reference fits: several seconds
def test_random_arms_with_the_reflector_on_the_last_axis_reach_the_complete_fit():
    """Issue 14, case 3 on arms nobody chose: the parameters redundant only at the nominal (a
    reflector on the last axis) are freed where the identified geometry determines them, however
    weakly (their standard errors are in the warning and in the covariance), instead of being
    held biased; each arm reaches the complete fit's hold-out accuracy within 5 %."""
    for seed in ON_AXIS_SEEDS:
        nom, truth, rng = random_case(seed)
        data = simulate_measurements(truth, random_configurations(nom, 150, rng), rng, sigma_m=SIGMA, targets=("smr",))
        result = identify(nom, data, sigma_m=SIGMA)
        q = random_configurations(nom, 500, rng)
        true_p = target_positions(truth, q, "smr")
        ours = np.sqrt(np.mean(np.sum((target_positions(result.model, q, "smr") - true_p) ** 2, axis=1)))
        ref = np.sqrt(np.mean(np.sum((reference_fit(nom, data)(q) - true_p) ** 2, axis=1)))
        assert ours <= 1.05 * ref, (seed, ours, ref, result.warnings)
        assert any("on the last joint's axis" in w for w in result.warnings), (seed, result.warnings)


def test_scara_is_written_in_a_complete_form():
    """The SCARA's prismatic joint sits between parallel axes: its links take Hayati's form (the
    tilt between the parallel axes is a parameter), or the model goes to poe."""
    result = identify(
        _robot("scara-rrpr"),
        simulate_measurements(
            _truth(_robot("scara-rrpr"), np.random.default_rng(1), ""),
            random_configurations(_robot("scara-rrpr"), 60, np.random.default_rng(2)),
            np.random.default_rng(3),
            targets=("smr",),
        ),
    )
    assert not any("cannot move d" in n for n in result.notes), result.notes
    assert result.model.convention == "poe" or any(j.hayati for j in result.model.joints[:3])


def test_collinear_axes_go_to_poe():
    """Axes 3 and 4 on one line (a = 0, alpha = 0 on link 3): a Hayati link cannot describe a
    sideways shift of axis 4, so the model goes to poe, and reaches the complete fit."""
    nom = _robot("collinear")
    rng = np.random.default_rng(4)
    truth = _truth(nom, rng, "")
    data = simulate_measurements(truth, random_configurations(nom, 150, rng), rng, targets=("smr",))
    result = identify(nom, data)
    assert result.model.convention == "poe"
    assert any("poe" in n for n in result.notes)
    q = random_configurations(nom, 500, rng)
    true_p = target_positions(truth, q, "smr")
    ours = np.sqrt(np.mean(np.sum((target_positions(result.model, q, "smr") - true_p) ** 2, axis=1)))
    ref = np.sqrt(np.mean(np.sum((reference_fit(nom, data)(q) - true_p) ** 2, axis=1)))
    assert ours <= 1.05 * ref, (ours, ref)


def test_a_target_on_the_last_axis_is_warned_about():
    nom = _robot("kr16-target-on-axis")
    rng = np.random.default_rng(7)
    data = simulate_measurements(
        _truth(nom, rng, "kr16-target-on-axis"), random_configurations(nom, 150, rng), rng, targets=("smr",)
    )
    result = identify(nom, data)
    assert any("on the last joint's axis" in w for w in result.warnings), result.warnings


def test_a_freed_set_that_does_not_settle_keeps_the_last_fits_set(monkeypatch):
    """The selection at the answer is repeated until the freed set is stable, at most
    MAX_SELECTION_ROUNDS times; when it has not settled by then, the result is that of the last
    fit, with its own set (the code before took the new set with the old fit's normal equations
    and failed on their shapes), and a note says so. One round on the KR 16 whose reflector is on
    the flange axis: the answer frees j5's parameters, which the one fit did not have."""
    import calibration.identify as identify_module

    monkeypatch.setattr(identify_module, "MAX_SELECTION_ROUNDS", 1)
    nom = _robot("kr16-target-on-axis")
    rng = np.random.default_rng(5)
    truth = _truth(nom, rng, "kr16-target-on-axis")
    data = simulate_measurements(truth, random_configurations(nom, 150, rng), rng, sigma_m=SIGMA, targets=("smr",))
    result = identify(nom, data)
    assert result.success and result.covariance.shape == (len(result.params),) * 2
    assert result.completeness["identified"] == len(result.params) < result.completeness["measurable"]
    assert any("did not settle in 1 selections" in n for n in result.notes), result.notes


def test_two_rows_are_refused_with_the_rows_needed():
    nom = _robot("kr16-target-on-axis")
    rng = np.random.default_rng(8)
    data = simulate_measurements(_truth(nom, rng, ""), random_configurations(nom, 2, rng), rng, targets=("smr",))
    with pytest.raises(NotEnoughData, match="no redundancy") as exc:
        identify(nom, data)
    assert exc.value.rows_needed > 10
    assert f"at least {exc.value.rows_needed} rows" in str(exc.value)


def test_plan_predicts_what_identification_reaches_on_the_scara():
    """`recal plan` on the SCARA predicted 0.016 mm for a model that reached 0.29 mm: it now plans
    for the complete form identification fits, and the hold-out error is what it predicted."""
    from calibration.planning import plan

    nom = _robot("scara-rrpr")
    rng = np.random.default_rng(5)
    truth = _truth(nom, rng, "")
    res = plan(nom, random_configurations(nom, 1000, rng), 40, targets=("smr",), sigma_m=SIGMA, rng=rng)
    data = simulate_measurements(truth, res.q, rng, sigma_m=SIGMA, targets=("smr",))
    result = identify(nom, data, sigma_m=SIGMA)
    q = random_configurations(nom, 500, rng)
    e = np.linalg.norm(target_positions(result.model, q, "smr") - target_positions(truth, q, "smr"), axis=1)
    # (the model before this fix reached 12 times the predicted error here)
    assert 0.5 < np.sqrt(np.mean(e**2)) / res.predicted_rms_m < 1.5, (np.sqrt(np.mean(e**2)), res.predicted_rms_m)
