"""Cell preparation (issue 23): the named step a session takes with its open devices before its
first move (``service.cell_preparation.prepare_cell``). What it does follows what the robot's
driver declares (drivers/base.py: ``takes_payload``, ``kinematics_source``), never ``hasattr``:
here on the simulated controller's Modbus side (our driver and pymodbus' server, on NET.71 with a
free port), whose driver declares the TCP pose (with UR's register map) and no payload interface."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
from sqlmodel import Session

from calibration.robots import nominal, nominal_document
from drivers.modbus_robot import UR_REGISTER_MAP, ModbusRobot, ModbusRobotConfig
from drivers.ur_rtde import UrRtdeRobot
from fakes.modbus_server import ModbusRobotFake
from fakes.world import SimCell, draw_factory_calibration
from service.cell_preparation import CellPreparation, prepare_cell
from service.control import SessionStopped
from service.devices import CellDevices, parse_devices
from service.models import Cell, RunSession
from service.store import make_engine, migrate

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")
HOME = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])


@pytest.fixture
def modbus_fake():
    cell = SimCell(nominal("ur10e"), factory=draw_factory_calibration("ur10e", 4), q_home=HOME)
    fake = ModbusRobotFake(cell, host=f"{NET}.71", port=0)
    fake.start()
    host, port = fake.endpoint()["modbus"].rsplit(":", 1)
    yield host, int(port)
    fake.stop()


def _session(db: Session, plan_info: dict | None) -> tuple[Cell, RunSession]:
    cell = Cell(name="m", model=nominal_document("ur10e"), devices={})
    db.add(cell)
    db.commit()
    run = RunSession(cell_id=cell.id, kind="pose", planned=2, plan=[HOME.tolist(), HOME.tolist()], plan_info=plan_info)
    db.add(run)
    db.commit()
    return cell, run


def test_the_drivers_declare_what_preparation_uses():
    assert UrRtdeRobot.takes_payload and UrRtdeRobot.kinematics_source == "forward_kinematics"
    assert not ModbusRobot.takes_payload
    # what the cell's kind check asks before a session is stored, from the registry's driver
    assert parse_devices({"rtde": "10.0.0.1"}).robot_takes_payload
    assert not parse_devices({"modbus": "10.0.0.1:502"}).robot_takes_payload


def test_a_robot_that_reports_its_tcp_pose_is_sampled_and_nothing_moves(settings, modbus_fake):
    host, port = modbus_fake
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db, ModbusRobot(ModbusRobotConfig(host=host, port=port)) as robot:
        cell, run = _session(db, None)
        q_before = robot.read_joints()
        prepared = prepare_cell(db, run, cell, CellDevices(robot=robot))
        assert isinstance(prepared, CellPreparation)
        assert prepared.controller_model is None  # nothing stored to check against yet
        assert prepared.read_tcp_pose is not None and prepared.read_tcp_pose().shape == (4, 4)
        np.testing.assert_allclose(robot.read_joints(), q_before, atol=1e-9)
    engine.dispose()


def test_a_map_without_tcp_registers_declares_no_kinematics_and_nothing_is_sampled(settings, modbus_fake):
    host, port = modbus_fake
    no_tcp = dataclasses.replace(UR_REGISTER_MAP, tcp_pose=None)
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db, ModbusRobot(ModbusRobotConfig(host=host, port=port, register_map=no_tcp)) as robot:
        assert robot.kinematics_source is None
        cell, run = _session(db, None)
        prepared = prepare_cell(db, run, cell, CellDevices(robot=robot))
        assert prepared == CellPreparation(controller_model=None, read_tcp_pose=None)
    engine.dispose()


def test_payloads_on_a_robot_that_takes_none_fail_in_preparation_before_anything_moves(settings, modbus_fake):
    host, port = modbus_fake
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db, ModbusRobot(ModbusRobotConfig(host=host, port=port)) as robot:
        cell, run = _session(db, {"payloads": [[2.0, 0.0, 0.0, 0.05]]})
        q_before = robot.read_joints()
        with pytest.raises(SessionStopped) as stopped:
            prepare_cell(db, run, cell, CellDevices(robot=robot))
        assert stopped.value.state == "failed" and stopped.value.device == "robot"
        assert "a session with payloads needs a controller that takes one" in stopped.value.reason
        np.testing.assert_allclose(robot.read_joints(), q_before, atol=1e-9)
    engine.dispose()
