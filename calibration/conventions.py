"""Exact conversions between kinematic conventions.

- ``dh`` <-> ``mdh``: regrouping the same elementary transforms (Craig's modified links carry
  the previous link's ``alpha``, ``a``); exact when no link uses Hayati's ``beta``.
- ``dh``/``mdh`` -> ``poe``: each joint axis and a point on it, in the base frame at zero joint
  variables, and the flange frame there as ``home`` (book §2.8.2); always exact.
- :func:`hayati_for_parallel_axes`: rewrite ``dh`` links whose consecutive joint axes are
  parallel in Hayati's form (book §2.6, §2.8.1.1): plain DH has no unique common normal there, so
  a slight misalignment of a real robot needs a huge, jumping ``d``; Hayati's ``beta`` describes
  it with a small parameter.
- :func:`poe_to_dh`: any model -> ``dh`` from its joint-axis lines (Sklar's method, book
  §4.6.5.2): common normals between consecutive axes, Hayati's form where they are parallel;
  exact. :func:`common_normal` and :func:`mutual_moment` are the line geometry it rests on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .kinematics import walk
from .model import KinematicModel
from .transforms import homogeneous, invert, matrix_to_pose, pose_to_matrix, rot


def _has_beta(model: KinematicModel) -> bool:
    return any(j.hayati for j in model.joints)


def dh_to_mdh(model: KinematicModel) -> KinematicModel:
    """Standard DH -> Craig's modified DH, same kinematics.

    ``B·Π[Rz(θi)Tz(di)Tx(ai)Rx(αi)]·F = B·Π[Rx(α(i-1))Tx(a(i-1))Rz(θi)Tz(di)]·Tx(an)Rx(αn)·F``
    with ``α0 = a0 = 0``: the last link's ``a``, ``alpha`` move into the tool.
    """
    if model.convention != "dh" or _has_beta(model):
        raise ValueError("dh_to_mdh needs a dh model without Hayati (beta) links")
    js = model.joints
    new = []
    for i, j in enumerate(js):
        prev_a, prev_alpha = (js[i - 1].a, js[i - 1].alpha) if i > 0 else (0.0, 0.0)
        new.append(dataclasses.replace(j, a=prev_a, alpha=prev_alpha))
    last = js[-1]
    tail = homogeneous(np.eye(3), np.array([last.a, 0.0, 0.0])) @ homogeneous(rot(0, last.alpha), np.zeros(3))
    tool = matrix_to_pose(tail @ pose_to_matrix(model.tool))
    return dataclasses.replace(model, convention="mdh", joints=tuple(new), tool=tool)


def mdh_to_dh(model: KinematicModel) -> KinematicModel:
    """Craig's modified DH -> standard DH, same kinematics (the inverse regrouping: the first
    link's ``alpha``, ``a`` move into the base)."""
    if model.convention != "mdh":
        raise ValueError("mdh_to_dh needs an mdh model")
    js = model.joints
    head = homogeneous(rot(0, js[0].alpha), np.zeros(3)) @ homogeneous(np.eye(3), np.array([js[0].a, 0.0, 0.0]))
    base = matrix_to_pose(pose_to_matrix(model.base) @ head)
    new = []
    for i, j in enumerate(js):
        nxt_a, nxt_alpha = (js[i + 1].a, js[i + 1].alpha) if i + 1 < len(js) else (0.0, 0.0)
        new.append(dataclasses.replace(j, a=nxt_a, alpha=nxt_alpha))
    return dataclasses.replace(model, convention="dh", joints=tuple(new), base=base)


def to_poe(model: KinematicModel) -> KinematicModel:
    """Any model -> ``poe`` (zero-reference position), same kinematics.

    Walk the chain with zero joint variables (each joint at its ``theta``/``d``): joint i's axis
    is the z axis of its motion frame there, its point that frame's origin, both in the base
    frame; ``home`` is the flange (before the tool) in the base frame.
    """
    if model.convention == "poe":
        return model
    base_free = dataclasses.replace(
        model,
        base=np.zeros(6),
        tool=np.zeros(6),
        coupling=None,
        joints=tuple(dataclasses.replace(j, gain=1.0, harmonic=None) for j in model.joints),
    )
    keys = {f"{j.name}.theta" if j.revolute else f"{j.name}.d" for j in model.joints}
    w = walk(base_free, np.zeros((1, model.n_joints)), keys)
    joints = []
    for j in model.joints:
        u, o = w.axes[f"{j.name}.theta" if j.revolute else f"{j.name}.d"]
        joints.append(
            dataclasses.replace(j, axis=u[0].copy(), point=o[0].copy(), theta=0.0, d=0.0, a=0.0, alpha=0.0, beta=None)
        )
    home = matrix_to_pose(homogeneous(w.R[0], w.p[0]))
    return dataclasses.replace(model, convention="poe", joints=tuple(joints), home=home)


def hayati_for_parallel_axes(
    model: KinematicModel, *, parallel_tol_rad: float = np.deg2rad(5.0)
) -> tuple[KinematicModel, list[str]]:
    """Rewrite ``dh`` links i < n whose next joint axis is (nearly) parallel
    (``|sin alpha_i| < sin(parallel_tol_rad)``) in Hayati's form, exactly.

    A revolute link ``Rz(θ)Tz(d)Tx(a)Rx(α)`` with α = 0 or π equals ``Rz(θ)Tx(a)Rx(α)Ry(0)``
    followed by ``Tz(±d)``, which commutes with the next joint's motion (a rotation about, or a
    translation along, the same line) and joins the next link's ``d`` (``+d`` for α = 0, ``−d``
    for α = π): a revolute next joint's offset along its axis, or a prismatic next joint's offset.
    A prismatic link keeps its ``d`` (its joint offset) and gains ``beta = 0``
    (``Rz(θ)Tz(d)Tx(a)Rx(α)Ry(β)``), exactly. A revolute link whose α is near, but not exactly, 0
    or π and whose d is not 0 has no exact Hayati form: it is left as it is and reported.
    Returns the model and a note per link changed or left.
    """
    if model.convention != "dh":
        return model, []
    js = list(model.joints)
    notes: list[str] = []
    for i in range(len(js) - 1):
        j = js[i]
        if j.hayati or abs(np.sin(j.alpha)) >= np.sin(parallel_tol_rad):
            continue
        exact = abs(np.sin(j.alpha)) < 1e-12
        if not j.revolute:  # a prismatic link keeps d, its joint offset: Ry(0) is all it gains
            js[i] = dataclasses.replace(j, beta=0.0)
            notes.append(f"{j.name}: axes {i + 1} and {i + 2} are parallel: link rewritten in Hayati's form (beta)")
            continue
        if j.d != 0.0 and not exact:
            notes.append(
                f"{j.name}: axes {i + 1} and {i + 2} are nearly parallel but the link has d != 0 and "
                f"alpha is not exactly 0 or 180 deg, so it stays in plain DH form"
            )
            continue
        if j.d != 0.0:
            nxt = js[i + 1]
            sign = 1.0 if np.cos(j.alpha) > 0 else -1.0
            if nxt.hayati and nxt.revolute:  # a revolute Hayati link has no d to take it
                notes.append(f"{j.name}: cannot move d into {nxt.name}; left in plain DH form")
                continue
            js[i + 1] = dataclasses.replace(nxt, d=nxt.d + sign * j.d)
        js[i] = dataclasses.replace(j, d=0.0, beta=0.0)
        notes.append(f"{j.name}: axes {i + 1} and {i + 2} are parallel: link rewritten in Hayati's form (beta)")
    return dataclasses.replace(model, joints=tuple(js)), notes


# --------------------------------------------------------------------------- lines (Sklar)


def mutual_moment(s_j: np.ndarray, r_j: np.ndarray, s_k: np.ndarray, r_k: np.ndarray) -> float:
    """The mutual moment of two lines (book eq. 4.333-4.336): ``s_j·(r_k×s_k) + s_k·(r_j×s_j)``
    ``= −a_jk·sin(alpha_jk)``; zero for intersecting or parallel lines. ``s`` unit directions,
    ``r`` points on the lines."""
    s_j, r_j, s_k, r_k = (np.asarray(v, dtype=float) for v in (s_j, r_j, s_k, r_k))
    return float(s_j @ np.cross(r_k, s_k) + s_k @ np.cross(r_j, s_j))


@dataclass(frozen=True, slots=True)
class CommonNormal:
    """The common normal from line j to line k (book §4.6.5.2).

    ``kind``: ``"skew"``, ``"intersecting"`` or ``"parallel"``. ``length`` a_jk >= 0 and
    ``direction`` the unit normal **a**_jk from line j to line k (eq. 4.337; for intersecting
    lines ``s_j × s_k`` normalised, which puts the twist in (0, π); for coincident parallel lines
    a zero vector). ``twist``: alpha_jk (rad), the right-hand rotation of ``s_j`` into ``s_k``
    about **a**_jk (eq. 4.327-4.328). ``foot_j``, ``foot_k``: where the normal meets the lines
    (for parallel lines the normal's position along them is arbitrary: ``foot_j`` is then the
    given point ``r_j``). ``moment``: the mutual moment (eq. 4.333).
    """

    kind: str
    length: float
    direction: np.ndarray
    twist: float
    foot_j: np.ndarray
    foot_k: np.ndarray
    moment: float


def common_normal(
    s_j: np.ndarray,
    r_j: np.ndarray,
    s_k: np.ndarray,
    r_k: np.ndarray,
    *,
    parallel_tol_rad: float = 1e-9,
    intersect_tol_m: float = 1e-12,
) -> CommonNormal:
    """Sklar's common normal between the lines (``r_j``, ``s_j``) and (``r_k``, ``s_k``)
    (book §4.6.5.2, eq. 4.327-4.355, with the corrected 4.338).

    Lines count as parallel when the angle between them is below ``parallel_tol_rad``, and as
    intersecting when their distance ``|MM| / |s_j × s_k|`` is below ``intersect_tol_m``. The
    feet come from the book's "method 2" (eq. 4.349-4.353: the 2 x 2 system that makes
    ``P_k − P_j`` perpendicular to both lines), which is the same as the corrected eq. 4.339-4.340
    and better conditioned. Skew lines: **a**_jk = −sign(MM)·(s_j × s_k)/|s_j × s_k| (eq.
    4.337), so that ``a_jk = (P_k − P_j)·a_jk`` (eq. 4.338 corrected: the printed
    ``(A_j − A_k)·a_jk`` gives −a) is positive. Parallel lines: eq. 4.348,
    ``a_jk·a_jk = s_j × (cos(alpha)·s_0k − s_0j)`` with ``s_0 = r × s`` (eq. 4.332).
    """
    s_j = np.asarray(s_j, dtype=float) / np.linalg.norm(s_j)
    s_k = np.asarray(s_k, dtype=float) / np.linalg.norm(s_k)
    r_j = np.asarray(r_j, dtype=float)
    r_k = np.asarray(r_k, dtype=float)
    c = np.cross(s_j, s_k)
    sn = float(np.linalg.norm(c))
    cos_a = float(s_j @ s_k)
    mm = mutual_moment(s_j, r_j, s_k, r_k)
    if sn < np.sin(parallel_tol_rad):
        sign = 1.0 if cos_a >= 0 else -1.0
        v = np.cross(s_j, sign * np.cross(r_k, s_k) - np.cross(r_j, s_j))  # eq. 4.348
        a = float(np.linalg.norm(v))
        direction = v / a if a > 0 else np.zeros(3)
        twist = 0.0 if sign > 0 else np.pi
        return CommonNormal("parallel", a, direction, twist, r_j.copy(), r_j + v, mm)
    # Method 2 (eq. 4.352-4.353) with unit directions: t s_j and v s_k from r_j, r_k.
    dr = r_k - r_j
    A = np.array([[1.0, -cos_a], [cos_a, -1.0]])
    t, u = np.linalg.solve(A, [dr @ s_j, dr @ s_k])
    foot_j, foot_k = r_j + t * s_j, r_k + u * s_k
    if abs(mm) / sn < intersect_tol_m:
        kind, direction = "intersecting", c / sn
    else:
        kind, direction = "skew", -np.sign(mm) * c / sn
    a = float((foot_k - foot_j) @ direction) if kind == "skew" else 0.0
    twist = float(np.arctan2(c @ direction, cos_a))
    return CommonNormal(kind, a, direction, twist, foot_j, foot_k, mm)


def joint_angle(normal_in: np.ndarray, normal_out: np.ndarray, s: np.ndarray) -> float:
    """Book eq. 4.329-4.330: the right-hand rotation about axis ``s`` that takes the common
    normal arriving at the axis (**a**_ij) into the one leaving it (**a**_jk), rad."""
    normal_in, normal_out, s = (np.asarray(v, dtype=float) for v in (normal_in, normal_out, s))
    return float(np.arctan2(np.cross(normal_in, normal_out) @ s, normal_in @ normal_out))


# --------------------------------------------------------------------------- poe -> dh


def _wrap(angle: float, centre: float = 0.0) -> float:
    """``angle`` moved by whole turns into (centre − π, centre + π]."""
    return float(centre - np.remainder(centre - angle + np.pi, 2 * np.pi) + np.pi)


def _perpendicular_unit(v: np.ndarray, s: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """The unit vector along ``v`` with its component along unit ``s`` removed (``fallback``,
    then any perpendicular, when ``v`` is (nearly) parallel to ``s``)."""
    for cand in (v, fallback, np.eye(3)[int(np.argmin(np.abs(s)))]):
        w = np.asarray(cand, dtype=float) - s * (s @ cand)
        n = np.linalg.norm(w)
        if n > 1e-9:
            return w / n
    raise AssertionError("unreachable")


def _dh_reference(reference: KinematicModel | None, n: int):
    """The joints of ``reference`` as a dh chain (or None), for choosing between equivalent
    parameter sets."""
    if reference is None or reference.n_joints != n:
        return None
    if reference.convention == "mdh":
        if any(j.hayati for j in reference.joints):
            return None
        reference = mdh_to_dh(reference)
    return reference.joints if reference.convention == "dh" else None


def _link_to_axis(R_f: np.ndarray, o_f: np.ndarray, s_next: np.ndarray, r_next: np.ndarray, ref, hayati_tol: float):
    """Link parameters from frame (``R_f``, ``o_f``) (its z on joint i's axis) to the next axis.

    Returns ``(phi, d, a, alpha, beta, R_new, o_new)``: ``phi`` the rotation about z at the
    current joint values, ``d`` the shift along z (0 in Hayati's form), ``beta`` None for a plain
    DH link; the new frame is computed as the DH chain computes it, so that the chain stays
    exact.
    """
    s, x_f = R_f[:, 2], R_f[:, 0]
    c = np.cross(s, s_next)
    sn = float(np.linalg.norm(c))
    candidates: list[tuple[np.ndarray, float, float, float, float | None]] = []
    beta: float | None  # Hayati's tilt (rad), None for a plain DH link
    if sn < np.sin(hayati_tol):
        # Hayati (book eq. 2.64): no shift along z; x towards where axis i+1 crosses the plane
        # through the origin perpendicular to axis i.
        t = float((o_f - r_next) @ s) / float(s_next @ s)
        w = r_next + t * s_next - o_f
        w -= s * (s @ w)
        nw = float(np.linalg.norm(w))
        x_hat = w / nw if nw > 1e-12 else x_f
        for sigma in (1.0, -1.0):
            x = sigma * x_hat
            y = np.cross(s, x)
            beta = float(np.arctan2(s_next @ x, np.hypot(s_next @ y, s_next @ s)))
            alpha = float(np.arctan2(-(s_next @ y), s_next @ s))
            candidates.append((x, 0.0, float(w @ x), alpha, beta))
    else:
        cn = common_normal(s, o_f, s_next, r_next)
        x_hat = c / sn
        d = float((cn.foot_j - o_f) @ s)
        for sigma in (1.0, -1.0):
            x = sigma * x_hat
            a = float((cn.foot_k - cn.foot_j) @ x)
            alpha = float(np.arctan2(c @ x, s @ s_next))  # eq. 4.327-4.328
            candidates.append((x, d, a, alpha, None))
    if ref is not None:

        def cost(cand):
            _, _, a, alpha, _ = cand
            return abs(_wrap(alpha - ref.alpha)) + abs(a - ref.a) / max(abs(a), 1e-12)

        x, d, a, alpha, beta = min(candidates, key=cost)
    else:  # a >= 0; intersecting axes: twist in (0, π)
        first = candidates[0]
        x, d, a, alpha, beta = first if first[2] >= -1e-12 else candidates[1]
    phi = joint_angle(x_f, x, s)
    R_phi = R_f @ rot(2, phi)
    o_new = o_f + d * s + a * R_phi[:, 0]
    R_new = R_phi @ rot(0, alpha)
    if beta is not None:
        R_new = R_new @ rot(1, beta)
    return phi, d, a, alpha, beta, R_new, o_new


def poe_to_dh(
    model: KinematicModel, *, reference: KinematicModel | None = None, parallel_tol_rad: float = np.deg2rad(5.0)
) -> KinematicModel:
    """Any model -> ``dh``, same kinematics, from its joint-axis lines (Sklar's method, book
    §4.6.5.2; exact up to floating point).

    The axes are taken where the ``poe`` form puts them (``to_poe`` first for other
    conventions). Link i runs from axis i to axis i+1 along their common normal
    (:func:`common_normal`): ``d`` is where the normal leaves axis i, ``a`` its length,
    ``alpha`` the twist (eq. 4.327-4.328), ``theta`` the angle between consecutive normals
    (eq. 4.329-4.330) plus the joint's ``poe`` offset. Where consecutive axes are parallel
    within ``parallel_tol_rad`` the common normal has no unique position, and the link is
    written in Hayati's form ``Rz·Tx(a)·Rx(alpha)·Ry(beta)`` (book §2.6, §2.8.1.1) instead.

    Choices the lines leave open, made so that a model converted from ``dh`` and back comes
    out as it was:

    - frame 0 (the ``dh`` base): z on axis 1, origin the point of axis 1 nearest the ``poe``
      base origin, x the base x axis made perpendicular to axis 1;
    - frame n: z on axis n, origin the point of axis n nearest the flange (``home``) origin,
      x the flange x axis made perpendicular (so ``a_n = alpha_n = 0``); the rest goes to the tool;
    - the sign of each common normal: with a ``dh`` (or ``mdh``) ``reference`` of the same
      robot, the one whose ``a`` and ``alpha`` are nearer the reference's (and angles are
      wrapped near the reference's); without, ``a >= 0`` (twist in (0, π) for intersecting
      axes) and angles in (−π, π].

    Joint names, types, limits, gains, coupling and harmonics, targets and units are kept.
    """
    poe = to_poe(model)
    n = poe.n_joints
    ref = _dh_reference(reference, n)
    S = [np.asarray(j.axis_point()[0], dtype=float) / np.linalg.norm(j.axis_point()[0]) for j in poe.joints]
    P = [np.asarray(j.axis_point()[1], dtype=float) for j in poe.joints]
    H = pose_to_matrix(poe.poe_home())
    # frame 0: on axis 1, nearest the base origin
    o = P[0] + S[0] * (S[0] @ (np.zeros(3) - P[0]))
    x = _perpendicular_unit(np.array([1.0, 0.0, 0.0]), S[0], np.array([0.0, 1.0, 0.0]))
    R = np.column_stack([x, np.cross(S[0], x), S[0]])
    base = pose_to_matrix(poe.base) @ homogeneous(R, o)
    joints = []
    for i, j in enumerate(poe.joints):
        offset = j.theta if j.revolute else j.d
        if i + 1 < n:
            phi, d, a, alpha, beta, R_new, o_new = _link_to_axis(
                R, o, S[i + 1], P[i + 1], None if ref is None else ref[i], parallel_tol_rad
            )
        else:  # frame n on axis n, nearest the flange
            s = R[:, 2]
            o_new = o + s * (s @ (H[:3, 3] - o))
            x_n = _perpendicular_unit(H[:3, 0], s, H[:3, 1])
            phi = joint_angle(R[:, 0], x_n, s)
            d, a, alpha, beta = float(s @ (o_new - o)), 0.0, 0.0, None
            R_new = R @ rot(2, phi)
        theta = offset + phi if j.revolute else phi
        d_dh = d if j.revolute else offset + d
        r = None if ref is None else ref[i]
        theta = _wrap(theta, r.theta if r is not None else 0.0)
        alpha = _wrap(alpha, r.alpha if r is not None else 0.0)
        joints.append(dataclasses.replace(j, theta=theta, d=d_dh, a=a, alpha=alpha, beta=beta, axis=None, point=None))
        R, o = R_new, o_new
    tool = invert(homogeneous(R, o)) @ H @ pose_to_matrix(poe.tool)
    return dataclasses.replace(
        poe, convention="dh", joints=tuple(joints), base=matrix_to_pose(base), tool=matrix_to_pose(tool), home=None
    )
