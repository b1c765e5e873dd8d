"""ISO 9283-style accuracy figures (calibration.metrics) against small hand-computed examples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.metrics import error_statistics, group_configurations, orientation_deviation, pose_statistics
from calibration.transforms import rot

MM = 1e-3


def test_pose_accuracy_and_repeatability_by_hand():
    """Three commanded poses, all at the origin:
    A: (±1, 0, 0), (0, ±1, 0) mm -> barycentre 0, AP 0; l = 1, 1, 1, 1 -> RP = 1 + 3·0 = 1 mm.
    B: (1, 0, 0), (3, 0, 0) mm -> barycentre (2, 0, 0), AP 2 mm; l = 1, 1 -> RP = 1 mm.
    C: (0, 0, 0), (0, 0, 3), (0, 0, 0) mm -> barycentre (0, 0, 1), AP 1 mm; l = 1, 2, 1,
       l̄ = 4/3, S_l = √(((1/3)²·2 + (2/3)²)/2) = √(1/3) -> RP = 4/3 + √3 mm."""
    meas = (
        np.array(
            [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [1, 0, 0], [3, 0, 0], [0, 0, 0], [0, 0, 3], [0, 0, 0]], float
        )
        * MM
    )
    ids = ["A"] * 4 + ["B"] * 2 + ["C"] * 3
    # rows interleaved, as a session that cycles through the poses records them
    order = [0, 4, 6, 1, 5, 7, 2, 8, 3]
    s = pose_statistics(np.zeros((9, 3)), meas[order], np.array(ids, dtype=object)[order])
    assert list(s.pose_ids) == ["A", "B", "C"]
    assert list(s.n) == [4, 2, 3]
    np.testing.assert_allclose(s.barycentre_m / MM, [[0, 0, 0], [2, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(s.AP_m / MM, [0, 2, 1], atol=1e-12)
    np.testing.assert_allclose(s.AP_xyz_m[1] / MM, [2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(s.l_mean_m / MM, [1, 1, 4 / 3], atol=1e-12)
    np.testing.assert_allclose(s.S_l_m / MM, [0, 0, math.sqrt(1 / 3)], atol=1e-12)
    np.testing.assert_allclose(s.RP_m / MM, [1, 1, 4 / 3 + math.sqrt(3)], atol=1e-12)
    assert s.max_AP_m == pytest.approx(2 * MM) and s.max_RP_m == pytest.approx((4 / 3 + math.sqrt(3)) * MM)
    assert s.AP_abc_rad is None and s.RP_abc_rad is None


def test_accuracy_is_measured_from_the_command():
    """A command at (10, 20, 30) mm measured at (10.3, 20.4, 30) twice: AP = 0.5 mm, RP = 0."""
    cmd = np.tile([10, 20, 30], (2, 1)) * MM
    s = pose_statistics(cmd, np.tile([10.3, 20.4, 30], (2, 1)) * MM, [7, 7])
    assert s.AP_m[0] == pytest.approx(0.5 * MM)
    np.testing.assert_allclose(s.AP_xyz_m[0] / MM, [0.3, 0.4, 0.0], atol=1e-9)
    assert s.RP_m[0] == pytest.approx(0.0, abs=1e-15)


def test_orientation_accuracy_and_repeatability_per_axis():
    """Rotations about z by +1, −1, +3 mrad from a commanded orientation (itself rotated): mean
    1 mrad -> AP_c = 1 mrad; S = √((0² + 2² + 2²)/2) = 2 mrad -> RP_c = ±6 mrad; a and b are 0."""
    R_c = rot(0, 0.4) @ rot(1, -0.2)
    dz = np.array([1e-3, -1e-3, 3e-3])
    R_m = rot(2, dz) @ R_c  # a rotation about the world z axis
    s = pose_statistics(np.zeros((3, 3)), np.zeros((3, 3)), [1, 1, 1], R_cmd=np.stack([R_c] * 3), R_meas=R_m)
    np.testing.assert_allclose(s.AP_abc_rad[0], [0, 0, 1e-3], atol=1e-12)
    np.testing.assert_allclose(s.RP_abc_rad[0], [0, 0, 6e-3], atol=1e-12)


def test_single_pose_has_no_repeatability():
    s = pose_statistics(np.zeros((1, 3)), np.array([[0, 0, 1e-3]]), ["p"])
    assert s.AP_m[0] == pytest.approx(1e-3)
    assert math.isnan(s.RP_m[0]) and math.isnan(s.max_RP_m)


def test_error_statistics_by_hand():
    """Errors (3, 0, 0), (0, 4, 0), (0, 0, 5) mm: mean 4, sample std 1, 3σ 3, mean + 3σ 7,
    RMS √(50/3), max 5; bias (1, 4/3, 5/3)."""
    cmd = np.array([[100, 0, 0], [0, 100, 0], [0, 0, 100]], float) * MM
    meas = cmd + np.array([[3, 0, 0], [0, 4, 0], [0, 0, 5]]) * MM
    e = error_statistics(cmd, meas)
    assert e.n == 3
    assert e.mean_m / MM == pytest.approx(4) and e.std_m / MM == pytest.approx(1)
    assert e.three_sigma_m / MM == pytest.approx(3) and e.mean_plus_3sigma_m / MM == pytest.approx(7)
    assert e.rms_m / MM == pytest.approx(math.sqrt(50 / 3)) and e.max_m / MM == pytest.approx(5)
    assert e.p95_m / MM == pytest.approx(4.9)  # linear interpolation between 4 and 5
    np.testing.assert_allclose(e.bias_xyz_m / MM, [1, 4 / 3, 5 / 3])
    assert math.isnan(e.mean_rad) and e.errors_rad is None


def test_error_statistics_with_orientation():
    """Orientation errors of 1 and 3 mrad about x and y: angles 1, 3 -> mean 2, std √2."""
    R_c = np.stack([np.eye(3), rot(2, 1.0)])
    R_m = np.stack([rot(0, 1e-3) @ R_c[0], rot(1, -3e-3) @ R_c[1]])
    e = error_statistics(np.zeros((2, 3)), np.zeros((2, 3)), R_cmd=R_c, R_meas=R_m)
    np.testing.assert_allclose(e.errors_rad, [1e-3, 3e-3], atol=1e-12)
    assert e.mean_rad == pytest.approx(2e-3) and e.std_rad == pytest.approx(math.sqrt(2) * 1e-3)
    np.testing.assert_allclose(e.bias_abc_rad, [0.5e-3, -1.5e-3, 0], atol=1e-12)
    np.testing.assert_allclose(orientation_deviation(R_c, R_m), [[1e-3, 0, 0], [0, -3e-3, 0]], atol=1e-12)


def test_group_configurations_by_joint_readings():
    """Rows within the tolerance on every joint are one pose (transitively: a chain of readings
    each within it of the next); labels in order of first appearance; the tolerance per joint."""
    q = np.array([[1.0, 2.0], [0.0, 0.0], [1.004, 2.0], [0.0, 0.02], [1.008, 2.003], [5.0, 5.0], [0.0, 0.0]])
    assert group_configurations(q, 0.005).tolist() == [0, 1, 0, 2, 0, 3, 1]
    assert group_configurations(q, [0.005, 0.03]).tolist() == [0, 1, 0, 1, 0, 2, 1]
    assert group_configurations(q[:1], 0.005).tolist() == [0]
    with pytest.raises(ValueError, match="positive"):
        group_configurations(q, 0.0)


def test_bad_input():
    with pytest.raises(ValueError, match="shape"):
        error_statistics(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="both"):
        error_statistics(np.zeros((2, 3)), np.zeros((2, 3)), R_cmd=np.stack([np.eye(3)] * 2))
    with pytest.raises(ValueError, match="pose_id"):
        pose_statistics(np.zeros((2, 3)), np.zeros((2, 3)), [1])
    with pytest.raises(ValueError, match="finite"):
        error_statistics(np.zeros((1, 3)), np.full((1, 3), np.nan))


# --------------------------------------------------------------------------- a model's errors on data


def _ur5e_and_readings(n=40, seed=3):
    from calibration.robots import nominal

    model = nominal("ur5e")
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.5, 2.5, size=(n, model.n_joints))
    return model, q


def test_position_errors_are_measured_minus_the_models_point():
    from calibration.kinematics import fk
    from calibration.metrics import position_errors

    model, q = _ur5e_and_readings()
    p_tool = np.array([0.01, -0.02, 0.05])
    T = fk(model, q)
    p_world = T[:, :3, :3] @ p_tool + T[:, :3, 3] + np.array([1e-3, 0.0, -2e-3])
    e = position_errors(model, q, p_world, p_tool)
    np.testing.assert_allclose(e, np.broadcast_to([1e-3, 0.0, -2e-3], e.shape), atol=1e-12)


def test_registered_errors_absorb_the_instrument_placement_and_the_reflector_offset():
    """Data of the model itself, seen from a displaced instrument and with the reflector mounted
    off its drawing: the registered errors vanish, the plain ones do not, and the absorbed offset
    is the mounting error."""
    from calibration.kinematics import fk
    from calibration.metrics import position_errors, registered_errors
    from calibration.transforms import pose_to_matrix

    model, q = _ur5e_and_readings()
    p_drawn = np.array([0.0, 0.0, 0.05])
    mount = np.array([0.8e-3, -0.5e-3, 0.3e-3])
    X = pose_to_matrix(np.array([1.2, -0.4, 0.3, 0.2, -0.1, 0.7]))
    T = fk(model, q)
    p_model = T[:, :3, :3] @ (p_drawn + mount) + T[:, :3, 3]
    p_world = p_model @ X[:3, :3].T + X[:3, 3]
    e, c = registered_errors(model, q, p_world, p_drawn)
    assert np.max(np.linalg.norm(e, axis=1)) < 1e-9
    np.testing.assert_allclose(c, mount, atol=1e-9)
    assert np.min(np.linalg.norm(position_errors(model, q, p_world, p_drawn), axis=1)) > 0.1


def test_norm_statistics_by_hand():
    from calibration.metrics import norm_statistics

    e = np.array([3.0, 4.0, 0.0, 5.0])
    s = norm_statistics(e)
    assert s.n == 4
    assert s.rms == pytest.approx(math.sqrt((9 + 16 + 0 + 25) / 4))
    assert s.mean == pytest.approx(3.0)
    assert s.max == 5.0
    assert s.std == pytest.approx(math.sqrt(((0) ** 2 + 1 + 9 + 4) / 3))
    assert s.p95 == pytest.approx(4.85)  # linear interpolation between 4 and 5 at 0.95 * 3 = 2.85
    assert norm_statistics(np.array([2.0])).std == 0.0
    assert math.isnan(norm_statistics(np.zeros(0)).rms)


def test_compare_parameters_flags_what_moved_beyond_twice_its_uncertainty():
    import dataclasses

    from calibration.report import compare_parameters
    from calibration.robots import nominal

    a = nominal("ur5e")
    joints = list(a.joints)
    joints[1] = dataclasses.replace(joints[1], a=joints[1].a + 0.3e-3)  # 0.3 mm: 3 sigma of 0.1 mm
    b = dataclasses.replace(a, joints=tuple(joints), base=np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    name = f"{joints[1].name}.a"
    pa = [{"name": name, "unit": "m", "value": joints[1].a - 0.3e-3, "std_error": 0.1e-3 / math.sqrt(2)}]
    pb = [
        {"name": name, "unit": "m", "value": joints[1].a, "std_error": 0.1e-3 / math.sqrt(2)},
        {"name": "j3.d", "unit": "m", "value": 0.0, "std_error": 1e-3, "source": "prior"},
    ]
    rows = {r["name"]: r for r in compare_parameters(a, pa, b, pb)}
    assert rows[name]["moved"] and rows[name]["status"] == "both"
    assert rows[name]["change"] == pytest.approx(0.3e-3, abs=1e-12)
    assert rows[name]["change_sigmas"] == pytest.approx(3.0)
    assert rows["j3.d"]["status"] == "from the prior" and not rows["j3.d"]["moved"]
