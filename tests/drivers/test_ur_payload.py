"""A simulated cell whose true robot sags under gravity, and its payload changed through the
robot's own interface: the unmodified ur_rtde 1.6.5 client's ``setPayload`` (UR's
``set_payload``) against the simulated UR controller, in a child process (ur_rtde holds the
GIL while it waits)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.model import model_from_dict, model_to_dict
from calibration.simulate import sagging
from calibration.transforms import pose_to_matrix
from drivers import ur_rtde
from robot_contract import HOME

from conftest import POOL, TRUTH_PATH, host_is_free, start_cell

needs_ur_rtde = pytest.mark.skipif(importlib.util.find_spec("rtde_control") is None, reason="ur_rtde is not installed")


@pytest.fixture(scope="module")
def sagging_cell(tmp_path_factory):
    """The drivers' UR5e truth with the cobot's joint compliance and link masses."""
    truth = sagging(model_from_dict(json.loads(TRUTH_PATH.read_text())), "cobot")
    path = tmp_path_factory.mktemp("sag") / "truth.json"
    path.write_text(json.dumps(model_to_dict(truth)))
    host = next(h for h in reversed(POOL) if host_is_free(h))
    cell = start_cell(path, host, "--no-modbus", "--no-tracker", "--no-cmm", "--no-can")
    yield cell, truth
    cell.stop()


@needs_ur_rtde
def test_set_payload_through_ur_rtde_makes_the_true_robot_sag(sagging_cell):
    cell, truth = sagging_cell
    q = HOME + np.array([0.0, 0.6, -0.4, 0.0, 0.0, 0.0])
    script = textwrap.dedent(
        f"""
        import json, time, rtde_receive, rtde_control
        c = rtde_control.RTDEControlInterface({cell.host!r})
        r = rtde_receive.RTDEReceiveInterface({cell.host!r})
        assert c.moveJ({[float(v) for v in q]!r}, 1.0, 2.0)
        def pose():
            # a data package the controller sent after the command completed (poll to a deadline)
            t0, deadline = r.getTimestamp(), time.monotonic() + 2.0
            while r.getTimestamp() < t0 + 0.01:
                assert time.monotonic() < deadline, "no fresh RTDE data package"
            return r.getActualTCPPose()
        before = pose()
        assert c.setPayload(5.0, [0.0, 0.0, 0.08])
        loaded = pose()
        assert c.setPayload(0.0, [0.0, 0.0, 0.0])
        empty = pose()
        print(json.dumps(dict(before=before, loaded=loaded, empty=empty)))
        c.stopScript()
        c.disconnect(); r.disconnect()
        """
    )
    ur_rtde.probe_controller(cell.host, 1.0)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    F = pose_to_matrix(truth.tool)
    cog_tool = F[:3, :3].T @ (np.array([0.0, 0.0, 0.08]) - F[:3, 3])  # UR's centre of gravity is in the flange frame
    unloaded = fk(truth, q[None, :])[0][:3, 3]
    loaded = fk(truth, q[None, :], np.array([5.0, *cog_tool]))[0][:3, 3]
    assert np.linalg.norm(loaded - unloaded) > 1e-4  # 5 kg at this reach: a visible sag
    np.testing.assert_allclose(got["before"][:3], unloaded, atol=1e-9)
    np.testing.assert_allclose(got["loaded"][:3], loaded, atol=1e-9)
    # setPayload(0, [0, 0, 0]) keeps the centre of gravity (the control script does) and removes the mass
    np.testing.assert_allclose(got["empty"][:3], unloaded, atol=1e-9)


@needs_ur_rtde
def test_driver_set_payload_reaches_the_controller(sagging_cell):
    from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

    cell, _ = sagging_cell
    with UrRtdeRobot(UrRtdeConfig(cell.host)) as robot:
        robot.move_joints(HOME, speed_rad_s=1.0, accel_rad_s2=2.0)
        robot.set_payload(3.5, [0.0, 0.01, 0.05])
        # what the controller reports, read by ur_rtde's own receive interface in a child process
        script = textwrap.dedent(
            f"""
            import json, rtde_receive
            r = rtde_receive.RTDEReceiveInterface({cell.host!r})
            print(json.dumps(dict(mass=r.getPayload(), cog=r.getPayloadCog())))
            r.disconnect()
            """
        )
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        got = json.loads(done.stdout.strip().splitlines()[-1])
        assert got["mass"] == 3.5 and got["cog"] == pytest.approx([0.0, 0.01, 0.05])
        with pytest.raises(ValueError, match="payload"):
            robot.set_payload(-1.0, [0, 0, 0])
        robot.set_payload(0.0, [0.0, 0.0, 0.0])
