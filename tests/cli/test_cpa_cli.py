"""``recal cpa`` (contracts §4, §6): a model that ``recal predict`` and ``recal identify``
accept, the report, and one-line errors naming file, row and column for bad circle-point
files, with no output written."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.cpa import simulate_sweeps
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from service.cli import main as recal
from service.files import format_csv, load_model, save_model, write_atomic

SIGNATURE_DEG = [10.0, -80.0, 70.0, -60.0, 45.0, 20.0]
HEADER = [f"q{i}" for i in range(1, 7)] + ["x", "y", "z", "target", "joint"]


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """Files of a simulated UR10e cell (mm, degrees): nominal model, CPA sweeps with 0.02 mm
    noise, and pose measurements."""
    d = tmp_path_factory.mktemp("cpa")
    rng = np.random.default_rng(30)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.06, 0.04, 0.09])})
    truth = dataclasses.replace(
        perturbed(nominal, rng),
        base=np.array([1.8, -0.6, 0.3, 0.002, -0.004, 2.2]),
        targets={"smr": np.array([0.0608, 0.0388, 0.0912])},
    )
    save_model(d / "nominal.json", nominal)
    sw = simulate_sweeps(truth, np.deg2rad(SIGNATURE_DEG), rng, sigma_m=20e-6, target="smr")
    rows = [
        list(np.rad2deg(q)) + list(p * 1e3) + [t, j + 1] for q, p, t, j in zip(sw.q, sw.p_world, sw.target, sw.joint)
    ]
    write_atomic(d / "cpa.csv", "# circle-point sweeps, one joint at a time\n" + format_csv(HEADER, rows))
    data = simulate_measurements(truth, random_configurations(nominal, 50, rng), rng, targets=("smr",))
    rows = [list(np.rad2deg(q)) + list(p * 1e3) + [t] for q, p, t in zip(data.q, data.p_world, data.target)]
    write_atomic(d / "poses.csv", format_csv(HEADER[:-1], rows))
    return d


def test_cpa_writes_a_model_that_predict_and_identify_accept(cell, tmp_path, capsys):
    out, rep = tmp_path / "cpa.json", tmp_path / "report.json"
    assert (
        recal(
            [
                "cpa",
                "--model",
                str(cell / "nominal.json"),
                "--data",
                str(cell / "cpa.csv"),
                "--out",
                str(out),
                "--report",
                str(rep),
            ]
        )
        == 0
    )
    assert "6 of 6 axes identified from 144 points" in capsys.readouterr().out
    model = load_model(out)
    assert model.convention == "dh" and model.units.length == "mm" and "cpa" in model.metadata
    report = json.loads(rep.read_text())
    assert report["success"] and [j["joint"] for j in report["joints"]] == [1, 2, 3, 4, 5, 6]
    j6 = report["joints"][5]
    assert j6["rows"] == [121, 144] and j6["fits"][0]["points"] == 24
    assert abs(j6["fits"][0]["arc"] - 200) < 0.5 and 0.01 < j6["fits"][0]["noise"] < 0.03  # deg, mm
    assert report["signature"]["q"] == pytest.approx(SIGNATURE_DEG)

    (tmp_path / "joints.csv").write_text("q1,q2,q3,q4,q5,q6\n0,-90,90,0,45,0\n")
    assert (
        recal(
            [
                "predict",
                "--model",
                str(out),
                "--joints",
                str(tmp_path / "joints.csv"),
                "--target",
                "smr",
                "--out",
                str(tmp_path / "pred.csv"),
            ]
        )
        == 0
    )
    assert len((tmp_path / "pred.csv").read_text().splitlines()) == 2
    assert (
        recal(
            [
                "identify",
                "--model",
                str(out),
                "--data",
                str(cell / "poses.csv"),
                "--out",
                str(tmp_path / "identified.json"),
            ]
        )
        == 0
    )
    assert load_model(tmp_path / "identified.json").metadata["identification"]["success"]


def test_cpa_poe_output(cell, tmp_path):
    out = tmp_path / "cpa_poe.json"
    assert (
        recal(
            [
                "cpa",
                "--model",
                str(cell / "nominal.json"),
                "--data",
                str(cell / "cpa.csv"),
                "--out",
                str(out),
                "--convention",
                "poe",
                "--method",
                "kasa",
            ]
        )
        == 0
    )
    doc = json.loads(out.read_text())
    assert doc["convention"] == "poe" and len(doc["home"]) == 6
    assert all(abs(np.linalg.norm(j["axis"]) - 1) < 1e-9 for j in doc["joints"])


def _rewrite(src: Path, dst: Path, edit) -> None:
    lines = src.read_text().splitlines()
    dst.write_text("\n".join(edit(lines)) + "\n")


def _cell(line: str, column: str, value: str) -> str:
    cells = line.split(",")
    cells[HEADER.index(column)] = value
    return ",".join(cells)


def _still(line: str, first: str) -> str:
    """``line`` with the reflector position of ``first``."""
    for c in "xyz":
        line = _cell(line, c, first.split(",")[HEADER.index(c)])
    return line


# line 1 is a comment, line 2 the header, data row r is on line r + 2 (list index r + 1)
def _at(row: int, column: str, value: str):
    """An edit that puts ``value`` into ``column`` of data row ``row``."""
    return lambda ls: ls[: row + 1] + [_cell(ls[row + 1], column, value)] + ls[row + 2 :]


BAD = {
    "no joint column": (lambda ls: [l.rsplit(",", 1)[0] for l in ls], "missing required column 'joint'"),
    "joint out of range": (_at(6, "joint", "7"), "row 6 (line 8), column 'joint'"),
    "joint not whole": (_at(6, "joint", "2.5"), "row 6 (line 8), column 'joint'"),
    "joint not a number": (_at(6, "joint", "six"), "row 6 (line 8), column 'joint'"),
    "bad coordinate": (_at(3, "y", "1.2.3"), "row 3 (line 5), column 'y'"),
    "unknown target": (_at(3, "target", "smr9"), "row 3 (line 5), column 'target'"),
    "other joint moves": (
        _at(31, "q1", "11.5"),
        "row 31 (line 33), column 'q1': joint 1 moves during the sweep of joint 2",
    ),
    "too few points": (
        lambda ls: ls[:123] + ls[144:],
        "row 121 (line 123), column 'joint': the sweep of joint 6 has 3",
    ),
    "reflector still": (
        lambda ls: ls[:122] + [_still(l, ls[122]) for l in ls[122:]],
        "row 121 (line 123): the sweep of joint 6 (rows 121-144): the points are collinear",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_files_one_line_no_output(cell, tmp_path, capsys, case):
    edit, expected = BAD[case]
    bad, out = tmp_path / "bad.csv", tmp_path / "model.json"
    _rewrite(cell / "cpa.csv", bad, edit)
    assert recal(["cpa", "--model", str(cell / "nominal.json"), "--data", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"recal cpa: {bad}")
    assert expected in err
    assert not out.exists()


def test_missing_sweep_still_writes_but_fails(cell, tmp_path, capsys):
    src = cell / "cpa.csv"
    part = tmp_path / "part.csv"
    _rewrite(src, part, lambda ls: ls[:122])  # joint 6 not swept
    out = tmp_path / "model.json"
    assert recal(["cpa", "--model", str(cell / "nominal.json"), "--data", str(part), "--out", str(out)]) == 1
    assert out.exists() and "joint 6 (j6) was not swept" in capsys.readouterr().err
