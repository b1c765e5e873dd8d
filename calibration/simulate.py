"""Synthetic robots and measurements, for tests, benchmarks and the demo (book §4.5: simulate
the identification before measuring).

A "true" robot is the nominal one with every link carrying a small random 6-DOF error: the
nominal model is rewritten exactly in ``poe`` form (where every joint axis may tilt and shift
freely) and each axis, joint offset, the home, base and tool frames are perturbed.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .conventions import to_poe
from .identify import Measurements
from .kinematics import fk
from .model import KinematicModel
from .parameters import apply_step, candidate_parameters
from .transforms import matrix_to_quat, rotvec_to_matrix


def perturbed(
    model: KinematicModel,
    rng: np.random.Generator,
    *,
    length_m: float = 0.5e-3,
    angle_rad: float = np.deg2rad(0.05),
    offset_rad: float = np.deg2rad(0.1),
    base_length_m: float = 0.0,
    base_angle_rad: float = 0.0,
    tool_length_m: float = 0.0,
    tool_angle_rad: float = 0.0,
) -> KinematicModel:
    """A "true" robot near ``model`` (returned in ``poe`` form): normal errors of standard
    deviation ``length_m`` on every axis shift and the home position, ``angle_rad`` on every
    axis tilt and the home orientation, ``offset_rad`` on every joint offset; base and tool
    errors as given."""
    poe = to_poe(model)
    params = candidate_parameters(poe, targets=(), gains=False)
    delta = np.zeros(len(params))
    for k, p in enumerate(params):
        head, _, f = p.name.rpartition(".")
        if head == "base":
            delta[k] = rng.normal(0, base_length_m if f.startswith("t") else base_angle_rad)
        elif head == "tool":
            delta[k] = rng.normal(0, tool_length_m if f.startswith("t") else tool_angle_rad)
        elif head == "home":
            delta[k] = rng.normal(0, length_m if f.startswith("t") else angle_rad)
        elif f == "theta":
            delta[k] = rng.normal(0, offset_rad)
        elif f == "d":
            delta[k] = rng.normal(0, length_m)
        elif f.startswith("tilt"):
            delta[k] = rng.normal(0, angle_rad)
        elif f.startswith("shift"):
            delta[k] = rng.normal(0, length_m)
    return dataclasses.replace(apply_step(poe, params, delta), name=f"{model.name}-true")


def random_configurations(
    model: KinematicModel, n: int, rng: np.random.Generator, *, limits: np.ndarray | None = None
) -> np.ndarray:
    """``n`` joint vectors (n, joints) uniform within ``limits`` (n_joints, 2) (default the
    model's joint limits, clipped to ±pi for revolute joints)."""
    lim = model.joint_limits if limits is None else np.asarray(limits, dtype=float)
    lim = lim.copy()
    for i, j in enumerate(model.joints):
        if j.revolute and limits is None:
            lim[i] = np.clip(lim[i], -np.pi, np.pi)
    return rng.uniform(lim[:, 0], lim[:, 1], size=(n, model.n_joints))


def simulate_measurements(
    truth: KinematicModel,
    q: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma_m: float = 20e-6,
    targets: tuple[str | None, ...] = (None,),
    full_pose: bool = False,
    sigma_rad: float = 0.0,
) -> Measurements:
    """Measurements of ``truth`` at readings ``q`` (N, n): every named target (``None``: the tool
    origin) at every configuration, with normal noise ``sigma_m`` per axis; with ``full_pose``,
    the tool orientation too, rotated by normal noise ``sigma_rad`` per axis."""
    q = np.asarray(q, dtype=float)
    T = fk(truth, q)
    rows_q, rows_p, rows_t, rows_quat, pose_id = [], [], [], [], []
    for t in targets:
        p_tool = truth.target(t)
        p = T[:, :3, 3] + T[:, :3, :3] @ p_tool
        rows_q.append(q)
        rows_p.append(p + rng.normal(0, sigma_m, p.shape))
        rows_t += [t] * len(q)
        pose_id.append(np.arange(len(q)))
        if full_pose:
            R = T[:, :3, :3]
            if sigma_rad > 0:
                R = rotvec_to_matrix(rng.normal(0, sigma_rad, (len(q), 3))) @ R
            rows_quat.append(matrix_to_quat(R))
    order = np.argsort(np.concatenate(pose_id), kind="stable")
    cat = lambda a: np.concatenate(a)[order]  # noqa: E731
    return Measurements(
        q=cat(rows_q), p_world=cat(rows_p), quat=cat(rows_quat) if full_pose else None,
        target=np.array(rows_t, dtype=object)[order], pose_id=cat(pose_id),
    )
