"""``recal plan`` and ``recal export`` (contracts §6): files that the other verbs accept, the
predicted accuracy on stdout and in the report, and one-line errors naming file, row and column,
with no output written."""

from __future__ import annotations

import csv
import dataclasses
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from urdf_check import assert_urdf_is_predict, in_file_units

from calibration import robots
from calibration.kinematics import fk
from calibration.simulate import random_configurations
from service.cli import main as recal
from service.files import format_csv, load_model, save_model


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """A UR10e (mm, degrees) 2.5 m in front of a tracker, a reflector on the flange, and a file of
    candidate configurations."""
    d = tmp_path_factory.mktemp("plan")
    model = dataclasses.replace(
        robots.nominal("ur10e"), targets={"smr": np.array([0.03, 0.0, 0.08])}, base=np.array([2.5, 0, 0, 0, 0, np.pi])
    )
    save_model(d / "ur.json", model)
    q = np.rad2deg(random_configurations(model, 300, np.random.default_rng(11)))
    (d / "cand.csv").write_text("# candidates\n" + format_csv([f"q{i}" for i in range(1, 7)], q.tolist()))
    return d


def _rows(path):
    return list(csv.DictReader(line for line in open(path) if not line.startswith("#")))


def test_plan_from_a_candidate_file(cell, tmp_path, capsys):
    out, rep = tmp_path / "poses.csv", tmp_path / "plan.json"
    assert (
        recal(
            [
                "plan",
                "--model",
                str(cell / "ur.json"),
                "--count",
                "25",
                "--out",
                str(out),
                "--candidates",
                str(cell / "cand.csv"),
                "--target",
                "smr",
                "--report",
                str(rep),
                "--evaluation-count",
                "60",
            ]
        )
        == 0
    )
    line = capsys.readouterr().out
    assert line.startswith("planned 25 poses (from 300 candidates, criterion D = ") and "RMS" in line
    rows = _rows(out)
    assert len(rows) == 25 and list(rows[0]) == [f"q{i}" for i in range(1, 7)] + ["candidate"]
    cand = _rows(cell / "cand.csv")
    picked = {int(r["candidate"]) for r in rows}
    assert len(picked) == 25
    for r in rows:  # each pose is its candidate row, in degrees
        c = cand[int(r["candidate"]) - 1]
        assert [float(r[f"q{i}"]) for i in range(1, 7)] == pytest.approx([float(c[f"q{i}"]) for i in range(1, 7)])
    report = json.loads(rep.read_text())
    assert report["poses"] == 25 and report["units"] == {"length": "mm", "angle": "deg"}
    assert 0.005 < report["predicted"]["rms"] < 0.05  # mm, for a 0.02 mm tracker
    assert report["predicted"]["p95"] >= report["predicted"]["rms"] * 0.8
    assert f"{report['predicted']['rms']:.4g} mm" in line
    names = [p["name"] for p in report["parameters"]]
    assert "j2.theta" in names and all(p["predicted_std_error"] > 0 for p in report["parameters"])
    # the poses file is a joints file for `recal predict`
    assert (
        recal(
            [
                "predict",
                "--model",
                str(cell / "ur.json"),
                "--joints",
                str(out),
                "--target",
                "smr",
                "--out",
                str(tmp_path / "pred.csv"),
            ]
        )
        == 0
    )
    assert len(_rows(tmp_path / "pred.csv")) == 25


def test_plan_with_drawn_candidates_and_line_of_sight(cell, tmp_path, capsys):
    out = tmp_path / "poses.csv"
    assert (
        recal(
            [
                "plan",
                "--model",
                str(cell / "ur.json"),
                "--count",
                "20",
                "--out",
                str(out),
                "--target",
                "smr",
                "--candidates-count",
                "400",
                "--cone",
                "30",
                "--clearance",
                "50",
                "--volume-box",
                "1000",
                "-1500",
                "100",
                "4000",
                "1500",
                "2000",
                "--criterion",
                "O3",
                "--evaluation-count",
                "50",
                "--seed",
                "4",
            ]
        )
        == 0
    )
    assert "criterion O3" in capsys.readouterr().out
    q = np.deg2rad(np.array([[float(r[f"q{i}"]) for i in range(1, 7)] for r in _rows(out)]))
    model = load_model(cell / "ur.json")
    T = fk(model, q)
    p = T[:, :3, :3] @ model.targets["smr"] + T[:, :3, 3]
    assert np.all((p[:, 0] > 1.0) & (p[:, 0] < 4.0) & (p[:, 2] > 0.1) & (p[:, 2] < 2.0))
    facing = np.einsum("ni,ni->n", T[:, :3, 2], -p / np.linalg.norm(p, axis=1, keepdims=True))
    assert np.all(facing >= np.cos(np.deg2rad(30)) - 1e-9)


def test_plan_for_a_wanted_accuracy(cell, tmp_path, capsys):
    out, rep = tmp_path / "poses.csv", tmp_path / "r.json"
    assert (
        recal(
            [
                "plan",
                "--model",
                str(cell / "ur.json"),
                "--accuracy",
                "0.02",
                "--out",
                str(out),
                "--candidates",
                str(cell / "cand.csv"),
                "--target",
                "smr",
                "--report",
                str(rep),
                "--evaluation-count",
                "60",
            ]
        )
        == 0
    )
    line = capsys.readouterr().out
    report = json.loads(rep.read_text())
    k = report["accuracy"]["count"]
    assert line.startswith(f"{k} poses are needed for a predicted rms error of at most 0.02 mm")
    assert len(_rows(out)) == k and report["predicted"]["rms"] <= 0.02
    curve = report["accuracy"]["greedy_curve"]
    assert curve[-1]["poses"] >= k - 1 and all(c["predicted"] > 0.02 for c in curve if c["poses"] < k)
    # unreachable: exit non-zero, one line, no poses file
    out2 = tmp_path / "none.csv"
    assert (
        recal(
            [
                "plan",
                "--model",
                str(cell / "ur.json"),
                "--accuracy",
                "0.001",
                "--count",
                "40",
                "--out",
                str(out2),
                "--candidates",
                str(cell / "cand.csv"),
                "--target",
                "smr",
                "--evaluation-count",
                "30",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "even 40 poses" in err and not out2.exists()


@pytest.mark.parametrize(
    "content, expect",
    [
        (
            "q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n0,0,0,0,0,0\n0,abc,0,0,0,0\n",
            "row 3 (line 4), column 'q2': expected a number",
        ),
        (
            "q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n0,0,0,0,400,0\n",
            "row 2 (line 3), column 'q5': 400 is outside joint j5's limits",
        ),
        ("q1,q2,q3,q4,q5\n0,0,0,0,0\n", "missing joint column 'q6'"),
    ],
)
def test_plan_bad_candidates_name_file_row_column(cell, tmp_path, capsys, content, expect):
    bad, out = tmp_path / "bad.csv", tmp_path / "poses.csv"
    bad.write_text(content)
    assert (
        recal(["plan", "--model", str(cell / "ur.json"), "--count", "10", "--out", str(out), "--candidates", str(bad)])
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and expect in err
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, expect",
    [
        (["--count", "3", "--target", "smr"], "`count` must be at least"),
        (["--count", "10", "--target", "ball"], "unknown target 'ball'"),
        (["--count", "10", "--sigma", "-1"], "--sigma: expected a positive number"),
        ([], "give --count K"),
    ],
)
def test_plan_bad_arguments(cell, tmp_path, capsys, argv, expect):
    out = tmp_path / "poses.csv"
    assert (
        recal(
            ["plan", "--model", str(cell / "ur.json"), "--out", str(out), "--candidates", str(cell / "cand.csv"), *argv]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expect in err and not out.exists()


# --------------------------------------------------------------------------- export


def test_export_urdf_dh_csv_and_markdown(cell, tmp_path, capsys):
    urdf, dhcsv, md = tmp_path / "r.urdf", tmp_path / "dh.csv", tmp_path / "dh.md"
    model = cell / "ur.json"
    argv = ["export", "--model", str(model), "--format", "urdf", "--out", str(urdf), "--name", "cell1"]
    assert recal([*argv, "--world"]) == 0
    root = ET.parse(urdf).getroot()
    assert root.get("name") == "cell1"
    # a UR arm gets UR's names (ur_description); --world: the model's base before base_link
    assert [j.get("name") for j in root.findall("joint") if j.get("type") == "revolute"] == [
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    ]
    assert root.find("joint[@name='base_joint']/origin").get("xyz") == "2.5 0 0"
    assert all(float(lim.get("velocity")) > 0 and float(lim.get("effort")) > 0 for lim in root.iter("limit"))
    q = in_file_units(model, random_configurations(load_model(model), 10, np.random.default_rng(4)))
    assert_urdf_is_predict(urdf, model, q, tmp_path, names="ur")  # yourdfpy: tcp, tool0 and target_smr
    assert recal(["export", "--model", str(model), "--format", "dh-csv", "--out", str(dhcsv)]) == 0
    rows = _rows(dhcsv)
    assert [r["joint"] for r in rows] == [f"j{i}" for i in range(1, 7)] and float(rows[1]["a"]) == pytest.approx(-612.7)
    assert "# target smr: 30, 0, 80" in dhcsv.read_text()
    assert recal(["export", "--model", str(model), "--format", "dh-md", "--out", str(md)]) == 0
    assert "| j3 | revolute | 0 | 0 | -571.55 | 0 | -360 | 360 |" in md.read_text()
    assert capsys.readouterr().err == ""


def test_export_warns_about_what_urdf_cannot_hold(tmp_path, capsys):
    doc = robots.nominal_document("ur10e")
    doc["joints"][1]["gain"] = 1.001
    (tmp_path / "g.json").write_text(json.dumps(doc))
    assert (
        recal(["export", "--model", str(tmp_path / "g.json"), "--format", "urdf", "--out", str(tmp_path / "g.urdf")])
        == 0
    )
    assert "gain 1.001 is not representable in URDF" in capsys.readouterr().err


def test_export_bad_model_names_the_field(tmp_path, capsys):
    doc = robots.nominal_document("ur10e")
    doc["joints"][2]["alpha"] = "ninety"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    out = tmp_path / "x.urdf"
    assert recal(["export", "--model", str(tmp_path / "bad.json"), "--format", "urdf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "joints[2].alpha" in err and not out.exists()


def test_a_20_pose_plan_says_what_would_determine_what_it_cannot(cell, tmp_path, capsys):
    """Issue 27: the plan names the parameters it cannot determine, how many poses would determine
    the ones poses of this kind can, and which kind of measurement the others need."""
    out, rep = tmp_path / "poses.csv", tmp_path / "plan.json"
    args = ["plan", "--model", str(cell / "ur.json"), "--count", "20", "--out", str(out)]
    assert recal([*args, "--candidates", str(cell / "cand.csv"), "--target", "smr", "--report", str(rep)]) == 0
    stdout = capsys.readouterr().out
    report = json.loads(rep.read_text())
    sf = report["shortfall"]
    assert sf["count"] == 20 and sf["more_poses"] == 0 and sf["poses_needed"] <= 20
    undetermined = {u["name"] for u in report["unidentifiable"]}
    assert {n for k in sf["by_kind"] for n in k["parameters"]} == undetermined
    line = next(x for x in stdout.splitlines() if x.startswith("not determined: "))
    assert "orientation measurements" in line and "tool.rx" in line
