"""`recal controller-model` against the simulated UR cell, and what it is for: compensation
through the controller's own model brings the true robot to its targets, compensation through
the published DH table does not (issue 16).

The cell's controller has the factory calibration written into its truth file here; the
expected forward kinematics is the published UR5e table plus those deltas, composed in this
file with plain matrices. Where the robot truly went is the truth model at the joints the
controller reports (unmodified ``ur_rtde`` in a child process) after each ``moveL``.
Loopback addresses NET.60-NET.64 are this module's (the UR ports are fixed per address).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.transforms import homogeneous, matrix_to_quat, matrix_to_rotvec, pose_to_matrix, quat_to_matrix
from service.files import load_model
from service.processes import start_fake_cell

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")
REPO = Path(__file__).resolve().parents[2]
TRUTH = REPO / "tests" / "drivers" / "ur5e_truth.json"
_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
HOME = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])

pytestmark = pytest.mark.skipif(importlib.util.find_spec("rtde_control") is None, reason="ur_rtde is not installed")

D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
FACTORY = {  # calibration.conf [mounting] of the simulated controller, linearised
    "published": "ur5e",
    "delta_theta": [3.3e-4, -5.1e-4, 4.2e-4, -6.8e-4, 2.1e-4, -3.9e-4],
    "delta_a": [-1.5e-4, 4.1e-4, -3.2e-4, 1.5e-4, 2.1e-4, 0.0],
    "delta_d": [0.0004, 23.517, -61.204, 37.6871, -0.0003, 0.0002],
    "delta_alpha": [5.6e-4, -2.4e-5, 3.1e-5, -4.2e-4, -1.8e-4, 0.0],
}


def controller_fk(q) -> np.ndarray:
    """The simulated controller's T_base_flange (4, 4): published table plus FACTORY."""
    T = np.eye(4)
    for i, qi in enumerate(q):
        th = qi + FACTORY["delta_theta"][i]
        d, a, al = D[i] + FACTORY["delta_d"][i], A[i] + FACTORY["delta_a"][i], ALPHA[i] + FACTORY["delta_alpha"][i]
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )
    return T


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("controller-cell")
    doc = json.loads(TRUTH.read_text())
    doc["ur_factory_calibration"] = FACTORY
    (d / "truth.json").write_text(json.dumps(doc))
    proc = start_fake_cell(d / "truth.json", f"{NET}.60", extra=["--no-modbus", "--no-tracker", "--no-cmm", "--no-can"])
    yield proc.ready["rtde"]
    proc.stop()


@pytest.fixture(scope="module")
def controller_json(cell, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("controller-model")
    done = recal("controller-model", "--rtde", cell, "--out", d / "controller.json", cwd=d)
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("\n") == 1 and "reproduces the controller to" in done.stdout
    return d / "controller.json"


def test_controller_model_reproduces_the_controllers_forward_kinematics_to_a_micrometre(controller_json):
    doc = json.loads(controller_json.read_text())
    assert doc["format"] == "recal.model/1" and doc["name"] == "ur5e-controller"
    block = doc["controller"]
    assert block["reference"] == "ur5e-nominal" and block["poses_fit"] == 48 and block["poses_check"] == 48
    assert block["check"]["position_max_um"] < 1.0 and block["check"]["rotation_max_urad"] < 1.0
    model = model_from_dict(doc)
    q = np.random.default_rng(11).uniform(-np.pi, np.pi, (200, 6))
    T = fk(model, q)
    for Ti, qi in zip(T, q):
        expected = controller_fk(qi)
        assert np.linalg.norm(Ti[:3, 3] - expected[:3, 3]) < 1e-6
        assert np.linalg.norm(matrix_to_rotvec(Ti[:3, :3].T @ expected[:3, :3])) < 1e-6


def actual_q(host: str) -> list[float]:
    """The controller's ``actual_q`` now (unmodified ur_rtde receive interface, child process)."""
    script = textwrap.dedent(f"""
        import json, rtde_receive
        r = rtde_receive.RTDEReceiveInterface({host!r})
        t = r.getTimestamp()
        while r.getTimestamp() < t + 0.01:  # a data package sampled after this call began
            pass
        print(json.dumps(list(r.getActualQ())))
        r.disconnect()
        """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_reading_the_controllers_model_moves_nothing(cell, tmp_path):
    """96 getForwardKinematics queries over ±180 deg: the arm stays where it stands."""
    before = actual_q(cell)
    done = recal("controller-model", "--rtde", cell, "--out", tmp_path / "c.json", "--seed", "3", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert actual_q(cell) == before


def test_a_fit_that_does_not_reproduce_the_controller_is_refused_without_a_file(cell, tmp_path):
    done = recal("controller-model", "--rtde", cell, "--out", tmp_path / "c.json", "--tolerance", "1e-9", cwd=tmp_path)
    assert done.returncode == 2
    assert (
        done.stderr.count("\n") == 1 and "reproduces UR controller" in done.stderr and "nothing written" in done.stderr
    )
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--robot", "puma560"], "no UR arm"),
        (["--robot", "kr99"], "unknown robot 'kr99'"),  # (kr16 is a library arm, but no UR: the case above)
        (["--poses", "3"], "--poses 3: expected at least 5"),
    ],
)
def test_bad_arguments_get_one_line(cell, tmp_path, args, message):
    done = recal("controller-model", "--rtde", cell, "--out", tmp_path / "c.json", *args, cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and message in done.stderr, done.stderr
    assert not (tmp_path / "c.json").exists()


def test_an_absent_controller_gets_one_line(tmp_path):
    done = recal(
        "controller-model", "--rtde", f"{NET}.64", "--out", tmp_path / "c.json", "--robot", "ur5e", cwd=tmp_path
    )
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "cannot connect" in done.stderr, done.stderr


# ----------------------------------------------------------------------------- compensation


def move_l(host: str, poses: list[list[float]]) -> np.ndarray:
    """``moveJ`` home, then ``moveL`` to each UR pose in turn; the joints after each (N, 6)."""
    script = textwrap.dedent(f"""
        import json, rtde_control, rtde_receive
        c = rtde_control.RTDEControlInterface({host!r})
        r = rtde_receive.RTDEReceiveInterface({host!r})
        def fresh_q():  # a data package sampled after the move ended (the stream may lag)
            t = r.getTimestamp()
            while r.getTimestamp() < t + 0.01:
                pass
            return list(r.getActualQ())
        out = []
        for pose in {poses!r}:
            assert c.moveJ({[float(v) for v in HOME]!r}, 1.0, 2.0)
            assert c.moveL(pose, 0.25, 1.2)
            out.append(fresh_q())
        print(json.dumps(out))
        c.stopScript()
        c.disconnect(); r.disconnect()
        """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return np.array(json.loads(done.stdout.strip().splitlines()[-1]))


def run_programs(host: str, programs: list[str]) -> np.ndarray:
    """Send each URScript program to the controller's script port and wait (RTDE receive
    interface, unmodified ur_rtde) until it has moved the robot and stopped; the joints then."""
    script = textwrap.dedent(f"""
        import json, socket, time, rtde_receive
        r = rtde_receive.RTDEReceiveInterface({host!r}, -1.0, ["timestamp", "actual_q", "robot_status_bits"])
        def fresh():  # a data package that arrived after this call began
            t = r.getTimestamp()
            while r.getTimestamp() <= t:
                pass
            return list(r.getActualQ()), r.getRobotStatus()
        out = []
        for program in {programs!r}:
            q_before, _ = fresh()
            with socket.create_connection(({host!r}, 30003)) as s:
                s.sendall(program.encode())
            deadline = time.monotonic() + 10.0
            while True:  # moved, and the program no longer running (robot_status_bits bit 1)
                q, status = fresh()
                if q != q_before and not status & 2:
                    break
                assert time.monotonic() < deadline, "the program did not run"
            out.append(q)
        print(json.dumps(out))
        r.disconnect()
        """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return np.array(json.loads(done.stdout.strip().splitlines()[-1]))


def ur_pose(T: np.ndarray) -> list[float]:
    return [float(v) for v in (*T[:3, 3], *matrix_to_rotvec(T[:3, :3]))]


def pose_errors(T_true: np.ndarray, T_goal: np.ndarray) -> tuple[float, float]:
    dp = np.linalg.norm(T_true[:, :3, 3] - T_goal[:, :3, 3], axis=1)
    dr = np.linalg.norm(matrix_to_rotvec(np.einsum("nji,njk->nik", T_true[:, :3, :3], T_goal[:, :3, :3])), axis=1)
    return float(dp.max()), float(dr.max())


@pytest.fixture(scope="module")
def planned():
    """Task configurations near home (rad) and the true robot's tool poses there (world, m)."""
    q = HOME + np.random.default_rng(5).uniform(-0.25, 0.25, (6, 6))
    truth = model_from_dict(json.loads(TRUTH.read_text()))
    return q, truth, fk(truth, q)


@pytest.mark.parametrize("nominal, reaches", [("controller", True), ("ur5e", False)])
def test_targets_mode_reaches_the_targets_only_through_the_controllers_model(
    cell, controller_json, planned, tmp_path, nominal, reaches
):
    """Targets mode: desired world poses -> targets for the controller, sent with moveL."""
    q, truth, T_desired = planned
    rows = []
    for qi, T in zip(q, T_desired):
        quat = matrix_to_quat(T[:3, :3])
        rows.append([*(T[:3, 3] * 1e3), *quat, *np.rad2deg(qi)])  # the truth file is in mm and degrees
    with open(tmp_path / "task.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", "z", "qw", "qx", "qy", "qz", "q1", "q2", "q3", "q4", "q5", "q6"])
        w.writerows([[repr(float(v)) for v in r] for r in rows])
    nominal_arg = controller_json if nominal == "controller" else nominal
    done = recal(
        "compensate",
        "--model",
        TRUTH,
        "--nominal",
        nominal_arg,
        "--task",
        tmp_path / "task.csv",
        "--out",
        tmp_path / "out.csv",
        "--mode",
        "targets",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    with open(tmp_path / "out.csv", newline="") as f:
        out = list(csv.DictReader(f))
    poses = []
    for r in out:
        assert r["converged"] == "1", r
        p = np.array([float(r[k]) for k in "xyz"]) * 1e-3
        R = quat_to_matrix(np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]))
        poses.append(ur_pose(homogeneous(R, p)))  # the controller's base frame: what it is sent
    q_reached = move_l(cell, poses)
    dp, dr = pose_errors(fk(truth, q_reached), T_desired)
    if reaches:
        assert dp < 1e-6 and dr < 1e-6, (dp, dr)
    else:
        assert dp > 0.3e-3, dp  # the factory calibration's millimetres are left in


_P = re.compile(r"p\[([^\]]*)\]")


@pytest.mark.parametrize("nominal, reaches", [("controller", True), ("ur5e", False)])
def test_urscript_pose_targets_reach_their_targets_only_through_the_controllers_model(
    cell, controller_json, planned, tmp_path, nominal, reaches
):
    """A URScript program with p[...] targets (base frame), compensated, then run by the
    controller itself (each move as a program of its own, sent to the script port): the true
    robot must reach the world pose each target means, T_nominal_world^-1 · B · P
    (docs/compensation.md §6, the frame from the command's report)."""
    q, truth, _ = planned
    P = [controller_fk(qi) for qi in q]  # poses an off-line program would hold (base frame)
    lines = ["def task():"] + [f"  movel(p[{', '.join(f'{v:.9f}' for v in ur_pose(T))}], a=1.2, v=0.25)" for T in P]
    (tmp_path / "task.script").write_text("\n".join(lines + ["end", ""]))
    nominal_arg = controller_json if nominal == "controller" else nominal
    qnear = ",".join(f"{v:.6f}" for v in np.rad2deg(HOME))  # the branch the robot is in, as get_inverse_kin
    done = recal(
        "compensate",
        "--model",
        TRUTH,
        "--nominal",
        nominal_arg,
        "--task",
        tmp_path / "task.script",
        "--out",
        tmp_path / "out.script",
        "--report",
        tmp_path / "report.json",
        "--qnear",
        qnear,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    frame = np.array(report["frame"]["T_nominal_world"], dtype=float)  # mm and degrees (the truth file's units)
    T_nw = pose_to_matrix(np.concatenate([frame[:3] * 1e-3, np.deg2rad(frame[3:])]))
    B = pose_to_matrix(load_model(str(nominal_arg)).base)
    targets = np.array([np.linalg.inv(T_nw) @ B @ T for T in P])  # the world poses the program means
    compensated = (tmp_path / "out.script").read_text()
    assert len(_P.findall(compensated)) == len(P)
    # the compensated program itself, one move at a time, run by the controller (script port)
    home = ", ".join(f"{v:.9f}" for v in HOME)
    moves = [line for line in compensated.splitlines() if line.strip().startswith("movel(")]
    q_reached = run_programs(cell, [f"def task():\n  movej([{home}])\n{m}\nend\n" for m in moves])
    dp, dr = pose_errors(fk(truth, q_reached), targets)
    if reaches:
        assert dp < 1e-6 and dr < 1e-6, (dp, dr)
    else:
        assert dp > 0.3e-3, dp
