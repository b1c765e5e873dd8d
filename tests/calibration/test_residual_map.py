"""Residual maps (calibration.residual_map, book §5.4): kernel ridge regression of what the
parametric model leaves, smoothness chosen on held-out data, applied only inside the measured
region, kept only when cross-validation shows a gain."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from calibration import compliance as C
from calibration import residual_choice as RC
from calibration import residual_map as RM
from calibration.identify import identify
from calibration.model import model_from_dict, model_to_dict
from calibration.robots import nominal
from calibration.simulate import SAGGING_ARMS, perturbed, random_configurations, sagging, simulate_measurements

REV = np.ones(6, dtype=bool)
CENTRE = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
REGION = np.stack([CENTRE - np.deg2rad(40), CENTRE + np.deg2rad(40)], axis=1)  # a task's region of the workspace


def _smooth(q):
    """A smooth 'remaining error' (N, 3) m of the configuration."""
    return 1e-4 * np.stack([np.sin(q[:, 1] + q[:, 2]), np.cos(q[:, 1]) * np.sin(q[:, 3]), np.cos(q[:, 2])], axis=1)


def test_map_learns_a_smooth_error_and_stays_out_of_unmeasured_regions():
    rng = np.random.default_rng(0)
    q = rng.uniform(REGION[:, 0], REGION[:, 1], (300, 6))
    r = _smooth(q) + rng.normal(0, 5e-6, (300, 3))
    folds = [np.arange(k, 300, 5) for k in range(5)]
    ell, lam, cv = RM.select_smoothness(q, r, REV, folds)
    m = RM.fit(q, r, REV, ell, lam)
    q_new = rng.uniform(REGION[:, 0], REGION[:, 1], (200, 6))
    corr, inside = m.evaluate(q_new)
    assert inside.mean() > 0.9  # a few fall just outside the range some joint was measured over
    err = np.sqrt(np.mean(np.sum((corr - _smooth(q_new))[inside] ** 2, axis=1)))
    size = np.sqrt(np.mean(np.sum(_smooth(q_new) ** 2, axis=1)))
    assert err < 0.25 * size  # it learned most of the error
    assert cv < 0.5 * np.sqrt(np.mean(np.sum(r**2, axis=1)))
    far = np.array([CENTRE + np.deg2rad([150, 0, 0, 0, 0, 0])])  # the base turned away: never measured
    corr, inside = m.evaluate(far)
    assert not inside[0] and np.all(corr == 0.0)


def _sagging_cell(seed=3):
    rng = np.random.default_rng(seed)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = sagging(perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3), "cobot", frames_of=nom)

    def measure(n):
        q = random_configurations(nom, n, rng, limits=REGION)
        return simulate_measurements(
            truth, q, rng, sigma_m=20e-6, targets=("smr",), payload=np.array(SAGGING_ARMS["cobot"]["payload"])
        )

    return nom, measure


def test_auto_keeps_a_map_that_helps_and_leaves_out_one_that_does_not():
    nom, measure = _sagging_cell()
    train, holdout = measure(200), measure(500)
    kw = {"sigma_m": 20e-6}
    # the rigid model of a sagging arm leaves a smooth error: the map takes most of it
    rmap, fig = RC.choose_residual_map(nom, train, identify_kw=kw)
    assert fig["kept"] and rmap is not None and fig["gain"] > 0.3
    model = identify(nom, train, **kw).model
    r = RM.residuals(model, holdout)
    corr, inside = rmap.evaluate(holdout.q)
    before = np.sqrt(np.mean(np.sum(r**2, axis=1)))
    after = np.sqrt(np.mean(np.sum((r - corr) ** 2, axis=1)))
    assert inside.mean() > 0.9 and after < 0.6 * before
    # the compliant model leaves only noise: the map is left out, and the figures say why
    rmap, fig = RC.choose_residual_map(C.with_section(nom, C.default_section(nom)), train, identify_kw=kw)
    assert rmap is None and not fig["kept"] and fig["gain"] < RM.MIN_CV_GAIN
    assert fig["rms_without_m"] < 1.1 * np.sqrt(3) * 20e-6


def test_map_round_trips_through_the_model_file():
    rng = np.random.default_rng(1)
    q = rng.uniform(REGION[:, 0], REGION[:, 1], (50, 6))
    m = RM.fit(q, _smooth(q), REV, 1.2, 1e-3, {"rms_with_m": 1e-5})
    model = nominal("ur10e")  # mm, deg
    doc = json.loads(json.dumps({**model_to_dict(model), "residual_map": RM.to_dict(m, model)}))
    back = RM.from_model(model_from_dict(doc))
    q_new = rng.uniform(REGION[:, 0], REGION[:, 1], (20, 6))
    a, ia = m.evaluate(q_new)
    b, ib = back.evaluate(q_new)
    assert np.array_equal(ia, ib) and np.allclose(a, b, atol=1e-12)
    assert doc["residual_map"]["cross_validation"]["rms_with_m"] == 1e-2  # in mm
    doc["residual_map"]["coefficients"] = doc["residual_map"]["coefficients"][:-1]
    try:
        RM.from_model(model_from_dict(doc))
    except RM.ResidualMapError as exc:
        assert exc.field == "residual_map.configurations"
    else:
        raise AssertionError("a short coefficient list must be refused")


def _peak_bytes(fn) -> int:
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_auto_on_many_configurations_fits_a_bounded_map_in_memory_linear_in_rows():
    # issue 22: the map's kernel matrix was rows x rows (a 31,487-row import needed 16 GB); the
    # map now takes a seeded draw of at most MAX_MAP_CONFIGURATIONS configurations, and twice the
    # rows cost at most about twice the memory
    nom, measure = _sagging_cell()
    small, large = measure(600), measure(1200)
    kw = {"sigma_m": 20e-6}
    out = {}
    peaks = [
        _peak_bytes(lambda d=d: out.setdefault(len(d), RC.choose_residual_map(nom, d, identify_kw=kw)))
        for d in (small, large)
    ]
    rmap, fig = out[1200]
    assert fig["kept"] and rmap is not None
    assert len(rmap.q_train) == fig["rows"] <= RM.MAX_MAP_CONFIGURATIONS
    assert peaks[1] < 2.6 * peaks[0], peaks
    # the map drawn from the configurations still corrects fresh ones of the region
    model = identify(nom, large, **kw).model
    holdout = measure(300)
    r = RM.residuals(model, holdout)
    corr, inside = rmap.evaluate(holdout.q)
    assert inside.mean() > 0.9
    assert np.sqrt(np.mean(np.sum((r - corr) ** 2, axis=1))) < 0.6 * np.sqrt(np.mean(np.sum(r**2, axis=1)))
