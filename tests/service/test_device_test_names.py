"""The connection test tests what it names (issue 22, case 6): a cell with an RTDE address where
nothing listens beside a live Modbus robot (the simulated controller's Modbus server, read by
the pymodbus-based driver). The RTDE row tested the Modbus robot (a closure over a variable the
next branch reassigned), said ok and named itself after it."""

from __future__ import annotations

import dataclasses

import pytest

from calibration.robots import nominal
from fakes.modbus_server import ModbusRobotFake
from fakes.world import SimCell
from service.processes import free_port

from .conftest import auth, register_cell


@pytest.fixture
def client(idle_app, tokens):
    with idle_app() as c:
        yield c


def test_an_unreachable_rtde_beside_a_live_modbus_robot_is_reported_as_itself(client, tokens):
    fake = ModbusRobotFake(
        SimCell(dataclasses.replace(nominal("ur5e"), targets={"smr": [0.0, 0.0, 0.05]})), "127.0.0.1", 0
    )
    fake.start()
    try:
        cell = register_cell(client, tokens["technician"], "two-robots")
        t = auth(tokens["technician"])
        nobody = f"127.0.0.1:{free_port()}"  # a port where nothing listens
        devices = {"rtde": nobody.split(":", maxsplit=1)[0], "modbus": fake.endpoint()["modbus"]}
        r = client.patch(f"/api/v1/cells/{cell['id']}", json={"devices": devices}, headers=t)
        assert r.status_code == 200, r.text
        res = client.post(f"/api/v1/cells/{cell['id']}/devices/test?timeout_s=3", headers=t).json()["results"]
        rows = {r["device"]: r for r in res}
        assert set(rows) == {"robot (UR RTDE)", "robot (Modbus TCP)"}, res
        rtde, modbus = rows["robot (UR RTDE)"], rows["robot (Modbus TCP)"]
        assert modbus["ok"] and "Modbus" in modbus["name"], modbus
        assert not rtde["ok"] and "Modbus" not in str(rtde), rtde
    finally:
        fake.stop()
