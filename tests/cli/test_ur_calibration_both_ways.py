"""UR's calibration YAML both ways (issue 26), against files written here in the shapes UR's own
packages use: a ur_description-shaped URDF (base_link -> base_link_inertia turned by pi about z
-> shoulder_pan_joint ... wrist_3_joint, each joint's <origin> the calibration's x, y, z, roll,
pitch, yaw, then flange and tool0), and the YAML ur_calibration writes.

- export: whichever base link the URDF was imported from, the chain the YAML describes, composed
  as ur_description composes it, is ``recal predict``'s exactly (not up to a constant), and each
  link frame is the URDF's link frame (same joint axis, x not turned by pi);
- the hash is UR's (std::hash<std::string> of the DH values as the client library streams them):
  the nominal UR10e gives UR's published ``calib_5119701370761913513``;
- import (``recal model --from-ur-calibration FILE --robot ur10e``): the chain is ur_description's
  reading of the file, checked against yourdfpy on the URDF made from the same values.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from urdf_check import predict, yourdfpy_fk

from service.cli import main as recal

# UR's segments, its default UR10e file and ur_description's chain: one copy, beside the export's tests
from .test_ur_calibration_export import SEGMENTS, UR10E_DEFAULT, _chain, _origin, _rz

PI = np.pi
KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def _calibrated() -> dict:
    """UR's default UR10e segments with the small offsets a factory calibration has (every value)."""
    rng = np.random.default_rng(26)
    out = {}
    for seg in SEGMENTS:
        v = np.array(UR10E_DEFAULT[seg], dtype=float)
        v[:3] += rng.normal(0, 4e-4, 3)
        v[3:] += rng.normal(0, 2e-3, 3)
        out[seg] = dict(zip(KEYS, (float(x) for x in v)))
    return out


def _ur_description_urdf(kin: dict) -> str:
    """A URDF shaped as ur_description's ur_macro.xacro expands (kinematic part)."""

    def joint(name, jtype, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), moving=False):
        axis = '<axis xyz="0 0 1"/><limit lower="-6.28" upper="6.28" effort="330" velocity="2.09"/>' if moving else ""
        return (
            f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{" ".join(repr(float(v)) for v in xyz)}" rpy="{" ".join(repr(float(v)) for v in rpy)}"/>'
            f"{axis}</joint>"
        )

    links = ["base_link", "base_link_inertia", "base", "flange", "tool0"] + [f"{s}_link" for s in SEGMENTS]
    parts = [f'<link name="{n}"/>' for n in links]
    parts.append(joint("base_link-base_link_inertia", "fixed", "base_link", "base_link_inertia", rpy=(0, 0, PI)))
    parent = "base_link_inertia"
    for seg, jn in zip(SEGMENTS, JOINTS):
        s = kin[seg]
        xyz, rpy = (s["x"], s["y"], s["z"]), (s["roll"], s["pitch"], s["yaw"])
        parts.append(joint(jn, "revolute", parent, f"{seg}_link", xyz, rpy, moving=True))
        parent = f"{seg}_link"
    parts.append(joint("wrist_3-flange", "fixed", "wrist_3_link", "flange", rpy=(0, -PI / 2, -PI / 2)))
    parts.append(joint("flange-tool0", "fixed", "flange", "tool0", rpy=(PI / 2, 0, PI / 2)))
    parts.append(joint("base_link-base_fixed_joint", "fixed", "base_link", "base", rpy=(0, 0, PI)))
    return '<?xml version="1.0"?>\n<robot name="ur10e">\n' + "\n".join(parts) + "\n</robot>\n"


def _yaml_text(kin: dict, hash_: str = "calib_1") -> str:
    """The file as ur_calibration (yaml-cpp) writes it."""
    lines = ["kinematics:"]
    for seg in SEGMENTS:
        lines.append(f"  {seg}:")
        lines += [f"    {k}: {kin[seg][k]!r}" for k in KEYS]
    lines.append(f"  hash: {hash_}")
    return "\n".join(lines) + "\n"


def _frames(kin: dict, q: np.ndarray) -> list[np.ndarray]:
    """Each link frame of ur_description's chain from base_link_inertia: [(N, 4, 4)] x 6."""
    out = []
    T = np.tile(np.eye(4), (len(q), 1, 1))
    for i, seg in enumerate(SEGMENTS):
        s = kin[seg]
        R = np.tile(np.eye(4), (len(q), 1, 1))
        R[:, :3, :3] = np.array([_rz(a) for a in q[:, i]])
        T = T @ _origin(*(s[k] for k in KEYS)) @ R
        out.append(T)
    return out


RZ_PI = np.diag([-1.0, -1.0, 1.0, 1.0])
Q = np.random.default_rng(7).uniform(-PI, PI, (25, 6))


@pytest.mark.parametrize("base", ["base_link", "base_link_inertia"])
def test_export_from_either_base_link_is_the_true_chain(tmp_path, capsys, base):
    kin = _calibrated()
    urdf, model, out = tmp_path / "ur10e.urdf", tmp_path / "m.json", tmp_path / "calib.yaml"
    urdf.write_text(_ur_description_urdf(kin))
    assert recal(["model", "--from-urdf", str(urdf), "--base", base, "--tip", "tool0", "--out", str(model)]) == 0
    assert recal(["export", "--model", str(model), "--format", "ur-calibration", "--out", str(out)]) == 0
    text = out.read_text()
    assert "tool0 -> model flange" not in text and "warning" not in text
    y = yaml.safe_load(text)["kinematics"]
    T_base_bli = RZ_PI if base == "base_link" else np.eye(4)
    # the whole chain, exactly: base link -> tool0 at every configuration
    np.testing.assert_allclose(T_base_bli @ _chain(y, Q), predict(tmp_path, model, np.rad2deg(Q)), atol=1e-9)
    # each link frame is the URDF's: same joint axis through the same line, x not turned over
    for seg, F in zip(SEGMENTS, _frames(y, Q)):
        F = T_base_bli @ F
        G = yourdfpy_fk(urdf, Q, f"{seg}_link", base)
        np.testing.assert_allclose(F[:, :3, 2], G[:, :3, 2], atol=1e-9)
        off = F[:, :3, 3] - G[:, :3, 3]  # a shift along the axis at most
        np.testing.assert_allclose(np.cross(off, G[:, :3, 2]), 0.0, atol=1e-9)
        cos_x = np.einsum("ni,ni->n", F[:, :3, 0], G[:, :3, 0])
        assert np.all(cos_x > np.cos(np.deg2rad(1.0))), (seg, cos_x.min())
    # the URDF export (UR names by kinematics) has the same link frames as the YAML, from base_link
    back = tmp_path / "back.urdf"
    assert recal(["export", "--model", str(model), "--format", "urdf", "--out", str(back)]) == 0
    T_bl_bli = RZ_PI  # UR's base_link -> base_link_inertia
    for seg, F in zip(SEGMENTS, _frames(y, Q)):
        np.testing.assert_allclose(yourdfpy_fk(back, Q, f"{seg}_link", "base_link"), T_bl_bli @ F, atol=1e-9)


def test_nominal_ur10e_hash_is_urs(tmp_path):
    out = tmp_path / "calib.yaml"
    assert recal(["export", "--model", "ur10e", "--format", "ur-calibration", "--out", str(out)]) == 0
    # UR's default_kinematics.yaml for the UR10e (Universal_Robots_ROS2_Description) carries this hash
    assert yaml.safe_load(out.read_text())["kinematics"]["hash"] == "calib_5119701370761913513"


def test_nominal_ur10e_hash_is_urs_from_a_urdf_import_too(tmp_path):
    nominal = {seg: dict(zip(KEYS, UR10E_DEFAULT[seg])) for seg in SEGMENTS}
    urdf, model, out = tmp_path / "ur10e.urdf", tmp_path / "m.json", tmp_path / "calib.yaml"
    urdf.write_text(_ur_description_urdf(nominal))
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(model)]) == 0  # base_link -> tool0, no options
    assert recal(["export", "--model", str(model), "--format", "ur-calibration", "--out", str(out)]) == 0
    assert yaml.safe_load(out.read_text())["kinematics"]["hash"] == "calib_5119701370761913513"


def test_import_reads_the_file_as_ur_description_does(tmp_path, capsys):
    kin = _calibrated()
    calib, urdf, model = tmp_path / "c.yaml", tmp_path / "ur10e.urdf", tmp_path / "m.json"
    calib.write_text("# written by ur_calibration\n" + _yaml_text(kin, "calib_12345"))
    urdf.write_text(_ur_description_urdf(kin))
    assert recal(["model", "--from-ur-calibration", str(calib), "--robot", "ur10e", "--out", str(model)]) == 0
    doc = json.loads(model.read_text())
    assert [j["velocity"] for j in doc["joints"]] == [120, 120, 180, 180, 180, 180]
    T = predict(tmp_path, model, np.rad2deg(Q))
    np.testing.assert_allclose(T, _chain(kin, Q), atol=1e-9)  # the model's base is base_link_inertia
    np.testing.assert_allclose(T, yourdfpy_fk(urdf, Q, "tool0", "base_link_inertia"), atol=1e-9)
    # and back out: the same segments
    out = tmp_path / "again.yaml"
    assert recal(["export", "--model", str(model), "--format", "ur-calibration", "--out", str(out)]) == 0
    y = yaml.safe_load(out.read_text())["kinematics"]
    np.testing.assert_allclose(_chain(y, Q), _chain(kin, Q), atol=1e-9)


@pytest.mark.parametrize(
    "text, argv, expect",
    [
        (None, ["--robot", "ur10e"], "kinematics.forearm.yaw: expected a number, got 'abc'"),
        (None, ["--robot", "kr16"], "--robot: expected a library UR arm"),
        ("kinematics:\n  - 1\n", ["--robot", "ur10e"], "line 2: expected 'key: value'"),
    ],
)
def test_bad_calibration_file_gets_one_line(tmp_path, capsys, text, argv, expect):
    calib, out = tmp_path / "c.yaml", tmp_path / "m.json"
    if text is None:
        kin = _calibrated()
        text = _yaml_text(kin).replace(f"    yaw: {kin['forearm']['yaw']!r}", "    yaw: abc")
    calib.write_text(text)
    assert recal(["model", "--from-ur-calibration", str(calib), *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expect in err and str(calib) in err, err
    assert not out.exists()
