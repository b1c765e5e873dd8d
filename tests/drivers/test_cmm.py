"""The I++ DME CMM driver against the CMM fake, over real sockets."""

from __future__ import annotations

import dataclasses
import json
import os
import select
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.robots import nominal
from calibration.transforms import rot
from drivers.errors import (
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
)
from drivers.ippdme import IppDmeCmm, IppDmeConfig, parse_error, parse_items
from fakes._lineserver import LineServer
from fakes.cmm import IppCmmFake
from fakes.world import SimCell

REPO = Path(__file__).resolve().parents[2]
# Three tooling balls about 0.1 m from the tool axis (the book's end effector: +-3 in).
BALLS_TOOL = {
    "ball1": np.array([0.10, 0.0, 0.04]),
    "ball2": np.array([-0.05, 0.087, 0.04]),
    "ball3": np.array([-0.05, -0.087, 0.04]),
}
Q_POSE = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])
R_BALL = 0.0125


@pytest.fixture(scope="module")
def truth():
    return dataclasses.replace(nominal("ur5e"), targets=BALLS_TOOL)


@pytest.fixture
def cell(truth):
    return SimCell(truth, seed=7, q_home=Q_POSE, ball_radius_m=R_BALL)


@pytest.fixture
def fake(cell):
    f = IppCmmFake(cell, port=0)
    f.start()
    yield f
    f.stop()


def _config(fake, **kw) -> IppDmeConfig:
    return IppDmeConfig(url=f"socket://127.0.0.1:{fake.port}", **{"timeout_s": 0.5, "move_timeout_s": 1.0, **kw})


def _T_true(truth, q=Q_POSE) -> np.ndarray:
    return fk(truth, np.asarray(q, float)[None])[0]


def _centre(truth, name, q=Q_POSE) -> np.ndarray:
    T = _T_true(truth, q)
    return T[:3, :3] @ BALLS_TOOL[name] + T[:3, 3]


def _angle_deg(Ra, Rb) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _top_of(centre):
    return centre + [0, 0, R_BALL], np.array([0.0, 0.0, -1.0])


# --------------------------------------------------------------------------- measuring


def test_full_pose_from_three_balls_matches_truth(fake, truth):
    T_true = _T_true(truth)
    # Where the nominal model thinks the tool is: 0.6 mm and 0.3 deg off the truth.
    T_nominal = T_true.copy()
    T_nominal[:3, :3] = T_true[:3, :3] @ rot(2, np.radians(0.3))
    T_nominal[:3, 3] += [0.0004, -0.0003, 0.0003]
    balls = np.array(list(BALLS_TOOL.values()))
    with IppDmeCmm(_config(fake)) as cmm:
        pose = cmm.measure_pose(balls, T_nominal, R_BALL)
    position_error_mm = np.linalg.norm(pose.T_world_tool[:3, 3] - T_true[:3, 3]) * 1e3
    angle_error_deg = _angle_deg(pose.T_world_tool[:3, :3], T_true[:3, :3])
    assert position_error_mm < 0.05
    assert angle_error_deg < 0.005
    assert pose.residual_rms_m < 2e-5
    for ball in pose.balls:
        assert ball.radius_m == pytest.approx(R_BALL, abs=2e-5)
        assert ball.residual_rms_m < 1e-5


def test_probe_returns_the_compensated_surface_point(fake, truth, cell):
    top, approach = _top_of(_centre(truth, "ball1"))
    with IppDmeCmm(_config(fake)) as cmm:
        p = cmm.probe(top[None], approach[None])
        assert p.shape == (1, 3)
        assert np.linalg.norm(p[0] - top) < 5 * cell.noise.cmm_m
        # The same point with a different probe: the tip radius is compensated.
    with IppDmeCmm(_config(fake, tool_name="Probe2mm")) as cmm:
        p2 = cmm.probe(top, approach)
    assert fake.tool == "Probe2mm"
    assert np.linalg.norm(p2[0] - top) < 5 * cell.noise.cmm_m


def test_session_setup_reaches_the_server(fake):
    assert not fake.homed
    with IppDmeCmm(_config(fake, approach_m=0.004, search_m=0.008)) as cmm:
        assert fake.homed  # Home() was sent because IsHomed() said 0
        assert cmm.dme_version == "1.4.3"
        assert fake.props_mm["Tool.PtMeasPar.Approach"] == pytest.approx(4.0)
        assert fake.props_mm["Tool.PtMeasPar.Search"] == pytest.approx(8.0)
        assert cmm.error_status() is False
        cmm.position()


def test_measurement_follows_the_robot(fake, truth, cell):
    q2 = Q_POSE + np.array([0.1, 0.05, -0.05, 0.1, 0.1, 0.3])
    cell.start_move(q2, 1.0, 1.0)
    with IppDmeCmm(_config(fake)) as cmm:
        ball = cmm.measure_ball(_centre(truth, "ball2", q2) + 0.0005, R_BALL)
    assert np.linalg.norm(ball.centre_world - _centre(truth, "ball2", q2)) < 1e-5


# --------------------------------------------------------------------------- I++ errors


def test_probing_empty_space_is_no_touch(fake, truth):
    top, approach = _top_of(_centre(truth, "ball1"))
    with IppDmeCmm(_config(fake)) as cmm, pytest.raises(MeasurementError) as info:
        cmm.probe(top + [0.05, 0, 0], approach)
    assert info.value.code == 1003


def test_out_of_machine_volume(truth):
    cell = SimCell(
        truth, q_home=Q_POSE, ball_radius_m=R_BALL, cmm_volume_m=(np.array([-2.0, -2, 0.5]), np.array([2.0, 2, 2]))
    )
    fake = IppCmmFake(cell, port=0)
    fake.start()
    try:
        top, approach = _top_of(_centre(truth, "ball1"))
        with IppDmeCmm(_config(fake)) as cmm:
            with pytest.raises(MeasurementError, match="out of machine volume") as info:
                cmm.probe(top, approach)
            assert info.value.code == 1008
            assert info.value.severity == 3
            assert cmm.error_status() is False
    finally:
        fake.stop()


def test_moving_robot_is_illegal_touch(truth):
    cell = SimCell(truth, q_home=Q_POSE, ball_radius_m=R_BALL, time_scale=1.0)
    fake = IppCmmFake(cell, port=0, homed=True, ptmeas_time_s=0.0, tool_change_time_s=0.0)
    fake.start()
    try:
        with IppDmeCmm(_config(fake)) as cmm:
            top, approach = _top_of(_centre(truth, "ball1"))
            cell.start_move(Q_POSE + 0.5, 0.01, 0.1)
            with pytest.raises(MeasurementError) as info:
                cmm.probe(top, approach)
            assert info.value.code == 1001
    finally:
        fake.stop()


def test_unknown_tool(fake):
    with pytest.raises(DeviceFaultError, match="Tool not found") as info:
        IppDmeCmm(_config(fake, tool_name="Laser"))
    assert info.value.code == 1502
    assert not isinstance(info.value, MeasurementError)


def test_not_homed_without_permission_to_home(fake):
    with pytest.raises(DeviceFaultError, match="not homed"):
        IppDmeCmm(_config(fake, home_if_needed=False))
    assert not fake.homed


def test_error_event_fails_the_running_transaction(fake, truth):
    top, approach = _top_of(_centre(truth, "ball1"))
    with IppDmeCmm(_config(fake)) as cmm:
        fake.send_event('KeyPress("F1")')
        # send_event writes both lines to the driver's connection before it returns, so they
        # precede the PtMeas reply in the stream: no wait is needed for the driver to read them
        fake.send_event("Controller", error=(3, 500, "Emergency stop"))
        with pytest.raises(DeviceFaultError, match="Emergency stop") as info:
            cmm.probe(top, approach)
        assert info.value.code == 500
        assert [e.kind for e in cmm.events] == ["#", "!"]
        assert cmm.events[0].body == 'KeyPress("F1")'
        cmm.probe(top, approach)  # cleared, goes on


def test_config_validation():
    with pytest.raises(ValueError, match="approach_m"):
        IppDmeConfig(approach_m=0)
    with pytest.raises(ValueError, match="tool_name"):
        IppDmeConfig(tool_name='a"b')


def test_probe_argument_validation(fake):
    with IppDmeCmm(_config(fake)) as cmm:
        with pytest.raises(ValueError, match="non-zero"):
            cmm.probe(np.zeros((1, 3)), np.zeros((1, 3)))
        with pytest.raises(ValueError, match="shape"):
            cmm.probe(np.zeros((2, 3)), np.zeros((1, 3)))


# --------------------------------------------------------------------------- link faults


def test_slow_move_is_timeout(truth):
    cell = SimCell(truth, q_home=Q_POSE, ball_radius_m=R_BALL, time_scale=1.0)
    fake = IppCmmFake(cell, port=0, homed=True, ptmeas_time_s=0.8, tool_change_time_s=0.0)
    fake.start()
    try:
        top, approach = _top_of(_centre(truth, "ball1"))
        with IppDmeCmm(_config(fake, move_timeout_s=0.3)) as cmm, pytest.raises(DeviceTimeoutError, match="completion"):
            cmm.probe(top, approach)
    finally:
        fake.stop()


@pytest.mark.parametrize(
    "fault, error, match",
    [
        # The first session is commands 1-10 (with Home), so the first PtMeas is 11. It is
        # dropped: a new session (12-20, homed now) and the resent PtMeas (21) repair it. The
        # second PtMeas (22) and its resend after the next new session (32) are dropped.
        ("drop_connection_at=11,22,32", DeviceConnectionError, r"PtMeas\(.*failed after one reconnect"),
        ("garble_at=12", ProtocolError, "garbled reply"),
        ("no_touch_at=2", MeasurementError, r"I\+\+ error 1003 \(severity 2\) in PtMeas: No touch"),
    ],
    ids=["dropped", "garbled", "no-touch"],
)
def test_faults_of_a_cmm_in_another_process(fault_cell, cell_truth, fault, error, match):
    """``recal fake-cell`` with the fault: the first point is good, the second fails with the
    driver's error naming the CMM, and the driver goes on (a new session, or ClearAllErrors).
    (A reply later than the timeout: tests/drivers/test_late_replies.py.)"""
    cell = fault_cell(only=("cmm",), faults=(fault,))
    T = fk(cell_truth, np.zeros((1, 6)))[0]
    top = T[:3, :3] @ cell_truth.targets["ball1"] + T[:3, 3] + [0.0, 0.0, R_BALL]
    approach = np.array([0.0, 0.0, -1.0])
    with IppDmeCmm(IppDmeConfig(url=cell.endpoint["cmm"], timeout_s=0.5, move_timeout_s=2.0)) as cmm:
        assert np.linalg.norm(cmm.probe(top, approach) - top) < 1e-5
        with pytest.raises(error, match=match) as info:
            cmm.probe(top, approach)
        assert f"cmm socket://{cell.host}:1294" in str(info.value)
        assert np.linalg.norm(cmm.probe(top, approach) - top) < 1e-5
        assert cmm.error_status() is False


def test_no_cmm_there(fake):
    port = fake.port
    fake.stop()
    with pytest.raises(DeviceConnectionError, match="cannot open"):
        IppDmeCmm(IppDmeConfig(url=f"socket://127.0.0.1:{port}", timeout_s=0.5))


# --------------------------------------------------------------------------- bad replies


class ScriptedIpp(LineServer):
    """A minimal I++ server that answers every command with & and %, except the PtMeas reply
    lines given (``{tag}`` is replaced by the command's tag)."""

    device_name = "scripted-ipp"

    def __init__(self, ptmeas_lines: list[str]):
        super().__init__("127.0.0.1", 0)
        self.ptmeas_lines = ptmeas_lines

    def handle_line(self, client, line):
        tag, _, call = line.partition(" ")
        if call.startswith("PtMeas"):
            for reply in self.ptmeas_lines:
                client.send_line(reply.format(tag=tag))
            return
        client.send_line(f"{tag} &")
        if call.startswith("IsHomed"):
            client.send_line(f"{tag} # IsHomed(1)")
        if call.startswith("GetDMEVersion"):
            client.send_line(f'{tag} # DMEVersion("2.0")')
        client.send_line(f"{tag} %")


OK_POINT = "{tag} # X(1.0), Y(2.0), Z(3.0), IJK(0,0,1)"


@pytest.mark.parametrize(
    "lines, error, match",
    [
        (["{tag} &", "{tag} # X(1.0), Y(2.0), IJK(0,0,1)", "{tag} %"], ProtocolError, "bad data for PtMeas"),
        (["{tag} &", "{tag} # X(1.0), Y(2.0), Z(abc)", "{tag} %"], ProtocolError, "bad data"),
        (["{tag} &", "{tag} # X(1.0), Y(2.0), Z(nan)", "{tag} %"], ProtocolError, "bad data"),
        (["{tag} &", OK_POINT, OK_POINT, "{tag} %"], ProtocolError, "one data line"),
        (["{tag} &", "{tag} %"], ProtocolError, "one data line"),
        (["{tag} &", "{tag}# X(1.0)"], ProtocolError, "unparsable line"),
        (["{tag} &", "{tag} ! Oops"], ProtocolError, "malformed error"),
        (["{tag} &", '{tag} ! Error(3, 0509, "PtMeas", "Bad argument")', "{tag} %"], ProtocolError, "Bad argument"),
        (["{tag} &", '{tag} ! Error(9, 2503, "PtMeas", "Scale read head failure")'], DeviceFaultError, "read head"),
        (["{tag} &"], DeviceTimeoutError, "completion"),
        ([], DeviceTimeoutError, "acknowledgement"),
    ],
)
def test_bad_ptmeas_replies(lines, error, match):
    server = ScriptedIpp(lines)
    server.start()
    try:
        with IppDmeCmm(IppDmeConfig(url=f"socket://127.0.0.1:{server.port}", timeout_s=0.3, move_timeout_s=0.3)) as cmm:
            assert cmm.dme_version == "2.0"
            with pytest.raises(error, match=match):
                cmm.probe(np.zeros(3), np.array([0.0, 0, -1]))
    finally:
        server.stop()


def test_warnings_and_foreign_lines_are_tolerated():
    lines = [
        "00001 %",  # a late line of some finished transaction
        "{tag} &",
        '{tag} ! Error(1, 0504, "PtMeas", "Argument out of range")',
        'E0000 # KeyPress("F2")',
        "{tag} # X(10.0), Y(20.0), Z(30.0), IJK(0,0,1)",
        "{tag} %",
    ]
    server = ScriptedIpp(lines)
    server.start()
    try:
        with IppDmeCmm(IppDmeConfig(url=f"socket://127.0.0.1:{server.port}", timeout_s=0.3)) as cmm:
            p = cmm.probe(np.zeros(3), np.array([0.0, 0, -1]))
            assert np.allclose(p, [[0.01, 0.02, 0.03]])
            assert cmm.warnings[-1].number == 504
            assert cmm.events[-1].body == 'KeyPress("F2")'
    finally:
        server.stop()


def test_parsers():
    assert parse_items('X(1.5), Tool.PtMeasPar.Approach(2), IJK(0, 0.5,-1), DMEVersion("1.4")') == {
        "X": (1.5,),
        "Tool.PtMeasPar.Approach": (2.0,),
        "IJK": (0.0, 0.5, -1.0),
        "DMEVersion": ("1.4",),
    }
    with pytest.raises(ValueError):
        parse_items("X(1.5) Y(2)")
    e = parse_error('Error(2, 1003, "PtMeas", "No touch")')
    assert (e.severity, e.number, e.method, e.text) == (2, 1003, "PtMeas", "No touch")


# --------------------------------------------------------------------------- across processes


def test_across_processes(truth):
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    args = [
        sys.executable,
        "-m",
        "fakes.cmm",
        "--port",
        "0",
        "--robot",
        "ur5e",
        "--seed",
        "3",
        "--q",
        ",".join(str(v) for v in Q_POSE),
    ]
    for name, p in BALLS_TOOL.items():
        args += ["--ball", f"{name}={p[0]},{p[1]},{p[2]}"]
    proc = subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        assert ready, "the CMM fake printed no ready line"
        endpoint = json.loads(proc.stdout.readline())
        assert endpoint["ready"] is True
        T_true = _T_true(truth)
        with IppDmeCmm(IppDmeConfig(url=endpoint["cmm"], timeout_s=2.0)) as cmm:
            pose = cmm.measure_pose(np.array(list(BALLS_TOOL.values())), T_true, 0.0125)
        assert np.linalg.norm(pose.T_world_tool[:3, 3] - T_true[:3, 3]) < 5e-5
        assert _angle_deg(pose.T_world_tool[:3, :3], T_true[:3, :3]) < 0.005
    finally:
        proc.terminate()
        assert proc.wait(10) == 0
