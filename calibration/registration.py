"""Rigid registration: where the instrument stands relative to the robot.

- :func:`kabsch`: the rigid transform that best maps points onto points (least squares, SVD).
- :func:`kabsch_levelled`: the same with the rotation restricted to one about the vertical, for
  two frames that are both levelled (a tracker on its stand, a robot on the floor): from one
  or two points, where :func:`kabsch` needs three that are not collinear.
- :func:`register_points`: base frame (and one common tool-frame point offset) from
  position-only data, alternating a Kabsch fit with a linear solve for the offset.
- :func:`register_poses`: base and tool frames from full-pose data, ``T_meas = X · T_pred · Y``
  (the robot-world/hand-eye problem), rotations by the Kronecker-product null space of
  Shah (2013), then translations by linear least squares.
"""

from __future__ import annotations

import numpy as np

from .transforms import homogeneous, orthonormalize


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rigid transform T (4, 4) minimising sum w |T·src - dst|² for points (N, 3), N >= 3."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.full(len(src), 1.0 / len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst  # as matrix-vector products: far faster than a strided mean
    return _kabsch_from(((src - cs) * w[:, None]).T @ (dst - cd), cs, cd)


def kabsch_levelled(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The transform T (4, 4), a rotation about z and a translation, minimising sum |T·src - dst|²
    for points (N, 3), N >= 1 (one point: the translation alone). The rotation angle is the 2-D
    Kabsch solution ``atan2(sum(a_x b_y - a_y b_x), sum(a_x b_x + a_y b_y))`` of the centred
    points' horizontal components."""
    src = np.atleast_2d(np.asarray(src, dtype=float))
    dst = np.atleast_2d(np.asarray(dst, dtype=float))
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - cs, dst - cd
    yaw = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return homogeneous(R, cd - R @ cs)


def _kabsch_from(H: np.ndarray, cs: np.ndarray, cd: np.ndarray) -> np.ndarray:
    """The Kabsch transform from the cross-covariance ``H`` (3, 3) of the centred points and the
    two centroids."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return homogeneous(R, cd - R @ cs)


def register_points(
    R_base_tool: np.ndarray, p_base_tool: np.ndarray, p_world: np.ndarray, p_tool: np.ndarray, *, iterations: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Base transform ``T_world_base`` (4, 4) and a corrected common point offset (3,).

    ``R_base_tool`` (N, 3, 3), ``p_base_tool`` (N, 3): the tool frames the model predicts in its
    base frame; ``p_world`` (N, 3): measured points; ``p_tool`` (N, 3): the model's tool-frame
    point of each row. The offset correction ``c`` (same for all rows, tool frame) absorbs an
    unknown reflector mounting: ``p_world ≈ T (p_base_tool + R_base_tool (p_tool + c))``.

    Alternates a Kabsch fit of ``a_i + R_i c`` (``a_i`` the points before the correction) onto
    the measured ``m_i`` with the least-squares ``c`` for that fit. Both steps need only sums
    over the points, which are linear in ``c`` and in the fitted rotation: they are formed once
    (a few passes over the data), and each iteration is a 3 x 3 problem.
    """
    N = len(p_world)
    R = np.ascontiguousarray(R_base_tool, dtype=float)
    m = np.asarray(p_world, dtype=float)
    a = p_base_tool + np.einsum("nij,nj->ni", R, p_tool)  # the points before the correction
    w = np.full(N, 1.0 / N)
    a_bar, m_bar, R_bar = w @ a, w @ m, (w @ R.reshape(N, 9)).reshape(3, 3)
    m_c = m - m_bar
    H0 = (a - a_bar).T @ m_c
    # K[j] = Σ R_i[:, j] m̃_iᵀ: H(c) = H0 + Σ_j c_j K[j] (the centroid's part sums to zero)
    K = (R.reshape(N, 9).T @ m_c).reshape(3, 3, 3).transpose(1, 0, 2)
    # c for a fit (R_T, t_T): mean of R_iᵀ R_Tᵀ (m_i - t_T) - R_iᵀ a_i, each block orthonormal
    Q = (R.reshape(N, 9).T @ m).reshape(3, 3, 3).transpose(1, 0, 2) / N  # Q[j, a, b] = mean R_i[a, j] m_i[b]
    v = np.einsum("naj,na->j", R, a) / N

    def fit(c):
        return _kabsch_from(H0 + np.tensordot(c, K, axes=1), a_bar + R_bar @ c, m_bar)

    c = np.zeros(3)
    for _ in range(iterations):
        T = fit(c)
        RT, tT = T[:3, :3], T[:3, 3]
        c_new = np.einsum("jab,ba->j", Q, RT) - R_bar.T @ (RT.T @ tT) - v
        if np.linalg.norm(c_new - c) < 1e-12:
            c = c_new
            break
        c = c_new
    return fit(c), c


def register_poses(T_pred: np.ndarray, T_meas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``T_meas_i ≈ X · T_pred_i · Y`` for X (world <- base) and Y (tool correction).

    ``T_pred``, ``T_meas`` (N, 4, 4), N >= 3 with rotations not all about one axis.
    Rotation: ``R_X R_P,i R_Y = R_M,i`` is linear in (vec R_Y, vec R_X^T) — stacked, its null
    vector (SVD) gives both up to scale, projected onto SO(3). Translation: linear least squares.
    """
    RP, RM = T_pred[:, :3, :3], T_meas[:, :3, :3]
    N = len(RP)
    I3 = np.eye(3)
    # vec() is column-major: vec(A B) = (I ⊗ A) vec(B) = (B^T ⊗ I) vec(A)
    rows = []
    for i in range(N):
        rows.append(np.hstack([np.kron(I3, RP[i]), -np.kron(RM[i].T, I3)]))
    M = np.vstack(rows)
    # The thin SVD: only the right factor is used, and the full left one is 9N x 9N (3.2 GB at
    # 2,218 poses, 259 GB at 20,000: real full-pose data sets ran out of memory).
    _, _, Vt = np.linalg.svd(M, full_matrices=False)
    v = Vt[-1]
    RY = v[:9].reshape(3, 3, order="F")
    RXt = v[9:].reshape(3, 3, order="F")
    s = np.cbrt(np.linalg.det(RY))
    if s == 0:
        raise ValueError("poses do not determine the rotations (all about one axis?)")
    RY, RXt = orthonormalize(RY / s), orthonormalize(RXt / s)
    RX = RXt.T
    # Translation: RX (RP t_Y + t_P) + t_X = t_M  ->  [RX RP_i, I] [t_Y; t_X] = t_M - RX t_P
    A = np.concatenate([np.einsum("ij,njk->nik", RX, RP), np.broadcast_to(I3, (N, 3, 3))], axis=2).reshape(-1, 6)
    b = (T_meas[:, :3, 3] - np.einsum("ij,nj->ni", RX, T_pred[:, :3, 3])).reshape(-1)
    t, *_ = np.linalg.lstsq(A, b, rcond=None)
    return homogeneous(RX, t[3:]), homogeneous(RY, t[:3])
