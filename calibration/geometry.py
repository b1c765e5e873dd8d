"""Point geometry for measuring instruments: sphere fits and rigid poses from points.

Pure numpy. Everything is in one consistent length unit (SI metres by convention in Recal);
nothing here knows about units beyond that.

- :func:`fit_sphere`: the centre of a tooling ball from probed surface points (book §6.2:
  "4 touches per ball", solved by least squares).
- :func:`pose_from_points`: the rigid transform that best maps known tool-frame points onto
  their measured world positions (SVD / Kabsch), over all points. This is what Recal uses.
- :func:`pose_from_three_points`: the book's construction from exactly three ball centres
  (eqs. 6.12-6.15, same as eqs. 3.22-3.27), kept as the reference path.
- :func:`fit_joint_harmonic`: a joint's reference reading against its controller reading,
  book eq. 2.4 (gain, offset and an eccentricity harmonic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Relative tolerance under which a point set counts as degenerate (coplanar / collinear):
# the smallest relevant singular value of the centred points, relative to the largest.
_DEGENERATE_RTOL = 1e-9


# --------------------------------------------------------------------------- spheres


def fit_sphere(
    points: np.ndarray,
    radius: float | None = None,
    *,
    centre_hint: np.ndarray | None = None,
    max_iter: int = 50,
    xtol: float = 1e-12,
) -> tuple[np.ndarray, float, float]:
    """Fit a sphere to surface points: algebraic fit, refined by geometric least squares.

    The algebraic fit solves ``|x|^2 = 2 c.x + (r^2 - |c|^2)`` linearly; Gauss-Newton then
    minimises the sum of squared geometric distances ``(|x_i - c| - r)^2``.

    Parameters
    ----------
    points : (k, 3) float
        Points on the sphere surface. ``k >= 4`` and not coplanar for a free radius;
        ``k >= 3`` and not collinear when ``radius`` is given.
    radius : float, optional
        The known sphere radius (same unit as ``points``). Only the centre is fitted.
    centre_hint : (3,) float, optional
        With a known radius and coplanar points (always the case for three), two spheres fit
        equally well, one each side of the plane; the one whose centre is nearer the hint is
        returned. Without a hint such input raises ``ValueError``.
    max_iter, xtol : Gauss-Newton iteration limit and step tolerance (relative to the size of
        the point set).

    Returns
    -------
    centre : (3,) float
    radius : float
        The fitted radius (``radius`` itself when it was given).
    rms : float
        Root mean square of the geometric residuals ``|x_i - c| - r``.

    Raises
    ------
    ValueError
        Wrong shape, non-finite values, too few points, collinear or (free radius) coplanar
        points, a non-positive radius, or an ambiguous known-radius fit without a hint.

    Examples
    --------
    >>> p = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]]) + 2.0
    >>> c, r, rms = fit_sphere(p)
    >>> np.round(c, 9).tolist(), round(r, 9), rms < 1e-12
    ([2.0, 2.0, 2.0], 1.0, True)
    """
    x = np.asarray(points, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"`points` must have shape (k, 3); got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("`points` contains NaN or infinite values")
    k = x.shape[0]
    if radius is None and k < 4:
        raise ValueError(f"a sphere of unknown radius needs at least 4 points; got {k}")
    if radius is not None:
        radius = float(radius)
        if not np.isfinite(radius) or radius <= 0:
            raise ValueError(f"`radius` must be a positive finite number; got {radius}")
        if k < 3:
            raise ValueError(f"a sphere of known radius needs at least 3 points; got {k}")

    # Work in centred, scaled coordinates for conditioning.
    mean = x.mean(axis=0)
    y = x - mean
    _, s, vt = np.linalg.svd(y, full_matrices=False)
    scale = s[0] / np.sqrt(k) if s[0] > 0 else 0.0
    if s[0] == 0 or s[1] <= _DEGENERATE_RTOL * s[0]:
        raise ValueError("the points are collinear (or coincide): no unique sphere passes through them")
    coplanar = s[2] <= _DEGENERATE_RTOL * s[0]
    y = y / scale

    if radius is None:
        if coplanar:
            raise ValueError(
                "the points are coplanar: a sphere of unknown radius is not determined "
                "(probe at least one point off the plane, or give the radius)"
            )
        c0, r0 = _algebraic_sphere(y)
        c, r = _refine_sphere(y, c0, r0, free_radius=True, max_iter=max_iter, xtol=xtol)
    else:
        r_scaled = radius / scale
        hint = None if centre_hint is None else (np.asarray(centre_hint, float).reshape(3) - mean) / scale
        if coplanar or k == 3:
            c0 = _known_radius_start(y, vt[2], r_scaled, hint)
        else:
            c0, _ = _algebraic_sphere(y)
        c, r = _refine_sphere(y, c0, r_scaled, free_radius=False, max_iter=max_iter, xtol=xtol)

    residuals = np.linalg.norm(y - c, axis=1) - r
    rms = float(np.sqrt(np.mean(residuals**2)) * scale)
    return c * scale + mean, float(r * scale), rms


def _algebraic_sphere(y: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear least-squares sphere through centred points ``y`` (k, 3)."""
    A = np.hstack([2.0 * y, np.ones((y.shape[0], 1))])
    b = np.sum(y * y, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    r2 = sol[3] + c @ c
    return c, float(np.sqrt(max(r2, 0.0)))


def _known_radius_start(y: np.ndarray, normal: np.ndarray, r: float, hint: np.ndarray | None) -> np.ndarray:
    """Start for a known-radius fit to (nearly) coplanar points: the circle through them,
    lifted along the plane normal to the side nearer the hint."""
    # Circle fit in the plane: coordinates along the two in-plane axes.
    u = np.linalg.svd(y, full_matrices=False)[2][:2]
    p2 = y @ u.T
    A = np.hstack([2.0 * p2, np.ones((p2.shape[0], 1))])
    sol, *_ = np.linalg.lstsq(A, np.sum(p2 * p2, axis=1), rcond=None)
    c2 = sol[:2]
    rc = float(np.sqrt(max(sol[2] + c2 @ c2, 0.0)))
    centre_in_plane = c2 @ u
    if rc > r * (1.0 + 1e-3):
        raise ValueError(
            f"the points lie on a circle of radius {rc:.6g} (scaled), larger than the given sphere radius {r:.6g}"
        )
    h = float(np.sqrt(max(r * r - rc * rc, 0.0)))
    if h <= 1e-9 * r:
        return centre_in_plane
    candidates = [centre_in_plane + h * normal, centre_in_plane - h * normal]
    if hint is None:
        raise ValueError(
            "two spheres of the given radius fit these coplanar points, one each side of their "
            "plane; pass `centre_hint` to choose"
        )
    return min(candidates, key=lambda c: float(np.linalg.norm(c - hint)))


def _refine_sphere(
    y: np.ndarray, c: np.ndarray, r: float, *, free_radius: bool, max_iter: int, xtol: float
) -> tuple[np.ndarray, float]:
    """Gauss-Newton on the geometric residuals ``|y_i - c| - r`` (with step halving)."""

    def cost(c_, r_):
        return float(np.sum((np.linalg.norm(y - c_, axis=1) - r_) ** 2))

    current = cost(c, r)
    for _ in range(max_iter):
        d = y - c
        dist = np.linalg.norm(d, axis=1)
        if np.any(dist == 0):
            break
        res = dist - r
        J = -d / dist[:, None]
        if free_radius:
            J = np.hstack([J, -np.ones((y.shape[0], 1))])
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        t = 1.0
        while t > 1e-6:
            c_new = c + t * step[:3]
            r_new = r + t * step[3] if free_radius else r
            new = cost(c_new, r_new)
            if new <= current:
                break
            t *= 0.5
        else:
            break
        c, r, current = c_new, r_new, new
        if t * np.linalg.norm(step) < xtol:
            break
    return c, float(r)


# --------------------------------------------------------------------------- rigid poses


def pose_from_points(p_tool: np.ndarray, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray | float]:
    """Least-squares rigid transform from tool-frame points to their world positions (Kabsch).

    Finds ``T_world_tool`` minimising ``sum_i |R p_tool_i + t - p_world_i|^2`` over all
    points, with ``R`` a proper rotation (det +1), by the SVD of the cross-covariance of the
    centred point sets.

    Parameters
    ----------
    p_tool : (k, 3) or (N, k, 3) float
        Points in the tool frame (for example tooling-ball centres), ``k >= 3``, not collinear.
    p_world : (k, 3) or (N, k, 3) float
        The same points as measured in the world frame. With a leading ``N`` axis, ``p_tool``
        may be (k, 3) and is then shared by all ``N`` sets.

    Returns
    -------
    T_world_tool : (4, 4) or (N, 4, 4) float
    rms : float or (N,) float
        Root mean square distance ``|R p_tool_i + t - p_world_i|`` over the points.

    Raises
    ------
    ValueError
        Wrong shapes, non-finite values, fewer than 3 points, or collinear tool points.

    Examples
    --------
    >>> p_tool = np.array([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    >>> T, rms = pose_from_points(p_tool, p_tool + [1.0, 2.0, 3.0])
    >>> np.round(T[:3, 3], 12).tolist(), rms < 1e-12
    ([1.0, 2.0, 3.0], True)
    """
    pt = np.asarray(p_tool, dtype=float)
    pw = np.asarray(p_world, dtype=float)
    single = pw.ndim == 2
    if pw.ndim not in (2, 3) or pw.shape[-1] != 3:
        raise ValueError(f"`p_world` must have shape (k, 3) or (N, k, 3); got {pw.shape}")
    if pt.ndim not in (2, 3) or pt.shape[-1] != 3 or pt.shape[-2] != pw.shape[-2]:
        raise ValueError(f"`p_tool` must have shape (k, 3) or (N, k, 3) matching `p_world` {pw.shape}; got {pt.shape}")
    if pt.ndim == 3 and (single or pt.shape[0] != pw.shape[0]):
        raise ValueError(f"`p_tool` {pt.shape} and `p_world` {pw.shape} disagree in their leading axis")
    k = pw.shape[-2]
    if k < 3:
        raise ValueError(f"a rigid pose needs at least 3 points; got {k}")
    if not (np.all(np.isfinite(pt)) and np.all(np.isfinite(pw))):
        raise ValueError("`p_tool` or `p_world` contains NaN or infinite values")

    pw3 = pw[None] if single else pw
    pt3 = np.broadcast_to(pt, pw3.shape)
    ct = pt3.mean(axis=1, keepdims=True)
    cw = pw3.mean(axis=1, keepdims=True)
    a = pt3 - ct
    b = pw3 - cw
    s_tool = np.linalg.svd(a, compute_uv=False)
    if np.any(s_tool[:, 1] <= _DEGENERATE_RTOL * s_tool[:, 0]):
        raise ValueError("the tool points are collinear (or coincide): the rotation about their line is undetermined")

    H = np.einsum("nki,nkj->nij", a, b)  # sum_k a_k b_k^T
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d[d == 0] = 1.0
    D = np.zeros((len(d), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = V @ D @ np.swapaxes(U, -1, -2)
    t = cw[:, 0, :] - np.einsum("nij,nj->ni", R, ct[:, 0, :])

    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    fitted = np.einsum("nij,nkj->nki", R, pt3) + t[:, None, :]
    rms = np.sqrt(np.mean(np.sum((fitted - pw3) ** 2, axis=-1), axis=-1))
    if single:
        return T[0], float(rms[0])
    return T, rms


def pose_from_three_points(p_tool: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """The book's pose from exactly three ball centres (eqs. 6.12-6.15; also eqs. 3.22-3.27).

    With balls ``x2, x3, x5`` (any three, in this order) a fictitious fourth point
    ``x_f = (x3 - x2) x (x5 - x2) + x2`` is built in each frame (eq. 6.13; the cross product
    is not normalised), and ``T_we = [x2w x3w x5w xfw] [x2e x3e x5e xfe]^-1`` with 4 x 4
    matrices of homogeneous columns (eq. 6.15).

    This is the reference path only. It is exact with exact data, but with noisy centres the
    3 x 3 block of the result is not orthonormal (and the fourth point's lever arm scales with
    the square of the ball spacing). What the field does now, and what Recal uses, is the SVD /
    Kabsch least-squares fit over all measured balls, :func:`pose_from_points`, which always
    returns a proper rotation and a residual.

    Parameters
    ----------
    p_tool : (3, 3) or (N, 3, 3) float
        Three ball centres (rows) in the tool (end-effector) frame, not collinear.
    p_world : (3, 3) or (N, 3, 3) float
        The same three centres measured in the world frame.

    Returns
    -------
    T_world_tool : (4, 4) or (N, 4, 4) float

    Examples
    --------
    >>> p_tool = np.array([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    >>> T = pose_from_three_points(p_tool, p_tool + [1.0, 2.0, 3.0])
    >>> np.allclose(T[:3, :3], np.eye(3)), np.round(T[:3, 3], 12).tolist()
    (True, [1.0, 2.0, 3.0])
    """
    pt = np.asarray(p_tool, dtype=float)
    pw = np.asarray(p_world, dtype=float)
    single = pw.ndim == 2
    for name, arr in (("p_tool", pt), ("p_world", pw)):
        if arr.shape[-2:] != (3, 3) or arr.ndim not in (2, 3):
            raise ValueError(f"`{name}` must have shape (3, 3) or (N, 3, 3); got {arr.shape}")
    if pt.ndim != pw.ndim or pt.shape != pw.shape:
        raise ValueError(f"`p_tool` {pt.shape} and `p_world` {pw.shape} must have the same shape")
    if not (np.all(np.isfinite(pt)) and np.all(np.isfinite(pw))):
        raise ValueError("`p_tool` or `p_world` contains NaN or infinite values")
    Xe = _homogeneous_columns(pt[None] if single else pt)
    Xw = _homogeneous_columns(pw[None] if single else pw)
    # Collinear tool points make the cross product (and so the matrix) singular.
    arm = np.linalg.norm(Xe[:, :3, 3] - Xe[:, :3, 0], axis=-1)
    span = np.max(np.linalg.norm(Xe[:, :3, 1:3] - Xe[:, :3, :1], axis=1), axis=-1)
    if np.any(arm <= _DEGENERATE_RTOL * np.maximum(span, 1e-300) ** 2):
        raise ValueError("the tool points are collinear (or coincide): eq. 6.15 has no inverse")
    T = Xw @ np.linalg.inv(Xe)
    T[:, 3, :] = [0.0, 0.0, 0.0, 1.0]  # exact by construction; remove rounding noise
    return T[0] if single else T


def _homogeneous_columns(p: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rows x2, x3, x5 -> (N, 4, 4) columns [x2 x3 x5 xf] with a row of ones (eq. 6.14)."""
    x2, x3, x5 = p[:, 0], p[:, 1], p[:, 2]
    xf = np.cross(x3 - x2, x5 - x2) + x2
    cols = np.stack([x2, x3, x5, xf], axis=-1)  # (N, 3, 4)
    ones = np.ones((p.shape[0], 1, 4))
    return np.concatenate([cols, ones], axis=1)


# --------------------------------------------------------------------------- joint level


@dataclass(frozen=True)
class JointHarmonic:
    """Book eq. 2.4 for one joint, ``θ = k1·q + k2 + k3·sin(k4·q + k5)``: ``gain`` k1,
    ``offset`` k2 (rad), ``amplitude`` k3 (rad), ``frequency`` k4 (per rad of reading), ``phase``
    k5 (rad), the fit's ``residual_rms_rad`` and the number of ``points``."""

    gain: float
    offset: float
    amplitude: float
    frequency: float
    phase: float
    residual_rms_rad: float
    points: int


def fit_joint_harmonic(q: np.ndarray, ref: np.ndarray, frequency: float | None) -> JointHarmonic:
    """Book eq. 2.4 for one joint: ``ref = k1·q + k2 + k3·sin(k4·q + k5)`` by linear least squares
    for a given ``k4`` (``frequency``; when unknown, the best of the integer harmonics the sweep
    resolves, each kept only if it lowers the residual by a fifth). ``q``, ``ref`` (N,) rad."""
    q = np.asarray(q, float)
    ref = np.unwrap(np.asarray(ref, float))

    def solve(k4):
        cols = [q, np.ones_like(q)]
        if k4:
            cols += [np.sin(k4 * q), np.cos(k4 * q)]
        A = np.stack(cols, axis=1)
        x, *_ = np.linalg.lstsq(A, ref, rcond=None)
        res = ref - A @ x
        return x, float(np.sqrt(np.mean(res**2)))

    if frequency is None:
        span = float(q.max() - q.min())
        spacing = span / max(len(q) - 1, 1)
        max_k = int(np.floor(np.pi / max(spacing, 1e-9) / 2))  # at least four points a period
        best = (solve(0.0), 0.0)
        for k in range(1, max(max_k, 0) + 1):
            cand = solve(float(k))
            if cand[1] < best[0][1] * 0.8:
                best = (cand, float(k))
        (x, rms), k4 = best
    else:
        k4 = float(frequency)
        x, rms = solve(k4)
    k3 = k5 = 0.0
    if k4 and len(x) == 4:
        a, b = float(x[2]), float(x[3])  # a sin + b cos = k3 sin(k4 q + k5)
        k3, k5 = math.hypot(a, b), math.atan2(b, a)
    return JointHarmonic(gain=float(x[0]), offset=float(x[1]), amplitude=k3, frequency=k4, phase=k5,
                         residual_rms_rad=rms, points=int(len(q)))
