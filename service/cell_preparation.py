"""Cell preparation: what a session does with its open devices before its first move, as one
named step (:func:`prepare_cell`), so that the session loop (``service.session_loop``) only moves,
measures and commits.

- the controller's own kinematics (``service.controller``, docs/devices/ur.md), by what the robot
  declares it tells (``Robot.kinematics_source``, drivers/base.py): one that answers forward
  kinematics (UR over RTDE) has its model read again; one that reports its TCP pose (UR over
  Modbus) has the stored model checked against it, and the session loop samples it where the
  robot stands so that the model can be fitted again after the last pose
  (:meth:`CellPreparation.after_measuring`);
- the device checks: a session that carries payloads needs a robot that takes one
  (``Robot.takes_payload``); it fails here, before anything moves, naming the controller.

What it found is a typed record (:class:`CellPreparation`); what happened to the controller's
model is also stored on the session (its controller event, `RunSession.record_controller`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sqlmodel import Session

from . import controller, records
from .control import SessionStopped
from .devices import CellDevices
from .models import Cell, RunSession
from .store import measured_count

# (q, T_base_tcp): the controller's TCP pose read where the robot stood, at readings q
TcpSample = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class CellPreparation:
    """What preparing the cell found: ``controller_model``, what reading or checking the
    controller's kinematics recorded (``version``, ``changed``, ``warning``, ...; None when the
    robot tells nothing of them); ``read_tcp_pose``, what the session loop calls where the robot
    stands to sample the controller's TCP pose (None: nothing to sample)."""

    controller_model: dict | None
    read_tcp_pose: Callable[[], np.ndarray] | None

    def after_measuring(self, db: Session, run: RunSession, cell: Cell, devices: CellDevices, samples: list[TcpSample]):
        """Every pose measured: the controller's model fitted from the TCP poses the loop sampled,
        when the cell has none yet or the check found the stored one changed
        (``controller.learn_from_registers``); what happened, or None."""
        if self.read_tcp_pose is None:
            return None
        return controller.learn_from_registers(db, run, cell, devices.robot, samples)


def prepare_cell(db: Session, run: RunSession, cell: Cell, devices: CellDevices) -> CellPreparation:
    """Check the open devices against what the session needs and read or check the controller's
    kinematics (the module docstring). Raises :class:`SessionStopped` (``failed``) for a session
    the devices cannot run; never for the controller's kinematics (the session goes on with what
    is stored, and the session's controller event says why)."""
    robot = devices.robot
    assert robot is not None  # opened first (service.session_loop.open_session_devices)
    info = controller.refresh_on_session_start(db, run, cell, robot)
    check_payloads(db, run, robot)
    return CellPreparation(controller_model=info, read_tcp_pose=controller.register_sampler(cell, robot))


def check_payloads(db: Session, run: RunSession, robot) -> None:
    """A session with payloads still to measure needs a controller that takes the payload."""
    if robot.takes_payload or records.payload_of(run, np.arange(1)) is None:
        return
    assert run.id is not None  # a stored session
    if measured_count(db, run.id) >= len(run.plan or []):
        return  # every configuration is measured: nothing more is mounted
    raise no_payload_interface(robot)


def no_payload_interface(robot, exc: Exception | None = None) -> SessionStopped:
    """The session's end when its controller has no payload interface (said so, or found out)."""
    cause = exc or NotImplementedError(f"{type(robot).__name__}: this controller has no payload interface")
    return SessionStopped(
        "failed",
        f"{cause}: a session with payloads needs a controller that takes one (UR)",
        device="robot",
        cause=cause,
    )
