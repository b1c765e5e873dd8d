"""``recal export --format ur-calibration``: UR's calibration YAML (the ``kinematics_params_file``
of ur_robot_driver), read back with PyYAML.

The chain the file describes is composed here as ur_description composes it (each segment's
``<origin xyz rpy>``, URDF's ``Rz(yaw)·Ry(pitch)·Rx(roll)``, then the joint's rotation about z)
and compared with ``recal predict`` at many configurations: the two differ by one constant
transform (where the robot stands), and for a general identified model by one more on the flange
side, which the file states.
"""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import yaml

from calibration import robots
from calibration.model import Units, model_to_dict
from calibration.simulate import perturbed
from calibration.transforms import quat_to_matrix
from service.cli import main as recal

SEGMENTS = ["shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"]

# UR's own file for a UR10e (Universal_Robots_ROS2_Description, config/ur10e/default_kinematics.yaml).
UR10E_DEFAULT = {
    "shoulder": (0, 0, 0.1807, 0, 0, 0),
    "upper_arm": (0, 0, 0, 1.570796327, 0, 0),
    "forearm": (-0.6127, 0, 0, 0, 0, 0),
    "wrist_1": (-0.57155, 0, 0.17415, 0, 0, 0),
    "wrist_2": (0, -0.11985, -2.458164590756244e-11, 1.570796327, 0, 0),
    "wrist_3": (0, 0.11655, -2.390480459346185e-11, 1.570796326589793, 3.141592653589793, 3.141592653589793),
}


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _origin(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """A URDF <origin>: rpy is fixed-axis roll about x, then pitch about y, then yaw about z."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T = np.eye(4)
    T[:3, :3] = _rz(yaw) @ Ry @ Rx
    T[:3, 3] = (x, y, z)
    return T


def _chain(kin: dict, q: np.ndarray) -> np.ndarray:
    """shoulder_pan_joint ... wrist_3_joint of ur_description from the file: (N, 4, 4)."""
    out = []
    for qi in q:
        T = np.eye(4)
        for seg, angle in zip(SEGMENTS, qi):
            s = kin[seg]
            R = np.eye(4)
            R[:3, :3] = _rz(angle)
            T = T @ _origin(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"]) @ R
        out.append(T)
    return np.array(out)


def _predict(tmp_path, model_spec, q_deg) -> np.ndarray:
    joints, out = tmp_path / "q.csv", tmp_path / "p.csv"
    with open(joints, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i}" for i in range(1, 7)])
        w.writerows([[repr(float(v)) for v in row] for row in q_deg])
    assert recal(["predict", "--model", str(model_spec), "--joints", str(joints), "--out", str(out)]) == 0
    with open(out) as f:
        v = np.array(list(csv.reader(f))[1:], dtype=float)
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = quat_to_matrix(v[:, 3:7])
    T[:, :3, 3] = v[:, :3] * 1e-3
    return T


def _export(tmp_path, model_spec) -> tuple[dict, str]:
    out = tmp_path / "calib.yaml"
    assert recal(["export", "--model", str(model_spec), "--format", "ur-calibration", "--out", str(out)]) == 0
    text = out.read_text()
    return yaml.safe_load(text), text


def _readings(n, seed):
    return np.random.default_rng(seed).uniform(-np.pi, np.pi, (n, 6))


def test_nominal_ur10e_is_urs_default_file(tmp_path):
    doc, _ = _export(tmp_path, "ur10e")
    kin = doc["kinematics"]
    assert list(kin) == SEGMENTS + ["hash"] and str(kin["hash"]).startswith("calib_")
    for seg in SEGMENTS:
        assert set(kin[seg]) == {"x", "y", "z", "roll", "pitch", "yaw"}
        ours = _origin(*(kin[seg][k] for k in ("x", "y", "z", "roll", "pitch", "yaw")))
        np.testing.assert_allclose(ours, _origin(*UR10E_DEFAULT[seg]), atol=1e-8)


def test_a_ur_controllers_dh_model_is_the_files_chain_up_to_its_base(tmp_path):
    """A per-robot DH model (deltas on every link, as a UR controller's calibration has; flange on
    joint 6's axis): predict and the file's chain differ by one constant transform."""
    rng = np.random.default_rng(11)
    doc = robots.nominal_document("ur5e")
    for j in doc["joints"][:-1]:
        j["theta"] += rng.normal(0, 0.05)
        j["d"] += rng.normal(0, 0.5)
        j["a"] += rng.normal(0, 0.5)
        j["alpha"] += rng.normal(0, 0.05)
    doc["joints"][-1]["theta"] += 0.07
    doc["joints"][-1]["d"] += 0.3
    doc["name"] = "ur5e-controller"
    doc["base"] = [1200.0, -300.0, 40.0, 1.0, -2.0, 150.0]
    path = tmp_path / "ctrl.json"
    path.write_text(json.dumps(doc))
    y, text = _export(tmp_path, path)
    assert "tool0 -> model flange" not in text  # nothing left over
    q = _readings(30, 1)
    T = _predict(tmp_path, path, np.rad2deg(q))
    C = _chain(y["kinematics"], q)
    X = T @ np.linalg.inv(C)  # the one constant transform
    np.testing.assert_allclose(X, np.broadcast_to(X[0], X.shape), atol=1e-9)
    assert np.linalg.norm(X[0, :3, 3] - [1.2, -0.3, 0.04]) < 1e-9  # the model's base


def test_an_identified_model_is_the_files_chain_and_the_stated_flange(tmp_path):
    """A model identified in poe form (every axis moved): the file's chain, then the tool0 -> flange
    transform the file states, equals predict up to one constant transform."""
    rng = np.random.default_rng(12)
    truth = perturbed(robots.nominal("ur10e"), rng, base_length_m=0.3, base_angle_rad=0.5)
    model = dataclasses.replace(truth, name="ur10e-identified")
    path = tmp_path / "id.json"
    path.write_text(json.dumps(model_to_dict(model, units=Units("mm", "deg"))))
    y, text = _export(tmp_path, path)
    line = next(ln for ln in text.splitlines() if ln.startswith("# tool0 -> model flange"))
    x, yy, z, rx, ry, rz = (float(v) for v in line.split(": ", 1)[1].split(", "))
    R = _origin(x, yy, z, rx, ry, rz)  # a recal pose is the same Rz·Ry·Rx as URDF's rpy
    q = _readings(30, 2)
    T = _predict(tmp_path, path, np.rad2deg(q))
    X = T @ np.linalg.inv(_chain(y["kinematics"], q) @ R)
    np.testing.assert_allclose(X, np.broadcast_to(X[0], X.shape), atol=1e-9)
    assert np.linalg.norm(R[:3, 3]) < 5e-3  # the leftover is the small identified error


def test_a_seven_joint_arm_fails_in_one_line(tmp_path, capsys):
    out = tmp_path / "c.yaml"
    assert recal(["export", "--model", "fr3", "--format", "ur-calibration", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "needs six revolute joints" in err and not out.exists()
