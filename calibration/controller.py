"""A robot controller's own kinematics, fitted exactly to the forward kinematics it reports.

A Universal Robots controller never computes with the published DH table: it applies its
factory calibration (per-robot DH deltas) to ``actual_TCP_pose``, ``get_forward_kin()``,
``get_inverse_kin()`` and every Cartesian target. Asked for ``get_forward_kin(q)`` at N
configurations (tool offset zero), it gives flange poses ``T_base_flange`` (N, 4, 4) from which
its model is recovered here, to the controller's own precision.

The fit is done in the zero-reference (``poe``) form, book §2.8.2: each joint axis a line
(two tilts and two shifts about the reference's axis) and the flange pose at q = 0 (``home``,
six local motions). That is ``4n + 6`` parameters, the minimal set for a revolute chain (joint
offsets fold into the next axes and ``home``), all well conditioned: no parallel-axis
singularity, where the DH deltas a UR controller stores (its "linearised" form, ``delta_d`` of
tens of metres for joints 2-4) would make a DH fit crawl. One ``scipy.optimize.least_squares``
call (Levenberg–Marquardt) from the reference converges in a few iterations, since real
deltas are millimetres and milliradians. The result is written in ``dh`` form
(:func:`calibration.conventions.poe_to_dh`: Hayati's ``beta`` for the parallel joints, exact).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .conventions import poe_to_dh, to_poe
from .kinematics import fk
from .model import KinematicModel
from .parameters import apply_step, candidate_parameters
from .transforms import matrix_to_rotvec


@dataclass(frozen=True, eq=False)
class ControllerFit:
    """The controller's model and how well it reproduces the poses it was fitted to.

    ``position_rms_m`` / ``position_max_m``: flange position differences; ``rotation_max_rad``:
    largest flange rotation difference; ``n_poses`` configurations used; ``iterations``
    (function evaluations of the least-squares call) and its ``message``."""

    model: KinematicModel
    position_rms_m: float
    position_max_m: float
    rotation_max_rad: float
    n_poses: int
    iterations: int
    message: str


def pose_differences(model: KinematicModel, q: np.ndarray, T_base_flange: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (N,) m and rotation (N,) rad differences between ``model``'s flange and the
    poses ``T_base_flange`` (N, 4, 4) at readings ``q`` (N, n)."""
    T = fk(model, q)
    dp = np.linalg.norm(T[:, :3, 3] - T_base_flange[:, :3, 3], axis=1)
    dr = np.linalg.norm(matrix_to_rotvec(np.einsum("nji,njk->nik", T[:, :3, :3], T_base_flange[:, :3, :3])), axis=1)
    return dp, dr


def _fit_parameters(poe: KinematicModel) -> list:
    """Tilts and shifts of every axis and the home frame: no joint offsets, base or tool
    (each would duplicate the others)."""
    keep = ("tilt_x", "tilt_y", "shift_x", "shift_y")
    return [
        p
        for p in candidate_parameters(poe, base=False, tool=False)
        if p.name.startswith("home.") or p.name.rpartition(".")[2] in keep
    ]


def fit_controller_model(
    q: np.ndarray,
    T_base_flange: np.ndarray,
    reference: KinematicModel,
    *,
    length_scale_m: float = 1.0,
) -> ControllerFit:
    """The serial-chain model whose flange is at ``T_base_flange`` (N, 4, 4) for readings ``q``
    (N, n), starting from ``reference`` (the published table: its joint types, names, limits and
    units are kept; its base and tool are taken as identity, the controller's base and flange).

    Residuals: position differences (m) and flange rotation differences (rad) times
    ``length_scale_m``. Returns the model in ``dh`` form with its fit figures; the caller
    decides whether they are good enough (an exact fit reproduces a controller to rounding).
    """
    q = np.asarray(q, dtype=float)
    T_base_flange = np.asarray(T_base_flange, dtype=float)
    if q.ndim != 2 or q.shape[1] != reference.n_joints or T_base_flange.shape != (len(q), 4, 4):
        raise ValueError(
            f"expected q (N, {reference.n_joints}) and T_base_flange (N, 4, 4); got {q.shape} and {T_base_flange.shape}"
        )
    n_params = 4 * reference.n_joints + 6
    if len(q) * 6 < n_params:
        raise ValueError(f"{len(q)} poses give {6 * len(q)} equations for {n_params} parameters")
    if any(not j.revolute for j in reference.joints):
        raise ValueError("fit_controller_model handles revolute joints only")
    start = dataclasses.replace(
        reference,
        base=np.zeros(6),
        tool=np.zeros(6),
        coupling=None,
        joints=tuple(dataclasses.replace(j, gain=1.0, harmonic=None) for j in reference.joints),
        targets={},
    )
    poe = to_poe(start)
    params = _fit_parameters(poe)
    R_meas, p_meas = T_base_flange[:, :3, :3], T_base_flange[:, :3, 3]

    def residuals(x: np.ndarray) -> np.ndarray:
        T = fk(apply_step(poe, params, x), q)
        dr = matrix_to_rotvec(np.einsum("nji,njk->nik", R_meas, T[:, :3, :3]))
        return np.concatenate([(T[:, :3, 3] - p_meas).ravel(), length_scale_m * dr.ravel()])

    sol = least_squares(residuals, np.zeros(len(params)), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    fitted = apply_step(poe, params, sol.x)
    model = poe_to_dh(fitted, reference=start)
    model = dataclasses.replace(model, name=f"{reference.name.removesuffix('-nominal')}-controller", metadata={})
    dp, dr = pose_differences(model, q, T_base_flange)
    return ControllerFit(
        model=model,
        position_rms_m=float(np.sqrt(np.mean(dp**2))),
        position_max_m=float(dp.max()),
        rotation_max_rad=float(dr.max()),
        n_poses=len(q),
        iterations=int(sol.nfev),
        message=str(sol.message),
    )
