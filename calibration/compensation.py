"""Compensation: the commands that make the identified robot reach its task (book ch. 5,
"inverse calibration"), batched over N task points.

Three tasks, one result type (:class:`CompensatedPoints`):

- :func:`compensate_joints` — off-line programmed tasks, joint commands (book §5.2.1, eq. 5.19,
  5.30): Newton on the *identified* model, started from the nominal solution, so the command
  keeps the nominal configuration branch and joint turns.
- :func:`compensate_targets` — corrected targets for a controller that only knows the nominal
  model (book §5.2.2, eq. 5.55, "Algorithm B"): ``X_m ← X_m + (X_d − F_c(F_n⁻¹(X_m)))`` until the
  identified robot, driven by the nominal inverse kinematics, reaches ``X_d``.
- :func:`compensate_taught` — taught tasks (book eq. 5.21-5.22): joint vectors taught on one
  robot, mapped to another so that the second reaches the pose the first reached.

:func:`inverse_jacobian_iteration` is the book's own Algorithm A (§5.2.1, nominal Jacobian,
linear convergence) with its sign corrected; it is kept as a cross-check (T17 of the ch. 5
catalogue: A, B and Newton agree).

Frames. ``T_desired`` is in the world frame of the identified model (the instrument's). The
nominal model has its own world (for a library robot, the robot's base frame: what its
controller works in). ``T_nominal_world`` (4, 4) maps world coordinates into the nominal's; use
:func:`frame_map` to estimate it (the rigid transform under which the nominal model best
matches the identified one), or the identity when both share the world.

Every point reports ``converged``, the residual position (m) and orientation (rad) error, the
correction applied and flags (:data:`FLAGS`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .ik import (
    IKResult,
    _polish,
    characteristic_length,
    inverse_kinematics,
    pose_and_jacobian,
    pose_error,
    singular_values,
    solve_ik,
    ur_branch,
    ur_geometry,
    ur_ik,
)
from .kinematics import check_q, fk, walk
from .metrics import outside_joint_ranges
from .model import KinematicModel
from .registration import kabsch
from .simulate import random_configurations
from .transforms import invert, rotvec_to_matrix

FLAGS = (
    "joint_limit",
    "near_singular",
    "outside_calibrated_region",
    "no_convergence",
    "branch_change",
    "unreachable",
    "outside_mapped_region",
)
"""Flag names, in bit order: ``joint_limit`` the command is outside the model's joint limits;
``near_singular`` the smallest dimensionless singular value of the identified robot's Jacobian
at the command is below ``singular_tol``; ``outside_calibrated_region`` the command is outside
the joint ranges the calibration measured; ``no_convergence`` the residual did not reach the
tolerance; ``branch_change`` the command crossed a singular surface from the nominal solution
(the sign of det J changed), the correction exceeds ``max_correction_rad`` (a large correction
is a branch or singularity problem, ch5 §10), or a numerical nominal inverse reached a taught
point only in another branch than the taught joints'; ``unreachable`` the nominal inverse
kinematics found the pose out of reach (closed form) or no seed reached it (numerical);
``outside_mapped_region`` (set by ``recal compensate`` for a model with a residual map,
:mod:`calibration.residual_map`) the command is outside the region the map was fitted in, so
only the parametric model corrected it."""

FLAG_BIT = {name: 1 << k for k, name in enumerate(FLAGS)}


def flag_names(bits: int) -> list[str]:
    """The names of the flags set in ``bits``, in :data:`FLAGS` order."""
    return [name for name in FLAGS if int(bits) & FLAG_BIT[name]]


@dataclass(frozen=True, eq=False)
class CompensatedPoints:
    """Compensated task points (N), SI.

    ``q`` (N, n): the joint commands (joints and taught modes: for the identified robot; targets
    mode: what the nominal controller's inverse kinematics makes of ``T_command``).
    ``T_command`` (N, 4, 4): targets mode, the corrected targets in the nominal model's world;
    otherwise the desired poses. ``T_desired`` (N, 4, 4): the poses the identified robot must
    reach, world frame. ``q_nominal`` (N, n): the nominal solution the correction started from;
    ``correction`` (N, n) = ``q − q_nominal``. ``converged`` (N,), ``residual_m`` (N,) and
    ``residual_rad`` (N,): what remains between the identified robot at ``q`` and
    ``T_desired``. ``iterations`` (N,); ``sigma_min`` (N,) the smallest dimensionless singular
    value of the identified Jacobian at ``q``; ``flags`` (N,) bit set of :data:`FLAGS`.
    """

    q: np.ndarray
    T_command: np.ndarray
    T_desired: np.ndarray
    q_nominal: np.ndarray
    correction: np.ndarray
    converged: np.ndarray
    residual_m: np.ndarray
    residual_rad: np.ndarray
    iterations: np.ndarray
    sigma_min: np.ndarray
    flags: np.ndarray
    mode: str
    message: str

    @property
    def success(self) -> bool:
        return bool(np.all(self.converged))

    def __len__(self) -> int:
        return len(self.q)

    def flags_of(self, i: int) -> list[str]:
        return flag_names(self.flags[i])

    def count(self, flag: str) -> int:
        return int(np.count_nonzero(self.flags & FLAG_BIT[flag]))


# ----------------------------------------------------------------------------- frames


def frame_map(model_from: KinematicModel, model_to: KinematicModel, q_samples: np.ndarray) -> np.ndarray:
    """The rigid transform ``T`` (4, 4) with ``T · p_from ≈ p_to`` for the tool positions of the
    two models at the same readings ``q_samples`` (K, n), K >= 3 not collinear (Kabsch).

    ``frame_map(identified, nominal, q)`` is ``T_nominal_world``: where the robot's base frame,
    as the nominal model (and so the controller) understands it, sits in the instrument's world.
    """
    q = check_q(model_from, q_samples)
    if q.shape[0] < 3:
        raise ValueError("frame_map needs at least 3 configurations")
    return kabsch(fk(model_from, q)[:, :3, 3], fk(model_to, q)[:, :3, 3])


def nominal_world_frame(
    model: KinematicModel,
    nominal: KinematicModel,
    calibrated_range: np.ndarray | None = None,
    *,
    samples: int = 256,
    seed: int = 0,
) -> tuple[np.ndarray, float]:
    """``T_nominal_world`` (4, 4) and the RMS (m) of its fit: where the nominal model's world (the
    controller's base frame) sits in the identified model's, from :func:`frame_map` over
    ``samples`` configurations drawn in ``calibrated_range`` (n, 2) (else the joint limits within
    ±180°). The frame is geometry: a compliant model's sag under gravity is what compensation
    corrects, not part of where the nominal model's world sits, so the rigid part is fitted."""
    rigid = dataclasses.replace(model, compliance=None)
    q = random_configurations(rigid, samples, np.random.default_rng(seed), limits=calibrated_range)
    M = frame_map(rigid, nominal, q)
    p_id = fk(rigid, q)[:, :3, 3]
    p_nom = fk(nominal, q)[:, :3, 3]
    rms = float(np.sqrt(np.mean(np.sum((p_id @ M[:3, :3].T + M[:3, 3] - p_nom) ** 2, axis=1))))
    return M, rms


def source_poses(
    q: np.ndarray, taught: KinematicModel | None, nominal: KinematicModel, T_nominal_world: np.ndarray
) -> np.ndarray:
    """World poses (N, 4, 4) that the joint vectors ``q`` gave the robot they were taught on
    (``taught``, an identified model in the world frame), or planned on (the ``nominal`` model,
    whose world is ``T_nominal_world`` away)."""
    if taught is not None:
        return fk(taught, q)
    return np.linalg.inv(T_nominal_world) @ fk(nominal, q)


def _apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    return np.asarray(T, dtype=float) @ X


def _as_poses(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    T = T[None] if T.ndim == 2 else T
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (N, 4, 4); got {T.shape}")
    return T


# ----------------------------------------------------------------------------- flags


def assess(
    model: KinematicModel,
    q: np.ndarray,
    q_nominal: np.ndarray,
    converged: np.ndarray,
    *,
    reachable: np.ndarray | None = None,
    branch_changed: np.ndarray | None = None,
    calibrated_range: np.ndarray | None = None,
    singular_tol: float = 0.02,
    max_correction_rad: float = np.deg2rad(5.0),
    max_correction_m: float = 0.01,
    J: np.ndarray | None = None,
    J_nominal: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Flags (N,) (bit set of :data:`FLAGS`) and ``sigma_min`` (N,) of commands ``q`` (N, n) on
    ``model`` (the identified robot), started from ``q_nominal`` (N, n).

    ``calibrated_range`` (n, 2): the joint ranges the calibration measured (e.g. the
    identification data's min and max readings), SI; ``None`` skips that check.
    ``reachable`` and ``branch_changed`` (N,): what the nominal inverse kinematics found
    (:class:`calibration.ik.IKResult`); a changed branch sets ``branch_change``.
    """
    N, n = q.shape
    if J is None:
        J = pose_and_jacobian(model, q)[2]
    flags = np.zeros(N, dtype=np.int64)
    lim = model.joint_limits
    flags |= np.where(np.any((q < lim[:, 0]) | (q > lim[:, 1]), axis=1), FLAG_BIT["joint_limit"], 0)
    sv = singular_values(model, J)
    sigma_min = sv[:, -1] if n <= 6 else sv[:, 5]
    flags |= np.where(sigma_min < singular_tol, FLAG_BIT["near_singular"], 0)
    if calibrated_range is not None:
        out = outside_joint_ranges(q, calibrated_range)
        flags |= np.where(out, FLAG_BIT["outside_calibrated_region"], 0)
    flags |= np.where(~np.asarray(converged, bool), FLAG_BIT["no_convergence"], 0)
    cap = np.array([max_correction_rad if j.revolute else max_correction_m for j in model.joints])
    big = np.any(np.abs(q - q_nominal) > cap, axis=1)
    if n == 6:
        J0 = pose_and_jacobian(model, q_nominal)[2] if J_nominal is None else J_nominal
        big |= np.sign(np.linalg.det(J0)) != np.sign(np.linalg.det(J))
    if branch_changed is not None:
        big |= np.asarray(branch_changed, bool)
    flags |= np.where(big, FLAG_BIT["branch_change"], 0)
    if reachable is not None:
        flags |= np.where(~np.asarray(reachable, bool), FLAG_BIT["unreachable"], 0)
    return flags, sigma_min


# ----------------------------------------------------------------------------- nominal IK


def nominal_solution(
    nominal: KinematicModel,
    T_nominal_tool: np.ndarray,
    q_near: np.ndarray,
    *,
    keep_branch: bool | np.ndarray = True,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
) -> IKResult:
    """The nominal controller's solution of poses in the nominal model's world (N, 4, 4): the
    closed form where the nominal has UR structure (branch of ``q_near``, or nearest to it), else
    the numerical inverse from ``q_near``, the previous point's solution and seeds spread over the
    joint limits (:func:`calibration.ik.inverse_kinematics`, :func:`calibration.ik.numerical_ik`).
    ``keep_branch`` (a bool or one per point): ``q_near`` is the point's taught or planned
    configuration."""
    return inverse_kinematics(
        nominal,
        _as_poses(T_nominal_tool),
        q_near,
        keep_branch=keep_branch,
        position_tol_m=position_tol_m,
        rotation_tol_rad=rotation_tol_rad,
    )


def _nominal_ik_fixed(nominal, X, q_prev, branch, kw) -> IKResult:
    """One nominal IK pass of Algorithm B: the closed form in a fixed branch on the turns of
    ``q_prev`` (UR structure), else Newton from ``q_prev`` (continuity keeps the branch)."""
    if branch is not None:
        q0, ok = ur_ik(nominal, X, branch, q_prev)
        return _polish(nominal, X, q0, ok, kw)
    return solve_ik(nominal, X, q_prev, **kw)


# ----------------------------------------------------------------------------- the three tasks


def compensate_joints(
    identified: KinematicModel,
    T_desired: np.ndarray,
    q_nominal: np.ndarray,
    *,
    reachable: np.ndarray | None = None,
    branch_changed: np.ndarray | None = None,
    calibrated_range: np.ndarray | None = None,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
    max_iterations: int = 50,
    singular_tol: float = 0.02,
    max_correction_rad: float = np.deg2rad(5.0),
    max_correction_m: float = 0.01,
) -> CompensatedPoints:
    """Joint commands that bring the identified robot's tool to ``T_desired`` (N, 4, 4, world),
    by damped Newton (Levenberg–Marquardt) on the identified model started from the nominal
    solution ``q_nominal`` (N, n) (book eq. 5.19 solved as §5.2.1 suggests: nominal solution,
    then correction).

    The book's Algorithm A iterates with the *nominal* Jacobian (a chord method, linear
    convergence) because in 1991 the identified model's Jacobian was costly; here the identified
    model's analytic Jacobian is at hand, so Newton converges quadratically (2-3 iterations to
    1e-9 m from mm-level errors). The printed update sign of §5.2.1 (eq. 5.43-5.44) diverges: with
    ``e = X_d ⊖ X_c`` the step is ``+J⁻¹e`` (equivalently ``q − J⁻¹(X_c ⊖ X_d)``), accumulated
    over iterations.
    """
    T_desired = _as_poses(T_desired)
    q_nominal = check_q(identified, q_nominal)
    if len(q_nominal) != len(T_desired):
        raise ValueError(f"{len(T_desired)} poses but {len(q_nominal)} nominal solutions")
    r = solve_ik(
        identified,
        T_desired,
        q_nominal,
        position_tol_m=position_tol_m,
        rotation_tol_rad=rotation_tol_rad,
        max_iterations=max_iterations,
    )
    flags, smin = assess(
        identified,
        r.q,
        q_nominal,
        r.converged,
        reachable=reachable,
        branch_changed=branch_changed,
        calibrated_range=calibrated_range,
        singular_tol=singular_tol,
        max_correction_rad=max_correction_rad,
        max_correction_m=max_correction_m,
        J=r.jacobian,
        J_nominal=r.jacobian_start,
    )
    return CompensatedPoints(
        q=r.q,
        T_command=T_desired,
        T_desired=T_desired,
        q_nominal=q_nominal,
        correction=r.q - q_nominal,
        converged=r.converged,
        residual_m=r.residual_m,
        residual_rad=r.residual_rad,
        iterations=r.iterations,
        sigma_min=smin,
        flags=flags,
        mode="joints",
        message=_message(r.converged, flags),
    )


def compensate_targets(
    identified: KinematicModel,
    nominal: KinematicModel,
    T_desired: np.ndarray,
    q_near: np.ndarray,
    *,
    T_nominal_world: np.ndarray | None = None,
    keep_branch: bool | np.ndarray = True,
    calibrated_range: np.ndarray | None = None,
    position_tol_m: float = 1e-9,
    rotation_tol_rad: float = 1e-9,
    max_iterations: int = 30,
    singular_tol: float = 0.02,
    max_correction_rad: float = np.deg2rad(5.0),
    max_correction_m: float = 0.01,
) -> CompensatedPoints:
    """Corrected targets for a controller that knows only the ``nominal`` model (book §5.2.2,
    "Algorithm B", iterated as ch5 §3.4 recommends).

    ``X_m`` starts at the desired pose mapped into the nominal's world (``T_nominal_world ·
    X_d``); each pass runs the nominal inverse kinematics on ``X_m`` (the controller's closed
    form, in the configuration branch of ``q_near`` — the task's taught or planned joints — or
    the branch nearest it), evaluates the identified robot there, and moves ``X_m`` by the
    remaining error: ``p_m += R_M·(p_d − p_c)``, ``R_m ← exp(R_M·rotvec(R_d R_cᵀ))·R_m`` with
    ``R_M`` the rotation of ``T_nominal_world``. The first pass is the book's linearised
    correction (eq. 5.57-5.58) evaluated as an exact difference; later passes remove what the
    linearisation leaves (the error shrinks by the relative model difference each pass).

    ``q`` of the result are the joints the controller will command for ``T_command`` (= ``X_m``,
    nominal world); ``correction`` is their difference from the nominal solution of ``X_d``.
    """
    T_desired, M, q_near = _targets_input(identified, nominal, T_desired, q_near, T_nominal_world)
    RM = M[:3, :3]
    kw = dict(position_tol_m=position_tol_m * 1e-2, rotation_tol_rad=rotation_tol_rad * 1e-2, max_iterations=50)
    X = _apply(M, T_desired)
    first, branch = _nominal_start(nominal, X, q_near, keep_branch, kw)
    q_nom = first.q
    reachable = first.reachable.copy()
    branch_changed = first.branch_changed
    q = q_nom.copy()
    ik_ok = first.converged.copy()
    w = walk(identified, q)
    e = pose_error(T_desired, w.R, w.p)
    tol = (position_tol_m, rotation_tol_rad)
    iterations = _iterate_targets(
        identified, nominal, T_desired, X, q, e, ik_ok, reachable, branch, RM, kw, tol, max_iterations
    )
    converged = _done(e, tol) & ik_ok
    flags, smin = assess(
        identified,
        q,
        q_nom,
        converged,
        reachable=reachable,
        branch_changed=branch_changed,
        calibrated_range=calibrated_range,
        singular_tol=singular_tol,
        max_correction_rad=max_correction_rad,
        max_correction_m=max_correction_m,
    )
    return CompensatedPoints(
        q=q,
        T_command=X,
        T_desired=T_desired,
        q_nominal=q_nom,
        correction=q - q_nom,
        converged=converged,
        residual_m=np.linalg.norm(e[:, :3], axis=1),
        residual_rad=np.linalg.norm(e[:, 3:], axis=1),
        iterations=iterations,
        sigma_min=smin,
        flags=flags,
        mode="targets",
        message=_message(converged, flags),
    )


def _targets_input(
    identified: KinematicModel,
    nominal: KinematicModel,
    T_desired: np.ndarray,
    q_near: np.ndarray,
    T_nominal_world: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`compensate_targets`' input checked: the desired poses (N, 4, 4), ``T_nominal_world``
    (4, 4; the identity when not given) and ``q_near`` as one row (N, n) per pose."""
    T_desired = _as_poses(T_desired)
    N = len(T_desired)
    n = nominal.n_joints
    if identified.n_joints != n:
        raise ValueError(f"the identified model has {identified.n_joints} joints, the nominal {n}")
    M = np.eye(4) if T_nominal_world is None else np.asarray(T_nominal_world, dtype=float)
    q_near = np.broadcast_to(check_q(nominal, np.asarray(q_near, dtype=float).reshape(-1, n)), (N, n)).copy()
    return T_desired, M, q_near


def _nominal_start(nominal: KinematicModel, X: np.ndarray, q_near: np.ndarray, keep_branch, kw: dict):
    """Algorithm B's start: the nominal inverse kinematics of ``X`` (N, 4, 4) in the branch of
    ``q_near`` (:func:`nominal_solution`), and that solution's UR configuration branch (``None``
    for a robot without UR geometry)."""
    first = nominal_solution(
        nominal,
        X,
        q_near,
        keep_branch=keep_branch,
        position_tol_m=kw["position_tol_m"],
        rotation_tol_rad=kw["rotation_tol_rad"],
    )
    branch = ur_branch(nominal, first.q) if ur_geometry(nominal) is not None else None
    return first, branch


def _done(err: np.ndarray, tol: tuple[float, float]) -> np.ndarray:
    """(N,) whether pose errors ``err`` (N, 6) are within ``tol`` (m, rad)."""
    return (np.linalg.norm(err[:, :3], axis=1) <= tol[0]) & (np.linalg.norm(err[:, 3:], axis=1) <= tol[1])


def _iterate_targets(identified, nominal, T_desired, X, q, e, ik_ok, reachable, branch, RM, kw, tol, max_iterations):
    """The passes of :func:`compensate_targets`: move each target ``X`` (N, 4, 4) by the identified
    robot's remaining error ``e`` (N, 6), solve the nominal IK there, until within ``tol``. ``X``,
    ``q``, ``e`` and ``reachable`` are updated in place; returns the passes per point (N,)."""
    iterations = np.zeros(len(T_desired), dtype=int)
    L = characteristic_length(identified)
    active = ~_done(e, tol) & ik_ok
    for _ in range(max_iterations):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        Xi = X[idx].copy()
        Xi[:, :3, 3] += e[idx, :3] @ RM.T
        Xi[:, :3, :3] = rotvec_to_matrix(e[idx, 3:] @ RM.T) @ Xi[:, :3, :3]
        r = _nominal_ik_fixed(nominal, Xi, q[idx], None if branch is None else branch[idx], kw)
        w = walk(identified, r.q)
        e2 = pose_error(T_desired[idx], w.R, w.p)
        # a pass whose target the nominal IK cannot reach, or that doubles the error (the
        # iteration diverges there), is not taken: the point stops at its last valid target
        worse = _size(e2, L) > 2.0 * _size(e[idx], L)
        keep = r.converged & ~worse
        X[idx[keep]] = Xi[keep]
        q[idx[keep]] = r.q[keep]
        e[idx[keep]] = e2[keep]
        reachable[idx] &= r.reachable
        iterations[idx] += 1
        active[idx] = ~_done(e[idx], tol) & keep
    return iterations


def _size(e: np.ndarray, L: float) -> np.ndarray:
    """A pose error's size (N,) in m: translation plus rotation times the robot's reach."""
    return np.linalg.norm(e[:, :3], axis=1) + L * np.linalg.norm(e[:, 3:], axis=1)


def compensate_taught(
    model_from: KinematicModel,
    identified: KinematicModel,
    q_taught: np.ndarray,
    *,
    T_from_world: np.ndarray | None = None,
    **kwargs,
) -> CompensatedPoints:
    """Taught joint vectors ``q_taught`` (N, n) of robot ``model_from`` mapped to the identified
    robot (book eq. 5.21-5.22): the pose the first reaches, ``X = T_from_world⁻¹ · F_from(q)``
    (world), reached by the second, by Newton from ``q_taught`` (:func:`compensate_joints`).

    ``model_from`` is the nominal model (a program planned off-line, then ``T_from_world`` =
    :func:`frame_map` of identified -> nominal) or another identified robot in the same world
    (a program taught on robot A, replayed on robot B; identity). When A was calibrated, its
    identified model is the right one here, not the nominal (ch5 §1.2)."""
    q_taught = check_q(model_from, q_taught)
    X = fk(model_from, q_taught)
    if T_from_world is not None:
        X = _apply(invert(np.asarray(T_from_world, dtype=float)), X)
    result = compensate_joints(identified, X, q_taught, **kwargs)
    return _replace_mode(result, "taught")


def _replace_mode(c: CompensatedPoints, mode: str) -> CompensatedPoints:
    import dataclasses

    return dataclasses.replace(c, mode=mode)


def _message(converged: np.ndarray, flags: np.ndarray) -> str:
    n = len(converged)
    bad = int(np.count_nonzero(~converged))
    parts = [f"{n - bad} of {n} points converged"]
    for name in FLAGS:
        k = int(np.count_nonzero(flags & FLAG_BIT[name]))
        if k and name != "no_convergence":
            parts.append(f"{k} {name}")
    return "; ".join(parts)


def concatenate(parts: list[CompensatedPoints]) -> CompensatedPoints:
    """The points of several compensations, in order, as one."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    out: dict[str, Any] = {}
    for f in dataclasses.fields(first):
        v = getattr(first, f.name)
        out[f.name] = np.concatenate([getattr(p, f.name) for p in parts]) if isinstance(v, np.ndarray) else v
    out["message"] = _message(out["converged"], out["flags"])
    return dataclasses.replace(first, **out)


def take(comp: CompensatedPoints, idx: np.ndarray) -> CompensatedPoints:
    """The points ``idx`` of a compensation, in that order."""
    return dataclasses.replace(
        comp,
        **{
            f.name: getattr(comp, f.name)[idx]
            for f in dataclasses.fields(comp)
            if isinstance(getattr(comp, f.name), np.ndarray)
        },
    )


# A residual correction (``calibration.residual_map.from_model``: the smooth map, the joint
# transmission or boosted trees) is aimed through in passes: at most this many, and a point whose
# correction at its command still differs from the one aimed with by more than this is flagged.
MAX_CORRECTION_PASSES = 6
CORRECTION_SETTLED_M = 1e-6


def compensate_through_correction(
    run: Callable[[np.ndarray], CompensatedPoints],
    X_goal: np.ndarray,
    correction,
    p_tool: np.ndarray | None = None,
) -> CompensatedPoints:
    """Compensate for a model whose robot is the parametric model plus a learned correction of
    position: ``p_robot(q) = p_model(q) + c(q)``. ``run(X)`` compensates goal poses ``X`` (N, 4, 4)
    with the parametric model; ``correction.evaluate(q, p_tool)`` gives ``c`` (N, 3) m and (N,)
    whether each command is inside the region it was fitted in (``c`` is zero outside).

    A fixed-point iteration: aim the parametric model at ``X_goal − c(q_k)``, where ``q_k`` is the
    previous pass's command, until ``c`` at the new command is the one aimed with. A smooth map or
    the transmission settles in two passes to well below a micrometre; boosted trees are piecewise
    constant, and a command on a leaf's boundary can jump between two leaves: such a point is
    flagged ``no_convergence`` (the reached position misses the goal by the jump). A command
    outside the correction's region is compensated with the parametric model alone and flagged
    ``outside_mapped_region``. ``p_tool`` (3,): the point, in the model's tool frame, whose
    position the goals give (default its origin; only a correction with a physical model, the
    transmission, moves with it)."""
    comp = run(X_goal)
    corr, inside = correction.evaluate(comp.q, p_tool)
    unsettled = np.zeros(len(comp.q), dtype=bool)
    for _ in range(MAX_CORRECTION_PASSES):
        aimed = corr
        X = X_goal.copy()
        X[:, :3, 3] -= aimed
        comp = run(X)
        corr, inside = correction.evaluate(comp.q, p_tool)
        unsettled = np.linalg.norm(corr - aimed, axis=1) > CORRECTION_SETTLED_M
        if not unsettled.any():
            break
    flags = comp.flags | np.where(inside, 0, FLAG_BIT["outside_mapped_region"])
    flags |= np.where(unsettled, FLAG_BIT["no_convergence"], 0)
    return dataclasses.replace(comp, flags=flags, converged=comp.converged & ~unsettled)


# ----------------------------------------------------------------------------- book Algorithm A


def inverse_jacobian_iteration(
    identified: KinematicModel,
    nominal: KinematicModel,
    T_desired: np.ndarray,
    q_nominal: np.ndarray,
    *,
    T_nominal_world: np.ndarray | None = None,
    resolution_rad: float = 1e-10,
    max_iterations: int = 50,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The book's Algorithm A (§5.2.1, eq. 5.31-5.44) with the corrections of ch5 §2.3: the
    chord iteration ``q ← q − J_n(q)⁻¹ dx`` with ``dx = X_c ⊖ X_d`` (the printed ``+`` diverges),
    ``X_c = F_c(q)`` recomputed and the steps accumulated each pass, the *nominal* Jacobian
    (tool-point translation with the world-frame rotation, the consistent pair), stopping when
    *all* ``|dq_i|`` are below the encoder resolution (the printed "at least one element" is too
    weak) or after ``max_iterations``.

    Returns ``q`` (N, n), ``iterations`` (N,), ``converged`` (N,). It converges linearly (the
    nominal Jacobian is a chord of the identified one): a few passes for mm-level errors (book:
    "four to six iterations in all cases tested"). For production use :func:`compensate_joints`.
    """
    T_desired = _as_poses(T_desired)
    q = check_q(identified, q_nominal).copy()
    N = len(q)
    RM = np.eye(3) if T_nominal_world is None else np.asarray(T_nominal_world, dtype=float)[:3, :3]
    iterations = np.zeros(N, dtype=int)
    converged = np.zeros(N, dtype=bool)
    active = np.ones(N, dtype=bool)
    for _ in range(max_iterations):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        R_c, p_c, _ = pose_and_jacobian(identified, q[idx])
        dx = -pose_error(T_desired[idx], R_c, p_c)  # X_c ⊖ X_d, world axes
        dx_nom = np.concatenate([dx[:, :3] @ RM.T, dx[:, 3:] @ RM.T], axis=1)  # into the nominal's axes
        Jn = pose_and_jacobian(nominal, q[idx])[2]
        if Jn.shape[1] == Jn.shape[2]:
            dq = np.linalg.solve(Jn, dx_nom[:, :, None])[:, :, 0]
        else:
            dq = np.einsum("nij,nj->ni", np.linalg.pinv(Jn), dx_nom)
        q[idx] -= dq
        iterations[idx] += 1
        small = np.all(np.abs(dq) < resolution_rad, axis=1)
        converged[idx[small]] = True
        active[idx[small]] = False
    return q, iterations, converged


# ----------------------------------------------------------------------------- reporting


def error_table(dp_initial: np.ndarray, dp_compensated: np.ndarray) -> dict:
    """Per-point errors before and after compensation as in the book's Table 5.2: the absolute
    X, Y, Z components and their "Total RMS", which is the Euclidean norm ``√(X²+Y²+Z²)`` (not
    divided by √3: ch5 §2.4 reproduces all six of the table's totals that way), and the
    improvement ratio. Arrays (N, 3) in any one length unit."""
    a = np.abs(np.asarray(dp_initial, dtype=float))
    b = np.abs(np.asarray(dp_compensated, dtype=float))
    ta, tb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(tb > 0, ta / tb, np.inf)
    return {"initial": a, "compensated": b, "total_initial": ta, "total_compensated": tb, "improvement": ratio}


__all__ = [
    "FLAGS",
    "FLAG_BIT",
    "CompensatedPoints",
    "assess",
    "compensate_joints",
    "compensate_targets",
    "compensate_taught",
    "error_table",
    "flag_names",
    "frame_map",
    "inverse_jacobian_iteration",
    "nominal_solution",
]
