"""Identification says honestly what the data determine (calibration.identify, report).

- What cannot be determined is explained in the dimensionless parameterisation the selection
  uses: "the same motion" only when one freed parameter alone explains it; otherwise the whole
  combination, with coefficients and units.
- Of two parameters that move the measured points alike, the one kept is the physically
  meaningful one: with position-only data a reflector's offset, not the last joint's offset
  (which would turn the tool orientation by the reflector's mounting error).
- With a prior (minimum-variance estimation, book §4.3.2), every parameter is either determined
  (by the data, or by data and prior) or undetermined, never both; the conditioning reported
  is that of what was estimated; what the data cannot see keeps the prior's value and
  uncertainty. What the previous calibration could not determine is not held by it: a CMM's
  full poses after a tracker calibration determine the tool frame, and the reflector's offset
  (which stood in for the tool's) moves with it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.geometry import pose_from_points
from calibration.identify import Prior, drift_scale, held_relations, identify
from calibration.jacobian import predict
from calibration.kinematics import fk
from calibration.model import Units
from calibration.parameters import apply_step, candidate_parameters, parameter_values
from calibration.report import identification_report
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.transforms import matrix_to_pose, matrix_to_rotvec, pose_to_matrix
from calibration.uncertainty import predicted_uncertainty, propagate, radius_95

SIGMA = 20e-6
REFLECTOR = np.array([0.04, 0.04, 0.06])  # a reflector near the flange, off the last axis


@pytest.fixture(scope="module")
def flange_case():
    """The audit's case: a UR10e, one reflector `smr1` near the flange (its true mounting 1 mm or
    so off the nominal), 4,000 position-only rows with 0.02 mm noise from a perturbed truth."""
    rng = np.random.default_rng(1)
    nom = dataclasses.replace(nominal("ur10e"), targets={"smr1": REFLECTOR})
    truth = perturbed(nom, rng)
    truth = dataclasses.replace(truth, targets={"smr1": REFLECTOR + rng.normal(0, 1e-3, 3)})
    data = simulate_measurements(truth, random_configurations(nom, 4000, rng), rng, sigma_m=SIGMA, targets=("smr1",))
    return nom, truth, data, identify(nom, data)


def _unit_columns(model, data, names):
    """The weighted Jacobian's columns of ``names`` at ``model``, scaled to unit norm."""
    cands = {p.name: p for p in candidate_parameters(model, targets=("smr1",))}
    params = [cands[n] for n in names]
    Jp = predict(model, data.q, model.targets["smr1"], params, data.target).Jp.reshape(-1, len(names))
    return Jp / np.linalg.norm(Jp, axis=0)


def test_same_motion_only_when_one_parameter_explains_it(flange_case):
    _nom, _truth, data, result = flange_case
    why = {u.name: u for u in result.unidentifiable}
    for r in ("tool.rx", "tool.ry", "tool.rz"):
        assert why[r].reason.startswith("tool orientation is unobservable from position-only data"), why[r].reason
        assert "same motion" not in why[r].reason
    same = [u for u in result.unidentifiable if "same motion" in u.reason]
    assert {"j1.theta", "j1.d"} <= {u.name for u in same}
    for u in same:  # checked on the Jacobian itself: the two unit columns are parallel
        c = _unit_columns(result.start_model, data, [u.name, u.relation[0][0]])
        assert abs(c[:, 0] @ c[:, 1]) > 1 - 1e-6, u.reason
    for u in result.unidentifiable:
        if u.category == "combination":
            names = [u.name] + [n for n, _ in u.relation]
            c = _unit_columns(result.start_model, data, names[:2])
            assert abs(c[:, 0] @ c[:, 1]) < 1 - 1e-6, u.reason  # not one parameter's motion
            assert "≡" in u.reason and all(n in u.reason for n in names[:3])


def test_relations_are_written_with_units(flange_case):
    result = flange_case[3]
    rep = identification_report(result, Units("mm", "deg"))
    un = {u["name"]: u for u in rep["unidentifiable"]}
    # 1 deg of tool.rx moves the reflector as target offsets of about 1 mm do (0.06 m * pi / 180)
    rx = {s["name"]: s for s in un["tool.rx"]["same_as"]}
    assert rx["target.smr1.y"]["unit"] == "mm/deg"
    assert rx["target.smr1.y"]["coefficient"] == pytest.approx(
        -result.model.targets["smr1"][2] * np.pi / 0.180, rel=0.05
    )
    assert "deg of tool.rx" in un["tool.rx"]["reason"] and "mm of target.smr1.y" in un["tool.rx"]["reason"]
    assert un["j1.theta"]["same_as"][0]["unit"] == "1"


def test_the_reflector_offset_is_kept_and_the_last_joint_offset_stays_nominal(flange_case):
    nom, truth, _data, result = flange_case
    assert {"target.smr1.x", "target.smr1.y", "target.smr1.z"} <= set(result.param_names)
    assert "j6.theta" not in result.param_names
    why = {u.name: u for u in result.unidentifiable}
    assert why["j6.theta"].category == "last_joint_offset" and "target offsets" in why["j6.theta"].reason
    # nothing that was not freed moved away from where it started
    start = result.start_model
    fixed = [p for p in candidate_parameters(start, targets=("smr1",)) if p.name in why]
    assert np.array_equal(parameter_values(result.model, fixed), parameter_values(start, fixed))
    assert np.array_equal(result.model.tool, start.tool)
    assert result.model.joints[5].theta == nom.joints[5].theta
    # so the model's tool orientation is the robot's, within the simulated link errors
    # (0.05-0.1 deg), instead of turned by the reflector's mounting error
    q = random_configurations(nom, 200, np.random.default_rng(3))
    R_id, R_true = fk(result.model, q)[:, :3, :3], fk(truth, q)[:, :3, :3]
    angle = np.linalg.norm(matrix_to_rotvec(R_id @ np.swapaxes(R_true, 1, 2)), axis=1)
    assert np.degrees(angle.max()) < 0.5


# --------------------------------------------------------------------------- with a prior


def _truth_of_two_sessions():
    rng = np.random.default_rng(7)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), "ball1": np.array([0.06, 0.0, 0.04])}
    nom = dataclasses.replace(nominal("ur5e"), targets=targets)
    truth = perturbed(nom, rng)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.2, 0.4, -0.2, 0.003, 0.002, np.deg2rad(-60)]),
        targets={k: v + rng.normal(0, 0.5e-3, 3) for k, v in targets.items()},
    )
    return nom, truth, rng


@pytest.fixture(scope="module")
def two_sessions():
    """A UR5e with a reflector `smr` and a tooling ball `ball1`. First calibration: 24 poses, both
    measured; the second, 16 poses of `smr` only, with the first as its prior (the previous
    covariance plus the full drift allowance)."""
    nom, truth, rng = _truth_of_two_sessions()
    first = identify(
        nom, simulate_measurements(truth, random_configurations(nom, 24, rng), rng, targets=("smr", "ball1"))
    )
    drift = np.array([np.deg2rad(0.005) if p.kind == "angle" else 0.05e-3 for p in first.params])
    prior = Prior(first.param_names, first.covariance + np.diag(drift**2), held_relations(first))
    data2 = simulate_measurements(truth, random_configurations(nom, 16, rng), rng, targets=("smr",))
    second = identify(first.model, data2, prior=prior)
    alone = identify(nom, data2)
    return nom, first, prior, second, alone


def test_with_a_prior_every_parameter_is_determined_or_undetermined_never_both(two_sessions):
    _nom, _first, prior, second, _alone = two_sessions
    assert second.success
    freed, dropped = set(second.param_names), {u.name for u in second.unidentifiable}
    assert not freed & dropped
    assert len(second.sources) == len(second.params)
    assert set(second.sources) <= {"data", "data + prior", "prior"}
    with_prior = set(prior.names)
    for name, source in zip(second.param_names, second.sources):
        assert (source == "data") == (name not in with_prior), (name, source)
    # conditioning of what was estimated (data and prior together), and of the data alone
    assert 1.0 < second.condition_number < 1e4
    assert second.data_only is not None and 1.0 < second.data_only["condition_number"] < 1e6
    assert set(second.data_only["parameters"]) < freed
    # the data can only sharpen what the prior knew
    est = np.array([s == "data + prior" for s in second.sources])
    assert np.all(second.std_errors[est] <= second.prior_std_errors[est] * second.sigma_scale * (1 + 1e-9))


def test_what_the_data_cannot_see_keeps_the_prior(two_sessions):
    _nom, first, prior, second, _alone = two_sessions
    src = dict(zip(second.param_names, second.sources))
    unseen = [n for n, s in src.items() if s == "prior"]
    assert {"target.ball1.x", "target.ball1.y", "target.ball1.z"} <= set(unseen)  # not measured this time
    k = [second.param_names.index(n) for n in unseen]
    kp = [prior.names.index(n) for n in unseen]
    assert np.array_equal(second.covariance[np.ix_(k, k)], prior.covariance[np.ix_(kp, kp)])
    assert np.all(second.steps[k] == 0.0)
    assert np.array_equal(second.model.targets["ball1"], first.model.targets["ball1"])
    rep = identification_report(second, Units("mm", "deg"))
    assert {p["name"]: p["source"] for p in rep["parameters"]} == src
    assert rep["data_only"]["condition_number"] > 1.0


def test_the_prior_improves_the_predicted_accuracy(two_sessions):
    nom, first, prior, second, alone = two_sessions
    q = random_configurations(nom, 300, np.random.default_rng(9))
    names = np.array(["smr"] * len(q), dtype=object)
    u_second = np.median(predicted_uncertainty(second, q, "smr"))
    u_alone = np.median(predicted_uncertainty(alone, q, "smr"))
    C_prior = propagate(first.model, list(first.params), prior.covariance, q, names)
    u_prior = np.median(radius_95(C_prior))
    assert u_second < u_alone and u_second <= u_prior * second.sigma_scale


def test_drift_scale_follows_what_the_data_show():
    """The service's prior is the previous covariance plus a drift allowance scaled by what the
    new data show: nothing when the robot did not move, about the allowance when it did. With
    it, a second calibration (16 poses) of a robot that did not move is predicted at least as
    accurate as the first (24 poses), not less accurate as with the full allowance."""
    nom, truth, rng = _truth_of_two_sessions()
    first = identify(nom, simulate_measurements(truth, random_configurations(nom, 24, rng), rng, targets=("smr",)))
    q2 = random_configurations(nom, 16, rng)
    drift = np.array([np.deg2rad(0.005) if p.kind == "angle" else 0.05e-3 for p in first.params])
    same = simulate_measurements(truth, q2, rng, targets=("smr",))
    s_same = drift_scale(first.model, same, first.param_names, first.covariance, drift)
    cands = candidate_parameters(truth)
    moved_by = np.array([rng.normal(0, 3 * (np.deg2rad(0.005) if p.kind == "angle" else 0.05e-3)) for p in cands])
    moved = dataclasses.replace(apply_step(truth, cands, moved_by), targets=truth.targets)
    s_moved = drift_scale(
        first.model, simulate_measurements(moved, q2, rng, targets=("smr",)), first.param_names, first.covariance, drift
    )
    assert s_same < 0.3 and s_moved > 1.0, (s_same, s_moved)

    q = random_configurations(nom, 300, np.random.default_rng(9))
    u_first = np.median(predicted_uncertainty(first, q, "smr"))
    u = {}
    for scale in (1.0, max(s_same, 0.1)):
        prior = Prior(first.param_names, first.covariance + np.diag((scale * drift) ** 2))
        u[scale] = np.median(predicted_uncertainty(identify(first.model, same, prior=prior), q, "smr"))
    assert u[max(s_same, 0.1)] <= u_first < u[1.0]


# --------------------------------------------------------------------------- a CMM after a tracker

BALLS = {"ball1": [0.06, 0.0, 0.04], "ball2": [-0.03, 0.052, 0.04], "ball3": [-0.03, -0.052, 0.04]}
CMM_SIGMA_M, CMM_SIGMA_RAD = 5e-6, 5e-5


def _drift(params):
    return np.array([np.deg2rad(0.005) if p.kind == "angle" else 0.05e-3 for p in params])


@pytest.fixture(scope="module")
def tracker_then_cmm():
    """A UR5e with a reflector `smr` and three tooling balls, all mounted about 0.5 mm off their
    drawing. First a tracker calibration (24 poses of `smr`, position only: it cannot see the
    tool orientation, and the reflector's offset stands in for the tool's); then a CMM session
    (16 full poses) with it as the prior, built as the service builds it (held relations, drift
    allowance scaled by drift_scale). The CMM measures the frame the balls' drawn layout fits
    best on the real balls (service.session_loop, book eq. 6.12-6.15): the true tool frame times
    the constant X, simulated here with the noise the rows state."""
    rng = np.random.default_rng(11)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), **{k: np.array(v) for k, v in BALLS.items()}}
    nom = dataclasses.replace(nominal("ur5e"), targets=targets)
    truth = perturbed(nom, rng)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.2, 0.4, -0.2, 0.003, 0.002, np.deg2rad(-60)]),
        targets={k: v + rng.normal(0, 0.5e-3, 3) for k, v in targets.items()},
    )
    first = identify(nom, simulate_measurements(truth, random_configurations(nom, 24, rng), rng, targets=("smr",)))
    X, misfit = pose_from_points(np.array(list(BALLS.values())), np.array([truth.targets[k] for k in BALLS]))
    seen_by_cmm = dataclasses.replace(truth, tool=matrix_to_pose(pose_to_matrix(truth.tool) @ X))
    cmm = simulate_measurements(
        seen_by_cmm,
        random_configurations(nom, 16, rng),
        rng,
        sigma_m=CMM_SIGMA_M,
        full_pose=True,
        sigma_rad=CMM_SIGMA_RAD,
    )
    held = held_relations(first)
    kw = dict(sigma_m=CMM_SIGMA_M, sigma_rad=CMM_SIGMA_RAD)
    drift = _drift(first.params)
    scale = drift_scale(first.model, cmm, first.param_names, first.covariance, drift, held=held, **kw)
    prior = Prior(first.param_names, first.covariance + np.diag((max(scale, 0.1) * drift) ** 2), held)
    second = identify(first.model, cmm, prior=prior, **kw)
    return truth, seen_by_cmm, misfit, first, cmm, scale, prior, second


def test_a_cmm_after_a_tracker_determines_the_tool_frame_the_tracker_could_not(tracker_then_cmm):
    truth, seen_by_cmm, misfit, first, _cmm, scale, prior, second = tracker_then_cmm
    assert misfit > 0.2e-3  # the balls are off their drawing
    held = {u.name for u in first.unidentifiable}
    assert {"tool.tx", "tool.ty", "tool.tz", "tool.rx", "tool.ry"} <= held  # the tracker could not see them
    # the data determine what they can: the tool frame, and (sharper) the wrist parameters the
    # reflector nominally on the flange axis let the tracker determine only to millimetres and
    # degrees (issue 14: freed at its identified geometry, not held at the nominal)
    src = dict(zip(second.param_names, second.sources))
    for name in ("tool.tx", "tool.ty", "tool.tz", "tool.rx", "tool.ry"):
        assert src[name] == "data", (name, src.get(name))
    sd1, sd2 = dict(zip(first.param_names, first.std_errors)), dict(zip(second.param_names, second.std_errors))
    for name in ("j5.a", "j5.alpha"):
        assert src[name] == "data + prior" and sd2[name] < sd1[name] / 10, (name, src[name], sd1[name], sd2[name])
    # the robot did not move: no drift, and the fit reaches the noise the rows state
    assert scale < 0.3, scale
    assert second.success and 0.6 < second.chi2 / second.dof < 1.4, second.chi2 / second.dof
    assert second.chi2_prior < len(prior.names), second.chi2_prior
    q = random_configurations(truth, 200, np.random.default_rng(12))
    T_cmm, T_id = fk(seen_by_cmm, q), fk(second.model, q)
    err = np.linalg.norm(T_cmm[:, :3, 3] - T_id[:, :3, 3], axis=1)
    angle = np.linalg.norm(matrix_to_rotvec(T_id[:, :3, :3] @ np.swapaxes(T_cmm[:, :3, :3], 1, 2)), axis=1)
    assert np.sqrt(np.mean(err**2)) < 20e-6 and np.degrees(angle.max()) < 0.01, (err.max(), angle.max())
    # the reflector's offset moved with the tool frame: it is still where the tracker measured it
    smr = lambda m: fk(m, q)[:, :3, :3] @ m.targets["smr"] + fk(m, q)[:, :3, 3]  # noqa: E731
    assert np.sqrt(np.mean(np.sum((smr(truth) - smr(second.model)) ** 2, axis=1))) < 30e-6
    assert src["target.smr.x"] == "data + prior"
    rep = identification_report(second, Units("mm", "deg"))
    assert {p["name"]: p["source"] for p in rep["parameters"]} == src


def test_without_its_held_relations_the_tracker_prior_holds_the_cmm_off(tracker_then_cmm):
    """The prior's covariance is of what the tracker determined with the held parameters at the
    model's value (its reflector offset stands in for the tool frame's translation): taken for the
    parameters themselves, it keeps the reflector where the tracker put it in the old tool frame
    while the CMM moves the tool frame, half a millimetre off."""
    truth, _seen_by_cmm, _misfit, first, cmm, _scale, prior, second = tracker_then_cmm
    naive = identify(
        first.model, cmm, prior=Prior(prior.names, prior.covariance), sigma_m=CMM_SIGMA_M, sigma_rad=CMM_SIGMA_RAD
    )
    q = random_configurations(truth, 200, np.random.default_rng(12))
    smr = lambda m: fk(m, q)[:, :3, :3] @ m.targets["smr"] + fk(m, q)[:, :3, 3]  # noqa: E731
    rms = {
        k: np.sqrt(np.mean(np.sum((smr(truth) - smr(r.model)) ** 2, axis=1)))
        for k, r in (("naive", naive), ("held", second))
    }
    assert rms["naive"] > 10 * rms["held"] and rms["naive"] > 0.2e-3, rms
