"""calibration.vendors against references written here: scipy's Rotation for the angle sets and
quaternions, the brands' per-joint rules spelled out for the configurations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration import vendors
from calibration.kinematics import fk

from ..programs.arms import arm

RNG = np.random.default_rng(7)
R = Rotation.random(200, random_state=11)


def test_kuka_abc_is_intrinsic_zyx():
    abc = R.as_euler("ZYX")  # scipy: intrinsic Z, Y', X'' = Rz(A)·Ry(B)·Rx(C)
    np.testing.assert_allclose(vendors.kuka_abc_to_matrix(abc), R.as_matrix(), atol=1e-12)
    back = vendors.matrix_to_kuka_abc(R.as_matrix())
    np.testing.assert_allclose(Rotation.from_euler("ZYX", back).as_matrix(), R.as_matrix(), atol=1e-10)


def test_fanuc_wpr_is_fixed_xyz():
    wpr = R.as_euler("xyz")  # scipy: extrinsic x, y, z = Rz(R)·Ry(P)·Rx(W)
    np.testing.assert_allclose(vendors.fanuc_wpr_to_matrix(wpr), R.as_matrix(), atol=1e-12)
    back = vendors.matrix_to_fanuc_wpr(R.as_matrix())
    np.testing.assert_allclose(Rotation.from_euler("xyz", back).as_matrix(), R.as_matrix(), atol=1e-10)


def test_the_equivalent_angle_set_nearest_the_written_one_is_returned():
    # the other solution (A+180, 180-B, C+180) shifted by turns: the same rotation, written otherwise
    abc = R.as_euler("ZYX")
    other = np.stack([abc[:, 0] + math.pi, math.pi - abc[:, 1], abc[:, 2] - math.pi], axis=1) + 2 * math.pi
    got = vendors.matrix_to_kuka_abc(R.as_matrix(), near=other + 1e-4)
    np.testing.assert_allclose(got, other, atol=1e-9)
    wpr = R.as_euler("xyz")
    got = vendors.matrix_to_fanuc_wpr(R.as_matrix(), near=wpr - 2 * math.pi)
    np.testing.assert_allclose(got, wpr - 2 * math.pi, atol=1e-9)


def test_quaternions_are_scalar_first_with_the_written_sign():
    xyzw = R.as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    got = vendors.quat_near(R.as_matrix(), near=-wxyz)
    np.testing.assert_allclose(got, -wxyz, atol=1e-12)


@pytest.mark.parametrize("brand", ["abb", "kuka", "fanuc"])
def test_configured_ik_recovers_the_joints_a_configuration_was_read_from(brand):
    m = arm(brand)
    lim = np.degrees(m.joint_limits)
    q = np.radians(RNG.uniform(lim[:, 0] * 0.8, lim[:, 1] * 0.8, (30, 6)))
    q[:, 2] = np.clip(q[:, 2], np.radians(-150), np.radians(150))  # J3 within one turn (Fanuc's is not encoded)
    if brand == "kuka":
        q[:, 1] = np.radians(RNG.uniform(-130, -20, 30))
    front, up = vendors.arm_flags(m, q, brand)
    codes = vendors.joint_codes(q, brand)
    got, found = vendors.configured_ik(m, fk(m, q), brand, front, up, codes, np.zeros(6))
    assert found.all()
    np.testing.assert_allclose(got, q, atol=1e-6)


def test_per_joint_rules():
    q = np.radians([[91, -45, 37, 1, -1, 0], [-200, 10, -10, 359, 181, -181]])
    # KUKA T: bit i where axis i+1 < 0 (the example of KUKA's documentation: T = 0b010010 = 18)
    S_T = vendors.kuka_status_turn(arm("kuka"), q)
    assert S_T[0, 1] == 18 and S_T[1, 1] == 0b100101
    assert S_T[0, 0] & 4 and S_T[1, 0] & 4  # S bit 2: sin A5 < 0 (A5 = -1° and 181°)
    # ABB quadrants of axes 1, 4, 6; cfx bit 0 for axis 5 < 0
    c = vendors.abb_confdata(arm("abb"), q)
    assert c[0, :3].tolist() == [1, 0, 0] and c[1, :3].tolist() == [-3, 3, -3]
    assert c[0, 3] & 1 and not c[1, 3] & 1
    # Fanuc: F where J5 > 0; turn numbers of J1, J4, J6 (J5 never turns)
    f = vendors.fanuc_config(arm("fanuc"), q)
    assert f[0, 0] == 0 and f[1, 0] == 1
    assert f[1, 3:].tolist() == [-1, 1, -1]


@pytest.mark.parametrize(
    "brand, ref", [("abb", [0, 0, 0, 0, 30, 0]), ("kuka", [0, -90, 90, 0, 30, 0]), ("fanuc", [0, 0, 0, 0, -30, 0])]
)
def test_geometric_flags_turn_with_the_arm(brand, ref):
    m = arm(brand)
    q = np.radians([ref])
    f, u = vendors.arm_flags(m, q, brand)
    assert f[0] and u[0]
    over = q.copy()
    # over the top: joint 2 far back puts the wrist behind axis 1
    over[0, 1] += np.radians(-120 if brand != "kuka" else -100)
    if brand == "fanuc":  # J3 is measured from the horizon: the forearm too must point back
        over[0, 2] += np.radians(150)
    f, _ = vendors.arm_flags(m, over, brand)
    assert not f[0]
