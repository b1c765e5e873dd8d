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
from robot_contract import HOME

from calibration.kinematics import points_world
from calibration.model import model_from_dict, model_to_dict
from calibration.simulate import sagging
from calibration.transforms import pose_to_matrix
from drivers import ur_rtde

needs_ur_rtde = pytest.mark.skipif(importlib.util.find_spec("rtde_control") is None, reason="ur_rtde is not installed")


@pytest.fixture
def sagging_cell(tmp_path, truth_path, cell_factory):
    """The drivers' UR5e truth with the cobot's joint compliance and link masses, with a noiseless
    line-protocol tracker watching its reflector."""
    truth = sagging(model_from_dict(json.loads(truth_path.read_text())), "cobot")
    path = tmp_path / "truth.json"
    path.write_text(json.dumps(model_to_dict(truth)))
    cell = cell_factory("--no-modbus", "--no-cmm", "--no-can", "--no-emscon", "--noise", "tracker_m=0", truth=path)
    yield cell, truth
    cell.stop()


@needs_ur_rtde
def test_set_payload_through_ur_rtde_makes_the_true_robot_sag(sagging_cell):
    """ur_rtde's setPayload reaches the simulated controller, and the true arm sags under the payload:
    the tracker sees the reflector move by the compliant truth's prediction. (The controller's own
    actual_TCP_pose comes from its joint readings and its model, so it never shows the sag, as on a
    real UR.)"""
    from drivers.tracker import LineTracker, TrackerConfig

    cell, truth = sagging_cell
    q = HOME + np.array([0.0, 0.6, -0.4, 0.0, 0.0, 0.0])
    script = textwrap.dedent(
        f"""
        import sys, rtde_control
        c = rtde_control.RTDEControlInterface({cell.host!r})
        assert c.moveJ({[float(v) for v in q]!r}, 1.0, 2.0)
        print("moved", flush=True); sys.stdin.readline()
        assert c.setPayload(5.0, [0.0, 0.0, 0.08])
        print("loaded", flush=True); sys.stdin.readline()
        assert c.setPayload(0.0, [0.0, 0.0, 0.0])
        print("empty", flush=True); sys.stdin.readline()
        c.stopScript()
        c.disconnect()
        """
    )
    ur_rtde.probe_controller(cell.host, 1.0)
    child = subprocess.Popen(
        [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    seen = {}
    try:
        with LineTracker(TrackerConfig(url=cell.endpoint["tracker"], timeout_s=5.0)) as tracker:
            for step in ("moved", "loaded", "empty"):
                line = child.stdout.readline().strip()
                assert line == step, (line, child.stderr.read() if child.poll() is not None else "")
                seen[step] = tracker.measure().p_world
                child.stdin.write("\n")
                child.stdin.flush()
        assert child.wait(timeout=30) == 0, child.stderr.read()
    finally:
        if child.poll() is None:
            child.kill()
    F = pose_to_matrix(truth.tool)
    cog_tool = F[:3, :3].T @ (np.array([0.0, 0.0, 0.08]) - F[:3, 3])  # UR's centre of gravity is in the flange frame
    smr = truth.targets["smr1"]
    unloaded = points_world(truth, q[None, :], smr)[0]
    loaded = points_world(truth, q[None, :], smr, np.array([[5.0, *cog_tool]]))[0]
    assert np.linalg.norm(loaded - unloaded) > 1e-4  # 5 kg at this reach: a visible sag
    np.testing.assert_allclose(seen["moved"], unloaded, atol=1e-7)
    np.testing.assert_allclose(seen["loaded"], loaded, atol=1e-7)
    # setPayload(0, [0, 0, 0]) keeps the centre of gravity (the control script does) and removes the mass
    np.testing.assert_allclose(seen["empty"], unloaded, atol=1e-7)
