"""Every URDF a test writes is checked the same way (issue 16): read back by an independent parser
from PyPI (yourdfpy, which follows the URDF specification), its forward kinematics compared with
``recal predict`` on the model file it was exported from. Shared by the test folders (the tests
directory is on ``sys.path``, tests/conftest.py)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

# The tool frame and the flange frame of each naming scheme (calibration.export.to_urdf).
TOOL_LINKS = {"ur": ("tcp", "tool0"), "ros": ("tcp", "tool0"), "recal": ("tool", "flange")}


def predict(workdir: Path, model_spec, q_file: np.ndarray, *, target: str | None = None) -> np.ndarray:
    """``recal predict`` at readings ``q_file`` (N, n) in the model file's units: T_world_tool
    (N, 4, 4) in metres, or with ``target`` the target's position (N, 3) in metres."""
    from service.cli import main as recal
    from service.files import load_model

    joints, out = Path(workdir) / "urdf_check_q.csv", Path(workdir) / "urdf_check_pred.csv"
    with open(joints, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(q_file.shape[1])])
        w.writerows([[repr(float(v)) for v in row] for row in q_file])
    argv = ["predict", "--model", str(model_spec), "--joints", str(joints), "--out", str(out)]
    assert recal(argv + (["--target", target] if target else [])) == 0
    with open(out) as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    v = np.array(rows[1:], dtype=float)
    L = load_model(str(model_spec)).units.length_m
    if target:
        assert rows[0][:3] == ["x", "y", "z"]
        return v[:, :3] * L
    assert rows[0][:7] == ["x", "y", "z", "qw", "qx", "qy", "qz"]
    from calibration.transforms import quat_to_matrix

    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = quat_to_matrix(v[:, 3:7])
    T[:, :3, 3] = v[:, :3] * L
    return T


def in_file_units(model_spec, q_si: np.ndarray) -> np.ndarray:
    """Readings (N, n) in rad and m -> the model file's angle and length units."""
    from service.files import load_model

    model = load_model(str(model_spec))
    return q_si / np.array([model.units.angle_rad if j.revolute else model.units.length_m for j in model.joints])


def yourdfpy_fk(urdf: Path, q_urdf: np.ndarray, tip: str, base: str) -> np.ndarray:
    """T_base_tip (N, 4, 4), metres, from yourdfpy at the URDF's joint positions ``q_urdf`` (N, n)."""
    import yourdfpy

    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    out = []
    for qi in q_urdf:
        robot.update_cfg(qi)
        out.append(robot.get_transform(tip, base))
    return np.array(out)


def assert_urdf_is_predict(
    urdf: Path,
    model_spec,
    q_file: np.ndarray,
    workdir: Path,
    *,
    names: str,
    prefix: str = "",
    atol_m: float = 1e-9,
) -> None:
    """The URDF ``urdf`` exported from ``model_spec`` parses with yourdfpy, has one movable joint
    per model joint with non-zero velocity and effort limits, and its tool, flange and target
    frames are ``recal predict``'s at ``q_file`` (N, n, the model file's units; a coupled model's
    URDF joint positions are the serial angles C·q, as its ROS driver publishes them)."""
    import yourdfpy

    from service.files import load_model

    model = load_model(str(model_spec))
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    movable = [j for j in robot.robot.joints if j.type != "fixed"]  # in the model's joint order
    assert len(movable) == model.n_joints, [j.name for j in movable]
    for j in movable:
        assert j.limit is not None and j.limit.velocity > 0 and j.limit.effort > 0, (j.name, j.limit)
    scale = np.array([model.units.angle_rad if j.revolute else model.units.length_m for j in model.joints])
    q_all = (q_file * scale) @ model.coupling_matrix.T
    # yourdfpy takes the actuated joints' positions and works out the mimic joints' itself
    actuated = [i for i, j in enumerate(movable) if j.mimic is None]
    assert [movable[i].name for i in actuated] == list(robot.actuated_joint_names)
    q_urdf = q_all[:, actuated]
    from calibration.transforms import pose_to_matrix

    tool, flange = TOOL_LINKS[names]
    T_pred = predict(workdir, model_spec, q_file)
    if prefix + "world" in robot.link_map:  # --world: the instrument's frame is the root
        world, T_world_root = prefix + "world", np.eye(4)
    else:  # robot-only: rooted at base_link, the model's base is not in the file
        world, T_world_root = prefix + "base_link", pose_to_matrix(model.base) @ _base_to_base_link(model, names)

    def fk_world(link: str) -> np.ndarray:
        return T_world_root @ yourdfpy_fk(urdf, q_urdf, link, world)

    np.testing.assert_allclose(fk_world(prefix + tool), T_pred, atol=atol_m)
    # the flange: the tool frame without the model's tool transform
    T_flange = T_pred @ np.linalg.inv(pose_to_matrix(model.tool))
    np.testing.assert_allclose(fk_world(prefix + flange), T_flange, atol=atol_m)
    for t in model.targets:
        p = fk_world(f"{prefix}target_{t}")[:, :3, 3]
        np.testing.assert_allclose(p, predict(workdir, model_spec, q_file, target=t), atol=atol_m)


def _base_to_base_link(model, names: str) -> np.ndarray:
    """The model's robot base frame -> the URDF's base_link: identity, but for UR names, where
    base_link is UR's (the controller's base frame, base_link_inertia, turned by pi about z) and
    the model's base frame either the controller's or base_link (calibration.export.ur_match)."""
    if names != "ur":
        return np.eye(4)
    from calibration.export import ur_match

    match = ur_match(model)
    T_bli_base = np.eye(4) if match is None else match[1]
    return np.linalg.inv(T_bli_base) @ np.diag([-1.0, -1.0, 1.0, 1.0])
