"""The UR controller's own kinematics, read from the controller (issue 16).

A UR controller computes ``actual_TCP_pose``, ``get_forward_kin()``, ``get_inverse_kin()`` and
every Cartesian target of a program with its factory calibration, not with the published DH
table. :func:`read_controller_model` asks it for ``get_forward_kin(q)`` (``ur_rtde``'s
``getForwardKinematics``, tool offset zero) at configurations it never moves to, fits its model
exactly (:func:`calibration.controller.fit_controller_model`), checks it on other configurations
and returns a ``recal.model/1`` document with a ``controller`` block of check figures. The
``recal controller-model`` command writes it; a session on a UR cell refreshes the cell's copy.
"""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np

from calibration import robots
from calibration.controller import fit_controller_model, pose_differences
from calibration.model import KinematicModel, model_to_dict

BLOCK = "controller"  # the check figures' field in the model document
DEFAULT_TOLERANCE_M = 1e-6  # "exact": the controller reproduced to 1 um (and 1 urad)
# "get robot model" (dashboard) -> the library's published table; e-Series answer without the "e".
_DASHBOARD_MODELS = {"UR3": "ur3e", "UR5": "ur5e", "UR10": "ur10e", "UR16": "ur16e"}


class ControllerModelError(ValueError):
    """The controller's kinematics could not be read or fitted exactly (one line for the user)."""


def library_name(robot_model: str) -> str:
    """The library robot for a dashboard ``get robot model`` answer (``UR5`` -> ``ur5e``)."""
    key = robot_model.strip().upper().removesuffix("E")
    if key not in _DASHBOARD_MODELS:
        raise ControllerModelError(f"the controller says it is a {robot_model.strip()!r}, which is no UR arm in the "
                                   f"library ({', '.join(sorted(_DASHBOARD_MODELS))}): give --robot")
    return _DASHBOARD_MODELS[key]


def probe_configurations(n: int, seed: int = 0) -> np.ndarray:
    """``n`` readings (n, 6) rad to ask the controller about: the zero configuration, then
    uniform within ±pi (nothing moves there: they only need to be distinct)."""
    q = np.random.default_rng(seed).uniform(-np.pi, np.pi, (n, 6))
    q[0] = 0.0
    return q


def read_controller_model(
    robot,
    reference: KinematicModel,
    *,
    source: str,
    n_fit: int = 48,
    n_check: int = 48,
    seed: int = 0,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
) -> dict:
    """The controller's model as a ``recal.model/1`` document, in ``reference``'s units (the
    published table it starts from; its names and limits are kept).

    ``robot`` has ``forward_kinematics(q) -> T_base_tcp (N, 4, 4)`` (``UrRtdeRobot``). The fit
    uses ``n_fit`` configurations, the check ``n_check`` others; both must reproduce the
    controller within ``tolerance_m`` (and ``tolerance_m`` per metre in rotation), else
    ``ControllerModelError``: a model that is not exact is never returned."""
    q = probe_configurations(n_fit + n_check, seed)
    T = robot.forward_kinematics(q)
    q_fit, q_check = q[:n_fit], q[n_fit:]
    fit = fit_controller_model(q_fit, T[:n_fit], reference)
    dp, dr = pose_differences(fit.model, q_check, T[n_fit:])
    worst_m = max(fit.position_max_m, float(dp.max()))
    worst_rad = max(fit.rotation_max_rad, float(dr.max()))
    if worst_m > tolerance_m or worst_rad > tolerance_m:
        raise ControllerModelError(
            f"the fitted model reproduces {source}'s forward kinematics only to {worst_m * 1e6:.3g} um and "
            f"{worst_rad * 1e6:.3g} urad (tolerance {tolerance_m * 1e6:g}): this controller does not compute with "
            f"a serial chain of revolute joints that Recal can fit (or it is not a {reference.name.removesuffix('-nominal')}); "
            f"nothing written")
    doc = model_to_dict(fit.model)
    doc[BLOCK] = {
        "source": source,
        "method": "get_forward_kin (ur_rtde getForwardKinematics), tool offset zero; nothing moved",
        "reference": reference.name,
        "read_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "poses_fit": n_fit,
        "poses_check": n_check,
        "tolerance_um": tolerance_m * 1e6,
        "fit": {"position_rms_um": fit.position_rms_m * 1e6, "position_max_um": fit.position_max_m * 1e6,
                "rotation_max_urad": fit.rotation_max_rad * 1e6},
        "check": {"position_rms_um": float(np.sqrt(np.mean(dp**2))) * 1e6, "position_max_um": float(dp.max()) * 1e6,
                  "rotation_max_urad": float(dr.max()) * 1e6},
    }
    return doc


def reference_model(name: str | None, robot_model: str | None) -> KinematicModel:
    """The published table to start from: library robot ``name``, else the one the dashboard's
    ``get robot model`` answer names."""
    if name is None:
        if robot_model is None:
            raise ControllerModelError("no robot model: give --robot")
        name = library_name(robot_model)
    try:
        model = robots.nominal(name)
    except KeyError as exc:
        raise ControllerModelError(str(exc.args[0])) from None
    if name.lower() not in _DASHBOARD_MODELS.values():
        raise ControllerModelError(f"{name}: no UR arm (a UR controller's published table is one of "
                                   f"{', '.join(sorted(_DASHBOARD_MODELS.values()))})")
    return model


def models_differ(old: dict | None, new: dict, *, tolerance_m: float = DEFAULT_TOLERANCE_M) -> float | None:
    """How far (m, worst flange position over the probe configurations) the controller model
    ``new`` moved from ``old``; ``None`` when they agree within ``tolerance_m`` (or there was
    none before)."""
    from calibration.kinematics import fk
    from calibration.model import model_from_dict

    if old is None:
        return None
    a, b = model_from_dict(old), model_from_dict(new)
    q = probe_configurations(32, seed=1)
    d = float(np.max(np.linalg.norm(fk(a, q)[:, :3, 3] - fk(b, q)[:, :3, 3], axis=1)))
    return d if d > tolerance_m else None
