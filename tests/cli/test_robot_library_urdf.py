"""The robot library, ROS-ready URDF export and URDF import, as a user runs them (``recal model``,
``recal export``, ``recal predict`` on files).

Every URDF written is read back by an independent parser from PyPI (yourdfpy, which follows the
URDF specification and is used by the ROS-free Python tooling) and its forward kinematics is
compared with ``recal predict`` at many configurations. URDF import round-trips every library
arm and reads URDFs yourdfpy agrees with. The library's figures are checked against sums of the
public descriptions' numbers (the zero pose of each arm's tool0), worked out by hand here.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yourdfpy
from urdf_check import assert_urdf_is_predict, predict, yourdfpy_fk

from calibration import robots
from calibration.kinematics import fk
from calibration.transforms import quat_to_matrix
from service.cli import main as recal

ARMS = ["kr16", "kr210", "irb4600", "irb6700", "m20ia", "r2000ic", "gp25", "tx2-90", "fr3", "iiwa14"]
UR = ["ur3e", "ur5e", "ur10e", "ur16e"]
COUPLED = {"m20ia", "r2000ic"}


def _rows(path) -> tuple[list[str], np.ndarray]:
    with open(path) as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    return rows[0], np.array(rows[1:], dtype=float)


def _write_joints(path, q_file_units: np.ndarray) -> None:
    n = q_file_units.shape[1]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(n)])
        w.writerows([[repr(float(v)) for v in row] for row in q_file_units])


def _readings(name: str, n: int, seed: int) -> np.ndarray:
    """``n`` readings (rad) inside the arm's joint limits."""
    model = robots.nominal(name)
    lim = np.clip(model.joint_limits, -np.pi, np.pi)
    return np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], (n, model.n_joints))


def _predict(tmp_path, model_spec: str, q_deg: np.ndarray) -> np.ndarray:
    """``recal predict`` -> T_world_tool (N, 4, 4) in metres (model files here are mm)."""
    joints, out = tmp_path / "q.csv", tmp_path / "pred.csv"
    _write_joints(joints, q_deg)
    assert recal(["predict", "--model", model_spec, "--joints", str(joints), "--out", str(out)]) == 0
    header, v = _rows(out)
    assert header == ["x", "y", "z", "qw", "qx", "qy", "qz"]
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = quat_to_matrix(v[:, 3:7])
    T[:, :3, 3] = v[:, :3] * 1e-3
    return T


# --------------------------------------------------------------------------- the library


def test_recal_model_lists_the_library_with_descriptions(capsys):
    assert recal(["model"]) == 0
    lines = capsys.readouterr().out.splitlines()
    listed = {line.split()[0]: line for line in lines}
    assert set(ARMS + UR + ["puma560", "puma560-zrp"]) <= set(listed)
    assert "KUKA KR 16" in listed["kr16"] and "Fanuc R-2000iC" in listed["r2000ic"] and "7-axis" in listed["fr3"]


@pytest.mark.parametrize("name", ARMS + UR)
def test_library_documents_name_their_source_and_limits(name, tmp_path):
    out = tmp_path / f"{name}.json"
    assert recal(["model", name, "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "recal.model/1" and len(doc["source"]) > 20 and doc["description"]
    n = 7 if name in ("fr3", "iiwa14") else 6
    assert len(doc["joints"]) == n
    for j in doc["joints"]:
        assert j["lower"] < j["upper"] and j["velocity"] > 0  # every arm's source publishes speeds
        assert "effort" not in j or j["effort"] > 0
    if name in COUPLED:  # Fanuc: J3 relative to the horizon, the serial angle is J2 + J3
        C = np.array(doc["coupling"])
        assert C[2, 1] == 1 and C[2, 2] == 1 and np.count_nonzero(C) == 7
    # a library name works wherever a model file is expected, and the file is the same robot
    q = np.rad2deg(_readings(name, 5, 1))
    np.testing.assert_allclose(_predict(tmp_path, name, q), _predict(tmp_path, str(out), q), atol=1e-9)


# tool0 at zero readings, summed by hand from the descriptions' joint origins (m), and the
# direction of tool0's z axis (out of the flange).
ZERO_POSE = {
    "kr16": ((0.26 + 0.68 + 0.67 + 0.158, 0, 0.675 - 0.035), (1, 0, 0)),
    "kr210": (
        (
            -0.00262 + 0.35277 - 9.8483e-05 + 0.95795 + 0.542 + 0.1925 + 0.0375,
            0.00097586 - 0.037476 - 0.1475 + 0.184,
            0.33099 + 0.4192 + 1.2499 - 0.055059 - 0.00023924,
        ),
        (1, 0, 0),
    ),
    "irb4600": ((0.175 + 0.96 + 0.135, 0, 0.495 + 0.9 + 0.175), (1, 0, 0)),
    "irb6700": ((0.32 + 1.1425 + 0.2, 0, 0.78 + 1.125 + 0.2), (1, 0, 0)),
    "m20ia": ((0.15 + 0.835 + 0.1, 0, 0.525 + 0.79 + 0.25), (1, 0, 0)),
    "r2000ic": ((0.312 + 1.28 + 0.215, 0, 0.67 + 1.075 + 0.225), (1, 0, 0)),
    "gp25": ((0.15 + 0.795 + 0.1, 0, 0.505 + 0.76 + 0.2), (1, 0, 0)),
    "tx2-90": ((0.05, 0.05, 0.478 + 0.425 + 0.425 + 0.1), (0, 0, 1)),
    "fr3": ((0.088, 0, 0.333 + 0.316 + 0.384 - 0.107), (0, 0, -1)),
    "iiwa14": ((0, 0, 0.36 + 0.42 + 0.4 + 0.126), (0, 0, 1)),
}


@pytest.mark.parametrize("name", ARMS)
def test_library_arm_zero_pose_is_its_descriptions(name):
    model = robots.nominal(name)
    # fk, not recal predict: the FR3's zero (joints 4 and 6) is outside its joint limits
    T = fk(model, np.zeros((1, model.n_joints)))[0]
    p, z = ZERO_POSE[name]
    np.testing.assert_allclose(T[:3, 3], p, atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], z, atol=1e-12)


@pytest.mark.parametrize("name", sorted(COUPLED))
def test_fanuc_j3_reading_is_relative_to_the_horizon(name, tmp_path):
    """With the J3 reading held, moving J2 keeps the forearm's attitude: the tool's orientation does
    not change (the parallel linkage of the Fanuc arms, contracts §2)."""
    q = np.zeros((4, 6))
    q[:, 1] = [-30, -10, 10, 30]  # J2, degrees
    q[:, 2] = 15.0
    T = _predict(tmp_path, name, q)
    for Ti in T[1:]:
        np.testing.assert_allclose(Ti[:3, :3], T[0, :3, :3], atol=1e-9)
    assert np.ptp(T[:, 0, 3]) > 0.1  # while the wrist moves


# --------------------------------------------------------------------------- URDF export


@pytest.mark.parametrize("name", ARMS + UR)
def test_exported_urdf_parses_with_yourdfpy_and_matches_predict(name, tmp_path, capsys):
    urdf = tmp_path / f"{name}.urdf"
    # every library arm exports as it comes (issue 26): no --effort, no --velocity
    assert recal(["export", "--model", name, "--format", "urdf", "--out", str(urdf)]) == 0
    err = capsys.readouterr().err
    assert ("coupling" in err) == (name in COUPLED)
    # the KUKA, ABB and Fanuc descriptions publish no torques: a placeholder, said
    no_torques = name in ("kr16", "kr210", "irb4600", "irb6700", "m20ia", "r2000ic")
    assert ("effort limit not published for this arm; written as a placeholder" in err) == no_torques
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    model = robots.nominal(name)
    assert robot.actuated_joint_names == (
        ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
        if name in UR
        else [j.name for j in model.joints]
    )
    for jn in robot.actuated_joint_names:
        lim = robot.joint_map[jn].limit
        assert lim.velocity > 0 and lim.effort > 0
    lib_velocity = [j.velocity for j in model.joints]
    np.testing.assert_allclose(
        [robot.joint_map[jn].limit.velocity for jn in robot.actuated_joint_names], lib_velocity, rtol=1e-12
    )
    links = set(robot.link_map)
    # robot-only, rooted at base_link (no world link at the instrument's coordinates)
    assert {"base_link", "base", "flange", "tool0", "tcp"} <= links and "world" not in links
    assert robot.base_link == "base_link"
    if name in UR:
        assert {
            "shoulder_link",
            "upper_arm_link",
            "forearm_link",
            "wrist_1_link",
            "wrist_2_link",
            "wrist_3_link",
            "base_link_inertia",
        } <= links
    else:
        assert {f"link_{i + 1}" for i in range(model.n_joints)} <= links
    q = _readings(name, 25, 2)
    T_pred = _predict(tmp_path, name, np.rad2deg(q))
    # a URDF joint position is a serial angle: for Fanuc, what fanuc_driver publishes (C·q)
    q_urdf = q @ model.coupling_matrix.T
    # `base` is the model's robot base frame (UR: the controller's, base_link turned by pi)
    np.testing.assert_allclose(yourdfpy_fk(urdf, q_urdf, "tcp", "base"), T_pred, atol=1e-9)
    np.testing.assert_allclose(yourdfpy_fk(urdf, q_urdf, "tool0", "base"), T_pred, atol=1e-9)  # no tool: tool0 = flange
    T_base = yourdfpy_fk(urdf, q_urdf[:1], "base", "base_link")[0]
    np.testing.assert_allclose(T_base, np.diag([-1.0, -1, 1, 1]) if name in UR else np.eye(4), atol=1e-12)


def _sample_models():
    """tests/calibration/sample_models.py: one model document per convention and feature."""
    path = Path(__file__).resolve().parents[1] / "calibration" / "sample_models.py"
    spec = importlib.util.spec_from_file_location("sample_models_for_urdf", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SAMPLES = _sample_models()
CONVENTION_DOCS = SAMPLES.all_convention_docs()
# gains and harmonics have no URDF form (the export says so, tests/calibration/test_export.py)
URDF_EXACT = [k for k, d in CONVENTION_DOCS.items() if not any("gain" in j or "harmonic" in j for j in d["joints"])]


def test_the_sample_documents_cover_every_convention():
    assert {d["convention"] for k, d in CONVENTION_DOCS.items() if k in URDF_EXACT} == {"dh", "mdh", "poe"}
    assert any(j.get("beta") is not None for j in CONVENTION_DOCS["dh_hayati"]["joints"])  # Hayati's form


@pytest.mark.parametrize("names", ["auto", "ros", "recal"])
@pytest.mark.parametrize("doc_id", URDF_EXACT)
def test_every_convention_exports_a_urdf_yourdfpy_reads_as_predict(doc_id, names, tmp_path):
    """dh, mdh (Craig), poe, Hayati's beta, prismatic joints, the Fanuc coupling, base, tool and
    targets, in inches or millimetres: each exported URDF, under each naming scheme, is
    ``recal predict`` to a nanometre in yourdfpy."""
    doc = CONVENTION_DOCS[doc_id]
    path, urdf = tmp_path / f"{doc_id}.json", tmp_path / f"{doc_id}.urdf"
    path.write_text(json.dumps(doc))
    argv = ["export", "--model", str(path), "--format", "urdf", "--out", str(urdf), "--names", names]
    assert recal([*argv, "--velocity", "1.5", "--effort", "80", "--prefix", "c_"]) == 0
    from calibration.export import naming
    from service.files import load_model

    scheme = naming(load_model(str(path)), names)
    q = SAMPLES.random_readings(doc, 12, np.random.default_rng(21))
    assert_urdf_is_predict(urdf, path, q, tmp_path, names=scheme, prefix="c_")


def test_export_of_an_identified_ur_keeps_ur_names_tool_and_targets(tmp_path):
    """An identified UR model (every axis moved, poe form, with base, tool and a target) exports with
    UR's names, and yourdfpy's tcp and target frames are recal predict's."""
    from calibration.model import model_to_dict
    from calibration.simulate import perturbed

    nominal = robots.nominal("ur5e")
    truth = perturbed(
        nominal, np.random.default_rng(3), base_length_m=0.2, base_angle_rad=0.3, tool_length_m=0.05, tool_angle_rad=0.2
    )
    import dataclasses

    model = dataclasses.replace(truth, name="ur5e-identified", targets={"smr": np.array([0.01, 0.02, 0.05])})
    path = tmp_path / "ur5e-identified.json"
    from calibration.model import Units

    path.write_text(json.dumps(model_to_dict(model, units=Units("mm", "deg"))))
    urdf = tmp_path / "id.urdf"
    assert (
        recal(
            [
                "export",
                "--model",
                str(path),
                "--format",
                "urdf",
                "--out",
                str(urdf),
                "--prefix",
                "r1_",
                "--velocity",
                "1.5",
                "--world",
            ]
        )
        == 0
    )
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.base_link == "r1_world"  # --world: the instrument's frame, the model's base under it
    assert robot.actuated_joint_names[0] == "r1_shoulder_pan_joint"
    assert all(robot.joint_map[j].limit.velocity == 1.5 for j in robot.actuated_joint_names)
    assert robot.joint_map["r1_elbow_joint"].limit.effort == 150.0  # from the library (ur5e)
    q = _readings("ur5e", 20, 4)
    T = _predict(tmp_path, str(path), np.rad2deg(q))
    np.testing.assert_allclose(yourdfpy_fk(urdf, q, "r1_tcp", "r1_world"), T, atol=1e-9)
    p = yourdfpy_fk(urdf, q, "r1_target_smr", "r1_world")[:, :3, 3]
    np.testing.assert_allclose(p, T[:, :3, 3] + T[:, :3, :3] @ [0.01, 0.02, 0.05], atol=1e-9)


def test_export_without_a_velocity_limit_fails_in_one_line(tmp_path, capsys):
    out = tmp_path / "p.urdf"
    assert recal(["export", "--model", "puma560", "--format", "urdf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "joint 'j1' has no velocity limit" in err and "--velocity" in err
    assert not out.exists()
    assert (
        recal(
            [
                "export",
                "--model",
                "puma560",
                "--format",
                "urdf",
                "--out",
                str(out),
                "--velocity",
                "2",
                "--effort",
                "100",
                "--names",
                "recal",
            ]
        )
        == 0
    )
    root = ET.parse(out).getroot()
    assert {lim.get("velocity") for lim in root.iter("limit")} == {"2.0"}
    assert [j.get("name") for j in root.findall("joint") if j.get("type") == "revolute"] == [
        f"j{i}" for i in range(1, 7)
    ]
    assert_urdf_is_predict(out, "puma560", np.rad2deg(_readings("puma560", 10, 3)), tmp_path, names="recal")


# --------------------------------------------------------------------------- URDF import


def test_the_tests_cover_the_whole_library():
    assert set(ARMS + UR + ["puma560", "puma560-zrp"]) == set(robots.names())


@pytest.mark.parametrize("world", [False, True])
@pytest.mark.parametrize("name", robots.names())
def test_urdf_import_round_trips_every_library_arm(name, world, tmp_path, capsys):
    """export -> recal model --from-urdf with no options -> the same forward kinematics (readings:
    the URDF's joint positions; the coupling of the Fanuc arms is not in a URDF). Every robot
    `recal model` lists, the book's PUMA 560 (inches, a base before joint 1) too. Robot-only (the
    default), the model read back starts at base_link: the library model's base frame for every
    arm but the UR's (base_link is UR's, the controller's frame turned by pi) and the PUMA's (its
    base is not in the file); with --world it starts at the world link, the library's frame."""
    urdf, back = tmp_path / "a.urdf", tmp_path / "back.json"
    argv = ["export", "--model", name, "--format", "urdf", "--out", str(urdf)]
    if name.startswith("puma"):  # the book gives no speeds or torques
        argv += ["--velocity", "1", "--effort", "1"]
    assert recal(argv + (["--world"] if world else [])) == 0
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(back)]) == 0
    assert "note:" in capsys.readouterr().err  # the side frames (base, flange ...) are named as ignored
    doc = json.loads(back.read_text())
    model = robots.nominal(name)
    # dh where the chain starts on the base link and ends on the tip exactly (poe for the KUKA KR arms,
    # whose joint 1 turns about -z or sits off the base link's z axis), as the library
    assert "URDF" in doc["source"]
    if name in ARMS + UR:  # (the PUMA's base stands off joint 1's axis: poe, the base folded in)
        assert doc["convention"] == model.convention
        assert doc["base"] == [0.0] * 6 and doc["tool"] == [0.0] * 6
    last = {"puma560": "joint_6", "puma560-zrp": "joint_6"}.get(name, model.joints[-1].name)
    assert [j["name"] for j in doc["joints"]][-1] == ("wrist_3_joint" if name in UR else last)
    # readings that are inside the limits both as the controller reports them and, for the coupled
    # Fanuc arms, as the URDF's serial joint positions (recal refuses readings beyond the limits)
    q = _readings(name, 400, 5)
    lim = model.joint_limits
    q_serial = q @ model.coupling_matrix.T
    inside = np.all((q_serial >= lim[:, 0]) & (q_serial <= lim[:, 1]), axis=1)
    q, q_serial = q[inside][:20], q_serial[inside][:20]
    assert len(q) == 20
    T_root_base = np.eye(4)  # the root link of the URDF -> the library model's base frame
    if not world:
        from calibration.transforms import pose_to_matrix

        T_root_base = np.linalg.inv(pose_to_matrix(model.base))  # the model is SI inside
        if name in UR:
            T_root_base = np.diag([-1.0, -1.0, 1.0, 1.0])
    T_lib = predict(tmp_path, name, np.rad2deg(q))
    np.testing.assert_allclose(predict(tmp_path, back, np.rad2deg(q_serial)), T_root_base @ T_lib, atol=1e-9)
    np.testing.assert_allclose([j["lower"] for j in doc["joints"]], np.rad2deg(model.joint_limits[:, 0]), atol=1e-9)


# A hand-written URDF with what real descriptions contain: fixed joints between moving ones, rpy on
# every origin, a rotation axis that is not a unit vector, a continuous joint, a prismatic joint, a side
# branch (a camera) and links without joints to them.
HAND_URDF = """<?xml version="1.0"?>
<robot name="gantry_arm">
  <link name="floor"/><link name="rail"/><link name="carriage"/><link name="l1"/><link name="l2"/>
  <link name="l2b"/><link name="l3"/><link name="l4"/><link name="flange"/><link name="camera"/>
  <joint name="floor-rail" type="fixed">
    <origin xyz="0.1 -0.2 0.3" rpy="0.1 0.2 -0.3"/><parent link="floor"/><child link="rail"/>
  </joint>
  <joint name="slide" type="prismatic">
    <origin xyz="0 0 0.05" rpy="0 0 0.4"/><parent link="rail"/><child link="carriage"/>
    <axis xyz="1 0 0"/><limit lower="-0.5" upper="1.5" effort="800" velocity="0.5"/>
  </joint>
  <joint name="j1" type="revolute">
    <origin xyz="0.2 0.1 0.4" rpy="0.3 -0.2 1.0"/><parent link="carriage"/><child link="l1"/>
    <axis xyz="0 0 2"/><limit lower="-3" upper="3" effort="100" velocity="2"/>
  </joint>
  <joint name="j2" type="revolute">
    <origin xyz="0.05 0 0.3" rpy="-1.5707963267948966 0 0"/><parent link="l1"/><child link="l2"/>
    <axis xyz="0 0.6 0.8"/><limit lower="-2" upper="2" effort="100" velocity="2"/>
  </joint>
  <joint name="l2-l2b" type="fixed">
    <origin xyz="0.4 0.01 0" rpy="0 0.05 0"/><parent link="l2"/><child link="l2b"/>
  </joint>
  <joint name="j3" type="continuous">
    <origin xyz="0.3 0 0.02" rpy="0.7 0.1 0.2"/><parent link="l2b"/><child link="l3"/>
    <axis xyz="1 0 0"/><limit effort="30" velocity="3"/>
  </joint>
  <joint name="j4" type="revolute">
    <origin xyz="0.1 0.05 -0.03" rpy="0 1.2 0"/><parent link="l3"/><child link="l4"/>
    <axis xyz="0 -1 0"/><limit lower="-1" upper="2.5" effort="30" velocity="3"/>
  </joint>
  <joint name="l4-flange" type="fixed">
    <origin xyz="0 0 0.12" rpy="3.14159 -1.5 0.5"/><parent link="l4"/><child link="flange"/>
  </joint>
  <joint name="l1-camera" type="fixed">
    <origin xyz="0 0.1 0" rpy="0 0 0"/><parent link="l1"/><child link="camera"/>
  </joint>
</robot>
"""


@pytest.mark.parametrize("convention", ["auto", "dh", "poe"])
def test_urdf_import_matches_yourdfpy(tmp_path, convention, capsys):
    urdf, out = tmp_path / "hand.urdf", tmp_path / "m.json"
    urdf.write_text(HAND_URDF)
    assert (
        recal(["model", "--from-urdf", str(urdf), "--tip", "flange", "--convention", convention, "--out", str(out)])
        == 0
    )
    doc = json.loads(out.read_text())
    # the rail's offset and the prismatic joint's axis off the floor's z: DH needs a base transform,
    # so auto writes poe (the floor link is the robot base, the flange the tip)
    assert doc["convention"] == ("poe" if convention == "auto" else convention)
    assert (doc["base"] != [0.0] * 6) == (doc["tool"] != [0.0] * 6) == (convention == "dh")
    assert doc["units"] == {"length": "mm", "angle": "deg"}
    assert [(j["name"], j["type"]) for j in doc["joints"]] == [
        ("slide", "prismatic"),
        ("j1", "revolute"),
        ("j2", "revolute"),
        ("j3", "revolute"),
        ("j4", "revolute"),
    ]
    assert doc["joints"][0]["lower"] == pytest.approx(-500) and doc["joints"][0]["velocity"] == pytest.approx(500)
    assert doc["joints"][1]["upper"] == pytest.approx(np.rad2deg(3)) and doc["joints"][1]["effort"] == 100
    rng = np.random.default_rng(8)
    # inside every joint's limits (j4: -1 to 2.5 rad)
    q = np.column_stack([rng.uniform(-0.5, 1.5, 30), rng.uniform(-2, 2, (30, 3)), rng.uniform(-1, 2, 30)])
    q_file = np.column_stack([q[:, 0] * 1e3, np.rad2deg(q[:, 1:])])
    np.testing.assert_allclose(_predict(tmp_path, str(out), q_file), yourdfpy_fk(urdf, q, "flange", "floor"), atol=1e-9)
    # --base: the chain from a link inside the tree
    assert recal(["model", "--from-urdf", str(urdf), "--base", "l1", "--tip", "flange", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [j["name"] for j in doc["joints"]] == ["j2", "j3", "j4"]
    np.testing.assert_allclose(
        _predict(tmp_path, str(out), np.rad2deg(q[:, 2:])),
        yourdfpy_fk(urdf, np.column_stack([np.zeros((30, 2)), q[:, 2:]]), "flange", "l1"),
        atol=1e-9,
    )


def _broken(**edits) -> str:
    text = HAND_URDF
    for old, new in edits.values():
        assert old in text
        text = text.replace(old, new)
    return text


@pytest.mark.parametrize(
    "text, argv, expect",
    [
        (
            _broken(a=('name="l1-camera" type="fixed"', 'name="l1-camera" type="revolute"')),
            [],
            "link 'l1' branches ('j2', 'l1-camera' lead to moving joints; leaves camera, flange): give --tip LINK",
        ),
        (HAND_URDF, ["--tip", "gripper"], "link 'gripper' (the tip) is not a <link> of the robot"),
        (HAND_URDF, ["--base", "camera", "--tip", "flange"], "link 'flange' (the tip) is not below link 'camera'"),
        (
            _broken(a=('<child link="l3"/>', '<child link="l3x"/>')),
            ["--tip", "flange"],
            "joint 'j3': child link 'l3x' is not a <link> of the robot",
        ),
        (
            _broken(a=('name="j2" type="revolute"', 'name="j2" type="floating"')),
            ["--tip", "flange"],
            "joint 'j2': type 'floating' is not a single-axis joint",
        ),
        (
            _broken(a=('name="j4" type="revolute"', 'name="j4" type="planar"')),
            ["--tip", "flange"],
            "joint 'j4': type 'planar' is not a single-axis joint",
        ),
        (
            _broken(a=('xyz="0.1 0.05 -0.03"', 'xyz="0.1 abc -0.03"')),
            ["--tip", "flange"],
            "joint 'j4' <origin xyz>: expected 3 numbers, got '0.1 abc -0.03'",
        ),
        ("<robot name='x'><link name='a'/>", ["--tip", "a"], "not well-formed XML"),
    ],
)
def test_bad_urdf_gets_one_line_naming_the_element(tmp_path, capsys, text, argv, expect):
    urdf, out = tmp_path / "bad.urdf", tmp_path / "m.json"
    urdf.write_text(text)
    assert recal(["model", "--from-urdf", str(urdf), *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(urdf) in err and expect in err, err
    assert not out.exists()


def test_a_floating_joint_off_the_chain_does_not_matter(tmp_path):
    urdf, out = tmp_path / "f.urdf", tmp_path / "m.json"
    urdf.write_text(_broken(a=('name="l1-camera" type="fixed"', 'name="l1-camera" type="floating"')))
    assert recal(["model", "--from-urdf", str(urdf), "--tip", "flange", "--out", str(out)]) == 0


def test_a_fixed_side_branch_does_not_need_tip(tmp_path, capsys):
    """The camera on a fixed joint is not a second arm: the default tip follows the moving joints."""
    urdf, out = tmp_path / "f.urdf", tmp_path / "m.json"
    urdf.write_text(HAND_URDF)
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(out)]) == 0
    assert [j["name"] for j in json.loads(out.read_text())["joints"]] == ["slide", "j1", "j2", "j3", "j4"]
    assert "1 fixed frame(s) off the chain ('camera'): ignored" in capsys.readouterr().err


def test_velocity_and_effort_in_the_model_file(tmp_path, capsys):
    """``velocity`` is in the reading's unit per second (deg/s here), ``effort`` in N·m; both must be
    positive, and a bad one is named by its JSON field."""
    doc = robots.nominal_document("ur5e")
    doc["joints"][0]["velocity"] = 90.0
    path, urdf = tmp_path / "m.json", tmp_path / "m.urdf"
    path.write_text(json.dumps(doc))
    assert recal(["export", "--model", str(path), "--format", "urdf", "--out", str(urdf)]) == 0
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.joint_map["shoulder_pan_joint"].limit.velocity == pytest.approx(np.pi / 2)
    assert robot.joint_map["shoulder_pan_joint"].limit.effort == 150.0
    assert_urdf_is_predict(urdf, path, np.rad2deg(_readings("ur5e", 10, 6)), tmp_path, names="ur")
    doc["joints"][2]["effort"] = -5
    path.write_text(json.dumps(doc))
    out = tmp_path / "p.csv"
    (tmp_path / "q.csv").write_text("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n")
    assert recal(["predict", "--model", str(path), "--joints", str(tmp_path / "q.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "joints[2].effort" in err and "positive" in err and not out.exists()
