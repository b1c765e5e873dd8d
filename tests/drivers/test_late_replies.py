"""Late replies across processes: never a stale value.

A measuring device in a ``recal fake-cell`` answers one request later than its driver's
timeout (``--fault delay_at=N --fault delay_s=...``), and meanwhile the robot moves to another
pose (through the Modbus driver). The driver raises ``DeviceTimeoutError`` at its timeout, and
its next measurement belongs to the new pose: the late reply, which belongs to the old pose
and arrives while the next request is under way, is never taken for it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from calibration.kinematics import fk, joint_variables
from drivers.canopen_encoder import CanBusConfig, CanopenEncoder, CanopenEncoderConfig
from drivers.errors import DeviceTimeoutError
from drivers.ippdme import IppDmeCmm, IppDmeConfig
from drivers.leica_emscon import EmsconConfig, EmsconTracker
from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig
from drivers.tracker import LineTracker, TrackerConfig
from fakes.canopen_nodes import default_mount_offset_rad

TIMEOUT_S = 0.4
LATE_S = 0.7  # the late reply comes after the timeout, while the next request is under way
Q_A = np.zeros(6)  # where a cell's robot starts
Q_B = np.array([0.5, -0.4, 0.3, 0.2, 0.3, 0.4])
BALL_RADIUS_M = 0.0125  # the cell's tooling balls


def _target_world(truth, q: np.ndarray, name: str) -> np.ndarray:
    T = fk(truth, q[None, :])[0]
    return T[:3, :3] @ truth.targets[name] + T[:3, 3]


def _tracker(endpoint: dict):
    tracker = LineTracker(TrackerConfig(url=endpoint["tracker"], timeout_s=TIMEOUT_S))

    def error_m(truth, q: np.ndarray) -> float:
        return float(np.linalg.norm(tracker.measure().p_world - _target_world(truth, q, "smr1")))

    return tracker, error_m


def _emscon(endpoint: dict):
    config = EmsconConfig.from_endpoint(endpoint["emscon"], timeout_s=TIMEOUT_S - 0.1, measure_time_s=0.1)
    tracker = EmsconTracker(config)

    def error_m(truth, q: np.ndarray) -> float:
        return float(np.linalg.norm(tracker.measure().p_world - _target_world(truth, q, "smr1")))

    return tracker, error_m


def _cmm(endpoint: dict):
    cmm = IppDmeCmm(IppDmeConfig(url=endpoint["cmm"], timeout_s=TIMEOUT_S, move_timeout_s=2.0))

    def error_m(truth, q: np.ndarray) -> float:
        top = _target_world(truth, q, "ball1") + [0.0, 0.0, BALL_RADIUS_M]
        return float(np.linalg.norm(cmm.probe(top, np.array([0.0, 0.0, -1.0])) - top))

    return cmm, error_m


def _encoder(use_pdo: bool):
    def open_encoder(endpoint: dict):
        bus = CanBusConfig.from_endpoint(endpoint["can"])
        encoder = CanopenEncoder(CanopenEncoderConfig(bus=bus, node_id=17, use_pdo=use_pdo, timeout_s=TIMEOUT_S))

        def error_rad(truth, q: np.ndarray) -> float:
            expected = joint_variables(truth, q[None, :])[0, 0] + default_mount_offset_rad(17)
            difference = encoder.read().angle_rad - expected
            return abs((difference + math.pi) % (2 * math.pi) - math.pi)

        return encoder, error_rad

    return open_encoder


@dataclass(frozen=True)
class Late:
    device: str  # the cell's key of the device
    late_request: int  # which of the device's requests is answered late
    open: Callable[[dict], tuple[Any, Callable]]  # endpoint -> (driver, error from the truth at q)
    tolerance: float
    match: str  # the DeviceTimeoutError's message


CASES = {
    # handshake: requests 1-3; the second MEAS? is 5
    "tracker": Late("tracker", 5, _tracker, 1e-4, r"no reply to MEAS\? within 0\.4 s"),
    # set-up: commands 1-10 (with Initialize); the second StartMeasurement is 12
    "emscon": Late("emscon", 12, _emscon, 1e-4, r"no answer to command 49 within 0\.4 s"),
    # session: commands 1-10 (with Home); the second PtMeas is 12
    "cmm": Late("cmm", 12, _cmm, 1e-5, r"no acknowledgement of 00012 PtMeas\(.* within 0\.4 s"),
    # position requests: SDO uploads of 0x6004 or SYNCs; the set-up reads other objects
    "encoder-sdo": Late(
        "can", 2, _encoder(False), 3e-4, r"no SDO answer reading the position value 0x6004 within 0\.4 s"
    ),
    "encoder-pdo": Late("can", 2, _encoder(True), 3e-4, r"no TPDO1 \(COB-ID 0x191\) within 0\.4 s after SYNC"),
}


@pytest.mark.parametrize("case", CASES.values(), ids=CASES.keys())
def test_late_reply_is_never_taken_for_the_next_measurement(fault_cell, cell_truth, case):
    cell = fault_cell(only=("modbus", case.device), faults=(f"delay_at={case.late_request}", f"delay_s={LATE_S}"))
    host, port = cell.endpoint["modbus"].rsplit(":", 1)
    driver, error = case.open(cell.endpoint)
    with contextlib.closing(driver), ModbusRobot(ModbusRobotConfig(host, port=int(port))) as robot:
        assert error(cell_truth, Q_A) < case.tolerance
        with pytest.raises(DeviceTimeoutError, match=case.match):
            error(cell_truth, Q_A)
        robot.move_joints(Q_B, speed_rad_s=1.0, accel_rad_s2=2.0)
        assert error(cell_truth, Q_B) < case.tolerance
