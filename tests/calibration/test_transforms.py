"""Rigid-body transforms (calibration.transforms): poses, quaternions, rotation vectors."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.transforms import (
    homogeneous,
    invert,
    matrix_to_pose,
    matrix_to_quat,
    matrix_to_rotvec,
    matrix_to_rpy,
    orthonormalize,
    pose_to_matrix,
    quat_to_matrix,
    rot,
    rotvec_to_matrix,
    rpy_to_matrix,
    skew,
)


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _random_rotations(rng, n):
    q = rng.normal(size=(n, 4))
    return quat_to_matrix(q)


def test_elementary_rotations_match_written_out_matrices():
    for a in (-2.5, -0.3, 0.0, 0.7, 3.0):
        assert np.allclose(rot(0, a), _rx(a), atol=1e-15)
        assert np.allclose(rot(1, a), _ry(a), atol=1e-15)
        assert np.allclose(rot(2, a), _rz(a), atol=1e-15)


def test_pose_is_trans_rz_ry_rx():
    """Contracts §1: [x, y, z, rx, ry, rz] means Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx)."""
    pose = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    expected = np.eye(4)
    expected[:3, :3] = _rz(0.6) @ _ry(-0.5) @ _rx(0.4)
    expected[:3, 3] = [0.1, -0.2, 0.3]
    assert np.allclose(pose_to_matrix(pose), expected, atol=1e-15)


def test_pose_round_trip_batched():
    rng = np.random.default_rng(0)
    poses = np.concatenate(
        [
            rng.uniform(-2, 2, (200, 3)),
            rng.uniform(-np.pi, np.pi, (200, 1)),
            rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, (200, 1)),
            rng.uniform(-np.pi, np.pi, (200, 1)),
        ],
        axis=1,
    )
    T = pose_to_matrix(poses)
    assert T.shape == (200, 4, 4)
    back = matrix_to_pose(T)
    assert back.shape == (200, 6)
    assert np.allclose(back, poses, atol=1e-12)
    assert np.allclose(pose_to_matrix(back), T, atol=1e-12)


@pytest.mark.parametrize("ry", [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-7, -np.pi / 2 + 1e-9, np.pi / 2 - 1e-12])
def test_pose_round_trip_near_gimbal_lock(ry):
    """At (or next to) ry = ±90 deg the angles are not unique, but the matrix must come back."""
    for rx, rz in ((0.3, -1.1), (-2.0, 2.5), (0.0, 0.0)):
        pose = np.array([1.0, 2.0, 3.0, rx, ry, rz])
        T = pose_to_matrix(pose)
        back = matrix_to_pose(T)
        assert abs(back[4] - ry) < 1e-6
        assert np.allclose(pose_to_matrix(back), T, atol=1e-9)
        assert np.allclose(back[:3], pose[:3])


def test_rpy_round_trip_batched_shapes():
    rng = np.random.default_rng(1)
    R = _random_rotations(rng, 24).reshape(2, 3, 4, 3, 3)
    rpy = matrix_to_rpy(R)
    assert rpy.shape == (2, 3, 4, 3)
    assert np.allclose(rpy_to_matrix(rpy), R, atol=1e-12)


def test_quaternion_round_trip_and_hamilton_convention():
    rng = np.random.default_rng(2)
    R = _random_rotations(rng, 500)
    q = matrix_to_quat(R)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    assert np.all(q[:, 0] >= 0)
    assert np.allclose(quat_to_matrix(q), R, atol=1e-12)
    # Hamilton, scalar first: (cos(a/2), sin(a/2)·axis) is a right-handed rotation by a about axis.
    a = 0.8
    assert np.allclose(quat_to_matrix([np.cos(a / 2), 0, 0, np.sin(a / 2)]), _rz(a))
    assert np.allclose(quat_to_matrix([np.cos(a / 2), np.sin(a / 2), 0, 0]), _rx(a))
    # Not normalised on input: normalised first.
    assert np.allclose(quat_to_matrix([2 * np.cos(a / 2), 0, 2 * np.sin(a / 2), 0]), _ry(a))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_quaternion_of_half_turns(axis):
    """Rotations by pi (trace -1): the branch of Shepperd's method that is not the trace."""
    R = rot(axis, np.pi)
    q = matrix_to_quat(R)
    expected = np.zeros(4)
    expected[1 + axis] = 1.0
    assert np.allclose(np.abs(q), expected, atol=1e-12)
    assert np.allclose(quat_to_matrix(q), R, atol=1e-12)


def test_rotvec_round_trip_and_rodrigues():
    rng = np.random.default_rng(3)
    axis = rng.normal(size=(300, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, np.pi - 1e-6, 300)
    w = axis * angle[:, None]
    R = rotvec_to_matrix(w)
    # Rodrigues, book eq. 2.73, written out
    K = skew(axis)
    expected = np.eye(3) + np.sin(angle)[:, None, None] * K + (1 - np.cos(angle))[:, None, None] * (K @ K)
    assert np.allclose(R, expected, atol=1e-12)
    assert np.allclose(matrix_to_rotvec(R), w, atol=1e-9)


def test_rotvec_tiny_angles_are_accurate():
    for t in (0.0, 1e-12, 1e-9, 1e-7, 1e-5):
        w = np.array([t, -2 * t, 0.5 * t])
        R = rotvec_to_matrix(w)
        assert np.allclose(R, np.eye(3) + skew(w) + 0.5 * skew(w) @ skew(w), atol=1e-15)
        back = matrix_to_rotvec(R)
        assert np.allclose(back, w, atol=1e-15 + 1e-9 * t)


def test_skew_is_cross_product():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(2, 10, 3))
    assert np.allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b))


def test_invert_and_homogeneous():
    rng = np.random.default_rng(5)
    T = homogeneous(_random_rotations(rng, 50), rng.normal(size=(50, 3)))
    assert np.allclose(invert(T) @ T, np.eye(4), atol=1e-12)
    assert np.allclose(invert(T), np.linalg.inv(T), atol=1e-12)


def test_orthonormalize_projects_onto_rotations():
    rng = np.random.default_rng(6)
    R = _random_rotations(rng, 20)
    noisy = R + rng.normal(0, 1e-3, R.shape)
    P = orthonormalize(noisy)
    assert np.allclose(P @ np.swapaxes(P, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(P), 1.0)
    assert np.max(np.abs(P - R)) < 5e-3
