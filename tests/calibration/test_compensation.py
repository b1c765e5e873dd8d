"""Inverse kinematics and compensation (calibration.ik, calibration.compensation; book ch. 5).

The "identified" robot here is what ``recal identify`` writes for a UR: the nominal DH model with
Hayati links on the parallel axes and small errors in every link parameter (a "near-simple"
robot without closed-form inverse kinematics), standing far from the instrument's origin.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from sample_models import all_convention_docs, random_readings, si_readings, stanford_5r1p_doc

from calibration import robots
from calibration.compensation import (
    FLAG_BIT,
    FLAGS,
    assess,
    compensate_joints,
    compensate_targets,
    compensate_taught,
    error_table,
    flag_names,
    frame_map,
    inverse_jacobian_iteration,
    nominal_solution,
)
from calibration.conventions import hayati_for_parallel_axes
from calibration.ik import (
    geometric_jacobian,
    inverse_kinematics,
    numerical_ik,
    pose_error,
    singular_values,
    solve_ik,
    spread_seeds,
    ur_branch,
    ur_geometry,
    ur_ik,
    ur_ik_all,
    wrap_into_limits,
)
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.parameters import apply_step, candidate_parameters
from calibration.transforms import matrix_to_rotvec

UM = 1e-6


def identified_like(
    nominal,
    rng,
    *,
    base=(1.8, -0.6, 0.3, 0.002, -0.004, math.radians(130.0)),
    length_m=0.5e-3,
    angle_rad=math.radians(0.05),
    offset_rad=math.radians(0.1),
):
    """A robot as identification describes it: Hayati links on parallel axes, every link
    parameter off by a little, the base where the instrument sees it."""
    m, _ = hayati_for_parallel_axes(nominal)
    params = candidate_parameters(m, base=False, tool=False)
    sig = [length_m if p.kind == "length" else offset_rad if p.name.endswith(".theta") else angle_rad for p in params]
    m = apply_step(m, params, rng.normal(0.0, sig))
    return dataclasses.replace(m, base=np.array(base), name="identified")


def typical_configurations(rng, n):
    """Task-like UR configurations: arm bent, wrist away from its singularity."""
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    q[:, 1] = rng.uniform(math.radians(-160), math.radians(-20), n)
    q[:, 2] = rng.uniform(math.radians(25), math.radians(155), n) * rng.choice([-1, 1], n)
    q[:, 4] = rng.uniform(math.radians(25), math.radians(155), n) * rng.choice([-1, 1], n)
    return q


@pytest.fixture(scope="module")
def cell():
    """(nominal, identified, T_nominal_world, task joints, desired world poses)."""
    rng = np.random.default_rng(7)
    nominal = robots.nominal("ur10e")
    identified = identified_like(nominal, rng)
    M = frame_map(identified, nominal, rng.uniform(-np.pi, np.pi, (300, 6)))
    q = typical_configurations(rng, 1500)
    X = np.linalg.inv(M) @ fk(nominal, q)  # planned on the nominal, to be reached in the world
    return nominal, identified, M, q, X


def position_error(model, q, X):
    return np.linalg.norm(fk(model, q)[:, :3, 3] - X[:, :3, 3], axis=1)


def orientation_error(model, q, X):
    T = fk(model, q)
    return np.linalg.norm(matrix_to_rotvec(T[:, :3, :3] @ np.swapaxes(X[:, :3, :3], 1, 2)), axis=1)


# ----------------------------------------------------------------------------- Jacobian


@pytest.mark.parametrize(
    "key", ["dh", "dh_gain", "dh_harmonic", "dh_hayati", "dh_coupling", "mdh", "poe", "dh_prismatic", "poe_prismatic"]
)
def test_geometric_jacobian_matches_central_differences_of_the_readings(key):
    doc = all_convention_docs()[key]
    model = model_from_dict(doc)
    rng = np.random.default_rng(3)
    q = si_readings(doc, random_readings(doc, 4, rng))
    J = geometric_jacobian(model, q)
    h = 1e-6
    for i in range(model.n_joints):
        dq = np.zeros(model.n_joints)
        dq[i] = h
        Tp, Tm = fk(model, q + dq), fk(model, q - dq)
        dp = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
        dw = matrix_to_rotvec(Tp[:, :3, :3] @ np.swapaxes(Tm[:, :3, :3], 1, 2)) / (2 * h)
        np.testing.assert_allclose(J[:, :3, i], dp, atol=2e-8)
        np.testing.assert_allclose(J[:, 3:, i], dw, atol=2e-8)


# ----------------------------------------------------------------------------- UR closed form


@pytest.mark.parametrize("name", ["ur3e", "ur5e", "ur10e", "ur16e"])
def test_ur_closed_form_round_trips_on_all_8_branches(name):
    model = robots.nominal(name)
    assert ur_geometry(model) is not None
    rng = np.random.default_rng(11)
    q = rng.uniform(-np.pi, np.pi, (400, 6))
    T = fk(model, q)
    qs, ok, flags = ur_ik_all(model, T, q)
    assert sorted(map(tuple, flags)) == sorted({(a, b, c) for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)})
    for b in range(8):
        assert ok[:, b].mean() > 0.7  # most poses are reachable in every branch
        reached = fk(model, qs[ok[:, b], b])
        np.testing.assert_allclose(reached[:, :3, 3], T[ok[:, b], :3, 3], atol=1e-10)
        np.testing.assert_allclose(reached[:, :3, :3], T[ok[:, b], :3, :3], atol=1e-10)
        assert np.all(ur_branch(model, qs[ok[:, b], b]) == flags[b])
    # the branch of the configuration itself gives the configuration back
    q_back, ok_back = ur_ik(model, T, ur_branch(model, q), q)
    assert ok_back.all()
    np.testing.assert_allclose(q_back, q, atol=1e-9)


@pytest.mark.parametrize("key", ["dh", "dh_gain", "dh_harmonic"])
def test_nominal_inverse_kinematics_with_base_tool_gains_and_harmonics(key):
    """The closed form removes base and tool, honours gains; gear harmonics are polished by Newton."""
    doc = all_convention_docs()[key]
    model = model_from_dict(doc)
    assert ur_geometry(model) is not None
    rng = np.random.default_rng(5)
    q = typical_configurations(rng, 200)
    T = fk(model, q)
    r = inverse_kinematics(model, T, q)
    assert r.success
    assert position_error(model, r.q, T).max() < 1e-9 and orientation_error(model, r.q, T).max() < 1e-9
    np.testing.assert_allclose(r.q, q, atol=1e-6)


def test_closed_form_keeps_the_joint_turns_of_the_taught_configuration():
    model = robots.nominal("ur10e")
    q = np.radians([[300.0, -70.0, 100.0, -400.0 + 360.0, 80.0, -300.0]])  # joints 1, 6 a turn off (-180, 180]
    r = inverse_kinematics(model, fk(model, q), q)
    np.testing.assert_allclose(r.q, q, atol=1e-9)
    # without a taught configuration the nearest solution to q_near is taken, as UR's get_inverse_kin does
    near = inverse_kinematics(model, fk(model, q), np.zeros(6), keep_branch=False)
    assert np.all(np.abs(near.q) <= np.pi + 1e-9)


def test_non_ur_models_are_recognised_and_solved_by_newton_from_the_taught_joints():
    puma = robots.nominal("puma560")
    assert ur_geometry(puma) is None
    rng = np.random.default_rng(2)
    q = rng.uniform(-1.0, 1.0, (300, 6)) + np.radians([0, -90, 90, 0, 60, 0])
    T = fk(puma, q)
    r = solve_ik(puma, T, q + rng.normal(0, 0.02, q.shape))
    assert r.converged.mean() > 0.98
    ok = r.converged
    assert position_error(puma, r.q[ok], T[ok]).max() < 1e-9
    # away from singularities (where two solutions come close) Newton returns the taught branch
    regular = ok & (singular_values(puma, geometric_jacobian(puma, q))[:, -1] > 0.02)
    assert regular.mean() > 0.7
    np.testing.assert_allclose(r.q[regular], q[regular], atol=1e-6)


# ----------------------------------------------------------------------------- numerical IK (no closed form)


def no_closed_form_models():
    return {
        "puma560 (dh, Hayati)": robots.nominal("puma560"),
        "5r1p (dh, prismatic joint 3)": model_from_dict(stanford_5r1p_doc()),
        "puma560-zrp (poe)": robots.nominal("puma560-zrp"),
    }


def inside_limits(model, q):
    lim = model.joint_limits
    return np.all((q >= lim[:, 0] - 1e-12) & (q <= lim[:, 1] + 1e-12), axis=1)


@pytest.mark.parametrize("name", list(no_closed_form_models()))
def test_numerical_ik_solves_pose_only_points_from_one_qnear(name):
    """Task points with a pose and no joints, all from one q_near (``--qnear``): Newton from there
    alone misses some (other branches, joint limits); with the previous point's solution and the
    spread seeds every reachable point is solved, within the joint limits, to 1e-9 m."""
    model = no_closed_form_models()[name]
    assert ur_geometry(model) is None
    rng = np.random.default_rng(3)
    q_true = random_readings_si(model, 300, rng)
    T = fk(model, q_true)
    q_near = model.joint_limits.mean(axis=1)
    seeds = np.tile(q_near, (len(T), 1))
    plain = solve_ik(model, T, seeds)
    plain_q = wrap_into_limits(model, plain.q, seeds)  # the same poses, on the turns nearest q_near
    plain_ok = plain.converged & inside_limits(model, plain_q)
    r = numerical_ik(model, T, q_near)
    assert plain_ok.mean() < 0.97  # the fallbacks have work to do
    assert r.success and r.reachable.all() and inside_limits(model, r.q).all()
    assert position_error(model, r.q, T).max() < 1e-9 and orientation_error(model, r.q, T).max() < 1e-9
    # where Newton from q_near alone found a solution inside the limits, that one is kept
    np.testing.assert_allclose(r.q[plain_ok], plain_q[plain_ok], atol=1e-9)
    assert not r.branch_changed.any()  # no taught joints, no branch to keep


def random_readings_si(model, n, rng):
    lim = np.clip(model.joint_limits, -np.pi, np.pi)
    for i, j in enumerate(model.joints):
        if not j.revolute:
            lim[i] = model.joint_limits[i]
    return rng.uniform(lim[:, 0], lim[:, 1], (n, model.n_joints))


def test_numerical_ik_keeps_taught_branches_and_flags_a_changed_one():
    """Taught joints are the start and the branch to keep; a taught configuration outside the joint
    limits (a wrist flipped past joint 4's range) is solved in another branch, and says so."""
    puma = robots.nominal("puma560")
    q_a = np.radians([[20.0, -60.0, 150.0, 30.0, 50.0, 10.0]])
    T = fk(puma, q_a)
    flip = solve_ik(puma, T, q_a + np.radians([0, 0, 0, 180, -100, 180])).q  # the other wrist solution
    assert position_error(puma, flip, T)[0] < 1e-9 and not inside_limits(puma, wrap_into_limits(puma, flip))[0]
    path = fk(puma, q_a + np.radians(np.outer(np.arange(5), [3, -2, 2, 1, 2, -3])))
    r = numerical_ik(
        puma, np.concatenate([T, T, path]), np.concatenate([q_a, flip, q_a + 0.03 * np.ones((5, 6))]), taught=True
    )
    assert r.success
    np.testing.assert_allclose(r.q[0], q_a[0], atol=1e-9)  # taught and inside: kept as taught
    np.testing.assert_allclose(r.q[1], q_a[0], atol=1e-9)  # taught outside the limits: the other wrist
    assert list(r.branch_changed) == [False, True] + [False] * 5
    assert position_error(puma, r.q, np.concatenate([T, T, path])).max() < 1e-9
    c = compensate_joints(puma, np.concatenate([T, T]), r.q[:2], branch_changed=r.branch_changed[:2])
    assert c.flags_of(0) == [] and "branch_change" in c.flags_of(1)


def test_numerical_ik_reports_what_it_cannot_reach():
    puma = robots.nominal("puma560")
    q = np.radians([[40.0, -30.0, 120.0, 20.0, 60.0, 10.0]])
    T = fk(puma, q)
    far = T.copy()
    far[0, :3, 3] *= 20.0  # far beyond the reach
    r = numerical_ik(puma, np.concatenate([T, far]), q)
    assert list(r.converged) == [True, False] and list(r.reachable) == [True, False]
    assert r.residual_m[1] > 1.0 and np.isfinite(r.q).all()
    c = compensate_joints(puma, np.concatenate([T, far]), r.q, reachable=r.reachable)
    assert c.flags_of(0) == [] and {"unreachable", "no_convergence"} <= set(c.flags_of(1))
    m = model_from_dict(stanford_5r1p_doc())
    np.testing.assert_array_equal(spread_seeds(m, 8), spread_seeds(m, 8))  # the same seeds every call
    assert inside_limits(m, spread_seeds(m, 24)).all()


# ----------------------------------------------------------------------------- joints mode


def test_joints_mode_reaches_the_identified_pose_to_1_um(cell):
    nominal, identified, M, q, X = cell
    start = nominal_solution(nominal, M @ X, q)
    np.testing.assert_allclose(start.q, q, atol=1e-9)  # closed form: the planned configuration back
    c = compensate_joints(identified, X, start.q, reachable=start.reachable)
    assert c.mode == "joints" and c.converged.mean() > 0.995
    good = c.converged
    # checked independently of the solver: the identified robot's forward kinematics at the commands
    assert position_error(identified, c.q[good], X[good]).max() < UM
    assert orientation_error(identified, c.q[good], X[good]).max() < 1e-6
    assert c.residual_m[good].max() < 1e-9
    # without compensation the identified robot misses by mm
    assert np.median(position_error(identified, q, X)) > 0.5e-3
    # corrections are small perturbations on the nominal branch and turns (no wrap to another turn)
    clean = good & (c.flags == 0)
    assert clean.mean() > 0.8
    assert np.abs(c.correction[clean]).max() < math.radians(5.0)
    assert np.all(ur_branch(nominal, c.q[clean]) == ur_branch(nominal, q[clean]))
    assert np.median(c.iterations[clean]) <= 3  # Newton on the identified model: quadratic


def test_printed_sign_of_section_5_2_1_diverges_and_the_corrected_one_converges(cell):
    """Algorithm A as printed (q <- q + J⁻¹ dx with dx = X_c − X_d, nominal Jacobian) moves away
    from the target; with the sign corrected it converges (ch5 §2.3)."""
    nominal, identified, M, q, X = cell
    regular = singular_values(nominal, geometric_jacobian(nominal, q))[:, -1] > 0.05
    q0, Xd = q[regular][:50], X[regular][:50]
    R = M[:3, :3]

    def iterate(sign, passes=5):
        qk = q0.copy()
        for _ in range(passes):
            T = fk(identified, qk)
            dx = -pose_error(Xd, T[:, :3, :3], T[:, :3, 3])  # X_c ⊖ X_d, world axes
            dx = np.concatenate([dx[:, :3] @ R.T, dx[:, 3:] @ R.T], axis=1)  # nominal axes
            qk = qk + sign * np.linalg.solve(geometric_jacobian(nominal, qk), dx[:, :, None])[:, :, 0]
        return position_error(identified, qk, Xd)

    before = position_error(identified, q0, Xd)
    assert np.median(iterate(+1.0)) > 10 * np.median(before)
    assert np.all(iterate(-1.0) < 1e-8)


def test_cross_method_agreement_T17(cell):
    """ch5 §8 T17: Algorithm A (book, nominal Jacobian), Newton on the identified model and
    Algorithm B through the nominal controller give the same joint commands (book: ~1e-3 deg)."""
    nominal, identified, M, q, X = cell
    q, X = q[:300], X[:300]
    newton = compensate_joints(identified, X, q)
    qa, iters, conv = inverse_jacobian_iteration(identified, nominal, X, q, T_nominal_world=M)
    b = compensate_targets(identified, nominal, X, q, T_nominal_world=M)
    ok = newton.converged & conv & b.converged & (newton.flags == 0)
    assert ok.mean() > 0.8
    assert np.abs(np.degrees(qa[ok] - newton.q[ok])).max() < 1e-6
    assert np.abs(np.degrees(b.q[ok] - newton.q[ok])).max() < 1e-6
    # T3: Algorithm A converges linearly, in a few passes for mm-level errors (book: 4 to 6)
    assert 3 <= np.median(iters[ok]) <= 7


# ----------------------------------------------------------------------------- targets mode


def test_targets_mode_through_a_nominal_controller_reaches_the_pose(cell):
    nominal, identified, M, q, X = cell
    c = compensate_targets(identified, nominal, X, q, T_nominal_world=M)
    assert c.mode == "targets" and c.converged.mean() > 0.99
    good = c.converged & (c.flags == 0)
    # the controller: the nominal closed form on the corrected targets, in the taught branch
    ctrl = inverse_kinematics(nominal, c.T_command[good], q[good])
    np.testing.assert_allclose(ctrl.q, c.q[good], atol=1e-9)
    assert position_error(identified, ctrl.q, X[good]).max() < UM
    assert orientation_error(identified, ctrl.q, X[good]).max() < 1e-6
    # the uncorrected targets would miss by mm; the corrections themselves are mm-sized
    plain = inverse_kinematics(nominal, (M @ X)[good], q[good])
    assert np.median(position_error(identified, plain.q, X[good])) > 0.5e-3
    shift = np.linalg.norm(c.T_command[good, :3, 3] - (M @ X)[good, :3, 3], axis=1)
    assert 1e-4 < np.median(shift) < 2e-2
    assert np.median(c.iterations[good]) <= 4  # the error shrinks by ~1e-3 per pass


def test_targets_mode_with_a_numerical_nominal_inverse(cell):
    """A nominal without UR structure (PUMA, Hayati): the controller's inverse is Newton from the
    taught joints; the corrected targets still bring the identified robot there."""
    rng = np.random.default_rng(4)
    puma = robots.nominal("puma560")
    ident = identified_like(puma, rng, base=(0.5, 0.2, 0.1, 0.01, 0.0, 0.3))
    q = rng.uniform(-0.6, 0.6, (200, 6)) + np.radians([0, -90, 90, 0, 60, 0])
    M = frame_map(ident, puma, rng.uniform(-1, 1, (200, 6)))
    X = np.linalg.inv(M) @ fk(puma, q)
    c = compensate_targets(ident, puma, X, q, T_nominal_world=M)
    assert c.converged.mean() > 0.97
    good = c.converged
    ctrl = solve_ik(puma, c.T_command[good], q[good], position_tol_m=1e-12, rotation_tol_rad=1e-12)
    assert position_error(ident, ctrl.q, X[good]).max() < UM


# ----------------------------------------------------------------------------- taught tasks


def test_taught_joints_mapped_from_the_nominal_and_between_two_robots(cell):
    nominal, identified, M, q, _X = cell
    q = q[:400]
    # planned on the nominal (off line): the identified robot reaches the pose the nominal would
    c = compensate_taught(nominal, identified, q, T_from_world=M)
    good = c.converged
    assert c.mode == "taught" and good.mean() > 0.99
    assert position_error(identified, c.q[good], np.linalg.inv(M) @ fk(nominal, q[good])).max() < UM
    # taught on robot A, replayed on robot B (both identified, same world): B reaches what A reached
    robot_a = identified_like(robots.nominal("ur10e"), np.random.default_rng(99))
    ab = compensate_taught(robot_a, identified, q)
    ok = ab.converged
    assert ok.mean() > 0.99
    assert position_error(identified, ab.q[ok], fk(robot_a, q[ok])).max() < UM
    assert np.median(position_error(identified, q, fk(robot_a, q))) > 0.5e-3
    # the same robot: nothing to correct
    same = compensate_taught(identified, identified, q[:20])
    np.testing.assert_allclose(same.q, q[:20], atol=1e-12)


# ----------------------------------------------------------------------------- flags


def test_every_flag_is_triggered_by_a_constructed_case(cell):
    nominal, identified, M, q, X = cell
    q1, X1 = q[:1], X[:1]
    assert compensate_joints(identified, X1, q1).flags[0] == 0

    # joint_limit: the command is outside the model's limits
    joints = list(identified.joints)
    joints[0] = dataclasses.replace(joints[0], lower=q1[0, 0] - 2.0, upper=q1[0, 0] - 1.0)
    narrow = dataclasses.replace(identified, joints=tuple(joints))
    assert flag_names(compensate_joints(narrow, X1, q1).flags[0]) == ["joint_limit"]

    # near_singular: the wrist at its singularity (theta5 = 0)
    qs = q1.copy()
    qs[0, 4] = 1e-4
    Xs = np.linalg.inv(M) @ fk(nominal, qs)
    assert "near_singular" in compensate_joints(identified, Xs, qs).flags_of(0)

    # outside_calibrated_region: joint 1 outside the measured range
    cr = np.array([[q1[0, 0] + 0.1, q1[0, 0] + 0.5]] + [[-np.pi, np.pi]] * 5)
    assert flag_names(compensate_joints(identified, X1, q1, calibrated_range=cr).flags[0]) == [
        "outside_calibrated_region"
    ]

    # no_convergence: one Newton iteration is not enough for 1e-9 m
    c = compensate_joints(identified, X1, q1, max_iterations=1)
    assert flag_names(c.flags[0]) == ["no_convergence"] and not c.converged[0]

    # branch_change: a correction larger than allowed ...
    assert flag_names(compensate_joints(identified, X1, q1, max_correction_rad=1e-6).flags[0]) == ["branch_change"]
    # ... or a command across a singular surface from the nominal solution (det J changes sign)
    qa, qb = q1.copy(), q1.copy()
    qa[0, 4], qb[0, 4] = 0.005, -0.005
    flags, _ = assess(identified, qb, qa, np.array([True]))
    assert flags[0] & FLAG_BIT["branch_change"]

    # unreachable: 5 m away; the nominal closed form has no solution, nothing converges
    Xfar = X1.copy()
    Xfar[0, :3, 3] += 5.0 * Xfar[0, :3, 3] / np.linalg.norm(Xfar[0, :3, 3])
    far = nominal_solution(nominal, M @ Xfar, q1)
    assert not far.reachable[0]
    c = compensate_joints(identified, Xfar, far.q, reachable=far.reachable)
    assert {"unreachable", "no_convergence"} <= set(c.flags_of(0))
    t = compensate_targets(identified, nominal, Xfar, q1, T_nominal_world=M)
    assert {"unreachable", "no_convergence"} <= set(t.flags_of(0))
    # outside_mapped_region is set by `recal compensate` for a model with a residual map
    # (tests/cli/test_compliance_cli.py triggers it)
    assert set(FLAGS) == {
        "joint_limit",
        "near_singular",
        "outside_calibrated_region",
        "no_convergence",
        "branch_change",
        "unreachable",
        "outside_mapped_region",
    }


def test_bad_arguments_are_clear_value_errors(cell):
    nominal, identified, _M, q, X = cell
    with pytest.raises(ValueError, match="2 poses but 3"):
        compensate_joints(identified, X[:2], q[:3])
    with pytest.raises(ValueError, match=r"shape \(N, 6\)"):
        compensate_joints(identified, X[:2], q[:2, :5])
    with pytest.raises(ValueError, match="Universal Robots"):
        ur_ik(robots.nominal("puma560"), X[:1], [1, 1, 1], q[:1])
    with pytest.raises(ValueError, match="at least 3"):
        frame_map(identified, nominal, q[:2])


# ----------------------------------------------------------------------------- book numbers


def test_table_5_2_total_rms_is_the_euclidean_norm():
    """ch5 §8 T1: Table 5.2's "Total RMS" = √(X²+Y²+Z²) reproduces all six totals; the
    improvement is "approximately a factor of 40 to 1"."""
    initial = np.array([[5.59, 2.97, 2.55], [2.64, 3.08, 4.25], [2.67, 4.31, 2.18]])
    compensated = np.array([[0.04, 0.17, 0.07], [0.00, 0.13, 0.10], [0.08, 0.09, 0.04]])
    t = error_table(initial, compensated)
    np.testing.assert_allclose(np.round(t["total_initial"], 2), [6.82, 5.88, 5.52])
    np.testing.assert_allclose(np.round(t["total_compensated"], 2), [0.19, 0.16, 0.13])
    assert np.all((t["improvement"] > 35) & (t["improvement"] < 45))
