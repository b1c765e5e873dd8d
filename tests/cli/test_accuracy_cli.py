"""``recal accuracy``: ISO 9283 pose accuracy and repeatability of measurement files against a
model, on data built so that every figure is known by hand (docs/accuracy.md), and one-line
errors naming file, row and column, with no output written."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from calibration import robots
from calibration.kinematics import fk, target_positions
from calibration.transforms import matrix_to_quat, rot
from service.cli import main as recal
from service.files import format_csv, save_model

SMR = np.array([0.03, 0.0, 0.08])
Q_A = np.array([10.0, -80.0, 70.0, -60.0, 45.0, 20.0])  # degrees
Q_B = np.array([-40.0, -100.0, 100.0, -30.0, -60.0, 5.0])


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    d = tmp_path_factory.mktemp("accuracy")
    model = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": SMR})  # mm, deg
    save_model(d / "ur.json", model)
    return d, model


def smr_mm(model, q_deg):
    return target_positions(model, np.radians(np.atleast_2d(q_deg)), "smr") * 1e3


def write(path, header, rows):
    path.write_text(format_csv(header, rows))


Q = [f"q{i}" for i in range(1, 7)]


def test_repeated_configurations_are_grouped_by_their_joint_readings(robot, tmp_path, capsys):
    """Pose A measured 3 times with readings that scatter by 0.001°, at offsets (0, 0, 0), (0, 0, 3),
    (0, 0, 0) mm from where the model puts the reflector: barycentre (0, 0, 1), AP = 1 mm;
    l = 1, 2, 1, l̄ = 4/3, S_l = √(1/3), RP = 4/3 + √3 mm. Pose B measured once, 0.5 mm off: an AP,
    no RP."""
    d, model = robot
    jitter = np.array([[0, 0, 0, 0, 0, 0], [0.001, -0.001, 0, 0.001, 0, 0], [-0.001, 0.001, 0, -0.001, 0, 0]])
    rows = []  # the readings scatter (symmetrically: the mean command is where the model puts Q_A)
    for q, off in zip(Q_A + jitter, [[0, 0, 0], [0, 0, 3], [0, 0, 0]]):
        rows.append([*q, *(smr_mm(model, Q_A)[0] + off), "smr"])
    rows.insert(1, [*Q_B, *(smr_mm(model, Q_B)[0] + [0.3, 0.4, 0.0]), "smr"])  # interleaved, as sessions record
    write(tmp_path / "meas.csv", [*Q, "x", "y", "z", "target"], rows)
    assert (
        recal(
            [
                "accuracy",
                "--model",
                str(d / "ur.json"),
                "--data",
                str(tmp_path / "meas.csv"),
                "--out",
                str(tmp_path / "acc.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    rep = json.loads((tmp_path / "acc.json").read_text())
    assert rep["grouping"] == "by joint readings within 0.05 deg" and rep["measurements"] == 4
    a, b = rep["per_pose"]
    assert (a["pose"], a["n"], a["rows"], b["n"], b["rows"]) == ("1", 3, [1, 3, 4], 1, [2])
    assert a["AP"] == pytest.approx(1.0, abs=1e-5) and a["AP_xyz"] == pytest.approx([0, 0, 1], abs=1e-5)
    assert a["l_mean"] == pytest.approx(4 / 3, abs=1e-5) and a["S_l"] == pytest.approx(math.sqrt(1 / 3), abs=1e-5)
    assert a["RP"] == pytest.approx(4 / 3 + math.sqrt(3), abs=1e-5)
    assert a["three_S_l"] == pytest.approx(math.sqrt(3), abs=1e-5)
    assert b["AP"] == pytest.approx(0.5, abs=1e-6) and b["RP"] is None and b["l_mean"] is None
    assert rep["overall"]["AP"] == pytest.approx({"mean": 0.75, "max": 1.0}, abs=1e-5)
    assert rep["overall"]["RP"] == pytest.approx({"mean": 4 / 3 + math.sqrt(3), "max": 4 / 3 + math.sqrt(3)}, abs=1e-5)
    meas = np.array([r[6:9] for r in rows], float)
    e = np.linalg.norm(meas - smr_mm(model, np.array([r[:6] for r in rows], float)), axis=1)  # per row, mm
    assert rep["errors"]["mean"] == pytest.approx(np.mean(e), abs=1e-5)
    assert rep["errors"]["three_sigma"] == pytest.approx(3 * np.std(e, ddof=1), abs=1e-5)
    assert rep["errors"]["max"] == pytest.approx(e.max(), abs=1e-5) and e.max() == pytest.approx(3.0, abs=0.05)
    assert "1 of 2 poses were measured once" in rep["note"]
    # stdout: the summary (the overall figures); the per-pose table is the report's
    lines = out.splitlines()
    assert lines[0].startswith("ISO 9283 pose accuracy (AP) and repeatability (RP) of ur10e-nominal on")
    assert lines[1].startswith("overall: AP mean 0.75, max 1 mm; RP mean 3.065, max 3.065 mm")
    assert lines[2].startswith("position error of the 4 measurements:")
    assert lines[-1].endswith(str(tmp_path / "acc.json")) and "pose  target" not in out


def test_pose_labels_and_orientations(robot, tmp_path, capsys):
    """A pose_id column groups the rows (a new label at the same readings is another pose); full-pose
    rows add the orientation figures: rotations
    about the world z axis by +1, −1, +3 mrad give AP_c = 1 mrad and RP_c = 6 mrad (in degrees)."""
    d, model = robot
    T = fk(model, np.radians(Q_A)[None])[0]
    rows = []
    for dz in [1e-3, -1e-3, 3e-3]:
        quat = matrix_to_quat((rot(2, dz) @ T[:3, :3])[None])[0]
        rows.append([*Q_A, *(T[:3, 3] * 1e3), *quat, "p1"])
    rows.append([*Q_A, *(T[:3, 3] * 1e3 + [0, 0.2, 0]), *matrix_to_quat(T[None, :3, :3])[0], "p2"])
    write(tmp_path / "pose.csv", [*Q, "x", "y", "z", "qw", "qx", "qy", "qz", "pose_id"], rows)
    assert (
        recal(
            [
                "accuracy",
                "--model",
                str(d / "ur.json"),
                "--data",
                str(tmp_path / "pose.csv"),
                "--out",
                str(tmp_path / "acc.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    rep = json.loads((tmp_path / "acc.json").read_text())
    assert rep["grouping"] == "by the 'pose_id' column"
    p1, p2 = rep["per_pose"]
    assert (p1["pose"], p1["n"], p1["target"], p2["pose"], p2["n"]) == ("p1", 3, None, "p2", 1)
    # the tool origin was measured (no target named): positions within rounding of the command
    assert p1["AP"] < 1e-6 and p2["AP"] == pytest.approx(0.2, abs=1e-6)
    assert p1["AP_abc"] == pytest.approx([0, 0, math.degrees(1e-3)], rel=1e-5, abs=1e-7)  # 6 digits
    assert p1["RP_abc"] == pytest.approx([0, 0, math.degrees(6e-3)], rel=1e-5, abs=1e-7)
    overall = next(line for line in out.splitlines() if line.startswith("overall:"))
    assert "orientation AP_a, AP_b, AP_c max" in overall and overall.endswith(f", {math.degrees(1e-3):.4g} deg")
    assert "orientation error" in out


def test_one_measurement_per_pose_gives_accuracy_and_says_repeatability_needs_repeats(robot, tmp_path, capsys):
    d, model = robot
    offsets = np.array([[3, 0, 0], [0, 4, 0], [0, 0, 5]], float)  # the docs' hand example: mean 4, 3σ 3, max 5
    qs = [Q_A, Q_B, Q_A + 20]
    rows = [[*q, *(smr_mm(model, q)[0] + off)] for q, off in zip(qs, offsets)]
    write(tmp_path / "once.csv", [*Q, "x", "y", "z"], rows)
    assert (
        recal(["accuracy", "--model", str(d / "ur.json"), "--data", str(tmp_path / "once.csv"), "--target", "smr"]) == 0
    )
    out = capsys.readouterr().out
    assert "mean 4, 3σ 3, mean + 3σ 7" in out and "max 5 mm" in out
    assert "overall: AP mean 4, max 5 mm\n" in out and "RP mean" not in out
    assert "note: every pose was measured once" in out and "needs each configuration measured at least twice" in out


@pytest.mark.parametrize(
    "content, args, match",
    [
        (
            "q1,q2,q3,q4,q5,q6,x,y,z\n0,0,0,0,0,0,1,2,3\n0,0,0,0,0,0,1,oops,3\n",
            [],
            r"bad\.csv, row 2 \(line 3\), column 'y': expected a number, got 'oops'",
        ),
        (
            "q1,q2,q3,q4,q5,x,y,z\n0,0,0,0,0,1,2,3\n",
            [],
            r"bad\.csv, header \(line 1\), column 'q6': missing joint column",
        ),
        (
            "q1,q2,q3,q4,q5,q6,x,y,z,pose_id\n0,0,0,0,0,0,1,2,3,a\n0,0,0,0,0,0,1,2,3,\n",
            [],
            r"bad\.csv, row 2 \(line 3\), column 'pose_id': expected a pose label",
        ),
        (
            "q1,q2,q3,q4,q5,q6,x,y,z,target\n0,0,0,0,0,0,1,2,3,ball\n",
            [],
            r"bad\.csv, row 1 \(line 2\), column 'target': unknown target 'ball'",
        ),
        (
            "q1,q2,q3,q4,q5,q6,x,y,z\n0,0,0,0,0,0,1,2,3\n",
            ["--target", "ball"],
            r"ur\.json: field 'targets': no target 'ball'",
        ),
        (
            "q1,q2,q3,q4,q5,q6,x,y,z\n0,0,0,0,0,0,1,2,3\n",
            ["--joint-tol", "-1"],
            r"--joint-tol: expected a positive number",
        ),
    ],
)
def test_bad_input_is_one_line_and_no_output_file(robot, tmp_path, capsys, content, args, match):
    import re

    d, _ = robot
    (tmp_path / "bad.csv").write_text(content)
    out = tmp_path / "acc.json"
    assert (
        recal(
            ["accuracy", "--model", str(d / "ur.json"), "--data", str(tmp_path / "bad.csv"), "--out", str(out), *args]
        )
        == 2
    )
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recal accuracy: ") and re.search(match, lines[0]), lines
    assert captured.out == "" and not out.exists()
