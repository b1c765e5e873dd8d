"""URDF exports that drop into ROS and MoveIt (issue 26): names chosen by the arm's kinematics, not
its model name; limits for every library robot; a robot-only URDF rooted at base_link (the
instrument's world only with --world); an exported URDF that reads back with no options, its
targets kept. Each URDF is read by yourdfpy (tests/urdf_check.py)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import yourdfpy
from urdf_check import assert_urdf_is_predict, predict, yourdfpy_fk

from calibration import robots
from calibration.model import Units, model_to_dict
from calibration.simulate import perturbed
from calibration.transforms import pose_to_matrix
from service.cli import main as recal

UR_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]


def _calibrated(name: str, new_name: str, seed: int, **kw):
    """A calibrated-like model of a library arm (every axis moved by millimetres), renamed."""
    truth = perturbed(robots.nominal(name), np.random.default_rng(seed), **kw)
    return dataclasses.replace(truth, name=new_name)


def _write(tmp_path, model, file="m.json"):
    path = tmp_path / file
    path.write_text(json.dumps(model_to_dict(model, units=Units("mm", "deg"))))
    return path


def _export(tmp_path, model_path, *argv, out="r.urdf") -> tuple:
    urdf = tmp_path / out
    code = recal(["export", "--model", str(model_path), "--format", "urdf", "--out", str(urdf), *argv])
    return code, urdf


def _q(n_joints: int, seed: int, lib: str | None = None) -> np.ndarray:
    """Readings in degrees (inside the library arm ``lib``'s limits)."""
    rng = np.random.default_rng(seed)
    if lib is None:
        return rng.uniform(-150, 150, (10, n_joints))
    lim = np.rad2deg(np.clip(robots.nominal(lib).joint_limits, -np.pi, np.pi))
    return rng.uniform(lim[:, 0], lim[:, 1], (10, n_joints))


def test_a_calibrated_ur_gets_urs_names_whatever_it_is_called(tmp_path, capsys):
    """The service names a calibrated UR10e 'demo-ur10e-calibrated': its kinematics make it a UR."""
    model = _calibrated("ur10e", "demo-ur10e-calibrated", 1, base_length_m=1.5, base_angle_rad=0.3)
    path = _write(tmp_path, model)
    code, urdf = _export(tmp_path, path)
    assert code == 0
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.actuated_joint_names == UR_JOINTS
    assert robot.joint_map["elbow_joint"].limit.effort == 150.0  # the library ur10e's, found by kinematics
    assert_urdf_is_predict(urdf, path, _q(6, 2), tmp_path, names="ur")


def test_an_arm_named_like_a_ur_is_not_one(tmp_path, capsys):
    model = dataclasses.replace(robots.nominal("irb4600"), name="ur10e-cell-3")
    path = _write(tmp_path, model)
    code, urdf = _export(tmp_path, path, "--effort", "100")
    assert code == 0
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.actuated_joint_names == [f"joint_{i}" for i in range(1, 7)] and "link_6" in robot.link_map


def test_ros_names_are_ros_industrials(tmp_path, capsys):
    """--names ros on a model with Recal's generic joint names (j1 ...): joint_1 ... joint_6."""
    path = tmp_path / "ur.json"
    assert recal(["model", "ur10e", "--out", str(path)]) == 0
    code, urdf = _export(tmp_path, path, "--names", "ros")
    assert code == 0
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.actuated_joint_names == [f"joint_{i}" for i in range(1, 7)]
    assert {f"link_{i}" for i in range(1, 7)} <= set(robot.link_map)
    assert_urdf_is_predict(urdf, path, _q(6, 3), tmp_path, names="ros")
    # the library's ROS-Industrial names are kept (KUKA's joint_a1 ...)
    code, urdf = _export(tmp_path, "kr16", "--names", "ros", out="kr16.urdf")
    assert code == 0
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.actuated_joint_names == [f"joint_a{i}" for i in range(1, 7)]


def test_every_library_file_exports_as_it_comes(tmp_path, capsys):
    """`recal model kr16 --out kr16.json` then `recal export --model kr16.json --format urdf`: the
    KUKA description publishes no torques, so the effort is a stated placeholder, positive."""
    path = tmp_path / "kr16.json"
    assert recal(["model", "kr16", "--out", str(path)]) == 0
    capsys.readouterr()
    code, urdf = _export(tmp_path, path)
    assert code == 0
    err = capsys.readouterr().err
    assert "effort limit not published for this arm; written as a placeholder" in err
    text = urdf.read_text()
    assert "warning: joint(s) joint_a1" in text  # in an XML comment (which may not hold '--': parsed below)
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert all(robot.joint_map[j].limit.effort > 0 for j in robot.actuated_joint_names)
    assert_urdf_is_predict(urdf, path, _q(6, 4, "kr16"), tmp_path, names="ros")


def test_the_urdf_is_robot_only_unless_world_is_asked(tmp_path, capsys):
    """A calibrated model's base puts the robot at tracker coordinates: by default the URDF is
    rooted at base_link (a MoveIt configuration adds its own world joint) and says where the base
    is; --world adds the instrument's frame as a 'world' link."""
    model = _calibrated("ur5e", "ur5e-identified", 5, base_length_m=1.9, base_angle_rad=0.4)
    path = _write(tmp_path, model)
    code, urdf = _export(tmp_path, path)
    assert code == 0
    assert "base (instrument frame -> robot base) is not in the robot-only URDF" in capsys.readouterr().err
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.base_link == "base_link" and "world" not in robot.link_map
    assert_urdf_is_predict(urdf, path, _q(6, 6), tmp_path, names="ur")
    code, urdf_w = _export(tmp_path, path, "--world", out="w.urdf")
    assert code == 0 and capsys.readouterr().err == ""
    robot = yourdfpy.URDF.load(str(urdf_w), load_meshes=False, build_scene_graph=True)
    assert robot.base_link == "world"
    T = yourdfpy_fk(urdf_w, np.zeros((1, 6)), "base_link", "world")[0]
    assert np.linalg.norm(T[:3, 3]) > 1.0  # the tracker's coordinates, only here
    assert_urdf_is_predict(urdf_w, path, _q(6, 6), tmp_path, names="ur")


def test_an_exported_urdf_reads_back_with_no_options(tmp_path, capsys):
    """Export (robot-only) -> recal model --from-urdf with no options: the chain to the tool frame,
    the targets kept as the model's targets."""
    model = _calibrated("kr16", "kr16-identified", 7, tool_length_m=0.1, tool_angle_rad=0.3)
    model = dataclasses.replace(model, targets={"smr": np.array([0.01, 0.02, 0.15]), "b": np.array([0, 0.05, 0.1])})
    path = _write(tmp_path, model)
    code, urdf = _export(tmp_path, path)
    assert code == 0
    back = tmp_path / "back.json"
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(back)]) == 0
    doc = json.loads(back.read_text())
    assert [j["name"] for j in doc["joints"]] == [j.name for j in model.joints]
    assert set(doc["targets"]) == {"smr", "b"}
    q = _q(6, 8, "kr16")
    # the URDF has no base (robot-only): the model read back is the original from its base frame
    T_base = pose_to_matrix(model.base)
    np.testing.assert_allclose(T_base @ predict(tmp_path, back, q), predict(tmp_path, path, q), atol=1e-9)
    for t in ("smr", "b"):
        p_back = predict(tmp_path, back, q, target=t)
        p_orig = predict(tmp_path, path, q, target=t)
        np.testing.assert_allclose(p_back @ T_base[:3, :3].T + T_base[:3, 3], p_orig, atol=1e-9)
        # and yourdfpy's target frame is the read-back model's target
        np.testing.assert_allclose(
            yourdfpy_fk(urdf, np.deg2rad(q), f"target_{t}", "base_link")[:, :3, 3], p_back, atol=1e-9
        )
