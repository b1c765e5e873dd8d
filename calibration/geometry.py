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
- plane, circle and line fits (book §4.6.2, what circle-point analysis rests on):
  :func:`fit_plane`, :func:`plane_regression`, :func:`kasa_circle`, :func:`fit_circle`,
  :func:`fit_line`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Relative tolerance under which a point set counts as degenerate (coplanar / collinear):
# the smallest relevant singular value of the centred points, relative to the largest.
_DEGENERATE_RTOL = 1e-9

# Circle fits: the geometric fit (default) or the book's algebraic one alone.
METHODS = ("geometric", "kasa")


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
    x, radius = _sphere_input(points, radius)
    k = x.shape[0]
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


def _sphere_input(points: np.ndarray, radius: float | None) -> tuple[np.ndarray, float | None]:
    """:func:`fit_sphere`'s points (k, 3) and known radius checked: finite, enough points for
    the unknowns (4 with a free radius, 3 with a known one), a positive radius."""
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
    return x, radius


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
    return JointHarmonic(
        gain=float(x[0]),
        offset=float(x[1]),
        amplitude=k3,
        frequency=k4,
        phase=k5,
        residual_rms_rad=rms,
        points=int(len(q)),
    )


# --------------------------------------------------------------------------- plane, circle, line


def _points(points: np.ndarray, minimum: int) -> np.ndarray:
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"`points` must have shape (m, 3); got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("`points` contains NaN or infinite values")
    if len(P) < minimum:
        raise ValueError(f"at least {minimum} points are needed; got {len(P)}")
    return P


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Total-least-squares plane (book §4.6.2.1): ``(centroid (3,), unit normal (3,), rms)``.

    The normal is the right singular vector of the centred points with the smallest singular
    value; ``rms`` is the root mean square distance of the points from the plane. This is the
    fixed point of Stone's iterated regression (eq. 4.288-4.295, ch4b §7.3), without the
    iteration and without its breakdown for planes that contain the z direction.
    """
    P = _points(points, 3)
    c = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c, full_matrices=False)
    return c, vt[2], float(s[2] / np.sqrt(len(P)))


def plane_regression(points: np.ndarray) -> tuple[float, float, float]:
    """The book's plane regression ``z = E x + F y + G`` (eq. 4.249-4.262), with eq. 4.252
    corrected: ``E = (σzx σyy − σzy σxy) / (σxx σyy − σxy²)`` (the printed numerator
    ``σxx σyy − σzy σxy`` is wrong). Only z residuals are minimised, so it depends on the
    frame; kept as the reference path, :func:`fit_plane` is what CPA uses.
    """
    P = _points(points, 3)
    d = P - P.mean(axis=0)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    sxx, syy, sxy, szx, szy = x @ x, y @ y, x @ y, z @ x, z @ y
    det = sxx * syy - sxy**2
    if not abs(det) > 1e-300:
        raise ValueError("the plane contains the z direction: z = E x + F y + G cannot describe it")
    E = (szx * syy - szy * sxy) / det  # eq. 4.252, corrected
    F = (sxx * szy - sxy * szx) / det  # eq. 4.253
    G = P[:, 2].mean() - E * P[:, 0].mean() - F * P[:, 1].mean()  # eq. 4.254
    return float(E), float(F), float(G)


def kasa_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kåsa) circle through plane points ``xy`` (m, 2): ``(centre (2,), radius)``.

    Book eq. 4.263-4.271: ``w = x² + y² = A x + B y + C`` by linear regression, then (not
    printed in the book) ``g = A/2, h = B/2, r = sqrt(C + g² + h²)``. Exact for exact points;
    biased towards a smaller radius on short arcs with noise, and translation invariant (moving
    the origin to the centre and solving again gives the same circle, ch4b §4).
    """
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 3:
        raise ValueError(f"`xy` must have shape (m >= 3, 2); got {xy.shape}")
    m0 = xy.mean(axis=0)  # centred sums: same solution, better conditioned
    x, y = (xy - m0).T
    w = x**2 + y**2
    dx, dy, dw = x - x.mean(), y - y.mean(), w - w.mean()
    sxx, syy, sxy, swx, swy = dx @ dx, dy @ dy, dx @ dy, dw @ dx, dw @ dy
    det = sxx * syy - sxy**2
    if not det > 1e-300 * max(sxx * syy, 1e-300):
        raise ValueError("the points are collinear: no circle passes through them")
    A = (swx * syy - swy * sxy) / det  # eq. 4.266
    B = (sxx * swy - sxy * swx) / det  # eq. 4.267
    C = w.mean() - A * x.mean() - B * y.mean()  # eq. 4.268
    g, h = A / 2.0, B / 2.0
    return m0 + np.array([g, h]), float(np.sqrt(max(C + g * g + h * h, 0.0)))


def fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """3D line by the principal-axis method (book §4.6.2.3, L3560): ``(centroid, unit
    direction, rms)``; ``rms`` of the perpendicular distances. The book's two projected
    regressions (eq. 4.273-4.280) minimise y and z residuals and fail for lines perpendicular
    to x; the principal axis is the true perpendicular-distance fit."""
    P = _points(points, 2)
    c = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c, full_matrices=False)
    if not s[0] > 0:
        raise ValueError("the points coincide: no line through them")
    off = (P - c) - np.outer((P - c) @ vt[0], vt[0])
    return c, vt[0], float(np.sqrt(np.mean(np.sum(off**2, axis=1))))


@dataclass(frozen=True, eq=False)
class Circle:
    """A circle in space. ``centre`` (3,) m, unit ``normal`` (3,) (sign arbitrary), ``radius``
    m; per point ``out_of_plane`` and ``radial`` residuals (m,) m; ``covariance`` (6, 6) of
    (centre x, y, z in m, tilt of the normal about two perpendicular axes in rad, radius in m)
    from the residual scatter (NaN with too few points); ``method``: ``geometric`` or ``kasa``."""

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    out_of_plane: np.ndarray
    radial: np.ndarray
    covariance: np.ndarray
    method: str


def _circle_residuals(Y, n0, u, w, x):
    """Residuals (out of plane, radial) of scaled points ``Y`` for parameters ``x`` = (centre,
    tilt a, tilt b, radius) with normal ``n0 + a u + b w`` normalised; and their Jacobian."""
    c, a, b, r = x[:3], x[3], x[4], x[5]
    mvec = n0 + a * u + b * w
    nm = np.linalg.norm(mvec)
    n = mvec / nm
    d = Y - c
    z = d @ n
    e = d - np.outer(z, n)
    rho = np.linalg.norm(e, axis=1)
    e_hat = e / np.where(rho > 0, rho, 1.0)[:, None]
    dn_da = (u - n * (n @ u)) / nm
    dn_db = (w - n * (n @ w)) / nm
    m = len(Y)
    J = np.zeros((2 * m, 6))
    J[:m, :3] = -n
    J[:m, 3] = d @ dn_da
    J[:m, 4] = d @ dn_db
    J[m:, :3] = -e_hat
    J[m:, 3] = -z * (e_hat @ dn_da)
    J[m:, 4] = -z * (e_hat @ dn_db)
    J[m:, 5] = -1.0
    return np.concatenate([z, rho - r]), J


def fit_circle(points: np.ndarray, *, method: str = "geometric", xtol: float = 1e-12) -> Circle:
    """Circle through 3D points (m >= 3, not collinear): book §4.6.2, §4.6.4.

    ``kasa``: the total-least-squares plane, then the algebraic circle in it (eq. 4.263-4.271):
    the book's plane-plus-circle. ``geometric`` (default): from there, least squares on the true
    distances of the points to the circle (out of the plane and radially, 2m residuals, 6
    parameters), which removes the Kåsa fit's bias on short arcs.
    """
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {', '.join(METHODS)}; got {method!r}")
    P = _points(points, 3)
    c0 = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c0, full_matrices=False)
    if not s[0] > 0 or s[1] <= _DEGENERATE_RTOL * s[0]:
        raise ValueError("the points are collinear (or coincide): no circle passes through them")
    u, w, n0 = vt
    g2, r0 = kasa_circle(np.column_stack([(P - c0) @ u, (P - c0) @ w]))
    centre = c0 + g2[0] * u + g2[1] * w
    if not r0 > 0:
        raise ValueError("the points are collinear (or coincide): no circle passes through them")
    Y = (P - centre) / r0  # scaled: circle of radius ~1 about the origin
    x = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    if method == "geometric":
        # imported here: the drivers import this module, and scipy.optimize is slow to import
        from scipy.optimize import least_squares

        sol = least_squares(
            lambda x_: _circle_residuals(Y, n0, u, w, x_)[0],
            x,
            jac=lambda x_: _circle_residuals(Y, n0, u, w, x_)[1],
            method="lm",
            xtol=xtol,
            ftol=xtol,
            gtol=xtol,
        )
        x = sol.x
    res, J = _circle_residuals(Y, n0, u, w, x)
    mvec = n0 + x[3] * u + x[4] * w
    normal = mvec / np.linalg.norm(mvec)
    m = len(P)
    dof = 2 * m - 6
    scale = np.array([r0, r0, r0, 1.0, 1.0, r0])
    if dof > 0:
        s2 = float(res @ res) / dof
        cov = s2 * np.linalg.pinv(J.T @ J) * np.outer(scale, scale)
    else:
        cov = np.full((6, 6), np.nan)
    return Circle(centre + r0 * x[:3], normal, float(r0 * x[5]), res[:m] * r0, res[m:] * r0, cov, method)
