"""Sphere fits and rigid poses from points (calibration.geometry)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.geometry import fit_sphere, pose_from_points, pose_from_three_points


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _random_rotation(rng)
    T[:3, 3] = rng.uniform(-1.0, 1.0, 3)
    return T


def _sphere_points(centre, radius, n, rng, *, cap_deg=180.0) -> np.ndarray:
    """n points on the sphere within ``cap_deg`` of its +z pole."""
    z = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z**2)
    return np.asarray(centre) + radius * np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


# --------------------------------------------------------------------------- fit_sphere


def test_fit_sphere_recovers_exact_sphere():
    rng = np.random.default_rng(1)
    centre = np.array([0.4, -0.25, 0.9])
    pts = _sphere_points(centre, 0.0125, 5, rng, cap_deg=60)
    c, r, rms = fit_sphere(pts)
    assert np.allclose(c, centre, atol=1e-12)
    assert r == pytest.approx(0.0125, abs=1e-12)
    assert rms < 1e-12


def test_fit_sphere_minimum_four_points():
    pts = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0]]) * 3 + [5, 6, 7]
    c, r, _rms = fit_sphere(pts)
    assert np.allclose(c, [5, 6, 7], atol=1e-12)
    assert r == pytest.approx(3.0)


def test_fit_sphere_with_noise_is_within_noise():
    rng = np.random.default_rng(2)
    centre = np.array([0.1, 0.2, 0.3])
    sigma = 2e-6
    errors = []
    for _ in range(50):
        pts = _sphere_points(centre, 0.0125, 10, rng, cap_deg=80)
        pts += rng.normal(0, sigma, pts.shape)
        c, r, rms = fit_sphere(pts)
        errors.append(np.linalg.norm(c - centre))
        assert rms < 4 * sigma
        assert abs(r - 0.0125) < 10 * sigma
    assert np.mean(errors) < 10 * sigma


def test_fit_sphere_geometric_refinement_beats_algebraic_start():
    # Points on a small cap with large noise: the algebraic fit is biased, the geometric
    # refinement must not make the geometric cost worse than the algebraic solution.
    rng = np.random.default_rng(3)
    pts = _sphere_points([0, 0, 0], 1.0, 30, rng, cap_deg=40) + rng.normal(0, 0.01, (30, 3))
    y = pts - pts.mean(0)
    A = np.hstack([2 * y, np.ones((30, 1))])
    sol = np.linalg.lstsq(A, np.sum(y * y, 1), rcond=None)[0]
    c_alg = sol[:3] + pts.mean(0)
    r_alg = np.sqrt(sol[3] + sol[:3] @ sol[:3])
    rms_alg = np.sqrt(np.mean((np.linalg.norm(pts - c_alg, axis=1) - r_alg) ** 2))
    _, _, rms = fit_sphere(pts)
    assert rms <= rms_alg + 1e-15


def test_fit_sphere_known_radius_three_points_with_hint():
    centre = np.array([0.2, 0.3, 0.1])
    R = 0.0125
    dirs = np.array([[1, 0, 1], [-0.5, 0.8, 1], [-0.5, -0.8, 1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = centre + R * dirs
    c, r, rms = fit_sphere(pts, radius=R, centre_hint=centre + [0, 0, -0.001])
    assert np.allclose(c, centre, atol=1e-12)
    assert r == R
    assert rms < 1e-12
    # The hint on the other side picks the mirror sphere.
    c2, _, rms2 = fit_sphere(pts, radius=R, centre_hint=centre + [0, 0, 0.02])
    assert c2[2] > pts[:, 2].mean()
    assert rms2 < 1e-12


def test_fit_sphere_known_radius_ambiguous_without_hint():
    pts = np.array([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0]])
    with pytest.raises(ValueError, match="centre_hint"):
        fit_sphere(pts, radius=2.0)


def test_fit_sphere_known_radius_many_points_with_noise():
    rng = np.random.default_rng(4)
    centre = np.array([-0.3, 0.6, 0.2])
    pts = _sphere_points(centre, 0.01, 8, rng, cap_deg=70) + rng.normal(0, 1e-6, (8, 3))
    c, r, rms = fit_sphere(pts, radius=0.01)
    assert r == 0.01
    assert np.linalg.norm(c - centre) < 1e-5
    assert rms < 4e-6


@pytest.mark.parametrize(
    "points, radius, message",
    [
        (np.zeros((3, 3)), None, "at least 4"),
        (np.zeros((2, 3)), 1.0, "at least 3"),
        (np.zeros((5, 2)), None, "shape"),
        (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]]), None, "collinear"),
        (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0.0]]), None, "coplanar"),
        (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, 0, np.nan]]), None, "NaN"),
        (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0.0]]), -1.0, "positive"),
        (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0.0]]) * 5, 1.0, "larger than"),
        (np.ones((6, 3)), None, "collinear"),
    ],
)
def test_fit_sphere_rejects_degenerate_input(points, radius, message):
    with pytest.raises(ValueError, match=message):
        fit_sphere(points, radius=radius)


# --------------------------------------------------------------------------- pose_from_points


def test_pose_from_points_exact_recovery():
    rng = np.random.default_rng(5)
    p_tool = rng.uniform(-0.1, 0.1, (5, 3))
    T = _random_pose(rng)
    p_world = p_tool @ T[:3, :3].T + T[:3, 3]
    T_fit, rms = pose_from_points(p_tool, p_world)
    assert np.allclose(T_fit, T, atol=1e-12)
    assert rms < 1e-12
    assert isinstance(rms, float)


def test_pose_from_points_three_points_and_reflection_safe():
    # Three points: a proper rotation is returned (det +1), never a reflection.
    rng = np.random.default_rng(6)
    p_tool = np.array([[0.05, 0, 0.03], [-0.03, 0.05, 0.03], [-0.03, -0.05, 0.03]])
    for _ in range(20):
        T = _random_pose(rng)
        p_world = p_tool @ T[:3, :3].T + T[:3, 3]
        T_fit, _rms = pose_from_points(p_tool, p_world)
        assert np.linalg.det(T_fit[:3, :3]) == pytest.approx(1.0)
        assert np.allclose(T_fit, T, atol=1e-12)


def test_pose_from_points_noise_and_batch():
    rng = np.random.default_rng(7)
    p_tool = np.array([[0.05, 0, 0.03], [-0.03, 0.05, 0.03], [-0.03, -0.05, 0.03], [0, 0, 0.08]])
    N = 30
    Ts = np.stack([_random_pose(rng) for _ in range(N)])
    sigma = 2e-6
    p_world = np.einsum("nij,kj->nki", Ts[:, :3, :3], p_tool) + Ts[:, None, :3, 3]
    p_world += rng.normal(0, sigma, p_world.shape)
    T_fit, rms = pose_from_points(p_tool, p_world)
    assert T_fit.shape == (N, 4, 4) and rms.shape == (N,)
    for n in range(N):
        assert np.linalg.norm(T_fit[n, :3, 3] - Ts[n, :3, 3]) < 20 * sigma
        assert _angle_deg(T_fit[n, :3, :3], Ts[n, :3, :3]) < np.degrees(20 * sigma / 0.05)
        assert np.allclose(T_fit[n, :3, :3].T @ T_fit[n, :3, :3], np.eye(3), atol=1e-12)
    assert np.all(rms < 5 * sigma)
    # Batched tool points give the same answer.
    T_fit2, rms2 = pose_from_points(np.broadcast_to(p_tool, (N, 4, 3)), p_world)
    assert np.allclose(T_fit2, T_fit) and np.allclose(rms2, rms)


def test_pose_from_points_residual_reports_a_moved_ball():
    p_tool = np.array([[0.05, 0, 0.03], [-0.03, 0.05, 0.03], [-0.03, -0.05, 0.03], [0, 0, 0.08]])
    p_world = p_tool.copy()
    p_world[3] += [0.001, 0, 0]
    _, rms = pose_from_points(p_tool, p_world)
    assert rms > 1e-4


@pytest.mark.parametrize(
    "p_tool, p_world, message",
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
        (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.zeros((3, 3)), "collinear"),
        (np.zeros((4, 3)), np.zeros((3, 3)), "shape"),
        (np.eye(3), np.full((3, 3), np.inf), "NaN or infinite"),
        (np.zeros((2, 4, 3)), np.zeros((3, 4, 3)), "leading axis"),
    ],
)
def test_pose_from_points_rejects_bad_input(p_tool, p_world, message):
    with pytest.raises(ValueError, match=message):
        pose_from_points(p_tool, p_world)


# --------------------------------------------------------------------------- eq. 6.15


def test_pose_from_three_points_exact_matches_kabsch():
    rng = np.random.default_rng(8)
    p_tool = np.array([[0.05, 0, 0.03], [-0.03, 0.05, 0.03], [-0.03, -0.05, 0.03]])
    T = _random_pose(rng)
    p_world = p_tool @ T[:3, :3].T + T[:3, 3]
    T_book = pose_from_three_points(p_tool, p_world)
    assert np.allclose(T_book, T, atol=1e-10)
    assert np.allclose(T_book, pose_from_points(p_tool, p_world)[0], atol=1e-10)


def test_pose_from_three_points_with_noise_is_not_orthonormal():
    # The documented departure from the book: noisy centres give a non-orthonormal block.
    rng = np.random.default_rng(9)
    p_tool = np.array([[0.05, 0, 0.03], [-0.03, 0.05, 0.03], [-0.03, -0.05, 0.03]])
    Ts = np.stack([_random_pose(rng) for _ in range(5)])
    p_world = np.einsum("nij,kj->nki", Ts[:, :3, :3], p_tool) + Ts[:, None, :3, 3]
    p_world += rng.normal(0, 1e-5, p_world.shape)
    T_book = pose_from_three_points(np.broadcast_to(p_tool, (5, 3, 3)), p_world)
    R = T_book[:, :3, :3]
    err = np.linalg.norm(np.swapaxes(R, 1, 2) @ R - np.eye(3), axis=(1, 2))
    assert np.all(err > 1e-6)
    T_kabsch, _ = pose_from_points(p_tool, p_world)
    Rk = T_kabsch[:, :3, :3]
    assert np.allclose(np.swapaxes(Rk, 1, 2) @ Rk, np.eye(3), atol=1e-12)


def test_pose_from_three_points_rejects_collinear():
    with pytest.raises(ValueError, match="collinear"):
        pose_from_three_points(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.eye(3))


def test_joint_harmonic_recovers_book_eq_2_4():
    """θ = k1·q + k2 + k3·sin(k4·q + k5) with known k's and a little noise: recovered, with the
    harmonic's frequency found among the integer ones when not given."""
    from calibration.geometry import fit_joint_harmonic

    rng = np.random.default_rng(4)
    q = np.linspace(-3.0, 3.0, 181)
    k = dict(gain=1.0004, offset=0.002, amplitude=3e-4, frequency=2.0, phase=0.7)
    ref = k["gain"] * q + k["offset"] + k["amplitude"] * np.sin(k["frequency"] * q + k["phase"])
    ref = ref + rng.normal(0.0, 1e-6, q.shape)
    for given in (None, 2.0):
        fit = fit_joint_harmonic(q, ref, given)
        assert fit.frequency == 2.0
        assert fit.gain == pytest.approx(k["gain"], abs=1e-6)
        assert fit.offset == pytest.approx(k["offset"], abs=1e-6)
        assert fit.amplitude == pytest.approx(k["amplitude"], rel=1e-2)
        assert fit.phase == pytest.approx(k["phase"], abs=1e-2)
        assert fit.residual_rms_rad < 2e-6 and fit.points == len(q)
    plain = fit_joint_harmonic(q, k["gain"] * q + k["offset"] + rng.normal(0.0, 1e-6, q.shape), None)
    assert plain.amplitude < 1e-6  # a noise harmonic at most: none is kept unless it helps
