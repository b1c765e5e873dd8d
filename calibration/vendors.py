"""How industrial controllers write poses and arm configurations (ABB, KUKA, Fanuc), batched
over N, SI (rad, m) unless a name says otherwise.

Orientations:

- ABB ``robtarget.rot``: a unit quaternion ``[q1, q2, q3, q4]`` = ``(w, x, y, z)``, scalar first
  (Hamilton): :func:`calibration.transforms.quat_to_matrix` and ``matrix_to_quat`` already use it;
  :func:`quat_near` picks the sign of a written one.
- KUKA ``A, B, C``: Euler angles ZYX, ``R = Rz(A)·Ry(B)·Rx(C)`` (:func:`kuka_abc_to_matrix`).
- Fanuc ``W, P, R``: fixed angles about the world X, Y, Z in that order, which is the same matrix
  ``R = Rz(R)·Ry(P)·Rx(W)`` (:func:`fanuc_wpr_to_matrix`).

Both angle sets have two solutions per rotation (``(a, b, c)`` and ``(a+π, π−b, c+π)``) and any
multiple of 2π; the ``near`` argument of the inverse functions returns the set nearest a written
one, so that a rewritten program keeps its style (``A 180`` stays ``180``, not ``-180``).

Arm configurations of a six-axis arm with a spherical wrist, from its readings ``q`` (N, 6):

- :func:`arm_flags`: the two geometric flags every brand encodes: the wrist centre in *front of*
  axis 1 (the side where it is in the brand's reference pose) and the *elbow* on the same side of
  the line through axes 2 and 3 as in that reference pose;
- :func:`abb_confdata` ``[cf1, cf4, cf6, cfx]``; :func:`kuka_status_turn` ``(S, T)``;
  :func:`fanuc_config` ``(flip, up, front, turn1, turn4, turn6)``.

Each brand function is a geometric part (:func:`arm_flags`) and a per-joint part that depends only
on each joint's own reading (:func:`joint_codes`), so that a solver can move a joint by whole
turns to match a written configuration without walking the chain again.
"""

from __future__ import annotations

import math

import numpy as np

from .kinematics import check_q, walk
from .model import KinematicModel
from .transforms import matrix_to_quat, matrix_to_rpy, rpy_to_matrix

TWO_PI = 2.0 * math.pi
HALF_PI = 0.5 * math.pi

# Reference readings (rad) of joints 2..6 in which each brand's arm has its wrist centre in front
# of axis 1 and its elbow "up": ABB and Fanuc at their zero pose (upper arm vertical, forearm
# horizontal; Fanuc's J3 is measured from the horizon), KUKA at A2 = −90°, A3 = +90° (its zero has
# the upper arm horizontal).
REFERENCE = {
    "abb": np.zeros(5),
    "fanuc": np.zeros(5),
    "kuka": np.radians([-90.0, 90.0, 0.0, 0.0, 0.0]),
}


# =============================================================================== orientations


def kuka_abc_to_matrix(abc: np.ndarray) -> np.ndarray:
    """KUKA ``A, B, C`` (..., 3), rad -> ``R = Rz(A)·Ry(B)·Rx(C)`` (..., 3, 3) (Euler ZYX)."""
    abc = np.asarray(abc, dtype=float)
    return rpy_to_matrix(abc[..., ::-1])


def fanuc_wpr_to_matrix(wpr: np.ndarray) -> np.ndarray:
    """Fanuc ``W, P, R`` (..., 3), rad -> ``R = Rz(R)·Ry(P)·Rx(W)`` (..., 3, 3) (fixed X, Y, Z)."""
    return rpy_to_matrix(np.asarray(wpr, dtype=float))


def _zyx_near(R: np.ndarray, near: np.ndarray | None) -> np.ndarray:
    """Angles ``(z, y, x)`` (N, 3) with ``R = Rz(z)·Ry(y)·Rx(x)``: of the two sets and their 2π
    shifts, the one nearest ``near`` (N, 3) (else the one with |y| <= π/2, angles in (−π, π])."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    rpy = matrix_to_rpy(R)
    a = np.stack([rpy[:, 2], rpy[:, 1], rpy[:, 0]], axis=1)
    if near is None:
        return a
    near = np.asarray(near, dtype=float).reshape(-1, 3)
    b = np.stack([a[:, 0] + math.pi, math.pi - a[:, 1], a[:, 2] + math.pi], axis=1)
    best: np.ndarray | None = None
    cost: np.ndarray = np.zeros(0)
    for cand in (a, b):
        c = cand + TWO_PI * np.round((near - cand) / TWO_PI)
        d = np.sum((c - near) ** 2, axis=1)
        if best is None:
            best, cost = c, d
        else:
            take = d < cost
            best = np.where(take[:, None], c, best)
            cost = np.where(take, d, cost)
    assert best is not None  # at least one candidate
    return best


def matrix_to_kuka_abc(R: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """``R`` (N, 3, 3) -> KUKA ``A, B, C`` (N, 3), rad; with ``near`` (N, 3) the equivalent set
    nearest it (see the module docstring)."""
    return _zyx_near(R, near)


def matrix_to_fanuc_wpr(R: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """``R`` (N, 3, 3) -> Fanuc ``W, P, R`` (N, 3), rad; with ``near`` the set nearest it."""
    near_zyx = None if near is None else np.asarray(near, dtype=float).reshape(-1, 3)[:, ::-1]
    return _zyx_near(R, near_zyx)[:, ::-1]


def quat_near(R: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """``R`` (N, 3, 3) -> unit quaternion ``(w, x, y, z)`` (N, 4), scalar first, with the sign of
    ``near`` (N, 4) where given (q and −q are the same rotation)."""
    q = matrix_to_quat(np.asarray(R, dtype=float).reshape(-1, 3, 3))
    if near is not None:
        flip = np.sum(q * np.asarray(near, dtype=float).reshape(-1, 4), axis=1) < 0
        q[flip] *= -1.0
    return q


# =============================================================================== configurations


def _closest_points(u1, o1, u2, o2):
    """The point of line 2 (N, 3) closest to line 1 (each a unit direction and a point)."""
    w = o2 - o1
    b = np.sum(u1 * u2, axis=1)
    d = np.sum(u1 * w, axis=1)
    e = np.sum(u2 * w, axis=1)
    den = 1.0 - b * b
    t = np.where(den > 1e-12, (b * d - e) / np.where(den > 1e-12, den, 1.0), 0.0)
    return o2 + t[:, None] * u2


def _wrist_geometry(model: KinematicModel, q: np.ndarray):
    keys = [f"{j.name}.theta" if j.revolute else f"{j.name}.d" for j in model.joints]
    w = walk(model, q, set(keys))
    (u1, o1), (u2, o2), (_, o3), (u4, o4), (u5, o5) = (w.axes[k] for k in keys[:5])
    wc = _closest_points(u4, o4, u5, o5)  # the wrist centre: where axes 4 and 5 meet
    return u1, o1, u2, o2, o3, wc


def arm_flags(model: KinematicModel, q: np.ndarray, brand: str) -> tuple[np.ndarray, np.ndarray]:
    """``front`` and ``elbow_up`` (N,) bool of readings ``q`` (N, 6) of a six-axis arm whose axes
    4 and 5 meet (spherical wrist).

    ``front``: the wrist centre ``w`` is on the same side of axis 1 as in the brand's reference
    pose (:data:`REFERENCE`, joint 1 as in ``q``): ``(w − o1)·d ≥ 0`` with ``d`` the reference
    wrist centre's direction from axis 1, perpendicular to it (KUKA: x of the wrist root point in
    the A1 frame ≥ 0, "basic area"; ABB: wrist centre in front of axis 1; Fanuc: "T", toward).
    ``elbow_up``: ``((o3 − o2) × (w − o3))·u2`` has the sign it has in the reference pose, with
    ``o2``, ``o3`` points of axes 2 and 3 (KUKA: A3 ≥ φ; ABB: wrist centre in front of the lower
    arm; Fanuc: "U")."""
    q = check_q(model, q)
    if model.n_joints != 6:
        raise ValueError(f"arm configurations are defined for six-axis arms; {model.name!r} has {model.n_joints}")
    ref = q.copy()
    ref[:, 1:] = REFERENCE[brand]
    u1, o1, u2, o2, o3, wc = _wrist_geometry(model, q)
    _, r_o1, r_u2, r_o2, r_o3, r_wc = _wrist_geometry(model, ref)

    def perp(v):
        return v - np.sum(v * u1, axis=1, keepdims=True) * u1

    d = perp(r_wc - r_o1)
    front = np.sum(perp(wc - o1) * d, axis=1) >= 0.0
    s = np.sum(np.cross(o3 - o2, wc - o3) * u2, axis=1)
    s_ref = np.sum(np.cross(r_o3 - r_o2, r_wc - r_o3) * r_u2, axis=1)
    return front, np.sign(s) == np.sign(s_ref)


def joint_codes(q: np.ndarray, brand: str) -> np.ndarray:
    """The per-joint part of a brand's configuration (N, 6) int, from each joint's own reading
    (rad). ABB: quadrant ``floor(q/90°)`` of joints 1, 4, 6 (cf1, cf4, cf6) and for joint 5 1 where
    it is negative (cfx's axis-5 bit); KUKA: 1 where a joint is negative (the T bits), and for
    A5 additionally 2 where sin A5 < 0 (S bit 2: A5 in [0°, 180°) or below −180° is 0); Fanuc:
    the turn number ``floor((q + 180°)/360°)`` of J1, J4, J6, times 2, and for J5 1 where it is
    positive ("F", flip; J5 never turns: its range is under ±180°). Joints a brand does not
    encode are 0 (docs/compensation.md §7 gives the evidence for J1, J4, J6)."""
    q = np.asarray(q, dtype=float)
    c = np.zeros(q.shape, dtype=np.int64)
    if brand == "abb":
        quad = np.floor(q / HALF_PI + 1e-12).astype(np.int64)
        for i in (0, 3, 5):
            c[:, i] = quad[:, i]
        c[:, 4] = q[:, 4] < 0
    elif brand == "kuka":
        c[:] = q < 0
        c[:, 4] += 2 * (np.sin(q[:, 4]) < 0)
    elif brand == "fanuc":
        turns = np.floor((q + math.pi) / TWO_PI).astype(np.int64)
        for i in (0, 3, 5):
            c[:, i] = 2 * turns[:, i]
        c[:, 4] = q[:, 4] > 0
    else:
        raise ValueError(f"unknown brand {brand!r}")
    return c


def abb_confdata(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """ABB ``confdata`` ``[cf1, cf4, cf6, cfx]`` (N, 4) int of readings ``q`` (N, 6), rad: the
    quadrants ``floor(angle/90°)`` of axes 1, 4 and 6, and ``cfx = 4·behind_axis1 +
    2·behind_lower_arm + (axis 5 < 0)`` (0..7, the table of ABB's confdata for serial arms)."""
    front, up = arm_flags(model, q, "abb")
    c = joint_codes(check_q(model, q), "abb")
    cfx = 4 * (~front) + 2 * (~up) + c[:, 4]
    return np.stack([c[:, 0], c[:, 3], c[:, 5], cfx], axis=1)


def kuka_status_turn(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """KUKA ``S`` and ``T`` (N, 2) int of readings ``q`` (N, 6), rad. ``S``: bit 0 the overhead
    area (wrist root point at x < 0 in the A1 frame), bit 1 ``A3 ≥ φ`` (the elbow as in
    A2 = −90°, A3 = +90°), bit 2 ``sin A5 < 0``. ``T``: bit i set where axis i+1 is negative."""
    front, up = arm_flags(model, q, "kuka")
    q = check_q(model, q)
    c = joint_codes(q, "kuka")
    S = (~front).astype(np.int64) + 2 * up + 4 * (c[:, 4] >= 2)
    T = np.sum((q < 0) * (1 << np.arange(6)), axis=1)
    return np.stack([S, T], axis=1)


def fanuc_config(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Fanuc ``CONFIG`` (N, 6) int of readings ``q`` (N, 6), rad: ``flip`` (1 = "F", J5 > 0; 0 =
    "N"), ``up`` (1 = "U"), ``front`` (1 = "T", toward; 0 = "B"), then the turn numbers of J1,
    J4 and J6, ``floor((J + 180°)/360°)`` (0 between −180° and 180°)."""
    front, up = arm_flags(model, q, "fanuc")
    q = check_q(model, q)
    c = joint_codes(q, "fanuc")
    return np.stack(
        [c[:, 4], up.astype(np.int64), front.astype(np.int64), c[:, 0] // 2, c[:, 3] // 2, c[:, 5] // 2], axis=1
    )


def configured_ik(
    model: KinematicModel,
    T_world_tool: np.ndarray,
    brand: str,
    front: np.ndarray | None,
    up: np.ndarray | None,
    codes: np.ndarray | None,
    q_near: np.ndarray,
    *,
    n_seeds: int = 48,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """Readings (N, 6) with ``model``'s tool at ``T_world_tool`` (N, 4, 4) in a written
    configuration, and ``found`` (N,): what a controller does with a Cartesian target and its
    configuration data.

    ``front``, ``up`` (N,) and ``codes`` (N, 6) are the configuration as :func:`arm_flags` and
    :func:`joint_codes` state it, as floats with NaN where a target does not state that part
    (``None``: none does). Damped Newton
    (:func:`calibration.ik.solve_ik`) runs from ``q_near`` (N, 6) and ``n_seeds`` configurations
    spread over the joint limits; each converged solution has its joints moved by whole turns
    (where a turn of the reading is a turn of the joint: integer coupling, no gear harmonic) to
    the codes asked for, or else to the turn nearest ``q_near``, within the joint limits. Of the
    solutions in the configuration the one nearest ``q_near`` is returned; where there is none,
    ``found`` is False and the row is the solution nearest ``q_near`` in any configuration."""
    from .ik import solve_ik, spread_seeds

    T = np.asarray(T_world_tool, dtype=float).reshape(-1, 4, 4)
    N = len(T)
    q_near = np.broadcast_to(check_q(model, np.asarray(q_near, dtype=float).reshape(-1, 6)), (N, 6))
    seeds = np.concatenate([q_near[:, None, :], np.broadcast_to(spread_seeds(model, n_seeds), (N, n_seeds, 6))], axis=1)
    K = seeds.shape[1]
    r = solve_ik(
        model,
        np.repeat(T, K, axis=0),
        seeds.reshape(-1, 6),
        position_tol_m=position_tol_m,
        rotation_tol_rad=rotation_tol_rad,
    )
    q = r.q.reshape(N, K, 6)
    near = np.repeat(q_near, K, axis=0).reshape(N, K, 6)
    C = model.coupling_matrix
    turnable = np.array([j.revolute and j.harmonic is None for j in model.joints]) & np.all(C == np.round(C), axis=0)
    lim = model.joint_limits
    shifts = np.arange(-2, 3) * TWO_PI  # (5,)
    cand = q[..., None] + np.where(turnable, 1.0, 0.0)[:, None] * shifts  # (N, K, 6, 5)
    ok = (cand >= lim[:, 0, None] - 1e-9) & (cand <= lim[:, 1, None] + 1e-9)
    if codes is not None:
        want = np.asarray(codes, dtype=float).reshape(N, 1, 6, 1)
        # a reading on a code's boundary (0°, ±90°, ...) to rounding matches either side
        hit = np.broadcast_to(np.isnan(want), ok.shape).copy()
        for eps in (-1e-7, 0.0, 1e-7):
            got = np.stack(
                [joint_codes(cand[..., s].reshape(-1, 6) + eps, brand).reshape(N, K, 6) for s in range(5)], axis=-1
            )
            hit |= got == want
        ok &= hit
    dist = np.where(ok, np.abs(cand - near[..., None]), np.inf)
    pick = np.argmin(dist, axis=-1)
    qs = np.take_along_axis(cand, pick[..., None], axis=-1)[..., 0]
    match = r.converged.reshape(N, K) & np.all(np.isfinite(np.min(dist, axis=-1)), axis=-1)
    if front is not None or up is not None:
        f, u = arm_flags(model, qs.reshape(-1, 6), brand)
        f, u = f.reshape(N, K), u.reshape(N, K)
        for got, wanted in ((f, front), (u, up)):
            if wanted is not None:
                w = np.asarray(wanted, dtype=float).reshape(N, 1)
                match &= np.isnan(w) | (got == (w == 1.0))
    d = np.sum((qs - near) ** 2, axis=-1)
    best = np.argmin(np.where(match, d, np.inf), axis=1)
    found = np.any(match, axis=1)
    # no solution in the configuration: the nearest converged one, in any configuration
    anyconv = r.converged.reshape(N, K)
    fallback = np.argmin(np.where(anyconv, np.sum((q - near) ** 2, axis=-1), np.inf), axis=1)
    idx = np.where(found, best, fallback)
    rows = np.arange(N)
    return np.where(found[:, None], qs[rows, idx], q[rows, idx]), found


__all__ = [
    "REFERENCE",
    "abb_confdata",
    "arm_flags",
    "configured_ik",
    "fanuc_config",
    "fanuc_wpr_to_matrix",
    "joint_codes",
    "kuka_abc_to_matrix",
    "kuka_status_turn",
    "matrix_to_fanuc_wpr",
    "matrix_to_kuka_abc",
    "quat_near",
]
