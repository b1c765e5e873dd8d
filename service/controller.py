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

import dataclasses
from datetime import UTC, datetime

import numpy as np

from calibration import robots
from calibration.controller import fit_controller_model, pose_differences
from calibration.errors import RecalError
from calibration.model import KinematicModel, model_to_dict
from calibration.transforms import matrix_to_rotvec

BLOCK = "controller"  # the check figures' field in the model document
DEFAULT_TOLERANCE_M = 1e-6  # "exact": the controller reproduced to 1 um (and 1 urad)
# "get robot model" (dashboard) -> the library's published table; e-Series answer without the "e".
_DASHBOARD_MODELS = {"UR3": "ur3e", "UR5": "ur5e", "UR10": "ur10e", "UR16": "ur16e"}


class ControllerModelError(RecalError, ValueError):
    """The controller's kinematics could not be read or fitted exactly (one line for the user)."""


def library_name(robot_model: str) -> str:
    """The library robot for a dashboard ``get robot model`` answer (``UR5`` -> ``ur5e``)."""
    key = robot_model.strip().upper().removesuffix("E")
    if key not in _DASHBOARD_MODELS:
        raise ControllerModelError(
            f"the controller says it is a {robot_model.strip()!r}, which is no UR arm in the "
            f"library ({', '.join(sorted(_DASHBOARD_MODELS))}): give --robot"
        )
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
            f"nothing written"
        )
    doc = model_to_dict(fit.model)
    doc[BLOCK] = {
        "source": source,
        "method": "get_forward_kin (ur_rtde getForwardKinematics), tool offset zero; nothing moved",
        "reference": reference.name,
        "read_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "poses_fit": n_fit,
        "poses_check": n_check,
        "tolerance_um": tolerance_m * 1e6,
        "fit": {
            "position_rms_um": fit.position_rms_m * 1e6,
            "position_max_um": fit.position_max_m * 1e6,
            "rotation_max_urad": fit.rotation_max_rad * 1e6,
        },
        "check": {
            "position_rms_um": float(np.sqrt(np.mean(dp**2))) * 1e6,
            "position_max_um": float(dp.max()) * 1e6,
            "rotation_max_urad": float(dr.max()) * 1e6,
        },
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
        raise ControllerModelError(
            f"{name}: no UR arm (a UR controller's published table is one of "
            f"{', '.join(sorted(_DASHBOARD_MODELS.values()))})"
        )
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


# --------------------------------------------------------------------------- the cell's copy

# At a session's start fewer configurations do: 12 + 12 still over-determine the 30 parameters
# sixfold, and the session waits for them.
SESSION_POSES = 12
# UR's TCP-pose registers resolve 0.1 mm and 1 mrad: a stored model that disagrees with them by
# more than this has changed (or the TCP offset is not zero).
MODBUS_POSITION_TOL_M = 0.2e-3
MODBUS_ROTATION_TOL_RAD = 2e-3


def controller_nominal(db, cell) -> dict:
    """What the cell's controller computes with: its controller model (newest version) where one
    was read, else the cell's nominal model. Targets mode, URScript pose targets and the
    nominal model of compensation use it."""
    from .store import current_controller_model

    rec = current_controller_model(db, cell.id)
    return rec.model if rec is not None else cell.model


def refresh_on_session_start(db, run, cell, robot) -> dict | None:
    """A session starts on the cell: read its controller's kinematics again where the robot
    answers forward kinematics (UR over RTDE; ``Robot.kinematics_source``) and store a new
    version when it is the first or it changed, or, where it reports its TCP pose (UR over
    Modbus), check the stored one against it. What happened is the session's controller event
    (``RunSession.record_controller``: ``version``, ``changed``, ``warning``; the public
    ``plan_info.controller_model``) and, for a change, the audit log. Never raises for the
    controller's sake: the session goes on with what is stored."""
    from drivers.errors import DeviceError

    from .store import add_controller_model, audit, current_controller_model

    stored = current_controller_model(db, cell.id)
    info, new_doc = None, None
    try:
        if robot.kinematics_source == "forward_kinematics":
            info, new_doc = _read_again(run, cell, robot, stored)
        elif robot.kinematics_source == "tcp_pose" and stored is not None:
            info = _check_registers(robot, stored)
    except (ControllerModelError, DeviceError, ValueError) as exc:
        info = {
            "version": None if stored is None else stored.version,
            "changed": None,
            "warning": f"the controller's kinematics could not be read: {exc}",
        }
    if info is None:
        return None
    if new_doc is not None:
        moved_m = None if info["moved_mm"] is None else info["moved_mm"] * 1e-3
        rec = add_controller_model(db, cell_id=cell.id, model=new_doc, session_id=run.id, moved_m=moved_m)
        info["version"] = rec.version
        if info["changed"]:
            audit(
                db,
                actor=f"session {run.id}",
                action="controller model changed",
                subject=f"cell {cell.id}",
                detail={"version": rec.version, "moved_mm": info["moved_mm"]},
            )
    _record(db, run, info)
    return info


def _record(db, run, info: dict) -> None:
    """Store what the session did with the controller's kinematics (``RunSession.controller_event``,
    the public ``plan_info.controller_model``), committed."""
    from .models import ControllerEvent

    run.record_controller(ControllerEvent.from_json(info))
    db.add(run)
    db.commit()
    db.refresh(run)


def _read_again(run, cell, robot, stored) -> tuple[dict, dict | None]:
    """Read the controller's model through the session's robot: (what happened, the document
    to store as a new version, or ``None`` when it is the stored one)."""
    from calibration.model import model_from_dict

    reference = model_from_dict(cell.model)
    doc = read_controller_model(
        robot, reference, source=f"session {run.id}", n_fit=SESSION_POSES, n_check=SESSION_POSES, seed=run.id or 0
    )
    moved = models_differ(stored.model if stored is not None else None, doc)
    if stored is not None and moved is None:
        return {"version": stored.version, "changed": False, "warning": None}, None
    info = {
        "version": None,
        "changed": stored is not None,
        "warning": None,
        "moved_mm": None if moved is None else moved * 1e3,
    }
    if stored is not None:
        info["warning"] = (
            f"the controller's kinematics changed since version {stored.version} (its flange moves "
            f"up to {moved * 1e3:.3g} mm): its factory calibration was replaced; the new version is "
            f"used from now on, earlier compensations used the old one"
        )
    return info, doc


def register_tolerances(model: KinematicModel, q: np.ndarray, joint_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """How far (position m, rotation rad; each (N,)) UR's TCP-pose registers may lie from an
    exact model of the controller at readings ``q`` (N, 6): the registers' resolution
    (``MODBUS_*_TOL``, about twice it) plus what the joint readings' own resolution moves the
    flange (``J · resolution / 2``, summed over the joints): tight with the motion program's
    microradian joints, about a millimetre with UR's milliradian joint registers."""
    from calibration.ik import geometric_jacobian

    J = geometric_jacobian(model, np.atleast_2d(q))
    half_step = 0.5 * joint_step_rad
    tol_p = MODBUS_POSITION_TOL_M + half_step * np.sum(np.linalg.norm(J[:, :3], axis=1), axis=1)
    tol_r = MODBUS_ROTATION_TOL_RAD + half_step * np.sum(np.linalg.norm(J[:, 3:], axis=1), axis=1)
    return tol_p, tol_r


def _check_registers(robot, stored) -> dict:
    """Over Modbus: the stored model at the joints now against UR's TCP-pose registers, within
    :func:`register_tolerances`."""
    from calibration.kinematics import fk
    from calibration.model import model_from_dict

    model = model_from_dict(stored.model)
    q = robot.read_joints()
    T_registers = robot.read_tcp_pose()
    T_model = fk(model, q[None, :])[0]
    dp = float(np.linalg.norm(T_model[:3, 3] - T_registers[:3, 3]))
    dr = float(np.linalg.norm(matrix_to_rotvec(T_model[:3, :3].T @ T_registers[:3, :3])))
    tol_p, tol_r = (float(t[0]) for t in register_tolerances(model, q, robot.joint_resolution_rad))
    info = {
        "version": stored.version,
        "changed": None,
        "warning": None,
        "tcp_registers_mm": dp * 1e3,
        "tolerance_mm": tol_p * 1e3,
    }
    if dp > tol_p or dr > tol_r:
        info["changed"] = True
        info["warning"] = (
            f"UR's TCP-pose registers disagree with the stored controller model (version "
            f"{stored.version}) by {dp * 1e3:.3g} mm and {np.rad2deg(dr):.3g} deg (tolerance "
            f"{tol_p * 1e3:.2g} mm): the controller's kinematics (or its TCP offset) changed; read it "
            f"again: recal controller-model --rtde HOST"
        )
    return info


# ----------------------------------------------------------- over Modbus: the TCP-pose registers

# Over Modbus the controller answers no forward-kinematics query: its own kinematics shows only
# where the robot stands, in UR's TCP-pose registers (0.1 mm, 1 mrad). A session reads them at
# every configuration it measures, and fits the controller's model from them (the same fit as
# over RTDE) when the cell has none yet or the stored one no longer agrees with them. Not exact:
# on the simulated UR10e, 30 configurations give the controller to about 30 um RMS with the
# motion program's microradian joints and 0.2 mm with UR's milliradian ones (the published
# table: 4 mm).
REGISTER_MIN_POSES = 12  # 72 equations for the fit's 30 parameters
# The registers resolve 0.1 mm and 1 mrad: rotation residuals weigh as position ones at 0.1 m.
REGISTER_LENGTH_SCALE_M = 0.1
# The registers give the TCP, and the fit's flange frame would take in a TCP offset unnoticed. A
# factory calibration moves the flange by millimetres from the published table; a fit further
# off than this is refused as a TCP offset that is not zero (a smaller one is not seen: the TCP
# must be the flange while the session runs, as the docs say).
REGISTER_MAX_FROM_PUBLISHED_M = 0.02


def register_sampler(cell, robot):
    """On a cell whose robot reports its TCP pose (``kinematics_source == "tcp_pose"``: UR's
    TCP-pose registers over Modbus) and a six-revolute-joint nominal model: the function that
    reads it (``T_base_tcp`` (4, 4)) where the session's robot stands; ``None`` otherwise (a
    robot that answers forward kinematics has its model read at the session's start)."""
    if robot.kinematics_source != "tcp_pose":
        return None
    joints = (cell.model or {}).get("joints") or []
    if len(joints) != 6 or any(j.get("type", "revolute") != "revolute" for j in joints):
        return None
    return robot.read_tcp_pose


def model_from_registers(
    q: np.ndarray, T_registers: np.ndarray, reference: KinematicModel, *, source: str, joint_step_rad: float
) -> dict:
    """The controller's model fitted to its TCP-pose registers ``T_registers`` (N, 4, 4) read at
    readings ``q`` (N, 6) rad, as a ``recal.model/1`` document with a ``controller`` block (its
    figures are the residuals to the registers). ``ControllerModelError`` when there are fewer
    than ``REGISTER_MIN_POSES`` or a register lies beyond :func:`register_tolerances` of the fit
    (the controller's TCP offset is not zero, or it is no serial chain of this robot)."""
    q, T_registers = np.asarray(q, dtype=float), np.asarray(T_registers, dtype=float)
    if len(q) < REGISTER_MIN_POSES:
        raise ControllerModelError(
            f"{source}: {len(q)} configurations with TCP-pose registers, at least {REGISTER_MIN_POSES} needed"
        )
    fit = fit_controller_model(q, T_registers, reference, length_scale_m=REGISTER_LENGTH_SCALE_M)
    dp, dr = pose_differences(fit.model, q, T_registers)
    tol_p, tol_r = register_tolerances(fit.model, q, joint_step_rad)
    worst = int(np.argmax(np.maximum(dp / tol_p, dr / tol_r)))
    robot = reference.name.removesuffix("-nominal")
    if dp[worst] > tol_p[worst] or dr[worst] > tol_r[worst]:
        raise ControllerModelError(
            f"{source}: the TCP-pose registers lie {dp[worst] * 1e3:.3g} mm and {np.rad2deg(dr[worst]):.3g} deg from "
            f"the best serial chain (tolerance {tol_p[worst] * 1e3:.2g} mm): they do not belong to the joints read "
            f"with them, or the controller is no {robot}; nothing stored"
        )
    published = dataclasses.replace(reference, base=np.zeros(6), tool=np.zeros(6), targets={})
    off = models_differ(model_to_dict(published), model_to_dict(fit.model), tolerance_m=REGISTER_MAX_FROM_PUBLISHED_M)
    if off is not None:
        raise ControllerModelError(
            f"{source}: the TCP-pose registers are up to {off * 1e3:.3g} mm from the published {robot} table (a "
            f"factory calibration moves it millimetres): the controller's TCP offset is not zero (set it to the "
            f"flange for the session), or it is no {robot}; nothing stored"
        )
    doc = model_to_dict(fit.model)
    figures = {
        "position_rms_um": float(np.sqrt(np.mean(dp**2))) * 1e6,
        "position_max_um": float(dp.max()) * 1e6,
        "rotation_max_urad": float(dr.max()) * 1e6,
    }
    doc[BLOCK] = {
        "source": source,
        "method": "UR TCP-pose registers 400-405 over Modbus (0.1 mm, 1 mrad) at the configurations a "
        f"session measured, joints read to {joint_step_rad * 1e6:g} urad; fitted, not exact",
        "reference": reference.name,
        "read_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "poses_fit": len(q),
        "poses_check": 0,
        "tolerance_um": float(tol_p.max()) * 1e6,
        "fit": figures,
        "check": figures,  # the registers are all there is to check against
    }
    return doc


def learn_from_registers(db, run, cell, robot, samples: list[tuple[np.ndarray, np.ndarray]]) -> dict | None:
    """After a session measured over Modbus: fit the controller's model from the TCP-pose
    registers read at its configurations (``samples``: (q, T_base_tcp) pairs) and store it as a
    new version when the cell has none, or when the check at the session's start found the
    stored one disagreeing with the registers (then the audit log gets "controller model
    changed"). An exact model read over RTDE that agrees is kept. The session's controller event
    (``RunSession.controller()``) says what happened; never raises for the controller's sake."""
    from calibration.model import model_from_dict

    from .store import add_controller_model, audit, current_controller_model

    if not samples:
        return None
    stored = current_controller_model(db, cell.id)
    started = run.controller()
    at_start = {} if started is None else started.to_json()
    if stored is not None and not (started is not None and started.changed):
        return None
    q = np.array([s[0] for s in samples])
    T = np.array([s[1] for s in samples])
    try:
        doc = model_from_registers(
            q,
            T,
            model_from_dict(cell.model),
            source=f"session {run.id} (TCP-pose registers)",
            joint_step_rad=robot.joint_resolution_rad,
        )
    except (ControllerModelError, ValueError) as exc:
        info = {
            **at_start,
            "version": None if stored is None else stored.version,
            "warning": " ".join(
                w for w in (at_start.get("warning"), f"no model fitted from the registers: {exc}") if w
            ),
        }
    else:
        moved = models_differ(None if stored is None else stored.model, doc)
        rec = add_controller_model(db, cell_id=cell.id, model=doc, session_id=run.id, moved_m=moved)
        info = {
            **at_start,
            "version": rec.version,
            "changed": stored is not None,
            "warning": at_start.get("warning"),
            "moved_mm": None if moved is None else moved * 1e3,
            "from_registers": True,
            "registers_rms_um": doc[BLOCK]["fit"]["position_rms_um"],
        }
        if stored is not None:
            audit(
                db,
                actor=f"session {run.id}",
                action="controller model changed",
                subject=f"cell {cell.id}",
                detail={"version": rec.version, "moved_mm": info["moved_mm"], "from_registers": True},
            )
    _record(db, run, info)
    return info


def controller_summary(db, cell) -> dict | None:
    """The cell's controller model as the page shows it (``None``: never read)."""
    from sqlmodel import func, select

    from .models import ControllerModel
    from .store import current_controller_model

    rec = current_controller_model(db, cell.id)
    if rec is None:
        return None
    block = (rec.model or {}).get(BLOCK) or {}
    versions = db.exec(select(func.count(ControllerModel.id)).where(ControllerModel.cell_id == cell.id)).one()
    return {
        "version": rec.version,
        "versions": int(versions),
        "name": rec.model.get("name"),
        "source": block.get("source"),
        "read_at": block.get("read_at"),
        "session_id": rec.session_id,
        "check_um": (block.get("check") or {}).get("position_max_um"),
        # fitted to UR's TCP-pose registers over Modbus (check_um: to them), not read exactly over RTDE
        "from_registers": "TCP-pose registers" in str(block.get("method", "")),
        "moved_mm": None if rec.moved_m is None else rec.moved_m * 1e3,
        "created_at": rec.created_at.isoformat(),
    }


def controller_document(db, cell) -> dict:
    """The controller model the cell keeps, as ``GET /cells/{id}/controller-model`` answers: the
    newest version's ``recal.model/1`` document with its summary, and every version's summary.
    :class:`~service.problems.NotFound` when none was read or uploaded."""
    from sqlmodel import select

    from .models import ControllerModel
    from .problems import NotFound

    summary = controller_summary(db, cell)
    if summary is None:
        raise NotFound(
            f"cell {cell.id} has no controller model: a session on a UR cell over RTDE reads it, "
            f"or upload the file `recal controller-model` writes"
        )
    rows = db.exec(
        select(ControllerModel).where(ControllerModel.cell_id == cell.id).order_by(ControllerModel.version.desc())
    ).all()
    return {
        **summary,
        "model": rows[0].model,
        "history": [
            {
                "version": r.version,
                "session_id": r.session_id,
                "created_at": r.created_at,
                "moved_mm": None if r.moved_m is None else r.moved_m * 1e3,
            }
            for r in rows
        ],
    }


def store_controller_document(db, cell, doc: dict, *, actor: str) -> dict:
    """Store a controller model written by ``recal controller-model`` as the cell's newest
    version (audited); its summary. :class:`~service.problems.Invalid` naming the field when it
    is not a model or lacks the check figures block."""
    from calibration.model import ModelFormatError, model_from_dict

    from .problems import Invalid
    from .store import add_controller_model, audit, current_controller_model

    try:
        model_from_dict(doc)
    except ModelFormatError as exc:
        raise Invalid(f"body.{exc.field}" if exc.field else "body", str(exc).split(": ", 1)[-1]) from None
    if not isinstance(doc.get(BLOCK), dict):
        raise Invalid(f"body.{BLOCK}", "expected the check figures block `recal controller-model` writes")
    last = current_controller_model(db, cell.id)
    rec = add_controller_model(
        db, cell_id=cell.id, model=doc, moved_m=models_differ(None if last is None else last.model, doc)
    )
    audit(db, actor=actor, action="upload controller model", subject=f"cell {cell.id}", detail={"version": rec.version})
    return controller_summary(db, cell)
