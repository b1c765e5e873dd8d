"""URDF import as ROS's chain solvers read a description (issue 26): joints off the base -> tip
chain are ignored whatever their type, and said on stderr; a mimic joint on the chain is the
model's joint coupling. The URDFs are written here in the shapes the public descriptions use
(ABB's balancing cylinder, Franka's two-finger hand, a camera on a floating or planar joint, a
mimic joint on the arm); every model is checked against yourdfpy, an independent URDF parser
that evaluates mimic joints itself."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yourdfpy
from urdf_check import predict, yourdfpy_fk

from service.cli import main as recal

PI = np.pi


def _joint(name, jtype, parent, child, xyz="0 0 0", rpy="0 0 0", axis=None, limit=None, mimic=None) -> str:
    out = [f'  <joint name="{name}" type="{jtype}">', f'    <origin xyz="{xyz}" rpy="{rpy}"/>']
    out += [f'    <parent link="{parent}"/>', f'    <child link="{child}"/>']
    if axis:
        out.append(f'    <axis xyz="{axis}"/>')
    if limit:
        lo, hi = limit
        out.append(f'    <limit lower="{lo}" upper="{hi}" effort="100" velocity="2"/>')
    if mimic:
        out.append(f"    <mimic {mimic}/>")
    out.append("  </joint>")
    return "\n".join(out)


def _robot(name: str, joints: list[str]) -> str:
    links = set()
    for j in joints:
        for tag in ("parent", "child"):
            links.add(j.split(f'<{tag} link="')[1].split('"')[0])
    body = "\n".join(f'  <link name="{n}"/>' for n in sorted(links))
    return f'<?xml version="1.0"?>\n<robot name="{name}">\n{body}\n' + "\n".join(joints) + "\n</robot>\n"


# An ABB IRB 6640-like arm (abb_experimental's irb6640 macro layout): base_link -> link_1 ... link_6
# -> tool0, and the balancing cylinder: cylinder on link_1 turning with joint_2 (mimic), piston
# sliding in it (mimic of joint_2 too), plus ROS-Industrial's base_link -> base frame.
ABB = _robot(
    "irb6640_like",
    [
        _joint("joint_1", "revolute", "base_link", "link_1", "0 0 0.78", axis="0 0 1", limit=(-2.9, 2.9)),
        _joint("joint_2", "revolute", "link_1", "link_2", "0.32 0 0", axis="0 1 0", limit=(-1.1, 1.4)),
        _joint("joint_3", "revolute", "link_2", "link_3", "0 0 1.28", axis="0 1 0", limit=(-3.1, 1.2)),
        _joint("joint_4", "revolute", "link_3", "link_4", "0 0 0.2", axis="1 0 0", limit=(-5, 5)),
        _joint("joint_5", "revolute", "link_4", "link_5", "1.1425 0 0", axis="0 1 0", limit=(-2.0, 2.0)),
        _joint("joint_6", "revolute", "link_5", "link_6", "0.2 0 0", axis="1 0 0", limit=(-6, 6)),
        _joint("joint_6-tool0", "fixed", "link_6", "tool0", rpy=f"0 {PI / 2} 0"),
        _joint("base_link-base", "fixed", "base_link", "base"),
        _joint(
            "cylinder_joint",
            "revolute",
            "link_1",
            "cylinder",
            "-0.2 0 0.1",
            axis="0 1 0",
            limit=(-1, 1),
            mimic='joint="joint_2" multiplier="-0.35"',
        ),
        _joint(
            "piston_joint",
            "prismatic",
            "cylinder",
            "piston",
            "0 0 0.3",
            axis="0 0 1",
            limit=(-0.4, 0.4),
            mimic='joint="joint_2" multiplier="0.25" offset="0.01"',
        ),
    ],
)

# A Franka-like arm with its hand (franka_description's layout): link8 -> hand -> hand_tcp, and two
# prismatic fingers on the hand, the second a mimic of the first.
FRANKA_JOINTS = (
    _joint("fr3_joint1", "revolute", "fr3_link0", "fr3_link1", "0 0 0.333", axis="0 0 1", limit=(-2.7, 2.7)),
    _joint("fr3_joint2", "revolute", "fr3_link1", "fr3_link2", rpy=f"{-PI / 2} 0 0", axis="0 0 1", limit=(-1.7, 1.7)),
    _joint("fr3_joint3", "revolute", "fr3_link2", "fr3_link3", "0 -0.316 0", f"{PI / 2} 0 0", "0 0 1", (-2.9, 2.9)),
    _joint("fr3_joint4", "revolute", "fr3_link3", "fr3_link4", "0.0825 0 0", f"{PI / 2} 0 0", "0 0 1", (-3.0, -0.2)),
    _joint("fr3_joint8", "fixed", "fr3_link4", "fr3_link8", "0 0 0.107"),
    _joint("fr3_hand_joint", "fixed", "fr3_link8", "fr3_hand", rpy=f"0 0 {-PI / 4}"),
    _joint("fr3_hand_tcp_joint", "fixed", "fr3_hand", "fr3_hand_tcp", "0 0 0.1034"),
    _joint("fr3_finger_joint1", "prismatic", "fr3_hand", "fr3_leftfinger", "0 0 0.0584", axis="0 1 0", limit=(0, 0.04)),
    _joint(
        "fr3_finger_joint2",
        "prismatic",
        "fr3_hand",
        "fr3_rightfinger",
        "0 0 0.0584",
        axis="0 -1 0",
        limit=(0, 0.04),
        mimic='joint="fr3_finger_joint1"',
    ),
)
FRANKA = _robot("fr3_hand_like", list(FRANKA_JOINTS))

# An arm with a camera on a floating joint (a calibrated mount) and a planar joint (a mobile cart
# moving the tracker) off the chain.
OFF_CHAIN = _robot(
    "arm_with_camera",
    [
        _joint("j1", "revolute", "base_link", "l1", "0 0 0.4", axis="0 0 1", limit=(-3, 3)),
        _joint("j2", "revolute", "l1", "l2", "0.1 0 0.2", f"{-PI / 2} 0 0", "0 0 1", (-2, 2)),
        _joint("j3", "revolute", "l2", "l3", "0.5 0 0", axis="0 0 1", limit=(-2, 2)),
        _joint("j3-tool0", "fixed", "l3", "tool0", "0.4 0 0", f"0 {PI / 2} 0"),
        _joint("camera_mount", "floating", "l2", "camera", "0.2 0.1 0"),
        _joint("cart", "planar", "base_link", "tracker_cart", "2 0 0", axis="0 0 1"),
    ],
)

# An on-chain mimic, IRB 5400-like: joint_3 is driven with joint_2 (q3 = -0.8·q2 + 0.1), as a
# linkage couples them; the controller reads joint_1, joint_2, joint_4.
ON_CHAIN = _robot(
    "irb5400_like",
    [
        _joint("joint_1", "revolute", "base_link", "link_1", "0 0 0.5", axis="0 0 1", limit=(-2.5, 2.5)),
        _joint("joint_2", "revolute", "link_1", "link_2", "0.15 0 0", axis="0 1 0", limit=(-1.2, 1.2)),
        _joint(
            "joint_3",
            "revolute",
            "link_2",
            "link_3",
            "0 0 0.9",
            axis="0 1 0",
            limit=(-2, 2),
            mimic='joint="joint_2" multiplier="-0.8" offset="0.1"',
        ),
        _joint("joint_4", "revolute", "link_3", "link_4", "0.8 0 0.1", axis="1 0 0", limit=(-3, 3)),
        _joint("joint_4-tool0", "fixed", "link_4", "tool0", "0.1 0 0", f"0 {PI / 2} 0"),
    ],
)


def _import(tmp_path, capsys, text: str, *argv: str) -> tuple[dict, list[str]]:
    urdf, out = tmp_path / "r.urdf", tmp_path / "m.json"
    urdf.write_text(text)
    code = recal(["model", "--from-urdf", str(urdf), *argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    return json.loads(out.read_text()), err.splitlines()


def _check_fk(tmp_path, text: str, q_urdf: np.ndarray, tip: str, base: str, q_file: np.ndarray) -> None:
    urdf = tmp_path / "r.urdf"
    urdf.write_text(text)
    np.testing.assert_allclose(
        predict(tmp_path, tmp_path / "m.json", q_file), yourdfpy_fk(urdf, q_urdf, tip, base), atol=1e-9
    )


def _uniform(limits, n=25, seed=3) -> np.ndarray:
    lim = np.array(limits, dtype=float)
    return np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], (n, len(lim)))


def test_balancing_cylinder_mimic_joints_are_ignored_and_reported(tmp_path, capsys):
    doc, notes = _import(tmp_path, capsys, ABB)  # no --tip: base_link -> base and the cylinder are side branches
    assert [j["name"] for j in doc["joints"]] == [f"joint_{i}" for i in range(1, 7)]
    assert "coupling" not in doc
    text = "\n".join(notes)
    assert "'cylinder_joint' (revolute, mimic of 'joint_2')" in text and "ignored" in text
    assert "'piston_joint' (prismatic, mimic of 'joint_2')" in text
    assert "1 fixed frame(s) off the chain ('base')" in text
    q = _uniform([(-2.9, 2.9), (-1.1, 1.4), (-3.1, 1.2), (-5, 5), (-2, 2), (-6, 6)])
    robot = yourdfpy.URDF.load(str(tmp_path / "r.urdf"), load_meshes=False, build_scene_graph=True)
    assert robot.actuated_joint_names == [f"joint_{i}" for i in range(1, 7)]  # yourdfpy: the mimics follow
    _check_fk(tmp_path, ABB, q, "tool0", "base_link", np.rad2deg(q))


def test_two_finger_hand_fingers_are_ignored_and_reported(tmp_path, capsys):
    doc, notes = _import(tmp_path, capsys, FRANKA, "--tip", "fr3_hand_tcp")
    assert [j["name"] for j in doc["joints"]] == [f"fr3_joint{i}" for i in range(1, 5)]
    text = "\n".join(notes)
    assert "'fr3_finger_joint1' (prismatic) is not on the chain fr3_link0 -> fr3_hand_tcp: ignored" in text
    assert "'fr3_finger_joint2' (prismatic, mimic of 'fr3_finger_joint1')" in text
    q = _uniform([(-2.7, 2.7), (-1.7, 1.7), (-2.9, 2.9), (-3.0, -0.2)])
    q_urdf = np.column_stack([q, np.full(len(q), 0.02)])  # the finger opening does not move the tcp
    _check_fk(tmp_path, FRANKA, q_urdf, "fr3_hand_tcp", "fr3_link0", np.rad2deg(q))
    # a second actuated branch at the hand (a tool changer's slide) makes the default tip ambiguous
    slide = _joint("slide", "prismatic", "fr3_hand", "changer", axis="1 0 0", limit=(0, 1))
    two = _robot("fr3_hand_like", [*FRANKA_JOINTS, slide])
    urdf = tmp_path / "r.urdf"
    urdf.write_text(two)
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "link 'fr3_hand' branches" in err and "give --tip LINK" in err


def test_floating_and_planar_joints_off_the_chain_are_ignored_and_reported(tmp_path, capsys):
    doc, notes = _import(tmp_path, capsys, OFF_CHAIN)
    assert [j["name"] for j in doc["joints"]] == ["j1", "j2", "j3"]
    text = "\n".join(notes)
    assert "'camera_mount' (floating) is not on the chain base_link -> tool0: ignored" in text
    assert "'cart' (planar) is not on the chain" in text
    q = _uniform([(-3, 3), (-2, 2), (-2, 2)])
    # yourdfpy counts the floating and planar joints as actuated: they stay at zero
    _check_fk(tmp_path, OFF_CHAIN, np.column_stack([q, np.zeros((len(q), 2))]), "tool0", "base_link", np.rad2deg(q))
    # on the chain they still cannot be modelled
    urdf = tmp_path / "r.urdf"
    urdf.write_text(OFF_CHAIN)
    assert recal(["model", "--from-urdf", str(urdf), "--tip", "camera", "--out", str(tmp_path / "x.json")]) == 2
    assert "joint 'camera_mount': type 'floating' is not a single-axis joint" in capsys.readouterr().err


def test_a_mimic_joint_on_the_chain_is_the_models_coupling(tmp_path, capsys):
    doc, notes = _import(tmp_path, capsys, ON_CHAIN)
    assert notes == []
    assert [j["name"] for j in doc["joints"]] == ["joint_1", "joint_2", "joint_3", "joint_4"]
    # joint_3's variable is -0.8 x joint_2's reading (its own reading is not used), its offset 0.1 rad
    assert doc["coupling"] == [[1, 0, 0, 0], [0, 1, 0, 0], [0, -0.8, 0, 0], [0, 0, 0, 1]]
    assert doc["joints"][2]["theta"] == pytest.approx(np.rad2deg(0.1))
    q = _uniform([(-2.5, 2.5), (-1.2, 1.2), (-3, 3)])
    # the model's readings: joint_3's column is not used; a value that would move the arm shows it
    q_file = np.rad2deg(np.column_stack([q[:, :2], np.full(len(q), 1.3), q[:, 2]]))
    _check_fk(tmp_path, ON_CHAIN, q, "tool0", "base_link", q_file)


def test_a_mimic_joint_on_the_chain_following_a_joint_off_it_is_refused(tmp_path, capsys):
    text = ON_CHAIN.replace('joint="joint_2" multiplier="-0.8"', 'joint="joint_1" multiplier="-0.8"')
    urdf = tmp_path / "r.urdf"
    urdf.write_text(text)
    argv = ["model", "--from-urdf", str(urdf), "--base", "link_1", "--out", str(tmp_path / "x.json")]
    assert recal(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "joint 'joint_3' <mimic>: it follows joint 'joint_1'" in err


def test_a_mimic_joint_exports_as_mimic_and_reads_back(tmp_path, capsys):
    """The on-chain mimic model's URDF writes <mimic> (yourdfpy evaluates it), says nothing is
    lost, and reads back with no options to the same coupling."""
    from urdf_check import assert_urdf_is_predict

    doc, _ = _import(tmp_path, capsys, ON_CHAIN)
    model, urdf, back = tmp_path / "m.json", tmp_path / "out.urdf", tmp_path / "back.json"
    argv = ["export", "--model", str(model), "--format", "urdf", "--out", str(urdf), "--names", "ros"]
    assert recal(argv) == 0
    assert "coupling" not in capsys.readouterr().err
    robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_scene_graph=True)
    assert robot.joint_map["joint_3"].mimic.joint == "joint_2" and robot.joint_map["joint_3"].mimic.multiplier == -0.8
    q = np.rad2deg(np.column_stack([_uniform([(-2.5, 2.5), (-1.2, 1.2)]), np.zeros(25), _uniform([(-3, 3)], seed=4)]))
    assert_urdf_is_predict(urdf, model, q, tmp_path, names="ros")
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(back)]) == 0
    again = json.loads(back.read_text())
    assert again["coupling"] == doc["coupling"]
    np.testing.assert_allclose(predict(tmp_path, back, q), predict(tmp_path, model, q), atol=1e-9)
