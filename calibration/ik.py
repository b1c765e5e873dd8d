"""Inverse kinematics, batched over N task points.

- :func:`geometric_jacobian`: the robot's Jacobian with respect to the joint *readings*
  (analytic, from the same program walk as the forward kinematics): ``J = J_v · dv/dq`` where
  ``v = C·q + harmonic`` (:func:`calibration.kinematics.joint_variables`) are the joint
  variables and ``J_v`` the usual geometric Jacobian (book eq. 5.43's ``J``, tool-point form).
- :func:`ur_ik`: the closed-form inverse kinematics of the Universal Robots structure (three
  parallel axes 2-3-4 and a non-spherical wrist; UR3e/5e/10e/16e), its 8 branches selected by the
  shoulder, elbow and wrist flags of :func:`ur_branch`.
- :func:`solve_ik`: damped Newton (Levenberg–Marquardt) for any model, all points iterating
  together; points that have converged are masked out.
- :func:`numerical_ik`: inverse kinematics of any model (no closed form needed), batched:
  damped Newton from each point's own seed (its taught or planned joints, else ``q_near``), then
  from the previous point's solution, then from a few seeds spread over the joint limits for the
  points still not solved; the solution nearest the point's own seed is kept.
- :func:`inverse_kinematics`: the nominal solution of a task point: closed form where the model
  has UR structure (then polished by Newton, which only matters with gear harmonics), else
  :func:`numerical_ik`.

Pose errors are ``e = [p_d − p; rotvec(R_d·Rᵀ)]`` in world axes (tool-point translation and the
world-frame small rotation, the consistent pair of ch5 §2.3), so ``J·dq = e`` is the Newton step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .kinematics import check_q, joint_variables, walk
from .model import KinematicModel
from .transforms import invert, matrix_to_rotvec, pose_to_matrix

TWO_PI = 2.0 * math.pi
# Twist angles of the Universal Robots DH table (rad).
UR_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)


# ----------------------------------------------------------------------------- Jacobian


def _joint_keys(model: KinematicModel) -> list[str]:
    return [f"{j.name}.theta" if j.revolute else f"{j.name}.d" for j in model.joints]


def reading_derivative(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """``dv/dq`` (N, n, n): how the joint variables move with the readings (``C`` plus the
    derivative of each joint's gear harmonic ``A·k·cos(k·q_i + phi)``, book eq. 2.4)."""
    q = check_q(model, q)
    D = np.broadcast_to(model.coupling_matrix, (q.shape[0],) + model.coupling_matrix.shape).copy()
    for i, j in enumerate(model.joints):
        if j.harmonic is not None:
            amp, freq, phase = j.harmonic
            D[:, i, i] += amp * freq * np.cos(freq * q[:, i] + phase)
    return D


def pose_and_jacobian(model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``R_world_tool`` (N, 3, 3), ``p_world_tool`` (N, 3) and the geometric Jacobian (N, 6, n)
    with respect to the readings ``q`` (N, n), from one walk of the chain.

    Rows 0-2: ``d p_world_tool / dq`` (m per rad, or per m); rows 3-5: the world-frame angular
    velocity of the tool per unit reading. A revolute joint variable about world axis ``u``
    through ``o`` gives the column ``[u × (p − o); u]``, a prismatic one ``[u; 0]``.
    """
    q = check_q(model, q)
    keys = _joint_keys(model)
    w = walk(model, q, set(keys))
    N, n = q.shape
    Jv = np.zeros((N, 6, n))
    for i, (j, key) in enumerate(zip(model.joints, keys)):
        u, o = w.axes[key]
        if j.revolute:
            Jv[:, :3, i] = np.cross(u, w.p - o)
            Jv[:, 3:, i] = u
        else:
            Jv[:, :3, i] = u
    if model.coupling is None and all(j.harmonic is None for j in model.joints):
        gains = np.array([j.gain for j in model.joints])
        J = Jv if np.all(gains == 1.0) else Jv * gains
    else:
        J = Jv @ reading_derivative(model, q)
    return w.R, w.p, J


def geometric_jacobian(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """The geometric Jacobian (N, 6, n) of the tool frame w.r.t. the readings (see
    :func:`pose_and_jacobian`)."""
    return pose_and_jacobian(model, q)[2]


def pose_error(T_desired: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``[p_d − p; rotvec(R_d·Rᵀ)]`` (N, 6), world axes: what the tool frame (R, p) still has to
    move to reach ``T_desired`` (N, 4, 4)."""
    dp = T_desired[:, :3, 3] - p
    dr = matrix_to_rotvec(T_desired[:, :3, :3] @ np.swapaxes(R, -1, -2))
    return np.concatenate([dp, dr], axis=1)


def characteristic_length(model: KinematicModel) -> float:
    """A length (m) that makes a rotation comparable with a translation: the robot's reach,
    estimated as the sum of its link lengths and offsets (at least 0.1 m)."""
    if model.convention == "poe":
        pts = [j.axis_point()[1] for j in model.joints] + [model.poe_home()[:3]]
        reach = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    else:
        reach = float(sum(abs(j.a) + abs(j.d) for j in model.joints))
    return max(reach + float(np.linalg.norm(model.tool[:3])), 0.1)


def singular_values(model: KinematicModel, J: np.ndarray, *, length_scale_m: float | None = None) -> np.ndarray:
    """Singular values (N, min(6, n)) of the Jacobian made dimensionless: position rows divided
    by the robot's reach, prismatic columns likewise multiplied by 1/reach (so a value is "rad of
    tool motion per rad of joint motion")."""
    L = length_scale_m or characteristic_length(model)
    Js = J.copy()
    Js[:, :3, :] /= L
    for i, j in enumerate(model.joints):
        if not j.revolute:
            Js[:, :, i] *= L
    # eigenvalues of the small Gram matrix: twice as fast as an SVD of the batch, and accurate
    # far below any singularity threshold (values under ~1e-8 are rounding noise either way)
    G = Js @ np.swapaxes(Js, 1, 2) if Js.shape[2] >= 6 else np.swapaxes(Js, 1, 2) @ Js
    return np.sqrt(np.clip(np.linalg.eigvalsh(G), 0.0, None))[:, ::-1][:, : min(6, Js.shape[2])]


# ----------------------------------------------------------------------------- UR closed form


@dataclass(frozen=True, slots=True)
class URGeometry:
    """The numbers the UR closed form needs, SI: ``d1, a2, a3, d4`` (with ``d2 + d3`` folded in:
    offsets along the parallel axes 2-4 commute), ``d5, d6``; the joint offsets ``theta`` (6,);
    ``T_base`` and ``T_tool`` (4, 4)."""

    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float
    theta: np.ndarray
    T_base: np.ndarray
    T_tool: np.ndarray


def ur_geometry(model: KinematicModel, *, tol: float = 1e-9) -> URGeometry | None:
    """The UR structure of ``model``, or ``None`` when it has none: standard DH, six revolute
    joints, twists (90°, 0, 0, 90°, −90°, 0), ``a1 = a4 = a5 = a6 = 0``, no Hayati ``beta``
    other than an exact 0, an invertible coupling. (An identified robot is "near-simple" and has
    no such structure, book ch. 5 intro; its inverse is found by Newton from the nominal one.)"""
    if model.convention != "dh" or model.n_joints != 6:
        return None
    js = model.joints
    for j, alpha in zip(js, UR_ALPHA):
        if not j.revolute or abs(math.remainder(j.alpha - alpha, TWO_PI)) > tol:
            return None
        if j.beta is not None and abs(j.beta) > tol:
            return None
    if any(abs(js[i].a) > tol for i in (0, 3, 4, 5)):
        return None
    if abs(np.linalg.det(model.coupling_matrix)) < 1e-12:
        return None
    if not (abs(js[1].a) > tol and abs(js[2].a) > tol and abs(js[5].d) > tol):
        return None
    return URGeometry(
        d1=js[0].d,
        a2=js[1].a,
        a3=js[2].a,
        d4=js[1].d + js[2].d + js[3].d,
        d5=js[4].d,
        d6=js[5].d,
        theta=np.array([j.theta for j in js]),
        T_base=pose_to_matrix(model.base),
        T_tool=pose_to_matrix(model.tool),
    )


def _variables(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """:func:`calibration.kinematics.joint_variables`, with the common case (no coupling, no
    harmonics) done as a product by the gains, several times faster than ``q @ C.T`` on a batch."""
    if model.coupling is None and all(j.harmonic is None for j in model.joints):
        return check_q(model, q) * np.array([j.gain for j in model.joints])
    return joint_variables(model, q)


def _flange(g: URGeometry, T_world_tool: np.ndarray) -> np.ndarray:
    """``T_0_6`` (N, 4, 4): the flange in DH frame 0, base and tool removed."""
    return invert(g.T_base) @ np.asarray(T_world_tool, dtype=float) @ invert(g.T_tool)


def ur_branch(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Configuration flags (N, 3) of readings ``q`` on a UR-structured model, each ±1:
    shoulder = sign of the wrist centre's reach along the arm's forward direction,
    ``p05 · (cos θ1, sin θ1, 0) = a2·cos θ2 + a3·cos θ23 + d5·sin θ234``; elbow = sign(sin θ3);
    wrist = sign(sin θ5), with θ the DH angles. A zero counts as +1."""
    g = ur_geometry(model)
    if g is None:
        raise ValueError(f"model {model.name!r} does not have the Universal Robots structure")
    th = _variables(model, q) + g.theta
    t23, t234 = th[:, 1] + th[:, 2], th[:, 1] + th[:, 2] + th[:, 3]
    shoulder = g.a2 * np.cos(th[:, 1]) + g.a3 * np.cos(t23) + g.d5 * np.sin(t234)
    flags = np.stack([shoulder, np.sin(th[:, 2]), np.sin(th[:, 4])], axis=1)
    return np.where(flags < 0, -1, 1)


def ur_ik(
    model: KinematicModel,
    T_world_tool: np.ndarray,
    branch: np.ndarray,
    q_near: np.ndarray,
    *,
    singular_tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form inverse kinematics of a UR-structured model, one branch per point.

    ``T_world_tool`` (N, 4, 4); ``branch`` (N, 3) or (3,) flags ±1 (shoulder, elbow, wrist, see
    :func:`ur_branch`); ``q_near`` (N, 6) or (6,) readings whose joint turns the solution keeps
    (each joint variable is moved by whole turns to the one nearest ``q_near``'s) and whose θ6
    is taken when the wrist is singular (sin θ5 = 0). Returns readings (N, 6) and ``reachable``
    (N,) (False where an arccos argument left [-1, 1]: the pose is out of reach in that branch;
    the argument is then clipped and the readings are the nearest the branch can do).

    Derivation (standard DH, Hawkins' analysis of the UR arm): with ``z1 = (sin θ1, −cos θ1, 0)``
    the common direction of axes 2-4, the wrist centre ``p05 = p06 − d6·z6`` satisfies
    ``p05·z1 = d4`` (θ1, shoulder flag); ``p06·z1 = d4 + d6·cos θ5`` (θ5, wrist flag);
    ``x6·z1 = sin θ5 cos θ6``, ``y6·z1 = −sin θ5 sin θ6`` (θ6); the planar 2-link problem in
    frame 1 gives θ3 (elbow flag) and θ2; θ4 = θ234 − θ2 − θ3.
    """
    g = ur_geometry(model)
    if g is None:
        raise ValueError(f"model {model.name!r} does not have the Universal Robots structure")
    T06 = _flange(g, T_world_tool)
    if T06.ndim == 2:
        T06 = T06[None]
    N = T06.shape[0]
    branch = np.broadcast_to(np.asarray(branch, dtype=float), (N, 3))
    s_sh, s_el, s_wr = (
        np.where(branch[:, 0] < 0, -1.0, 1.0),
        np.where(branch[:, 1] < 0, -1.0, 1.0),
        np.where(branch[:, 2] < 0, -1.0, 1.0),
    )
    q_near = np.broadcast_to(np.asarray(q_near, dtype=float), (N, 6))
    th_near = _variables(model, q_near) + g.theta
    p06 = T06[:, :3, 3]
    x6, y6, z6 = T06[:, :3, 0], T06[:, :3, 1], T06[:, :3, 2]
    p05 = p06 - g.d6 * z6
    r = np.hypot(p05[:, 0], p05[:, 1])
    phi = np.arctan2(p05[:, 1], p05[:, 0])
    ratio = g.d4 / np.where(r > 0, r, 1e-300)
    ok = np.abs(ratio) <= 1.0
    asn = np.arcsin(np.clip(ratio, -1.0, 1.0))
    th1 = np.where(s_sh > 0, phi + asn, phi + math.pi - asn)
    z1 = np.stack([np.sin(th1), -np.cos(th1), np.zeros(N)], axis=1)
    c5 = (np.einsum("ni,ni->n", p06, z1) - g.d4) / g.d6
    ok &= np.abs(c5) <= 1.0
    th5 = s_wr * np.arccos(np.clip(c5, -1.0, 1.0))
    s5 = np.sin(th5)
    sing = np.abs(s5) < singular_tol
    xz, yz = np.einsum("ni,ni->n", x6, z1), np.einsum("ni,ni->n", y6, z1)
    th6 = np.where(sing, th_near[:, 5], np.arctan2(-yz * s_wr, xz * s_wr))
    # frame 4 from the flange: R46 = Rz(θ5)·Rx(−90°)·Rz(θ6), so x4 = c5c6·x6 − c5s6·y6 − s5·z6,
    # z4 = −s6·x6 − c6·y6, and o4 = o5 − d5·z4; in frame 1 (x1 = (c1, s1, 0), y1 = (0, 0, 1),
    # origin (0, 0, d1)) the planar arm's end is (x1·o4, o4z − d1) and θ234 = atan2(x4z, x1·x4).
    c5, c6, s6 = np.cos(th5), np.cos(th6), np.sin(th6)
    x4 = (c5 * c6)[:, None] * x6 - (c5 * s6)[:, None] * y6 - s5[:, None] * z6
    z4 = -s6[:, None] * x6 - c6[:, None] * y6
    o4 = p05 - g.d5 * z4
    c1, s1 = np.cos(th1), np.sin(th1)
    x = c1 * o4[:, 0] + s1 * o4[:, 1]
    y = o4[:, 2] - g.d1
    c3 = (x * x + y * y - g.a2**2 - g.a3**2) / (2.0 * g.a2 * g.a3)
    ok &= np.abs(c3) <= 1.0
    th3 = s_el * np.arccos(np.clip(c3, -1.0, 1.0))
    th2 = np.arctan2(y, x) - np.arctan2(g.a3 * np.sin(th3), g.a2 + g.a3 * np.cos(th3))
    th234 = np.arctan2(x4[:, 2], c1 * x4[:, 0] + s1 * x4[:, 1])
    th4 = th234 - th2 - th3
    th = np.stack([th1, th2, th3, th4, th5, th6], axis=1)
    # keep the joint turns of q_near: whole turns of the joint variable (the physical angle)
    th = th + TWO_PI * np.round((th_near - th) / TWO_PI)
    v = th - g.theta
    C = model.coupling_matrix
    q = v if np.allclose(C, np.eye(6)) else np.linalg.solve(C, v.T).T
    return q, ok


def ur_ik_all(
    model: KinematicModel, T_world_tool: np.ndarray, q_near: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All 8 closed-form solutions: readings (N, 8, 6), ``reachable`` (N, 8) and the branch
    flags (8, 3) (index bits: shoulder, elbow, wrist; bit set = −1)."""
    T = np.asarray(T_world_tool, dtype=float)
    T = T[None] if T.ndim == 2 else T
    q_near = np.zeros(6) if q_near is None else q_near
    flags = np.array([[-1 if (b >> k) & 1 else 1 for k in range(3)] for b in range(8)])
    qs, oks = [], []
    for f in flags:
        q, ok = ur_ik(model, T, f, q_near)
        qs.append(q)
        oks.append(ok)
    return np.stack(qs, axis=1), np.stack(oks, axis=1), flags


# ----------------------------------------------------------------------------- damped Newton


@dataclass(frozen=True, eq=False)
class IKResult:
    """Inverse kinematics of N points. ``q`` (N, n) readings; ``converged`` (N,) both residuals
    within tolerance; ``residual_m`` (N,) remaining position error; ``residual_rad`` (N,)
    remaining orientation error; ``iterations`` (N,); ``reachable`` (N,) False where a closed
    form found the pose out of reach (:func:`numerical_ik`: where no seed converged);
    ``branch_changed`` (N,) or None: True where :func:`numerical_ik` solved a point that has a
    taught configuration only from another seed, and the solution lies in another branch than
    the taught joints (the sign of det J differs; 6-joint robots)."""

    q: np.ndarray
    converged: np.ndarray
    residual_m: np.ndarray
    residual_rad: np.ndarray
    iterations: np.ndarray
    reachable: np.ndarray
    jacobian: np.ndarray | None = None
    jacobian_start: np.ndarray | None = None
    branch_changed: np.ndarray | None = None

    @property
    def success(self) -> bool:
        return bool(np.all(self.converged))


def solve_ik(
    model: KinematicModel,
    T_world_tool: np.ndarray,
    q0: np.ndarray,
    *,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
    max_iterations: int = 50,
    max_step_rad: float = 0.5,
    length_scale_m: float | None = None,
) -> IKResult:
    """Readings that bring ``model``'s tool frame to ``T_world_tool`` (N, 4, 4), by damped Newton
    (Levenberg–Marquardt) from ``q0`` (N, n), all points together.

    Each iteration solves ``(JᵀJ + μ·tr(JᵀJ)/n·I) dq = Jᵀe`` on the dimensionless problem
    (position rows divided by the robot's reach), accepts the step where it lowers ``|e|`` (μ /= 10)
    and refuses it elsewhere (μ *= 10), so a point near a singularity takes short safe steps and
    one far from it takes Newton steps (quadratic convergence). The step is capped at
    ``max_step_rad`` per joint, and nothing wraps angles: the solution stays on the turns of
    ``q0``. Points stop when both residuals are within tolerance (converged), or when the
    damping has grown without any progress (not converged).
    """
    q = check_q(model, q0).copy()
    T = np.asarray(T_world_tool, dtype=float)
    T = T[None] if T.ndim == 2 else T
    N = q.shape[0]
    if T.shape != (N, 4, 4):
        raise ValueError(f"`T_world_tool` must have shape ({N}, 4, 4); got {T.shape}")
    L = length_scale_m or characteristic_length(model)
    col = np.array([1.0 if j.revolute else 1.0 / L for j in model.joints])  # dimensionless columns
    cap = max_step_rad * np.array([1.0 if j.revolute else L for j in model.joints])
    R, p, J = pose_and_jacobian(model, q)
    J_start = J.copy()
    e = pose_error(T, R, p)
    iterations = np.zeros(N, dtype=int)
    mu = np.full(N, 1e-12)

    def done(err):
        return (np.linalg.norm(err[:, :3], axis=1) <= position_tol_m) & (
            np.linalg.norm(err[:, 3:], axis=1) <= rotation_tol_rad
        )

    def scaled(err):
        return np.concatenate([err[:, :3] / L, err[:, 3:]], axis=1)

    converged = done(e)
    active = ~converged
    for _ in range(max_iterations):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        es = scaled(e[idx])
        dq = _damped_newton_step(J[idx], es, mu[idx], col, L, cap)
        q_try = q[idx] + dq
        R2, p2, J2 = pose_and_jacobian(model, q_try)
        e2 = pose_error(T[idx], R2, p2)
        better = np.sum(scaled(e2) ** 2, axis=1) < np.sum(es**2, axis=1)
        acc = idx[better]
        q[acc], e[acc], J[acc] = q_try[better], e2[better], J2[better]
        mu[acc] = np.maximum(mu[acc] / 10.0, 1e-15)
        rej = idx[~better]
        mu[rej] *= 10.0
        iterations[idx] += 1
        now = done(e[idx])
        converged[idx[now]] = True
        stuck = (mu[idx] > 1e6) | (np.max(np.abs(dq) / cap, axis=1) < 1e-15)
        active[idx[now | stuck]] = False
    return IKResult(
        q=q,
        converged=converged,
        residual_m=np.linalg.norm(e[:, :3], axis=1),
        residual_rad=np.linalg.norm(e[:, 3:], axis=1),
        iterations=iterations,
        reachable=np.ones(N, dtype=bool),
        jacobian=J,
        jacobian_start=J_start,
    )


def _damped_newton_step(
    J: np.ndarray, es: np.ndarray, mu: np.ndarray, col: np.ndarray, L: float, cap: np.ndarray
) -> np.ndarray:
    """The Levenberg–Marquardt step dq (k, n) of :func:`solve_ik` for k points: Jacobians ``J``
    (k, 6, n), scaled pose errors ``es`` (k, 6), damping ``mu`` (k,). On the dimensionless
    problem (columns times ``col``, position rows over the length ``L``) it solves
    ``(JᵀJ + μ·tr(JᵀJ)/n·I) dq = Jᵀe``, then shrinks each point's step so that no joint moves
    more than its ``cap``."""
    n = J.shape[2]
    Js = J * col
    Js[:, :3, :] /= L
    A = np.einsum("nki,nkj->nij", Js, Js)
    g = np.einsum("nki,nk->ni", Js, es)
    tr = np.trace(A, axis1=1, axis2=2) / n
    damp = (mu * np.maximum(tr, 1e-300))[:, None, None] * np.eye(n)
    dq = np.linalg.solve(A + damp, g[:, :, None])[:, :, 0] * col
    over = np.max(np.abs(dq) / cap, axis=1)
    dq /= np.maximum(over, 1.0)[:, None]
    return dq


def spread_seeds(model: KinematicModel, count: int) -> np.ndarray:
    """``count`` readings (count, n) spread over the joint limits (revolute joints within ±π), the
    same every call: a Halton sequence (bases 2, 3, 5, ...), which covers the box more evenly than
    random draws of the same number."""
    lim = model.joint_limits.copy()
    for i, j in enumerate(model.joints):
        if j.revolute:
            lim[i] = np.clip(lim[i], -math.pi, math.pi)
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71]
    u = np.empty((count, model.n_joints))
    for i in range(model.n_joints):
        base = primes[i % len(primes)]
        for k in range(count):
            f, x, m = 1.0, 0.0, k + 1
            while m:
                f /= base
                x += f * (m % base)
                m //= base
            u[k, i] = x
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


def _branch_sign(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """The configuration branch as the sign of det J (N,) (6-joint robots; 0 elsewhere)."""
    if model.n_joints != 6 or len(q) == 0:
        return np.zeros(len(q))
    return np.sign(np.linalg.det(geometric_jacobian(model, q)))


def wrap_into_limits(model: KinematicModel, q: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """Readings ``q`` (N, n) with each revolute joint moved by whole turns, where a turn is the
    same pose (the reading is the joint angle: gain 1, no coupling, no gear harmonic): to the turn
    nearest ``near`` (N, n) when that one is within the joint's limits, else, for a joint outside
    its limits, into them where some turn fits. Other joints unchanged."""
    q = np.array(q, dtype=float)
    if model.coupling is not None:
        return q
    lim = model.joint_limits
    for i, j in enumerate(model.joints):
        if not j.revolute or j.gain != 1.0 or j.harmonic is not None:
            continue
        lo, hi = lim[i]
        if near is not None:
            turned = q[:, i] + TWO_PI * np.round((near[:, i] - q[:, i]) / TWO_PI)
            q[:, i] = np.where((turned >= lo) & (turned <= hi), turned, q[:, i])
        out = (q[:, i] < lo) | (q[:, i] > hi)
        if np.any(out):
            moved = q[out, i] - TWO_PI * np.ceil((q[out, i] - hi) / TWO_PI)  # the highest turn not above hi
            q[out, i] = np.where(moved >= lo, moved, q[out, i])
    return q


def _inside(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    lim = model.joint_limits
    return np.all((q >= lim[:, 0]) & (q <= lim[:, 1]), axis=-1)


def numerical_ik(
    model: KinematicModel,
    T_world_tool: np.ndarray,
    q_near: np.ndarray,
    *,
    taught: bool | np.ndarray = False,
    n_seeds: int = 24,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
    max_iterations: int = 50,
    max_chain: int = 32,
) -> IKResult:
    """Inverse kinematics of any model (no closed form needed): readings (N, n) with ``model``'s
    tool at ``T_world_tool`` (N, 4, 4), all points solved together by damped Newton
    (:func:`solve_ik`), each from a sequence of seeds until one gives a solution within the joint
    limits (:func:`wrap_into_limits` first puts revolute joints on the turn nearest the point's own
    seed, or into the limits, where a turn is the same pose):

    1. the point's own seed ``q_near`` (N, n) or (n,): its taught or planned joints where
       ``taught`` (a bool, or one per point) says it has some, else a configuration near which
       the solution is wanted (``--qnear``);
    2. the previous point's solution (a task is a path: the neighbour's configuration is usually
       a few degrees away, in the same branch), repeated while it solves more points, at most
       ``max_chain`` times;
    3. ``n_seeds`` configurations spread over the joint limits (:func:`spread_seeds`), those
       nearest the point's own seed first, four at a time until a group solves the point; of
       that group's solutions the one nearest the point's own seed is kept (as a UR controller's
       ``get_inverse_kin(x, qnear)`` takes the nearest closed-form solution); then step 2 again
       for the points after the newly solved ones.

    A converged solution outside the joint limits is kept when no seed finds one inside (it is
    then flagged by :func:`calibration.compensation.assess`). ``reachable`` is False where no
    seed converged (the pose is out of reach, or too near a singularity for Newton); the best
    attempt is returned there. ``branch_changed`` is True where a taught point was solved only
    from another seed and the solution's branch (sign of det J) differs from the taught joints'.
    """
    T = np.asarray(T_world_tool, dtype=float)
    T = T[None] if T.ndim == 2 else T
    N, n = T.shape[0], model.n_joints
    seed = np.broadcast_to(check_q(model, np.asarray(q_near, dtype=float).reshape(-1, n)), (N, n)).copy()
    taught = np.broadcast_to(np.asarray(taught, dtype=bool), (N,))
    kw: dict[str, Any] = dict(
        position_tol_m=position_tol_m, rotation_tol_rad=rotation_tol_rad, max_iterations=max_iterations
    )
    best = _Attempts(model, T, seed, kw)
    best.keep(np.arange(N), solve_ik(model, T, seed, **kw))
    own = best.rank == -2.0  # solved from the point's own seed
    best.chain(max_chain)
    if n_seeds > 0 and np.any(best.rank > -2.0):
        best.spread(n_seeds)
        best.chain(max_chain)
    q, conv = best.q, best.conv
    changed = taught & conv & ~own
    if np.any(changed):
        k = np.nonzero(changed)[0]
        changed[k] = _branch_sign(model, q[k]) != _branch_sign(model, seed[k])
    return IKResult(
        q=q,
        converged=conv,
        residual_m=best.res_m,
        residual_rad=best.res_rad,
        iterations=best.iters,
        reachable=conv.copy(),
        branch_changed=changed,
    )


class _Attempts:
    """:func:`numerical_ik`'s best attempt per point so far, ranked: solved (converged, inside the
    limits) > converged > closest; ``seed`` (N, n) the points' own seeds, ``kw`` :func:`solve_ik`'s
    tolerances."""

    def __init__(self, model: KinematicModel, T: np.ndarray, seed: np.ndarray, kw: dict[str, Any]):
        N = len(T)
        self.model, self.T, self.seed, self.kw = model, T, seed, kw
        self.L = characteristic_length(model)
        self.q = seed.copy()
        self.conv = np.zeros(N, dtype=bool)
        self.rank = np.full(N, np.inf)
        self.res_m, self.res_rad = np.full(N, np.inf), np.full(N, np.inf)
        self.iters = np.zeros(N, dtype=int)
        self.tried_prev = np.zeros(N, dtype=bool)

    def score(self, r, idx):
        """Lower is better: -2 solved, -1 converged outside the limits, else the residual size.
        Revolute joints are first put on the turn nearest the point's own seed."""
        model = self.model
        qw = wrap_into_limits(model, r.q, self.seed[idx])
        s = np.where(r.converged, np.where(_inside(model, qw), -2.0, -1.0), r.residual_m + self.L * r.residual_rad)
        return qw, s

    def keep(self, idx, r) -> None:
        qw, s = self.score(r, idx)
        take = s < self.rank[idx]
        t = idx[take]
        self.q[t], self.conv[t], self.rank[t] = qw[take], r.converged[take], s[take]
        self.res_m[t], self.res_rad[t] = r.residual_m[take], r.residual_rad[take]
        self.iters[idx] += r.iterations

    def chain(self, max_chain: int) -> None:
        """Step 2: the previous point's solution as the seed, while it solves more points."""
        rank, tried_prev = self.rank, self.tried_prev
        for _ in range(max_chain):
            idx = np.nonzero((rank[1:] > -2.0) & (rank[:-1] == -2.0) & ~tried_prev[1:])[0] + 1
            if idx.size == 0:
                return
            tried_prev[idx] = True
            self.keep(idx, solve_ik(self.model, self.T[idx], self.q[idx - 1], **self.kw))

    def spread(self, n_seeds: int) -> None:
        """Step 3: the spread seeds nearest each point's own seed first, ``group`` at a time,
        stopping at the first group that solves it: the nearest of that group's solutions is kept."""
        model, T, seed, n = self.model, self.T, self.seed, self.model.n_joints
        seeds = spread_seeds(model, n_seeds)
        order = np.argsort(np.sum((seed[:, None, :] - seeds[None, :, :]) ** 2, axis=2), axis=1)
        group = 4
        for start in range(0, len(seeds), group):
            idx = np.nonzero(self.rank > -2.0)[0]
            if idx.size == 0:
                break
            cols = order[idx, start : start + group]
            S = cols.shape[1]
            r = solve_ik(model, np.repeat(T[idx], S, axis=0), seeds[cols.reshape(-1)], **self.kw)
            qw, sc = self.score(r, np.repeat(idx, S))
            qw, sc = qw.reshape(idx.size, S, n), sc.reshape(idx.size, S)
            near = np.sum((qw - seed[idx][:, None, :]) ** 2, axis=2)
            best = np.argmin(np.where(sc == sc.min(axis=1, keepdims=True), np.where(sc < 0, near, 0.0), np.inf), axis=1)
            pick = np.arange(idx.size) * S + best
            self.keep(
                idx,
                IKResult(
                    q=r.q[pick],
                    converged=r.converged[pick],
                    residual_m=r.residual_m[pick],
                    residual_rad=r.residual_rad[pick],
                    iterations=r.iterations.reshape(idx.size, S).sum(axis=1),
                    reachable=np.ones(idx.size, dtype=bool),
                ),
            )


def inverse_kinematics(
    model: KinematicModel,
    T_world_tool: np.ndarray,
    q_near: np.ndarray,
    *,
    keep_branch: bool | np.ndarray = True,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
    max_iterations: int = 50,
) -> IKResult:
    """The nominal solution of task points: readings (N, n) with ``model``'s tool at
    ``T_world_tool`` (N, 4, 4).

    Where ``model`` has the UR structure: the closed form (:func:`ur_ik`) in the branch of
    ``q_near`` (``keep_branch``, a bool or one per point: for taught or planned
    configurations) or, without it, the
    branch whose solution is nearest ``q_near`` (what a UR controller's ``get_inverse_kin(x,
    qnear)`` does), on ``q_near``'s joint turns; then Newton polishes the points the closed form
    leaves above tolerance (gear harmonics). Elsewhere: :func:`numerical_ik`, from ``q_near``
    (the taught joints where ``keep_branch``, whose branch it keeps where Newton from them
    converges), the previous point's solution, and seeds spread over the joint limits. (A
    numerical IK from far away can land on any branch, ch5 §10: taught joints are the safe
    start.)"""
    T = np.asarray(T_world_tool, dtype=float)
    T = T[None] if T.ndim == 2 else T
    N = T.shape[0]
    q_near = np.broadcast_to(
        check_q(model, np.asarray(q_near, dtype=float).reshape(-1, model.n_joints)), (N, model.n_joints)
    ).copy()
    kw: dict[str, Any] = dict(
        position_tol_m=position_tol_m, rotation_tol_rad=rotation_tol_rad, max_iterations=max_iterations
    )
    if ur_geometry(model) is None:
        return numerical_ik(model, T, q_near, taught=keep_branch, **kw)
    keep = np.broadcast_to(np.asarray(keep_branch, dtype=bool), (N,))
    q0 = np.empty_like(q_near)
    ok = np.zeros(N, dtype=bool)
    if np.any(keep):
        q0[keep], ok[keep] = ur_ik(model, T[keep], ur_branch(model, q_near[keep]), q_near[keep])
    if not np.all(keep):
        free = ~keep
        qs, oks, _ = ur_ik_all(model, T[free], q_near[free])
        dist = np.sum((qs - q_near[free][:, None, :]) ** 2, axis=2) + np.where(oks, 0.0, 1e6)
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(best))
        q0[free], ok[free] = qs[rows, best], oks[rows, best]
    return _polish(model, T, q0, ok, kw)


def _polish(model: KinematicModel, T: np.ndarray, q0: np.ndarray, ok: np.ndarray, kw: dict) -> IKResult:
    """The closed form's result; Newton refines it only where the model has gear harmonics (the
    closed form ignores them), elsewhere it is exact to rounding."""
    N = len(q0)
    if all(j.harmonic is None for j in model.joints):
        z = np.zeros(N)
        return IKResult(
            q=q0,
            converged=ok.copy(),
            residual_m=z,
            residual_rad=z.copy(),
            iterations=np.zeros(N, dtype=int),
            reachable=ok,
        )
    r = solve_ik(model, T, q0, **kw)
    return IKResult(
        q=r.q,
        converged=r.converged & ok,
        residual_m=r.residual_m,
        residual_rad=r.residual_rad,
        iterations=r.iterations,
        reachable=ok,
    )
