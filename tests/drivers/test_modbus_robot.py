"""The Modbus TCP robot driver (pymodbus client) against the simulated UR controller's Modbus
server in another process, and the server's own behaviour in this one."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from robot_contract import HOME, RobotContract

from calibration.model import model_from_dict
from drivers.errors import DeviceTimeoutError, ProtocolError
from drivers.modbus_robot import (
    UR_REGISTER_MAP,
    UR_REGISTER_MAP_HIRES,
    ModbusRegisterMap,
    ModbusRobot,
    ModbusRobotConfig,
)
from fakes.modbus_server import ModbusRobotFake
from fakes.world import SimCell

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

TRUTH_PATH = Path(__file__).with_name("ur5e_truth.json")  # the cells' truth (conftest.py)


def connect(endpoint: dict, **config) -> ModbusRobot:
    host, port = endpoint["modbus"].rsplit(":", 1)
    return ModbusRobot(ModbusRobotConfig(host, port=int(port), **{"timeout_s": 0.5, **config}))


class TestModbusRobot(RobotContract):
    tolerance_rad = 1e-3  # UR's joint registers resolve 1 mrad
    # ten requests in a row lose their connection: more than one retry can repair
    drop_faults = ("--fault", "drop_connection_at=" + ",".join(str(n) for n in range(15, 25)))

    def connect(self, endpoint: dict) -> ModbusRobot:
        return connect(endpoint)


def test_microradian_registers_of_the_motion_program_agree_with_ur_registers(fake_cell):
    target = np.array([-4.0, -1.2, 5.0, -1.6, -1.5, 0.0004])
    with (
        connect(fake_cell.endpoint) as native,
        connect(fake_cell.endpoint, register_map=UR_REGISTER_MAP_HIRES) as hires,
    ):
        hires.move_joints(target, speed_rad_s=1.0, accel_rad_s2=2.0)
        np.testing.assert_allclose(hires.read_joints(), target, atol=1e-6)
        np.testing.assert_allclose(native.read_joints(), target, atol=5e-4)


def test_one_dropped_connection_is_repaired_transparently(fault_cell):
    cell = fault_cell("--fault", "drop_connection_at=4")
    with connect(cell.endpoint) as robot:
        for _ in range(3):
            robot.read_joints()
        robot.move_joints(HOME, speed_rad_s=1.0, accel_rad_s2=2.0)
        np.testing.assert_allclose(robot.read_joints(), HOME, atol=1e-3)
        assert robot.reconnects == 1


def test_one_garbled_reply_is_read_again(fault_cell):
    cell = fault_cell("--fault", "garble_at=3")
    with connect(cell.endpoint) as robot:
        readings = [robot.read_joints() for _ in range(3)]
        assert robot.reconnects == 1
        np.testing.assert_allclose(readings[0], readings[2], atol=1e-3)


def test_garbled_replies_give_a_protocol_error(fault_cell):
    cell = fault_cell("--fault", "garble_rate=1")
    with pytest.raises(ProtocolError, match="garbled"):
        connect(cell.endpoint)


def test_slow_controller_times_out(fault_cell):
    cell = fault_cell("--fault", "delay_s=1")
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match=r"no answer within 0.2 s"):
        connect(cell.endpoint, timeout_s=0.2)
    assert time.monotonic() - started < 2.0


def test_register_map_and_config_are_checked():
    with pytest.raises(ValueError, match="joint_angle_scale"):
        ModbusRegisterMap(joint_angle_scale=0.0)
    with pytest.raises(ValueError, match="joint_limits_rad"):
        ModbusRobot(ModbusRobotConfig(f"{NET}.19", joint_limits_rad=((-1.0, 1.0),)))
    assert UR_REGISTER_MAP.joint_angle == 270 and UR_REGISTER_MAP.joint_turns == 320


def test_fake_takes_a_free_port_when_its_port_is_taken():
    truth = model_from_dict(json.loads(TRUTH_PATH.read_text()))
    first = ModbusRobotFake(SimCell(truth), "127.0.0.1", 0)
    first.start()
    try:
        second = ModbusRobotFake(SimCell(truth), "127.0.0.1", first.port)
        second.start()
        try:
            assert second.port not in (0, first.port)
            assert second.endpoint() == {"modbus": f"127.0.0.1:{second.port}"}
            with connect(second.endpoint()) as robot:
                np.testing.assert_allclose(robot.read_joints(), np.zeros(6), atol=1e-3)
        finally:
            second.stop()
            second.stop()
    finally:
        first.stop()
