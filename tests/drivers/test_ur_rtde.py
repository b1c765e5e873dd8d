"""The UR RTDE driver (ur_rtde 1.6.5) against the simulated UR controller in another process.

``ur_rtde`` runs only in the driver's worker process or in a child process here: its
constructors hold the GIL while they wait, so it never runs in the test process itself.
"""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from robot_contract import HOME, RobotContract

from calibration import robots
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.transforms import rotvec_to_matrix
from drivers import ur_rtde
from drivers.errors import (
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    DeviceUnavailableError,
    ProtocolError,
)
from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot
from fakes.world import draw_factory_calibration

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

TRUTH_PATH = Path(__file__).with_name("ur5e_truth.json")  # the cells' truth (conftest.py)
needs_ur_rtde = pytest.mark.skipif(importlib.util.find_spec("rtde_control") is None, reason="ur_rtde is not installed")


@needs_ur_rtde
class TestUrRtdeRobot(RobotContract):
    tolerance_rad = 1e-9
    drop_faults = ("--fault", "drop_connection_at=2")  # the second command the script receives

    def connect(self, endpoint: dict) -> UrRtdeRobot:
        return UrRtdeRobot(UrRtdeConfig(endpoint["rtde"], probe_timeout_s=1.0))


@needs_ur_rtde
def test_hundred_moves_at_time_scale_zero_take_well_under_ten_seconds(fake_cell):
    with UrRtdeRobot(UrRtdeConfig(fake_cell.host)) as robot:
        started = time.monotonic()
        for i in range(100):
            robot.move_joints(HOME + 0.001 * i, speed_rad_s=1.0, accel_rad_s2=2.0)
        elapsed_s = time.monotonic() - started
        np.testing.assert_allclose(robot.read_joints(), HOME + 0.099, atol=1e-9)
    assert elapsed_s < 5.0, f"100 moves took {elapsed_s:.2f} s"


@needs_ur_rtde
def test_unmodified_ur_rtde_reads_the_robot_as_its_controller_computes_it_with_its_default_recipe(fake_cell):
    """The full default output recipe of RTDEReceiveInterface: a wrong type anywhere in the
    fake's table would shift every later field. Run in a child process (GIL, hangs).

    ``actual_TCP_pose`` is the controller's own forward kinematics (its factory calibration,
    here the one ``fakes.cell`` draws for the UR5e truth with --factory-seed 0, in the robot's
    base frame), not the true pose in the world: this test assumed the latter until the fake
    got a factory calibration, as a real controller has."""
    script = textwrap.dedent(
        f"""
        import json, rtde_receive, rtde_control
        c = rtde_control.RTDEControlInterface({fake_cell.host!r})
        assert c.moveJ({[float(v) for v in HOME + 0.3]!r}, 1.0, 2.0)  # blocking moveJ
        r = rtde_receive.RTDEReceiveInterface({fake_cell.host!r})
        print(json.dumps(dict(q=r.getActualQ(), pose=r.getActualTCPPose(), mode=r.getRobotMode(),
              safety=r.getSafetyMode(), bits=r.getSafetyStatusBits(), runtime=r.getRuntimeState(),
              voltage=r.getActualMainVoltage(), joint_mode=r.getJointMode())))
        c.stopScript()
        c.disconnect(); r.disconnect()
        """
    )
    ur_rtde.probe_controller(fake_cell.host, 1.0)  # never start ur_rtde on a broken fake
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(got["q"], HOME + 0.3, atol=1e-12)
    controller = draw_factory_calibration("ur5e", 0).model()
    T = fk(controller, (HOME + 0.3)[None, :])[0]
    np.testing.assert_allclose(got["pose"][:3], T[:3, 3], atol=1e-9)
    published = fk(model_from_dict(robots.nominal_document("ur5e")), (HOME + 0.3)[None, :])[0]
    assert np.linalg.norm(published[:3, 3] - T[:3, 3]) > 0.2e-3  # not the published table
    np.testing.assert_allclose(rotvec_to_matrix(np.array(got["pose"][3:])), T[:3, :3], atol=1e-9)
    assert (got["mode"], got["safety"], got["bits"], got["runtime"]) == (7, 1, 1, 2)
    assert got["voltage"] == 48.0
    assert got["joint_mode"] == [253] * 6


@needs_ur_rtde
def test_program_stopped_on_the_pendant_is_restarted_by_the_next_move(fake_cell):
    with UrRtdeRobot(UrRtdeConfig(fake_cell.host)) as robot:
        with socket.create_connection((fake_cell.host, ur_rtde.DASHBOARD_PORT), timeout=2) as dash:
            reader = dash.makefile("rb")
            reader.readline()  # greeting
            dash.sendall(b"stop\n")
            assert reader.readline().strip() == b"Stopped"
        deadline = time.monotonic() + 2.0  # data packages already on their way say "running"
        while robot.state().program_running:
            assert time.monotonic() < deadline, "the stopped program is still reported running"
        robot.move_joints(HOME - 0.2, speed_rad_s=1.0, accel_rad_s2=2.0)
        np.testing.assert_allclose(robot.read_joints(), HOME - 0.2, atol=1e-9)
        assert robot.state().program_running


@needs_ur_rtde
def test_malformed_rtde_package_ends_only_the_worker_and_the_next_move_runs(fault_cell):
    """The second move's command makes every RTDE stream send a header whose size is smaller
    than the header: ur_rtde aborts its (worker) process, this one goes on."""
    cell = fault_cell(only=("ur",), faults=("garble_at=2",))
    with UrRtdeRobot(UrRtdeConfig(cell.host, probe_timeout_s=1.0)) as robot:
        robot.move_joints(HOME, speed_rad_s=1.0, accel_rad_s2=2.0)
        with pytest.raises(DeviceConnectionError, match=r"worker aborted .*malformed RTDE package"):
            robot.move_joints(HOME + 0.1, speed_rad_s=1.0, accel_rad_s2=2.0)
        robot.move_joints(HOME - 0.1, speed_rad_s=1.0, accel_rad_s2=2.0)
        np.testing.assert_allclose(robot.read_joints(), HOME - 0.1, atol=1e-9)


@needs_ur_rtde
def test_silent_controller_times_out_quickly(fault_cell):
    cell = fault_cell("--fault", "delay_s=5")  # the dashboard answers after 5 s
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="dashboard"):
        UrRtdeRobot(UrRtdeConfig(cell.host, probe_timeout_s=0.3))
    assert time.monotonic() - started < 2.0


class _FakeDashboard:
    """A one-connection dashboard server on the free host that answers from a script."""

    def __init__(self, host: str, replies: list[bytes]):
        self.sock = socket.create_server((host, ur_rtde.DASHBOARD_PORT))
        self.replies = replies
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        conn, _ = self.sock.accept()
        with conn:
            conn.sendall(self.replies[0])
            reader = conn.makefile("rb")
            for reply in self.replies[1:]:
                if not reader.readline():
                    return
                conn.sendall(reply)
            time.sleep(0.2)

    def close(self):
        self.sock.close()
        self.thread.join(timeout=2.0)


@needs_ur_rtde
def test_something_else_on_the_dashboard_port_is_a_protocol_error(free_host):
    server = _FakeDashboard(free_host, [b"SSH-2.0-OpenSSH_9.2\r\n"])
    try:
        with pytest.raises(ProtocolError, match="not a UR dashboard"):
            UrRtdeRobot(UrRtdeConfig(free_host, probe_timeout_s=0.5))
    finally:
        server.close()


@needs_ur_rtde
def test_robot_in_local_control_is_reported(free_host):
    server = _FakeDashboard(
        free_host,
        [
            b"Connected: Universal Robots Dashboard Server\n",
            b"URSoftware 5.11.1.108318 (Mar 22 2022)\n",
            b"false\n",
        ],
    )
    try:
        with pytest.raises(DeviceFaultError, match="Remote Control"):
            UrRtdeRobot(UrRtdeConfig(free_host, probe_timeout_s=0.5))
    finally:
        server.close()


def test_missing_ur_rtde_is_reported_as_unavailable(monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        ur_rtde.importlib.util,
        "find_spec",
        lambda name, *a: None if name == "rtde_control" else real_find_spec(name, *a),
    )
    with pytest.raises(DeviceUnavailableError, match="pip install ur-rtde"):
        UrRtdeRobot(UrRtdeConfig(f"{NET}.19"))


def test_probe_of_an_absent_controller_names_the_port(free_host):
    with pytest.raises(DeviceConnectionError, match="dashboard port 29999"):
        ur_rtde.probe_controller(free_host, 0.5)
