"""The simulated UR controller computes with its factory calibration, as a real one does:
``actual_TCP_pose``, ``getForwardKinematics``, ``getInverseKinematics``, ``moveL`` and
``moveJ_IK`` pose targets (unmodified ``ur_rtde`` 1.6.5, in a child process) and UR's Modbus
TCP-pose registers (pymodbus, and our driver). The expected values come from the published
UR5e DH table plus the truth file's deltas, composed here with plain 4x4 matrices."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from robot_contract import HOME

from calibration.transforms import homogeneous, matrix_to_rotvec, rotvec_to_matrix
from drivers import ur_rtde
from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

needs_ur_rtde = pytest.mark.skipif(importlib.util.find_spec("rtde_control") is None, reason="ur_rtde is not installed")

D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
FACTORY = {  # calibration.conf [mounting], linearised (calibration_status 2)
    "published": "ur5e",
    "calibration_status": 2,
    "delta_theta": [2.1e-4, -3.9e-4, 6.2e-4, -2.8e-4, 1.1e-4, 4.9e-4],
    "delta_a": [1.2e-4, 3.1e-4, -2.2e-4, 5e-5, -1.1e-4, 0.0],
    "delta_d": [0.0005, 11.198, -92.527, 81.328, -0.0002, -0.0001],
    "delta_alpha": [-4.6e-4, 1.9e-5, -2.7e-5, 3.8e-4, 2.2e-4, 0.0],
}
ZERO = {k: [0.0] * 6 for k in ("delta_theta", "delta_a", "delta_d", "delta_alpha")}


def dh_fk(q, deltas=FACTORY) -> np.ndarray:
    """T_base_flange (4, 4) of the published table plus ``deltas``."""
    T = np.eye(4)
    for i, qi in enumerate(q):
        th = qi + deltas["delta_theta"][i]
        d, a, al = D[i] + deltas["delta_d"][i], A[i] + deltas["delta_a"][i], ALPHA[i] + deltas["delta_alpha"][i]
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )
    return T


def as_matrix(pose) -> np.ndarray:
    pose = np.asarray(pose, dtype=float)
    return homogeneous(rotvec_to_matrix(pose[3:]), pose[:3])


@pytest.fixture(scope="module")
def factory_cell(cell_factory, truth_path, tmp_path_factory):
    doc = json.loads(truth_path.read_text())
    doc["ur_factory_calibration"] = FACTORY
    path = tmp_path_factory.mktemp("factory") / "truth.json"
    path.write_text(json.dumps(doc))
    return cell_factory("--seed", "5", truth=path)


# The receive stream may lag the control interface that reported a move done: read the state
# from a data package sampled at least 10 ms of controller time later.
FRESH = textwrap.dedent("""
    def fresh(get):
        t = r.getTimestamp()
        while r.getTimestamp() < t + 0.01:
            pass
        return list(get())
    """)


def run_ur_rtde(host: str, body: str) -> dict:
    """Run ``body`` (with ``c``, ``r``: control and receive interfaces) in a child process;
    it prints one JSON line."""
    script = (
        "import json, rtde_control, rtde_receive\n"
        + f"c = rtde_control.RTDEControlInterface({host!r})\nr = rtde_receive.RTDEReceiveInterface({host!r})\n"
        + FRESH
        + textwrap.dedent(body)
        + "\nc.stopScript()\nc.disconnect(); r.disconnect()\n"
    )
    ur_rtde.probe_controller(host, 1.0)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@needs_ur_rtde
def test_forward_and_inverse_kinematics_and_tcp_pose_come_from_the_factory_calibration(factory_cell):
    qs = [[float(v) for v in HOME + s] for s in (0.0, 0.2, -0.3, 0.5)]
    flange = [[float(v) for v in (*dh_fk(q)[:3, 3], *matrix_to_rotvec(dh_fk(q)[:3, :3]))] for q in qs]
    # A tool offset that is not all zero: ur_rtde 1.6.5 sends none otherwise, and the script
    # reads whatever an earlier command left in input registers 6-11.
    tcp = [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]
    got = run_ur_rtde(
        factory_cell.host,
        f"""
        qs = {qs!r}
        fk = [list(c.getForwardKinematics(q, {tcp!r})) for q in qs]
        ik = [list(c.getInverseKinematics(p, [v + 0.05 for v in q])) for p, q in zip({flange!r}, qs)]
        assert c.moveJ(qs[2], 1.0, 2.0)
        actual = dict(q=fresh(r.getActualQ), pose=fresh(r.getActualTCPPose))
        print(json.dumps(dict(fk=fk, ik=ik, actual=actual)))
        """,
    )
    T_tcp = homogeneous(np.eye(3), tcp[:3])
    for q, pose in zip(qs, got["fk"]):
        T = as_matrix(pose)
        np.testing.assert_allclose(T, dh_fk(q) @ T_tcp, atol=1e-9)
        # millimetres away from what the published table says: the deltas are applied
        assert np.linalg.norm(T[:3, 3] - (dh_fk(q, ZERO) @ T_tcp)[:3, 3]) > 1e-3
    for q, q_ik in zip(qs, got["ik"]):
        np.testing.assert_allclose(q_ik, q, atol=1e-8)  # the branch nearest qnear, the same turns
    np.testing.assert_allclose(got["actual"]["q"], qs[2], atol=1e-12)
    np.testing.assert_allclose(as_matrix(got["actual"]["pose"]), dh_fk(qs[2]), atol=1e-9)


@needs_ur_rtde
def test_pose_targets_of_movel_and_movej_ik_are_reached_through_the_factory_calibration(factory_cell):
    T1 = dh_fk(HOME + 0.1)
    T2 = dh_fk(HOME - 0.2)
    p1 = [float(v) for v in (*T1[:3, 3], *matrix_to_rotvec(T1[:3, :3]))]
    p2 = [float(v) for v in (*T2[:3, 3], *matrix_to_rotvec(T2[:3, :3]))]
    home = [float(v) for v in HOME]
    got = run_ur_rtde(
        factory_cell.host,
        f"""
        assert c.moveJ({home!r}, 1.0, 2.0)
        assert c.moveL({p1!r}, 0.25, 1.2)
        after_movel = fresh(r.getActualQ)
        assert c.moveJ_IK({p2!r}, 1.0, 2.0)
        after_movej_ik = fresh(r.getActualQ)
        print(json.dumps(dict(movel=after_movel, movej_ik=after_movej_ik)))
        """,
    )
    for q, T in ((got["movel"], T1), (got["movej_ik"], T2)):
        np.testing.assert_allclose(dh_fk(q), T, atol=1e-9)  # the controller's model puts the tool there
        assert np.linalg.norm(dh_fk(q, ZERO)[:3, 3] - T[:3, 3]) > 1e-3  # the published table would not
    np.testing.assert_allclose(got["movel"], HOME + 0.1, atol=1e-8)  # nearest the joints it started from


def test_modbus_tcp_registers_hold_the_controllers_forward_kinematics(factory_cell):
    """UR's registers 400-405 (0.1 mm, mrad), read with pymodbus itself and with our driver."""
    from pymodbus.client import ModbusTcpClient

    host, port = factory_cell.endpoint["modbus"].rsplit(":", 1)
    with ModbusRobot(ModbusRobotConfig(host=host, port=int(port))) as robot:
        robot.move_joints(HOME + 0.3, speed_rad_s=1.0, accel_rad_s2=2.0)
        q = robot.read_joints()
        T_driver = robot.read_tcp_pose()
    client = ModbusTcpClient(host, port=int(port))
    assert client.connect()
    try:
        words = client.read_holding_registers(400, count=6, device_id=1).registers
    finally:
        client.close()
    signed = [w - 65536 if w >= 32768 else w for w in words]
    T = dh_fk(HOME + 0.3)
    np.testing.assert_allclose(np.array(signed[:3]) * 1e-4, T[:3, 3], atol=0.6e-4)
    np.testing.assert_allclose(np.array(signed[3:]) * 1e-3, matrix_to_rotvec(T[:3, :3]), atol=0.6e-3)
    np.testing.assert_allclose(q, HOME + 0.3, atol=2e-3)
    np.testing.assert_allclose(T_driver[:3, 3], T[:3, 3], atol=0.6e-4 * math.sqrt(3))
    np.testing.assert_allclose(T_driver[:3, :3], T[:3, :3], atol=2e-3)


@needs_ur_rtde
def test_driver_forward_kinematics_after_a_move_is_still_the_flange(factory_cell):
    """ur_rtde 1.6.5 sends no all-zero tool offset, so the control script would read the last
    moveJ's speed and acceleration (input registers 6, 7) as one: the driver sends a known
    offset and takes it off again."""
    from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

    with UrRtdeRobot(UrRtdeConfig(factory_cell.host)) as robot:
        robot.move_joints(HOME + 0.1, speed_rad_s=0.5, accel_rad_s2=1.0)
        q = np.stack([HOME, HOME + 0.2, HOME - 0.4])
        T = robot.forward_kinematics(q)
        T_tcp = robot.forward_kinematics(q, [0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    for Ti, Ti_tcp, qi in zip(T, T_tcp, q):
        np.testing.assert_allclose(Ti, dh_fk(qi), atol=1e-9)
        np.testing.assert_allclose(Ti_tcp, dh_fk(qi) @ homogeneous(np.eye(3), [0, 0, 0.05]), atol=1e-9)
