"""Analytic identification Jacobians (calibration.jacobian) against central finite differences
of the forward kinematics, the perturbation taken with ``apply_step`` (so that the Jacobian and
the update agree, which is what Levenberg–Marquardt needs)."""

from __future__ import annotations

import numpy as np
import pytest
from sample_models import all_convention_docs, random_readings, si_readings

from calibration.jacobian import predict
from calibration.kinematics import walk
from calibration.model import model_from_dict
from calibration.parameters import apply_step, candidate_parameters, parameter_values
from calibration.transforms import matrix_to_rotvec

DOCS = all_convention_docs()


def _p_tool(model, names):
    return np.array([model.target(t) for t in names])


def _predicted(model, q, names):
    w = walk(model, q)
    p = w.p + np.einsum("nij,nj->ni", w.R, _p_tool(model, names))
    return p, w.R


def _finite_difference(model, params, q, names, *, h_length=1e-6, h_angle=1e-6, h_scale=1e-7):
    """Central differences (N, 3, P) of the measured point and of the tool orientation
    (world-frame rotation vector), each parameter stepped with ``apply_step``."""
    N, P = len(q), len(params)
    Jp, Jr = np.zeros((N, 3, P)), np.zeros((N, 3, P))
    for k, par in enumerate(params):
        h = {"length": h_length, "angle": h_angle, "scale": h_scale}[par.kind]
        step = np.zeros(P)
        step[k] = h
        p_plus, R_plus = _predicted(apply_step(model, params, step), q, names)
        p_minus, R_minus = _predicted(apply_step(model, params, -step), q, names)
        Jp[:, :, k] = (p_plus - p_minus) / (2 * h)
        Jr[:, :, k] = matrix_to_rotvec(R_plus @ np.swapaxes(R_minus, 1, 2)) / (2 * h)
    return Jp, Jr


def _setup(doc_id, n=7, seed=0):
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    rng = np.random.default_rng(seed)
    q = si_readings(doc, random_readings(doc, n, rng))
    names = np.array(([None] + sorted(model.targets)) * n, dtype=object)[:n]
    params = candidate_parameters(model, targets=tuple(sorted(model.targets)), gains=True)
    return model, q, names, params


@pytest.mark.parametrize("doc_id", sorted(DOCS))
def test_analytic_jacobian_matches_finite_differences(doc_id):
    """Position rows and full-pose (orientation) rows, every candidate parameter: base, links
    (dh, Hayati, mdh, poe tilts and shifts), prismatic joints, targets, tool and gains."""
    model, q, names, params = _setup(doc_id)
    pred = predict(model, q, _p_tool(model, names), params, names)
    Jp_fd, Jr_fd = _finite_difference(model, params, q, names)
    assert pred.Jp.shape == (len(q), 3, len(params))
    scale_p = max(np.abs(Jp_fd).max(), 1.0)
    for k, par in enumerate(params):
        np.testing.assert_allclose(pred.Jp[:, :, k], Jp_fd[:, :, k], atol=1e-7 * scale_p, err_msg=par.name)
        np.testing.assert_allclose(pred.Jr[:, :, k], Jr_fd[:, :, k], atol=1e-7, err_msg=par.name)


def test_candidate_sets_cover_the_features():
    """The parameter sets the Jacobian test above runs over contain what they claim to."""
    names = {d: [p.name for p in _setup(d)[3]] for d in DOCS}
    assert "j2.beta" in names["dh_hayati"] and "j2.d" not in names["dh_hayati"]
    assert {"j3.tilt_x", "j3.shift_y", "home.rz"} <= set(names["poe"])
    assert {"j2.d", "j2.tilt_x", "j2.tilt_y"} <= set(names["poe_prismatic"])
    assert "j2.shift_x" not in names["poe_prismatic"]  # a prismatic axis has no position
    assert {"j1.gain", "j6.gain"} <= set(names["dh_gain"])
    assert not any(n.endswith(".gain") for n in names["dh_coupling"])  # coupling instead of gains
    assert {"target.smr1.x", "target.ball1.z"} <= set(names["dh"])
    assert {"j3.d", "j3.theta", "j3.a", "j3.alpha"} <= set(names["5r1p"])
    assert {"j1.alpha", "j2.a"} <= set(names["mdh"])


def test_target_columns_only_move_their_rows():
    model, q, names, params = _setup("dh", n=9)
    pred = predict(model, q, _p_tool(model, names), params, names)
    for k, par in enumerate(params):
        if par.target is not None:
            other = names != par.target
            assert np.all(pred.Jp[other, :, k] == 0)
            assert np.all(pred.Jr[:, :, k] == 0)
            assert np.all(np.linalg.norm(pred.Jp[~other, :, k], axis=1) > 0.99)


def test_gain_column_is_offset_column_times_reading():
    model, q, names, params = _setup("dh_gain")
    pred = predict(model, q, _p_tool(model, names), params, names)
    idx = {p.name: k for k, p in enumerate(params)}
    for j in range(6):
        np.testing.assert_allclose(
            pred.Jp[:, :, idx[f"j{j + 1}.gain"]], pred.Jp[:, :, idx[f"j{j + 1}.theta"]] * q[:, j, None], atol=1e-15
        )


def test_prediction_without_params_is_fk():
    model, q, names, _ = _setup("dh_coupling")
    pred = predict(model, q, _p_tool(model, names))
    p, R = _predicted(model, q, names)
    np.testing.assert_allclose(pred.p_world, p)
    np.testing.assert_allclose(pred.R_world_tool, R)
    assert pred.Jp is None and pred.Jr is None


def test_apply_step_is_a_new_model_and_values_follow():
    model, _q, _names, params = _setup("dh_prismatic")
    delta = np.linspace(-1e-3, 1e-3, len(params))
    moved = apply_step(model, params, delta)
    assert moved is not model
    v0, v1 = parameter_values(model, params), parameter_values(moved, params)
    for k, p in enumerate(params):
        head, _, _f = p.name.rpartition(".")
        if head in ("base", "tool"):
            continue
        assert v1[k] - v0[k] == pytest.approx(delta[k], abs=1e-15), p.name
    # the original is untouched
    np.testing.assert_array_equal(parameter_values(model, params), v0)
