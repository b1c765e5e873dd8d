"""The command line as an engineer expects it (issue 27): ``recal --version`` and ``python -m
recal``; a mistyped flag named, with the flag it most likely meant; a task file in another
language than ``--format`` says named as such; ``accuracy`` against a model whose world is not
the instrument's warns in one line and prints a summary (the per-pose table is the report's)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.kinematics import target_positions
from calibration.transforms import homogeneous, rot
from service.cli import main as recal
from service.files import format_csv, save_model

ROOT = Path(__file__).resolve().parents[2]
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def test_version_is_the_packages(capsys):
    assert recal(["--version"]) == 0
    assert capsys.readouterr().out == f"recal {VERSION}\n"


def test_python_dash_m_recal_is_the_same_cli(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "recal", "--version"], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert (done.returncode, done.stdout) == (0, f"recal {VERSION}\n"), done.stderr
    done = subprocess.run(
        [sys.executable, "-m", "recal", "model", "--help"], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert done.returncode == 0 and done.stdout.startswith("usage: recal model"), done.stderr


@pytest.mark.parametrize(
    "argv, expected",
    [
        (
            ["compensate", "--modle", "ur10e", "--task", "t.csv", "--out", "o.csv"],
            "recal compensate: unrecognized argument --modle; did you mean --model?",
        ),
        (
            ["accuracy", "--model", "ur10e", "--dta", "m.csv"],
            "recal accuracy: unrecognized argument --dta; did you mean --data?",
        ),
        (
            ["identify", "--model=ur10e", "--data", "m.csv", "--out", "x.json", "--reprot=r.json"],
            "recal identify: unrecognized argument --reprot; did you mean --report?",
        ),
        (["--verison"], "recal: unrecognized argument --verison; did you mean --version?"),
        (["predict", "--zzzz"], "recal predict: unrecognized argument --zzzz (see"),
        (
            ["token", "create", "--rloe", "viewer"],
            "recal token create: unrecognized argument --rloe; did you mean --role?",
        ),
    ],
)
def test_a_mistyped_flag_is_named_with_a_suggestion(argv, expected, capsys):
    with pytest.raises(SystemExit) as exc:
        recal(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.startswith(expected) and err.count("\n") == 1, err


def test_a_sub_commands_flags_are_its_own(tmp_path, monkeypatch, capsys):
    # `recal token create --role viewer`: --role is create's, not a typo of token's
    monkeypatch.setenv("RECAL_HOME", str(tmp_path))
    assert recal(["token", "create", "--role", "viewer", "--name", "create"]) == 0
    assert capsys.readouterr().out.startswith("rc_")


def test_a_unique_prefix_is_still_a_flag(tmp_path, capsys):
    # argparse takes --mod as --model when unique in the verb: not a typo
    assert (
        recal(
            ["model", "--help"]
            if False
            else ["export", "--mod", "ur10e", "--format", "dh-csv", "--out", str(tmp_path / "dh.csv")]
        )
        == 0
    )
    assert (tmp_path / "dh.csv").exists()


URSCRIPT = """def pick():
  set_tcp(p[0, 0, 0.1, 0, 0, 0])
  movej([0, -1.57, 1.57, -1.57, -1.57, 0], a=1.2, v=0.25)
  movel(p[0.5, -0.2, 0.4, 0, 3.14, 0], a=1.2, v=0.25)
end
"""
RAPID = """MODULE Pick
  CONST robtarget p10 := [[500,-200,400],[0,0,1,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  PROC main()
    MoveL p10, v100, fine, tool0;
  ENDPROC
ENDMODULE
"""


@pytest.mark.parametrize(
    "name, text, fmt, expected",
    [
        (
            "pick.script",
            URSCRIPT,
            "rapid",
            "looks like a URScript program, not an ABB RAPID program (read as such because of --format rapid); give --format urscript or leave --format out",
        ),
        ("pick.script", URSCRIPT, "krl", "looks like a URScript program, not a KUKA KRL program"),
        (
            "pick.mod",
            URSCRIPT,
            None,
            "looks like a URScript program, not an ABB RAPID program (read as such because of its extension .mod); give --format urscript",
        ),
        ("pick.script", RAPID, None, "looks like an ABB RAPID program, not a URScript program"),
        ("task.csv", URSCRIPT, None, "looks like a URScript program, not a task CSV"),
    ],
)
def test_a_program_in_another_language_is_named_as_such(tmp_path, capsys, name, text, fmt, expected):
    (tmp_path / name).write_text(text)
    argv = [
        "compensate",
        "--model",
        "ur10e",
        "--task",
        str(tmp_path / name),
        "--out",
        str(tmp_path / ("out" + Path(name).suffix)),
    ]
    assert recal(argv + (["--format", fmt] if fmt else [])) == 2
    err = capsys.readouterr().err
    assert expected in err and "no move target" not in err and err.count("\n") == 1, err
    assert not (tmp_path / ("out" + Path(name).suffix)).exists()


def test_a_program_in_its_own_language_is_not_refused(tmp_path, capsys):
    (tmp_path / "pick.script").write_text(URSCRIPT)
    code = recal(
        [
            "compensate",
            "--model",
            "ur10e",
            "--nominal",
            "ur10e",
            "--task",
            str(tmp_path / "pick.script"),
            "--out",
            str(tmp_path / "out.script"),
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert "looks like" not in capsys.readouterr().err


# ------------------------------------------------------------------------- accuracy


Q = [f"q{i}" for i in range(1, 7)]
SMR = np.array([0.03, 0.0, 0.08])


@pytest.fixture()
def nominal_and_rows(tmp_path):
    model = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": SMR})  # mm, deg
    save_model(tmp_path / "ur.json", model)
    rng = np.random.default_rng(7)
    q_deg = rng.uniform(-90, 90, size=(12, 6))
    p_base_mm = target_positions(model, np.radians(q_deg), "smr") * 1e3
    return tmp_path, model, q_deg, p_base_mm + rng.normal(0, 0.5, p_base_mm.shape)  # a robot 0.5 mm off


def _accuracy(d, rows, capsys):
    (d / "meas.csv").write_text(format_csv([*Q, "x", "y", "z", "target"], [[*q, *p, "smr"] for q, p in rows]))
    code = recal(
        ["accuracy", "--model", str(d / "ur.json"), "--data", str(d / "meas.csv"), "--out", str(d / "acc.json")]
    )
    cap = capsys.readouterr()
    return code, cap.out, cap.err, json.loads((d / "acc.json").read_text())


def test_accuracy_of_a_model_whose_base_is_not_registered_warns(nominal_and_rows, capsys):
    """Measured by a tracker 1.5 m away and turned 30°: the nominal model's world is its own base
    frame, so every "error" is about the tracker-to-robot distance; one line says so."""
    d, _model, q_deg, p_mm = nominal_and_rows
    T_tracker_base = homogeneous(rot(2, np.radians(30.0)), np.array([1500.0, -600.0, -300.0]))
    p_tracker = p_mm @ T_tracker_base[:3, :3].T + T_tracker_base[:3, 3]
    code, _out, err, rep = _accuracy(d, zip(q_deg, p_tracker), capsys)
    assert code == 0
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "warning: ur10e-nominal's base is not registered to the instrument (its base is the robot's own frame)"
    )
    assert rep["errors"]["rms"] > 1000 and rep["frame"]["rms_after_rigid_fit"] < 1.0  # mm: the 0.5 mm robot error
    assert "recal identify" in lines[0]


def test_accuracy_in_the_models_own_frame_does_not_warn(nominal_and_rows, capsys):
    d, _model, q_deg, p_mm = nominal_and_rows
    code, out, err, rep = _accuracy(d, zip(q_deg, p_mm), capsys)
    assert code == 0 and err == "" and rep["frame"] is None
    assert out.splitlines()[1].startswith("overall: AP mean") and "pose  target" not in out
