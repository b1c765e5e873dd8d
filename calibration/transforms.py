"""Rigid-body transforms, batched over a leading axis.

Conventions (contracts §1): a 6-vector pose ``[x, y, z, rx, ry, rz]`` is
``Trans(x, y, z) · Rz(rz) · Ry(ry) · Rx(rx)`` (URDF's xyz + rpy); quaternions are Hamilton,
scalar first ``(qw, qx, qy, qz)``. Homogeneous transforms are ``(..., 4, 4)``.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix of ``v`` (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rot(axis: int, angle) -> np.ndarray:
    """Rotation about a coordinate axis (0 = x, 1 = y, 2 = z) by ``angle`` (...,) rad -> (..., 3, 3).

    Book eq. 2.6-2.8.
    """
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i], R[..., i, j] = c, -s
    R[..., j, i], R[..., j, j] = s, c
    return R


def homogeneous(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Build (..., 4, 4) from rotation (..., 3, 3) and translation (..., 3)."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return homogeneous(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """``Rz(rz) · Ry(ry) · Rx(rx)`` from ``[rx, ry, rz]`` (..., 3) rad -> (..., 3, 3)."""
    rpy = np.asarray(rpy, dtype=float)
    return rot(2, rpy[..., 2]) @ rot(1, rpy[..., 1]) @ rot(0, rpy[..., 0])


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix`: ``[rx, ry, rz]`` (..., 3) with ry in [-pi/2, pi/2].

    At ry = ±pi/2 (gimbal lock) rx is set to 0 and the whole rotation about z goes to rz.
    """
    R = np.asarray(R, dtype=float)
    cy = np.hypot(R[..., 0, 0], R[..., 1, 0])
    ry = np.arctan2(-R[..., 2, 0], cy)  # atan2 keeps full precision near ry = ±pi/2
    regular = cy > 1e-9
    rx = np.where(regular, np.arctan2(R[..., 2, 1], R[..., 2, 2]), 0.0)
    rz = np.where(regular, np.arctan2(R[..., 1, 0], R[..., 0, 0]), np.arctan2(-R[..., 0, 1], R[..., 1, 1]))
    return np.stack([rx, ry, rz], axis=-1)


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """``[x, y, z, rx, ry, rz]`` (..., 6), SI -> (..., 4, 4)."""
    pose = np.asarray(pose, dtype=float)
    return homogeneous(rpy_to_matrix(pose[..., 3:6]), pose[..., 0:3])


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> ``[x, y, z, rx, ry, rz]`` (..., 6)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], matrix_to_rpy(T[..., :3, :3])], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qw, qx, qy, qz)`` (..., 4) -> rotation (..., 3, 3). Normalises first."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) -> unit quaternion ``(qw, qx, qy, qz)`` with qw >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((R.shape[0], 4))
    for case in range(4):
        m = k == case
        if not np.any(m):
            continue
        r = R[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack(
                [0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s],
                axis=1,
            )
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])
            q[m] = np.stack(
                [(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s],
                axis=1,
            )
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2])
            q[m] = np.stack(
                [(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s],
                axis=1,
            )
        else:
            s = 2.0 * np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1])
            q[m] = np.stack(
                [(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s],
                axis=1,
            )
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(shape + (4,))


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (book eq. 2.73): rotation vector (..., 3) rad -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    A = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    B = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + A * K + B * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Logarithm of SO(3): rotation (..., 3, 3) -> rotation vector (..., 3) rad, angle in [0, pi]."""
    q = matrix_to_quat(R)
    s = np.linalg.norm(q[..., 1:], axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    scale = np.where(s < 1e-12, 2.0, angle / np.where(s < 1e-12, 1.0, s))
    return q[..., 1:] * scale[..., None]


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """The nearest rotation matrix (SVD projection) to each (..., 3, 3)."""
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    return U @ Vt
