"""Exact conversions between kinematic conventions.

- ``dh`` <-> ``mdh``: regrouping the same elementary transforms (Craig's modified links carry
  the previous link's ``alpha``, ``a``); exact when no link uses Hayati's ``beta``.
- ``dh``/``mdh`` -> ``poe``: each joint axis and a point on it, in the base frame at zero joint
  variables, and the flange frame there as ``home`` (book §2.8.2); always exact.
- :func:`hayati_for_parallel_axes`: rewrite ``dh`` links whose consecutive joint axes are
  parallel in Hayati's form (book §2.6, §2.8.1.1): plain DH has no unique common normal there, so
  a slight misalignment of a real robot needs a huge, jumping ``d``; Hayati's ``beta`` describes
  it with a small parameter.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .kinematics import walk
from .model import KinematicModel
from .transforms import homogeneous, matrix_to_pose, pose_to_matrix, rot


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
    tail = homogeneous(np.eye(3), [last.a, 0, 0]) @ homogeneous(rot(0, last.alpha), np.zeros(3))
    tool = matrix_to_pose(tail @ pose_to_matrix(model.tool))
    return dataclasses.replace(model, convention="mdh", joints=tuple(new), tool=tool)


def mdh_to_dh(model: KinematicModel) -> KinematicModel:
    """Craig's modified DH -> standard DH, same kinematics (the inverse regrouping: the first
    link's ``alpha``, ``a`` move into the base)."""
    if model.convention != "mdh":
        raise ValueError("mdh_to_dh needs an mdh model")
    js = model.joints
    head = homogeneous(rot(0, js[0].alpha), np.zeros(3)) @ homogeneous(np.eye(3), [js[0].a, 0, 0])
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
    base_free = dataclasses.replace(model, base=np.zeros(6), tool=np.zeros(6), coupling=None,
                                    joints=tuple(dataclasses.replace(j, gain=1.0, harmonic=None) for j in model.joints))
    keys = {f"{j.name}.theta" if j.revolute else f"{j.name}.d" for j in model.joints}
    w = walk(base_free, np.zeros((1, model.n_joints)), keys)
    joints = []
    for j in model.joints:
        u, o = w.axes[f"{j.name}.theta" if j.revolute else f"{j.name}.d"]
        joints.append(dataclasses.replace(j, axis=u[0].copy(), point=o[0].copy(), theta=0.0, d=0.0,
                                          a=0.0, alpha=0.0, beta=None))
    home = matrix_to_pose(homogeneous(w.R[0], w.p[0]))
    return dataclasses.replace(model, convention="poe", joints=tuple(joints), home=home)


def hayati_for_parallel_axes(model: KinematicModel, *, parallel_tol_rad: float = np.deg2rad(5.0)) -> tuple[KinematicModel, list[str]]:
    """Rewrite revolute ``dh`` links i < n whose next joint axis is (nearly) parallel
    (``|sin alpha_i| < sin(parallel_tol_rad)``) in Hayati's form, exactly.

    A link ``Rz(θ)Tz(d)Tx(a)Rx(α)`` with α = 0 or π equals ``Rz(θ)Tx(a)Rx(α)Ry(0)`` followed by
    ``Tz(±d)``, which commutes with the next joint's rotation and joins the next link's ``d``
    (``+d`` for α = 0, ``−d`` for α = π). A link whose α is near, but not exactly, 0 or π and
    whose d is not 0 has no exact Hayati form: it is left as it is and reported.
    Returns the model and a note per link changed or left.
    """
    if model.convention != "dh":
        return model, []
    js = list(model.joints)
    notes: list[str] = []
    for i in range(len(js) - 1):
        j = js[i]
        if j.hayati or not j.revolute or abs(np.sin(j.alpha)) >= np.sin(parallel_tol_rad):
            continue
        exact = abs(np.sin(j.alpha)) < 1e-12
        if j.d != 0.0 and not exact:
            notes.append(f"{j.name}: axes {i + 1} and {i + 2} are nearly parallel but the link has d != 0 and "
                         f"alpha is not exactly 0 or 180 deg, so it stays in plain DH form")
            continue
        if j.d != 0.0:
            nxt = js[i + 1]
            sign = 1.0 if np.cos(j.alpha) > 0 else -1.0
            if nxt.hayati or not nxt.revolute:
                notes.append(f"{j.name}: cannot move d into {nxt.name}; left in plain DH form")
                continue
            js[i + 1] = dataclasses.replace(nxt, d=nxt.d + sign * j.d)
        js[i] = dataclasses.replace(j, d=0.0, beta=0.0)
        notes.append(f"{j.name}: axes {i + 1} and {i + 2} are parallel: link rewritten in Hayati's form (beta)")
    return dataclasses.replace(model, joints=tuple(js)), notes
