"""Observation planning (calibration.planning): feasibility of candidates, optimality of the design,
and the predicted accuracy against what identification then delivers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from calibration import planning
from calibration.identify import identify
from calibration.kinematics import fk, target_positions
from calibration.parameters import apply_step
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements

SMR = np.array([0.03, 0.0, 0.08])  # a reflector on a bracket, off the flange axis


@pytest.fixture(scope="module")
def ur():
    return dataclasses.replace(nominal("ur10e"), targets={"smr": SMR})


@pytest.fixture(scope="module")
def cand(ur):
    return planning.generate_candidates(ur, 600, np.random.default_rng(0), targets=("smr",))


# --------------------------------------------------------------------------- geometry of feasibility


def test_segment_distance_against_dense_sampling():
    rng = np.random.default_rng(1)
    a0, a1, b0, b1 = (rng.normal(size=(100, 3)) for _ in range(4))
    b1[:20] = b0[:20]  # some point-like segments
    a1[20:30] = a0[20:30]
    b0[30:40] = a0[30:40] + 0.3 * (a1[30:40] - a0[30:40])  # parallel segments
    b1[30:40] = b0[30:40] + 0.5 * (a1[30:40] - a0[30:40]) + [0, 0.1, 0]
    d = planning.segment_distance(a0, a1, b0, b1)
    s = np.linspace(0, 1, 201)
    pa = a0[:, None, :] + s[None, :, None] * (a1 - a0)[:, None, :]
    pb = b0[:, None, :] + s[None, :, None] * (b1 - b0)[:, None, :]
    brute = np.min(np.linalg.norm(pa[:, :, None, :] - pb[:, None, :, :], axis=3), axis=(1, 2))
    assert np.all(d <= brute + 1e-12)
    np.testing.assert_allclose(d, brute, atol=1e-2)


def test_volumes():
    box = planning.Volume.box([0, 0, 0], [1, 2, 3])
    assert list(box.contains([[0.5, 1, 1], [1.5, 1, 1], [0.5, 1, -0.1]])) == [True, False, False]
    shell = planning.Volume.sphere([1, 0, 0], 2.0, inner_radius=0.5)
    assert list(shell.contains([[1, 0, 0], [2, 0, 0], [3.5, 0, 0]])) == [False, True, False]
    with pytest.raises(ValueError):
        planning.Volume.box([0, 0, 0], [1, 0, 1])
    with pytest.raises(ValueError):
        planning.Volume.sphere([0, 0, 0], 1.0, inner_radius=2.0)


def test_stick_figure_runs_from_base_to_flange(ur):
    q = random_configurations(ur, 5, np.random.default_rng(2))
    pts = planning.stick_figure(ur, q)
    np.testing.assert_allclose(pts[:, 0], np.zeros((5, 3)), atol=1e-12)  # base origin
    np.testing.assert_allclose(pts[:, -1], fk(ur, q)[:, :3, 3], atol=1e-12)  # flange (tool is identity)


def test_generated_candidates_are_feasible(ur):
    """Tracker 2.5 m in front of the robot: every candidate's reflector is in the box, faces the
    tracker within 30° and the beam clears the arm by 5 cm; and the constraints do reject."""
    robot = dataclasses.replace(ur, base=np.array([2.5, 0, 0, 0, 0, np.pi]))
    sight = planning.LineOfSight(cone_rad=np.deg2rad(30), clearance_m=0.05, near_target_m=0.1)
    box = planning.Volume.box([1.0, -1.5, 0.1], [4.0, 1.5, 2.0])
    rng = np.random.default_rng(3)
    q = planning.generate_candidates(robot, 40, rng, targets=("smr",), volume=box, sight=sight)
    assert len(q) == 40
    T = fk(robot, q)
    p = T[:, :3, :3] @ SMR + T[:, :3, 3]
    assert box.contains(p).all()
    beam = -p / np.linalg.norm(p, axis=1, keepdims=True)  # towards the tracker at the origin
    cos = np.einsum("ni,ni->n", T[:, :3, 2], beam)
    assert np.all(cos >= math.cos(np.deg2rad(30)) - 1e-12)
    # clearance, by sampling the beam (short of its last 0.1 m) against the stick figure's links
    pts = planning.stick_figure(robot, q)
    length = np.linalg.norm(p, axis=1)
    s = np.linspace(0, 1, 150)[None, :, None]
    end = p + beam * 0.1  # the beam stops 0.1 m short of the reflector
    beam_pts = s * end[:, None, :]  # from the tracker (origin) to that end
    t = np.linspace(0, 1, 25)[None, None, :, None]
    link_pts = pts[:, :-1, None, :] + t * (pts[:, 1:, None, :] - pts[:, :-1, None, :])
    link_pts = link_pts.reshape(len(q), -1, 3)
    dmin = np.min(np.linalg.norm(beam_pts[:, :, None, :] - link_pts[:, None, :, :], axis=3), axis=(1, 2))
    assert np.all(dmin >= 0.05 - 1e-9) and np.all(length > 0.1)
    assert np.all(planning.visible(robot, q, sight, "smr"))
    # the constraints are not vacuous
    q_all = random_configurations(robot, 400, rng)
    ok = planning.feasible(robot, q_all, targets=("smr",), volume=box, sight=sight)
    assert 0 < ok.mean() < 0.2


def test_impossible_constraints_are_reported(ur):
    far = planning.Volume.sphere([10.0, 0, 0], 0.5)
    with pytest.raises(ValueError, match="none of"):
        planning.generate_candidates(ur, 10, np.random.default_rng(0), volume=far, max_draws=2000)


# --------------------------------------------------------------------------- the design


def _reference_jacobian(model, q: np.ndarray, params) -> np.ndarray:
    """(K, 3, P): the reflector's position differentiated by each of the plan's parameters (SI),
    by central differences of the public forward kinematics of the planner's identification form
    (``apply_step``): a reference that shares nothing with the planner's analytic Jacobian."""
    work = planning.identification_form(model)
    params, h = list(params), 1e-6
    J = np.empty((len(q), 3, len(params)))
    for k in range(len(params)):
        step = np.zeros(len(params))
        step[k] = h
        hi = target_positions(apply_step(work, params, step), q, "smr")
        lo = target_positions(apply_step(work, params, -step), q, "smr")
        J[:, :, k] = (hi - lo) / (2 * h)
    return J


def _info(J: np.ndarray, idx) -> np.ndarray:
    return np.einsum("krp,krq->pq", J[idx], J[idx])


def _log_det(J: np.ndarray, idx) -> float:
    return float(np.linalg.slogdet(_info(J, idx))[1])


def _predicted_rms_m(J: np.ndarray, Je: np.ndarray, idx, sigma_m: float) -> float:
    """RMS over the evaluation configurations of √trace(Jₑ Σ Jₑᵀ), Σ = σ² (JᵀJ)⁻¹: the position
    error the identified model is predicted to have (one target)."""
    cov = sigma_m**2 * np.linalg.inv(_info(J, idx))
    var = np.einsum("erp,pq,erq->e", Je, cov, Je)
    return float(np.sqrt(np.mean(var)))


def test_d_optimal_plan_admits_no_improving_swap(ur):
    """On a small problem, checked by brute force against the reference Jacobian: no exchange of
    one chosen pose for one candidate increases log det M (the exchange's Woodbury and
    determinant-lemma updates are right). Scaling the parameters shifts every log det alike, so
    the comparison holds in SI units."""
    rng = np.random.default_rng(4)
    cand = random_configurations(ur, 80, rng)
    res = planning.plan(ur, cand, 12, targets=("smr",), criterion="D", n_evaluation=20)
    assert res.success and res.value == pytest.approx(res.log_det) and res.value >= res.greedy_value
    J = _reference_jacobian(ur, cand, res.params)
    best = _log_det(J, res.indices)
    out = np.setdiff1d(np.arange(len(cand)), res.indices)
    for pos in range(len(res.indices)):
        for i in out:
            idx = res.indices.copy()
            idx[pos] = i
            assert _log_det(J, idx) <= best + 1e-6


def test_i_optimal_plan_admits_no_improving_swap(ur):
    """The I exchange scores swaps by rank-3 updates of trace(M⁻¹W): checked by brute force with
    the reference Jacobian, its predicted RMS error is the reference's, and no exchange of one
    chosen pose for one candidate lowers it."""
    rng = np.random.default_rng(4)
    cand = random_configurations(ur, 80, rng)
    res = planning.plan(ur, cand, 12, targets=("smr",), criterion="I", n_evaluation=20)
    assert res.criterion == "I" and res.success and res.swaps > 0 and res.value <= res.greedy_value
    J = _reference_jacobian(ur, cand, res.params)
    Je = _reference_jacobian(ur, res.evaluation_q, res.params)
    best = _predicted_rms_m(J, Je, res.indices, res.sigma_m)
    assert best == pytest.approx(res.predicted_rms_m, rel=1e-6) and res.value == pytest.approx(res.predicted_rms_m)
    out = np.setdiff1d(np.arange(len(cand)), res.indices)
    for pos in range(len(res.indices)):
        for i in out:
            idx = res.indices.copy()
            idx[pos] = i
            assert _predicted_rms_m(J, Je, idx, res.sigma_m) >= best * (1 - 1e-6)


def test_plan_beats_random_designs(ur, cand):
    """Planned poses beat every one of 20 random designs from the same candidates, by the
    reference Jacobian: I on the predicted RMS error, the default (D) on log det M."""
    res = planning.plan(ur, cand, 30, targets=("smr",), criterion="I", n_evaluation=100)
    res_d = planning.plan(ur, cand, 30, targets=("smr",), n_evaluation=100)
    assert res.param_names == res_d.param_names
    J = _reference_jacobian(ur, cand, res.params)
    Je = _reference_jacobian(ur, res.evaluation_q, res.params)
    rng = np.random.default_rng(5)
    designs = [rng.choice(len(cand), 30, replace=False) for _ in range(20)]
    logdets = [_log_det(J, idx) for idx in designs]
    rms = [_predicted_rms_m(J, Je, idx, res.sigma_m) for idx in designs]
    planned_rms = _predicted_rms_m(J, Je, res.indices, res.sigma_m)
    assert _log_det(J, res_d.indices) > max(logdets)
    assert planned_rms < min(rms) and planned_rms < 0.9 * np.median(rms)
    assert planned_rms < _predicted_rms_m(J, Je, res_d.indices, res.sigma_m)
    assert res.q.shape == (30, 6) and len(set(res.indices.tolist())) == 30
    np.testing.assert_array_equal(res.q, cand[res.indices])


def test_predicted_covariance_is_what_identification_reports(ur, cand):
    """Measure a perturbed robot at the planned poses and identify: the same parameters are freed,
    and the standard errors identify reports (divided by its sigma scale) are the predicted ones."""
    res = planning.plan(ur, cand, 30, targets=("smr",), n_evaluation=100)
    rng = np.random.default_rng(6)
    truth = perturbed(ur, rng)
    data = simulate_measurements(truth, res.q, rng, targets=("smr",), sigma_m=20e-6)
    fit = identify(ur, data, sigma_m=20e-6)
    assert fit.success and fit.param_names == res.param_names
    np.testing.assert_allclose(fit.std_errors / fit.sigma_scale, res.std_errors, rtol=0.08)
    # and the hold-out error of that model is of the predicted size (one noise draw: loose)
    qh = random_configurations(ur, 300, rng)
    e = np.linalg.norm(target_positions(fit.model, qh, "smr") - target_positions(truth, qh, "smr"), axis=1)
    assert 0.4 * res.predicted_rms_m < np.sqrt(np.mean(e**2)) < 2.5 * res.predicted_rms_m


@pytest.mark.parametrize("criterion", ["O3", "O4", "condition", "I"])
def test_each_criterion_improves_its_own_index(ur, cand, criterion):
    res = planning.plan(ur, cand[:250], 20, targets=("smr",), criterion=criterion, n_evaluation=60)
    assert res.success
    if criterion in ("condition", "I"):
        assert res.value <= res.greedy_value
    else:
        assert res.value >= res.greedy_value
    key = {"O3": "O3_min_singular", "O4": "O4_noise_amplification", "condition": "condition_number_physical"}
    if criterion in key:
        assert res.value == pytest.approx(res.observability[key[criterion]], rel=1e-6)
    else:
        assert res.value == pytest.approx(res.predicted_rms_m, rel=1e-9)


def test_observability_matches_identify_indices(ur, cand):
    """The plan's observability index is what identification reports for noise-free data at the
    planned poses (PlanResult's promise), through identify's public result."""
    res = planning.plan(ur, cand, 20, targets=("smr",), criterion="O1", n_evaluation=50)
    data = simulate_measurements(ur, res.q, np.random.default_rng(0), targets=("smr",), sigma_m=0.0)
    fit = identify(ur, data, sigma_m=20e-6, register="never")
    assert fit.param_names == res.param_names
    assert res.value == pytest.approx(fit.observability["O1_borm_menq"], rel=1e-6)


def test_predicted_accuracy_scales_with_the_instrument(ur, cand):
    a = planning.plan(ur, cand, 25, targets=("smr",), sigma_m=10e-6, n_evaluation=50)
    b = planning.plan(ur, cand, 25, targets=("smr",), sigma_m=40e-6, n_evaluation=50)
    np.testing.assert_array_equal(a.indices, b.indices)
    assert b.predicted_rms_m == pytest.approx(4 * a.predicted_rms_m, rel=1e-9)
    assert a.predicted_p95_m >= a.predicted_rms_m * 0.8 and a.predicted_max_m >= a.predicted_p95_m


def test_poses_for_accuracy(ur, cand):
    wanted = 25e-6
    r = planning.poses_for_accuracy(ur, cand, wanted, targets=("smr",), n_evaluation=80)
    assert r.success and r.count is not None
    assert r.plan.predicted_rms_m <= wanted and len(r.plan.indices) == r.count
    # along the greedy curve, one pose fewer than the answer did not yet reach it
    before = r.predicted_m[r.counts < r.count]
    assert len(before) and np.all(before > wanted)
    assert np.all(np.diff(r.predicted_m[np.isfinite(r.predicted_m)]) <= 1e-12)  # more poses never hurt
    p95 = planning.poses_for_accuracy(ur, cand, wanted, statistic="p95", targets=("smr",), n_evaluation=80)
    assert p95.count >= r.count and p95.plan.predicted_p95_m <= wanted
    never = planning.poses_for_accuracy(ur, cand, 1e-6, targets=("smr",), n_evaluation=40, k_max=40)
    assert not never.success and never.count is None and "even 40 poses" in never.message


def test_bad_input(ur, cand):
    with pytest.raises(ValueError, match="at least"):
        planning.plan(ur, cand, 3, targets=("smr",))
    with pytest.raises(ValueError, match="exceeds"):
        planning.plan(ur, cand[:20], 25, targets=("smr",))
    with pytest.raises(ValueError, match="criterion"):
        planning.plan(ur, cand, 20, criterion="A")
    with pytest.raises(KeyError, match="unknown target"):
        planning.plan(ur, cand, 20, targets=("ball",))
    with pytest.raises(ValueError, match="shape"):
        planning.plan(ur, cand[:, :5], 20)
    with pytest.raises(ValueError, match="accuracy"):
        planning.poses_for_accuracy(ur, cand, -1.0)


def test_measurement_order_is_a_short_tour():
    q = np.random.default_rng(8).uniform(-3, 3, (40, 6))
    order = planning.measurement_order(q)
    assert sorted(order.tolist()) == list(range(40))
    length = lambda o: np.sum(np.max(np.abs(np.diff(q[o], axis=0)), axis=1))  # noqa: E731
    assert length(order) < 0.7 * length(np.arange(40))


def test_a_plan_that_cannot_determine_everything_says_how_many_poses_or_which_kind_would():
    """Issue 27: the shortfall names the fewest planned poses that determine every parameter
    poses of this kind can (checked here by planning that many, and one fewer, from the same
    candidates), and what kind of measurement the others need."""
    import dataclasses as dc

    from calibration import planning as PL
    from calibration.robots import nominal as lib
    from calibration.simulate import random_configurations as draw

    model = dc.replace(lib("ur10e"), targets={"smr": np.array([0.03, 0.0, 0.08])})
    cand = draw(model, 1500, np.random.default_rng(4))
    s = PL.shortfall(model, cand, 5, targets=("smr",))
    assert s.poses_needed is not None and s.more_poses == s.poses_needed - 5 > 0
    assert f"{s.more_poses} more" in s.message
    # independent check: that many planned poses determine them all, one fewer does not
    full = PL.plan(model, cand, s.poses_needed, targets=("smr",), exchange=False)
    assert full.success and len(full.params) == s.identifiable
    try:
        fewer = PL.plan(model, cand, s.poses_needed - 1, targets=("smr",), exchange=False).success
    except ValueError:  # below the count the parameters need at all
        fewer = False
    assert not fewer
    # what no number of position-only poses determines: the tool's orientation needs another kind
    kinds = {k["category"]: k for k in s.by_kind}
    assert {"tool.rx", "tool.ry", "tool.rz"} <= set(kinds["tool_orientation"]["parameters"])
    assert (
        "orientation measurements" in kinds["tool_orientation"]["needs"] and not kinds["tool_orientation"]["harmless"]
    )
    names = [n for k in s.by_kind for n in k["parameters"]]
    assert sorted(names) == sorted(u.name for u in full.unidentifiable)  # every one of them accounted for
    # a plan with enough poses: no more poses needed, the kinds still named
    assert PL.shortfall(model, cand, 40, targets=("smr",)).more_poses == 0
