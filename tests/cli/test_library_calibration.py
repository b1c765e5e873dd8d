"""Every arm of the robot library calibrates end to end on files: its nominal model (written by
``recal model``, a reflector added, the robot 3 m in front of the tracker), measurements of a
perturbed "true" robot (calibration.simulate: every axis tilted and shifted, every offset moved,
an unknown base) written as a measurement CSV, then ``recal identify --validate`` on a hold-out
file. The hold-out error must come down from millimetres to the tracker's noise."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from calibration import robots
from calibration.model import model_from_dict
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from service.cli import main as recal

# every robot `recal model` lists (the library as it stands, so an arm added later is covered too)
ARMS = robots.names()
SIGMA_MM = 0.02


def test_the_library_is_what_issue_16_asked_for():
    wanted = ["kr16", "kr210", "irb4600", "irb6700", "m20ia", "r2000ic", "gp25", "tx2-90", "fr3", "iiwa14"]
    assert set(wanted + ["ur3e", "ur5e", "ur10e", "ur16e", "puma560", "puma560-zrp"]) <= set(ARMS)


def _write_measurements(path, model, data) -> None:
    L = model.units.length_m
    scale = np.array([model.units.angle_rad if j.revolute else L for j in model.joints])
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z", "target"])
        for q, p, t in zip(data.q / scale, data.p_world / L, data.target):
            w.writerow([f"{v:.12g}" for v in q] + [f"{v:.12g}" for v in p] + [t])


def _calibrate_on_files(nominal_path, tmp_path, seed: int) -> dict:
    """The nominal model file with a reflector and a base, a perturbed truth measured at 90
    random configurations (60 to identify, 30 held out), then ``recal identify --validate``:
    its report's validation block (the model written is checked too)."""
    doc = json.loads(nominal_path.read_text())
    mm = 1e-3 / model_from_dict(doc).units.length_m  # the file's length unit per mm (the PUMA's are inches)
    half_turn = 180.0 if doc["units"]["angle"] == "deg" else np.pi
    doc["targets"] = {"smr": [30.0 * mm, 0.0, 60.0 * mm]}
    doc["base"] = [3000.0 * mm, 0.0, 0.0, 0.0, 0.0, half_turn]
    nominal_path.write_text(json.dumps(doc))
    nominal = model_from_dict(doc)
    rng = np.random.default_rng(seed)
    truth = perturbed(nominal, rng, base_length_m=0.005, base_angle_rad=0.005)
    data = simulate_measurements(
        truth, random_configurations(nominal, 90, rng), rng, sigma_m=SIGMA_MM * 1e-3, targets=("smr",)
    )
    ident, check = tmp_path / "id.csv", tmp_path / "check.csv"
    _write_measurements(ident, nominal, data.subset(np.arange(60)))
    _write_measurements(check, nominal, data.subset(np.arange(60, 90)))
    out, report = tmp_path / "identified.json", tmp_path / "report.json"
    args = ["identify", "--model", str(nominal_path), "--data", str(ident), "--validate", str(check)]
    assert recal([*args, "--sigma", str(SIGMA_MM * mm), "--out", str(out), "--report", str(report)]) == 0
    assert json.loads(out.read_text())["format"] == "recal.model/1"
    v = json.loads(report.read_text())["validation"]  # in the model's length unit
    return {**v, "rms_mm": v["rms"] / mm, "before_rms_mm": v["before"]["rms"] / mm}


@pytest.mark.parametrize("name", ARMS)
def test_library_arm_calibrates_end_to_end(name, tmp_path, capsys):
    nominal_path = tmp_path / f"{name}.json"
    assert recal(["model", name, "--out", str(nominal_path)]) == 0
    v = _calibrate_on_files(nominal_path, tmp_path, seed=5)
    assert "hold-out RMS" in capsys.readouterr().out
    noise_rms = SIGMA_MM * np.sqrt(3)  # 3-D RMS of the tracker's noise
    assert v["rows"] == 30 and v["before_rms_mm"] > 1.0  # millimetres before
    assert v["rms_mm"] < 1.35 * noise_rms, v  # the noise after (60 poses, about 30 parameters)


# A gantry from a URDF: a prismatic rail, then a 5-axis arm (what `recal model --from-urdf` gives).
GANTRY_URDF = """<robot name="gantry">
  <link name="floor"/><link name="carriage"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="l4"/>
  <link name="l5"/><link name="tool0"/>
  <joint name="rail" type="prismatic"><origin xyz="0 0 0.8"/><parent link="floor"/><child link="carriage"/>
    <axis xyz="0 1 0"/><limit lower="-1.0" upper="1.0" effort="2000" velocity="1.0"/></joint>
  <joint name="j1" type="revolute"><origin xyz="0 0 0.3"/><parent link="carriage"/><child link="l1"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="300" velocity="2"/></joint>
  <joint name="j2" type="revolute"><origin xyz="0.15 0 0.2"/><parent link="l1"/><child link="l2"/>
    <axis xyz="0 1 0"/><limit lower="-1.5" upper="2" effort="300" velocity="2"/></joint>
  <joint name="j3" type="revolute"><origin xyz="0 0 0.7"/><parent link="l2"/><child link="l3"/>
    <axis xyz="0 1 0"/><limit lower="-2.5" upper="1.5" effort="100" velocity="2"/></joint>
  <joint name="j4" type="revolute"><origin xyz="0.6 0 0.1"/><parent link="l3"/><child link="l4"/>
    <axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <joint name="j5" type="revolute"><origin xyz="0.1 0 0"/><parent link="l4"/><child link="l5"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="50" velocity="3"/></joint>
  <joint name="l5-tool0" type="fixed"><origin xyz="0.12 0 0" rpy="0 1.5707963267948966 0"/>
    <parent link="l5"/><child link="tool0"/></joint>
</robot>
"""


def test_a_gantry_read_from_its_urdf_calibrates_end_to_end(tmp_path):
    urdf, nominal_path = tmp_path / "gantry.urdf", tmp_path / "gantry.json"
    urdf.write_text(GANTRY_URDF)
    assert recal(["model", "--from-urdf", str(urdf), "--out", str(nominal_path)]) == 0
    assert json.loads(nominal_path.read_text())["joints"][0]["type"] == "prismatic"
    v = _calibrate_on_files(nominal_path, tmp_path, seed=6)
    assert v["before_rms_mm"] > 1.0 and v["rms_mm"] < 1.35 * SIGMA_MM * np.sqrt(3), v
