"""Bad files are refused, never silently read (issue 12: CLI on bad files): a misspelt model
field, joint readings beyond the model's limits, binary or non-UTF-8 files and numbers no
robot cell can have each get one line naming the file, the row and the field, exit status 2
and no output file."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.kinematics import fk
from calibration.model import Units, model_to_dict
from calibration.simulate import random_configurations, simulate_measurements
from service.cli import main as recal

MM_DEG = Units("mm", "deg")


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    """A UR10e nominal model (mm, deg) with a reflector, 40 simulated measurements of it and
    a task CSV of 5 tool poses."""
    import dataclasses

    d = tmp_path_factory.mktemp("strict")
    model = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    doc = model_to_dict(model, units=MM_DEG)
    (d / "nominal.json").write_text(json.dumps(doc, indent=2))
    rng = np.random.default_rng(4)
    data = simulate_measurements(model, random_configurations(model, 40, rng), rng, sigma_m=20e-6, targets=("smr",))
    with (d / "meas.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i}" for i in range(1, 7)] + ["x", "y", "z", "target"])
        for q, p in zip(np.degrees(data.q), data.p_world * 1e3):
            w.writerow([f"{v:.10g}" for v in q] + [f"{v:.10g}" for v in p] + ["smr"])
    T = fk(model, random_configurations(model, 5, rng))
    from calibration.transforms import matrix_to_quat

    with (d / "task.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", "z", "qw", "qx", "qy", "qz"])
        for Ti in T:
            w.writerow([f"{v:.10g}" for v in Ti[:3, 3] * 1e3] + [f"{v:.10g}" for v in matrix_to_quat(Ti[:3, :3])])
    return d


def _run(capsys, *argv) -> tuple[int, str]:
    status = recal([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    return status, err


def _one_line(status: int, err: str, *parts: str) -> None:
    assert status == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    for part in parts:
        assert part in err, err


def _model(files: Path, tmp_path: Path, edit) -> Path:
    doc = json.loads((files / "nominal.json").read_text())
    edit(doc)
    path = tmp_path / "model.json"
    path.write_text(json.dumps(doc))
    return path


def _edit_joint(i: int, old: str, new: str):
    def edit(doc):
        doc["joints"][i][new] = doc["joints"][i].pop(old)

    return edit


@pytest.mark.parametrize(
    "edit, field, guess",
    [
        (_edit_joint(1, "alpha", "alpah"), "joints[1].alpah", "'alpha'"),
        (_edit_joint(2, "a", "aa"), "joints[2].aa", "'a'"),
        (_edit_joint(0, "theta", "Theta"), "joints[0].Theta", "'theta'"),
        (lambda doc: doc.update(tagets=doc.pop("targets")), "tagets", "'targets'"),
        (lambda doc: doc.update(tools=doc.pop("tool")), "tools", "'tool'"),
    ],
)
def test_a_misspelt_model_field_is_refused_with_a_did_you_mean(files, tmp_path, capsys, edit, field, guess):
    model = _model(files, tmp_path, edit)
    out = tmp_path / "out.json"
    status, err = _run(capsys, "identify", "--model", model, "--data", files / "meas.csv", "--out", out)
    _one_line(status, err, str(model), repr(field), "unknown field", f"did you mean {guess}")
    assert not out.exists()


def test_an_unknown_joint_field_without_a_near_miss_lists_the_known_ones(files, tmp_path, capsys):
    model = _model(files, tmp_path, lambda doc: doc["joints"][3].update(offset=2.0))
    status, err = _run(capsys, "predict", "--model", model, "--joints", files / "meas.csv", "--out", tmp_path / "p.csv")
    _one_line(status, err, "'joints[3].offset'", "expected one of", "alpha")


def test_other_sections_and_per_joint_velocity_and_effort_are_kept(files, tmp_path, capsys):
    def edit(doc):
        doc["identification"] = {"parameters": []}
        doc["source"] = {"vendor": "Universal Robots"}
        doc["calibration_notes"] = {"technician": "J. Doe"}
        doc["joints"][0].update(velocity=180.0, effort=330.0)

    model = _model(files, tmp_path, edit)
    out = tmp_path / "p.csv"
    status, err = _run(capsys, "predict", "--model", model, "--joints", files / "meas.csv", "--out", out)
    assert status == 0, err
    assert len(out.read_text().splitlines()) == 41


def test_joint_readings_beyond_the_limits_name_row_and_column(files, tmp_path, capsys):
    rows = list(csv.reader((files / "meas.csv").open()))
    rows[3][1] = "5000"  # data row 3, q2 (deg): far beyond ±360
    bad = tmp_path / "bad.csv"
    csv.writer(bad.open("w", newline="")).writerows(rows)
    out = tmp_path / "out.json"
    status, err = _run(capsys, "identify", "--model", files / "nominal.json", "--data", bad, "--out", out)
    _one_line(status, err, str(bad), "row 3", "column 'q2'", "5000 is outside joint", "[-360, 360] deg")
    assert not out.exists()


@pytest.mark.parametrize(
    "content, expect",
    [
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)), "binary file"),
        ("q1,q2\n# caf\xe9\n".encode("latin-1"), "not UTF-8"),
    ],
)
@pytest.mark.parametrize("role", ["data", "model"])
def test_a_binary_or_non_utf8_file_is_one_clean_line(files, tmp_path, capsys, content, expect, role):
    bad = tmp_path / ("bad.json" if role == "model" else "bad.csv")
    bad.write_bytes(content)
    model, data = (bad, files / "meas.csv") if role == "model" else (files / "nominal.json", bad)
    out = tmp_path / "out.json"
    status, err = _run(capsys, "identify", "--model", model, "--data", data, "--out", out)
    _one_line(status, err, str(bad), expect, "line ")
    assert not out.exists()


def test_1e308_in_a_measurement_row_is_named_not_an_svd_failure(files, tmp_path, capsys):
    rows = list(csv.reader((files / "meas.csv").open()))
    rows[5][6] = "1e308"  # data row 5, x
    bad = tmp_path / "bad.csv"
    csv.writer(bad.open("w", newline="")).writerows(rows)
    out = tmp_path / "out.json"
    status, err = _run(capsys, "identify", "--model", files / "nominal.json", "--data", bad, "--out", out)
    _one_line(status, err, str(bad), "row 5", "column 'x'", "1e308")
    assert "SVD" not in err and not out.exists()


def test_1e308_in_a_task_row_is_named_and_compensate_writes_nothing(files, tmp_path, capsys):
    rows = list(csv.reader((files / "task.csv").open()))
    rows[2][0] = "1e308"  # data row 2, x
    bad = tmp_path / "task.csv"
    csv.writer(bad.open("w", newline="")).writerows(rows)
    out = tmp_path / "out.csv"
    status, err = _run(capsys, "compensate", "--model", files / "nominal.json", "--task", bad, "--out", out)
    _one_line(status, err, str(bad), "row 2", "column 'x'", "1e308")
    assert not out.exists()


def test_1e308_in_a_urscript_target_is_named_and_compensate_writes_nothing(files, tmp_path, capsys):
    prog = tmp_path / "prog.script"
    prog.write_text(
        "def prog():\n  movej([0.1, -1.2, 1.3, -1.6, -1.5, 0.2], a=1.2, v=0.5)\n"
        "  movej([0.1, -1.2, 1.3, -1.6, -1.5, 1e308], a=1.2, v=0.5)\nend\n"
    )
    out = tmp_path / "out.script"
    status, err = _run(capsys, "compensate", "--model", files / "nominal.json", "--task", prog, "--out", out)
    _one_line(status, err, str(prog), "line 3", "1e+308")
    assert not out.exists()
