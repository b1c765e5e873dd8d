"""The residual correction's families and their choice (issue 28): joint transmission errors of a
harmonic drive's size in the simulated truth, the physical transmission family, boosted trees
stored as plain arrays and walked in numpy, nested cross-validation, and the region."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from calibration import residual_choice as RC
from calibration import residual_map as RM
from calibration import transmission as TR
from calibration import trees as TT
from calibration.jacobian import predict
from calibration.model import model_from_dict, model_to_dict
from calibration.robots import nominal
from calibration.simulate import harmonic_drive_errors, perturbed, random_configurations, simulate_measurements

CENTRE = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
REGION = np.stack([CENTRE - np.deg2rad(60), CENTRE + np.deg2rad(60)], axis=1)
SIGMA_M = 10e-6


def _arm(seed=5):
    """A UR10e-class arm with every link in error and harmonic-drive transmission errors."""
    rng = np.random.default_rng(seed)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3)
    return rng, nom, truth, harmonic_drive_errors(nom, rng)


def test_simulated_transmission_errors_have_a_harmonic_drives_size_and_shape():
    rng, nom, _, tx = _arm()
    q = random_configurations(nom, 20000, rng)
    dq_deg = np.rad2deg(tx.joint_errors(q))
    peak = np.abs(dq_deg).max(axis=0)
    # a few thousandths to a hundredth of a degree (arc-seconds to under a minute of arc)
    assert np.all(peak > 0.004) and np.all(peak < 0.02)
    # the wave generator's ripple (2N per output turn, N = 101) is there: sharp in the configuration
    for r, c in zip(tx.ratios, tx.coefficients):
        assert 202.0 in r.tolist()
        ripple = np.hypot(*c[r.tolist().index(202.0)])
        assert np.deg2rad(3 / 3600) <= ripple <= np.deg2rad(8 / 3600)


def test_the_trees_walked_in_numpy_equal_sklearns_predict_and_need_no_sklearn(tmp_path):
    from sklearn.ensemble import HistGradientBoostingRegressor
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    q = rng.uniform(REGION[:, 0], REGION[:, 1], (600, 6))
    y = 1e-4 * np.stack([np.sin(5 * q[:, 0]) * q[:, 1], np.cos(7 * q[:, 2]), np.sign(q[:, 3] - CENTRE[3])], axis=1)
    m = TT.fit_trees(q, y)
    X = rng.uniform(REGION[:, 0] - 0.2, REGION[:, 1] + 0.2, (2000, 6))
    for axis in range(3):
        count = m.settings["trees_per_axis"][axis]  # chosen by the inner cross-validation
        est = HistGradientBoostingRegressor(early_stopping=False, random_state=0, max_iter=count, **TT.TREE_SETTINGS)
        with threadpool_limits(limits=1, user_api="openmp"):  # as fit_trees fits (and as fast)
            est.fit(q, y[:, axis])
        assert np.array_equal(m.raw(X)[:, axis], est.predict(X))
    # through the model file (mm, deg) and back: plain JSON, the same numbers
    model = nominal("ur10e")
    doc = json.loads(json.dumps({**model_to_dict(model), "residual_map": TT.to_dict(m, model)}))
    assert doc["residual_map"]["format"] == "recal.residual_trees/1"
    back = RM.from_model(model_from_dict(doc))
    a, ia = m.evaluate(X)
    b, ib = back.evaluate(X)
    assert np.array_equal(ia, ib) and np.allclose(a, b, rtol=1e-12, atol=1e-15)
    # evaluating needs numpy alone: in a process where sklearn cannot be imported
    (tmp_path / "model.json").write_text(json.dumps(doc))
    np.save(tmp_path / "X.npy", X)
    code = (
        "import sys, json, numpy as np; sys.modules['sklearn'] = None\n"
        "from calibration.model import model_from_dict\nfrom calibration.residual_map import from_model\n"
        f"m = from_model(model_from_dict(json.load(open({str(tmp_path / 'model.json')!r}))))\n"
        f"c, i = m.evaluate(np.load({str(tmp_path / 'X.npy')!r}))\nprint(repr(float(c.sum())), int(i.sum()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert float(out[0]) == pytest.approx(float(b.sum()), rel=1e-12) and int(out[1]) == int(ib.sum())


def test_a_malformed_tree_is_refused_naming_the_field():
    rng = np.random.default_rng(1)
    q = rng.uniform(REGION[:, 0], REGION[:, 1], (100, 6))
    m = TT.fit_trees(q, 1e-4 * np.sin(q[:, :3]))
    model = nominal("ur10e")
    doc = json.loads(json.dumps({**model_to_dict(model), "residual_map": TT.to_dict(m, model)}))
    t = doc["residual_map"]["trees"][1][3]
    t["left"][0] = 0  # a node that is its own child: a walk that never ends
    with pytest.raises(RM.ResidualMapError) as exc:
        RM.from_model(model_from_dict(doc))
    assert exc.value.field == "residual_map.trees[1][3]"


@pytest.fixture(scope="module")
def chosen():
    rng, nom, truth, tx = _arm()
    data = simulate_measurements(
        truth,
        random_configurations(nom, 1000, rng, limits=REGION),
        rng,
        sigma_m=SIGMA_M,
        targets=("smr",),
        transmission=tx,
    )
    from calibration.identify import identify

    final = identify(nom, data, sigma_m=SIGMA_M).model
    choice = RC.choose_correction(nom, data, identify_kw={"sigma_m": SIGMA_M}, final=final)
    return rng, nom, truth, tx, final, choice


def _true_and_geometric(rng, nom, truth, tx, final, q):
    """Noise-free true positions of the SMR at readings ``q`` and the geometric model's."""
    clean = simulate_measurements(truth, q, rng, sigma_m=0.0, targets=("smr",), transmission=tx)
    p_tool = np.array([final.target(t) for t in clean.target])
    return clean.p_world, predict(final, clean.q, p_tool).p_world, p_tool


def test_the_chosen_correction_recovers_most_of_what_the_geometric_model_leaves(chosen):
    rng, nom, truth, tx, final, choice = chosen
    fig = choice.figures
    assert set(fig["families"]) == {"none", "map", "transmission", "trees"}
    assert choice.family == fig["chosen"] == "transmission"  # the physical family is the right one here
    assert fig["gain"] >= RC.MIN_CV_GAIN
    assert [p["poses"] for p in fig["learning_curve"]] == sorted(p["poses"] for p in fig["learning_curve"])
    # hold-out: fresh configurations of the region against the noise-free truth
    q = random_configurations(nom, 1000, rng, limits=REGION)
    true, geometric, p_tool = _true_and_geometric(rng, nom, truth, tx, final, q)
    corr, inside = choice.correction.evaluate(q, p_tool)
    assert inside.mean() > 0.95
    before = np.sqrt(np.mean(np.sum((geometric - true)[inside] ** 2, axis=1)))
    after = np.sqrt(np.mean(np.sum((geometric + corr - true)[inside] ** 2, axis=1)))
    assert 1.0 - after / before >= 0.70, (before, after)  # measured: 0.95 (52.8 µm -> 2.6 µm)
    # it survives the model file: the same correction, loaded as every verb loads it
    doc = json.loads(json.dumps({**model_to_dict(final), "residual_map": choice.section(final)}))
    back = RM.from_model(model_from_dict(doc))
    c2, i2 = back.evaluate(q, p_tool)
    assert np.array_equal(i2, inside) and np.allclose(c2, corr, atol=1e-9)


@pytest.mark.parametrize("family", ["map", "transmission", "trees"])
def test_outside_the_fitted_region_every_family_leaves_the_geometric_model_and_says_so(chosen, family):
    rng, nom, truth, tx, final, _ = chosen
    data = simulate_measurements(
        truth,
        random_configurations(nom, 300, rng, limits=REGION),
        rng,
        sigma_m=SIGMA_M,
        targets=("smr",),
        transmission=tx,
    )
    c = RC.fit_family(family, nom, final, data, {"sigma_m": SIGMA_M})
    # every joint in turn taken beyond the range it was measured over, and the base turned away
    q = np.repeat(random_configurations(nom, 7, rng, limits=REGION), 7, axis=0)
    for k in range(6):
        q[k::7, k] = REGION[k, 1] + np.deg2rad(15)
    q[6::7, 0] = CENTRE[0] + np.deg2rad(150)
    true, geometric, p_tool = _true_and_geometric(rng, nom, truth, tx, final, q)
    corr, inside = c.evaluate(q, p_tool)
    assert not inside.any()  # all flagged
    assert np.all(corr == 0.0)  # the geometric model alone: never worse than it
    assert np.array_equal(np.linalg.norm(geometric + corr - true, axis=1), np.linalg.norm(geometric - true, axis=1))


def test_transmission_fit_finds_the_wave_generator_and_refuses_chance(chosen):
    rng, nom, _truth, _tx, _final, choice = chosen
    t = choice.correction.transmission
    # the shoulder and elbow carry most of the arm: their 2N = 202 ripple is found
    assert 202.0 in t.ratios[1].tolist() and 202.0 in t.ratios[2].tolist()
    # on pure noise no gear ratio is found
    q = random_configurations(nom, 500, rng, limits=REGION)
    p_tool = np.tile(nom.targets["smr"], (len(q), 1))
    J = TR.position_jacobian(nom, q, p_tool)
    found = TR.find_gear_ratios(J, q, rng.normal(0, SIGMA_M, (len(q), 3)), np.ones(6, dtype=bool), [[1.0, 2.0]] * 6)
    assert found == [None] * 6


def test_the_simulated_cell_puts_the_arm_where_its_transmission_errors_say():
    from fakes.world import SimCell

    rng, nom, truth, tx = _arm()
    q = random_configurations(nom, 5, rng, limits=REGION)
    expected = simulate_measurements(truth, q, rng, sigma_m=0.0, targets=("smr",), transmission=tx).p_world
    rigid = simulate_measurements(truth, q, rng, sigma_m=0.0, targets=("smr",)).p_world
    cell, plain = SimCell(truth, transmission=tx), SimCell(truth)
    for k in range(len(q)):
        for c in (cell, plain):
            c.start_move(q[k], 1.0, 1.0)  # time_scale 0: the move is done at once
        assert np.allclose(cell.target_world("smr"), expected[k], atol=1e-12)
        assert np.allclose(plain.target_world("smr"), rigid[k], atol=1e-12)
        assert np.linalg.norm(expected[k] - rigid[k]) > 1e-5  # the transmission errors matter


def test_a_learning_curve_extrapolates_by_a_power_law_of_the_excess_over_the_noise():
    """``extrapolate_learning_curve``: points on rms² = 3σ² + a n^-b give back the law, and a
    prediction at more poses than measured; a curve at the noise predicts the noise; the
    exponent is bounded (three points cannot promise more than 1/n²)."""
    sigma, a, b = 10e-6, 4e-6, 0.7
    curve = [{"poses": n, "rms_m": float(np.sqrt(3 * sigma**2 + a * n**-b))} for n in (160, 320, 640)]
    p = RC.extrapolate_learning_curve(curve, 2000, sigma)
    assert p["extrapolated"] and p["b"] == pytest.approx(b, rel=1e-9) and p["a_m2"] == pytest.approx(a, rel=1e-9)
    assert p["rms_m"] == pytest.approx(np.sqrt(3 * sigma**2 + a * 2000**-b), rel=1e-9)
    assert np.sqrt(3) * sigma < p["rms_m"] < curve[-1]["rms_m"]  # better than measured, never below the noise
    flat = [{"poses": n, "rms_m": np.sqrt(3) * sigma * 0.99} for n in (100, 200)]
    assert RC.extrapolate_learning_curve(flat, 5000, sigma)["rms_m"] == pytest.approx(np.sqrt(3) * sigma)
    steep = [{"poses": n, "rms_m": float(np.sqrt(3 * sigma**2 + 1e3 * n**-5.0))} for n in (10, 20, 40)]
    assert RC.extrapolate_learning_curve(steep, 80, sigma)["b"] == 2.0
    assert RC.extrapolate_learning_curve([], 100, sigma) is None


def test_the_learning_curve_of_400_poses_predicts_the_error_of_800(chosen):
    """The procedure's learning curve (nested CV on 1,000 poses of the simulated cell with
    transmission errors), extrapolated, against the held-out RMS it reports: the prediction at
    the curve's own largest point is its measured value, and at twice that number it lies
    between the noise and the measured value."""
    *_, choice = chosen
    fig = choice.figures
    curve = fig["learning_curve"]
    assert len(curve) == 3 and fig["noise_sigma_m"] == pytest.approx(SIGMA_M)
    last = curve[-1]
    at_last = RC.extrapolate_learning_curve(curve, last["poses"], SIGMA_M)["rms_m"]
    assert at_last == pytest.approx(last["rms_m"], rel=0.15)
    ahead = RC.extrapolate_learning_curve(curve, 2 * last["poses"], SIGMA_M)
    assert ahead["extrapolated"] and np.sqrt(3) * SIGMA_M <= ahead["rms_m"] <= last["rms_m"] * 1.0001


def test_the_number_of_trees_is_chosen_on_the_fitting_rows_more_for_a_richer_error():
    """The inner cross-validation gives an error of the configuration that boosting builds up
    slowly more trees, and pure noise the fewest; a configuration's rows share a fold."""
    rng = np.random.default_rng(4)
    q = rng.uniform(REGION[:, 0], REGION[:, 1], (800, 6))
    # a smooth error of three joints: boosting builds it up over many rounds (measured: 400 trees)
    rich = 1e-4 * (np.sin(3 * q[:, 0]) + np.cos(4 * q[:, 1]) + np.sin(5 * q[:, 2]))
    noise = 1e-5 * rng.normal(size=len(q))
    folds = TT.configuration_folds(q, 3, 0)
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(q)))
    assert TT.choose_tree_count(q, rich + noise, folds, 0) >= 3 * TT.choose_tree_count(q, noise, folds, 0)
    assert TT.choose_tree_count(q, noise, folds, 0) == TT.TREES_STEP
    twice = np.vstack([q[:50], q[:50]])  # two rows of each configuration: never split
    fold_of = np.empty(len(twice), dtype=int)
    for k, f in enumerate(TT.configuration_folds(twice, 3, 1)):
        fold_of[f] = k
    assert np.array_equal(fold_of[:50], fold_of[50:])


def test_the_bounds_sigma_is_the_held_out_errors_own_95_percent_quantile():
    """Gaussian held-out errors: the quantile's σ is the RMS's; longer-tailed ones (a mixture of
    configurations with different errors) of the same RMS: wider, so that 95 % of them are inside."""
    from calibration.residual_base import quantile_model_sigma
    from calibration.uncertainty import chi2_quantile

    rng = np.random.default_rng(8)
    chi2 = chi2_quantile(0.95, 3)
    gauss = np.linalg.norm(rng.normal(0.0, 1e-4, (20000, 3)), axis=1)
    assert quantile_model_sigma(gauss, 0.0, chi2, 0.0) == pytest.approx(1e-4, rel=0.03)
    scale = np.where(rng.random(20000) < 0.9, 0.6e-4, 2.2e-4)  # a mixture, its RMS σ about 1e-4
    mixed = np.linalg.norm(rng.normal(0.0, 1.0, (20000, 3)) * scale[:, None], axis=1)
    rms_sigma = float(np.sqrt(np.mean(mixed**2) / 3))
    s = quantile_model_sigma(mixed, 0.0, chi2, rms_sigma)
    assert s > 1.1 * rms_sigma
    assert np.mean(mixed <= np.sqrt(chi2) * s) == pytest.approx(0.95, abs=0.005)
    assert np.mean(mixed <= np.sqrt(chi2) * rms_sigma) < 0.93
    # the instrument's noise is taken out, never below the floor given
    assert quantile_model_sigma(gauss, 0.5e-4, chi2, 0.0) < quantile_model_sigma(gauss, 0.0, chi2, 0.0)
    assert quantile_model_sigma(gauss[:5], 1.0, chi2, 3e-5) == 3e-5


def test_the_trees_are_not_tried_on_too_few_configurations_and_the_figures_say_why():
    """Below MIN_TREE_POSES configurations a tree's leaves (min_samples_leaf poses each) can barely
    split on an inner fold: the family is left out of the nested cross-validation, and said so."""
    fams, why = RC.families_tried(RC.FAMILIES, RC.MIN_TREE_POSES - 1)
    assert fams == ("none", "map", "transmission") and f"{RC.MIN_TREE_POSES - 1} configurations" in why["trees"]
    assert RC.families_tried(RC.FAMILIES, RC.MIN_TREE_POSES) == (RC.FAMILIES, {})
    assert RC.families_tried(("none", "map"), 10) == (("none", "map"), {})
