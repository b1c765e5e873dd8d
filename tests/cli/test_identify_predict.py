"""`recal identify` and `recal predict` as a user runs them: the real console script, in a
subprocess, on files written here (contracts §2, §3, §6).

Success paths check the report's fields against what they must be for the simulated robot, and
that the files written are in the input's units and agree with the library's own kinematics.
Bad input must exit non-zero with exactly one line on stderr that names the file, the row and
the column (or JSON field) and what was expected, and must write no output file.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.identify import excess_scale
from calibration.kinematics import fk, target_positions
from calibration.model import Units, model_to_dict
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from calibration.transforms import quat_to_matrix
from service.files import load_model

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
WEB_STACK = ("fastapi", "sqlmodel", "uvicorn", "sqlalchemy", "starlette")
MM_DEG = Units("mm", "deg")
M_RAD = Units("m", "rad")


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=120)


# --------------------------------------------------------------------------- files


def joints_in(units: Units, model, q_si: np.ndarray) -> np.ndarray:
    scale = np.array([units.angle_rad if j.revolute else units.length_m for j in model.joints])
    return q_si / scale


def write_measurements(path: Path, model, data, units: Units) -> None:
    """A measurement CSV (contracts §3) in ``units``, as `recal demo --offline` writes one."""
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z", "target"]
    with path.open("w", newline="") as f:
        f.write("# simulated laser-tracker measurements\n")
        w = csv.writer(f)
        w.writerow(header)
        for q, p, t in zip(joints_in(units, model, data.q), data.p_world / units.length_m, data.target):
            w.writerow([f"{v:.12g}" for v in q] + [f"{v:.12g}" for v in p] + [t or ""])


def write_model(path: Path, model, units: Units) -> None:
    path.write_text(json.dumps(model_to_dict(model, units=units), indent=2))


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    rows = list(csv.reader(path.open()))
    return rows[0], np.array(rows[1:], dtype=float)


@dataclasses.dataclass
class Cell:
    dir: Path
    nominal: object
    truth: object
    data: object
    q_check: np.ndarray


@pytest.fixture(scope="module")
def cell(tmp_path_factory) -> Cell:
    """A UR10e with random errors in every link, an unknown base and a reflector `smr`; 60
    measured configurations, 100 for validation; files in mm/deg and in m/rad."""
    d = tmp_path_factory.mktemp("cli")
    rng = np.random.default_rng(11)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.03, 0.0, 0.08])})
    truth = perturbed(nominal, rng, base_length_m=3e-3, base_angle_rad=np.deg2rad(0.2))
    truth = dataclasses.replace(truth, targets={"smr": np.array([0.0304, 0.0006, 0.0797])})
    data = simulate_measurements(truth, random_configurations(nominal, 60, rng), rng, sigma_m=20e-6, targets=("smr",))
    holdout = simulate_measurements(
        truth, random_configurations(nominal, 100, rng), rng, sigma_m=20e-6, targets=("smr",)
    )
    for units, tag in ((MM_DEG, "mm"), (M_RAD, "m")):
        write_model(d / f"nominal_{tag}.json", nominal, units)
        write_measurements(d / f"meas_{tag}.csv", nominal, data, units)
        write_measurements(d / f"holdout_{tag}.csv", nominal, holdout, units)
    return Cell(d, nominal, truth, data, random_configurations(nominal, 50, rng))


@pytest.fixture(scope="module")
def identified(cell) -> dict:
    """`recal identify` with --report and --validate, once per unit system."""
    out = {}
    for tag in ("mm", "m"):
        proc = recal(
            "identify",
            "--model",
            f"nominal_{tag}.json",
            "--data",
            f"meas_{tag}.csv",
            "--validate",
            f"holdout_{tag}.csv",
            "--out",
            f"identified_{tag}.json",
            "--report",
            f"report_{tag}.json",
            cwd=cell.dir,
        )
        out[tag] = proc
    return out


# --------------------------------------------------------------------------- success paths


@pytest.mark.parametrize("tag,units", [("mm", MM_DEG), ("m", M_RAD)])
def test_identify_writes_model_in_input_units_and_report(cell, identified, tag, units):
    proc = identified[tag]
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert "identified" in proc.stdout and "hold-out RMS" in proc.stdout
    L = units.length_m

    doc = json.loads((cell.dir / f"identified_{tag}.json").read_text())
    assert doc["format"] == "recal.model/1"
    assert doc["units"] == {"length": units.length, "angle": units.angle}
    model = load_model(cell.dir / f"identified_{tag}.json")
    assert model.units == units
    # the written numbers are in the input's units: link 2's length is -612.7 mm give or take
    # the simulated errors, whatever the convention identification chose
    assert abs(abs(doc["joints"][1]["a"]) * L - 0.6127) < 0.01
    # ... and the model is the identified robot: the reflector where the truth puts it
    err = np.linalg.norm(
        target_positions(model, cell.q_check, "smr") - target_positions(cell.truth, cell.q_check, "smr"), axis=1
    )
    assert np.sqrt(np.mean(err**2)) < 60e-6
    assert "identification" in doc and doc["identification"]["parameters"]

    rep = json.loads((cell.dir / f"report_{tag}.json").read_text())
    assert rep["success"] is True and rep["status"] > 0 and rep["message"]
    assert rep["iterations"] >= 1 and rep["function_evaluations"] >= rep["iterations"]
    assert rep["units"] == {"length": units.length, "angle": units.angle}
    assert rep["rows"] == len(cell.data)
    freed = {p["name"] for p in rep["parameters"]}
    assert {"base.tx", "base.rz", "target.smr.x"} <= freed
    for p in rep["parameters"]:
        assert p["unit"] in (units.length, units.angle, "1"), p
        assert math.isfinite(p["value"]) and p["std_error"] > 0, p
        # the change is what moved from the (registered) start; the std error is far smaller
        # than the errors simulated (0.5 mm, 0.05-0.1 deg)
        limit = 0.05e-3 / L if p["unit"] == units.length else np.deg2rad(0.02) / units.angle_rad
        assert p["std_error"] < limit, p
    un = {u["name"]: u for u in rep["unidentifiable"]}
    assert not freed & set(un)
    # the first joint's offset turns the whole robot exactly as the base rotation does
    assert "j1.theta" in un and "base.rz" in {s["name"] for s in un["j1.theta"]["same_as"]}
    assert all(u["reason"] for u in un.values())
    assert rep["correlation"]["names"] == [p["name"] for p in rep["parameters"]]
    C = np.array(rep["correlation"]["matrix"], dtype=float)
    assert np.allclose(np.diag(C), 1.0, atol=1e-3) and np.all(np.abs(C) <= 1.0 + 1e-3)
    assert 1.0 < rep["condition_number"] < 1e8
    obs = rep["observability"]
    for k in ("O1_borm_menq", "O2_inverse_condition", "O3_min_singular", "O4_noise_amplification"):
        assert obs[k] > 0, k
    assert obs["O2_inverse_condition"] <= 1.0
    assert obs["O4_noise_amplification"] == pytest.approx(
        obs["O3_min_singular"] * obs["O2_inverse_condition"], rel=1e-6
    )

    res = rep["residuals"]
    # 3-D residual of 0.02 mm per axis noise: about sqrt(3 (1 - P/M)) * 0.02 mm
    assert 0.012e-3 / L < res["rms"] < 0.04e-3 / L
    assert res["rms"] <= res["p95"] <= res["max"]
    assert res["dof"] == 3 * len(cell.data) - len(rep["parameters"])
    assert 0.5 < res["chi2"] / res["dof"] < 1.6
    # the residuals' own scale only where chi-squared is significantly above dof, else 1
    assert res["sigma_scale"] == pytest.approx(excess_scale(res["chi2"], res["dof"]), rel=1e-6)
    assert rep["outliers"] == []
    reg = rep["registration"]  # the base error simulated is 3 mm and 0.2 deg: registration helps
    assert reg["applied"] is True and reg["method"]
    assert reg["rms_after"] < reg["rms_before"] < 0.05 / L  # in the file's length unit

    val = rep["validation"]
    assert val["rows"] == 100
    assert val["rms"] < 0.06e-3 / L < val["before"]["rms"]
    assert val["rms"] <= val["max"] and val["before"]["rms"] <= val["before"]["max"]
    assert 0.8 <= val["inside_predicted_95"] <= 1.0


def test_identify_result_does_not_depend_on_units(cell, identified):
    a = load_model(cell.dir / "identified_mm.json")
    b = load_model(cell.dir / "identified_m.json")
    q = cell.q_check
    assert np.allclose(target_positions(a, q, "smr"), target_positions(b, q, "smr"), atol=1e-9)


@pytest.mark.parametrize("model_file", ["nominal_mm.json", "identified_mm.json", "nominal_m.json"])
def test_predict_tool_pose_and_target_equal_fk(cell, identified, model_file):
    assert identified["mm"].returncode == 0
    model = load_model(cell.dir / model_file)
    u = model.units
    with (cell.dir / "joints.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)] + ["note"])  # extra columns are ignored
        for q in joints_in(u, model, cell.q_check):
            w.writerow([repr(float(v)) for v in q] + ["x"])
    q_si = joints_in(u, model, cell.q_check) * np.array([u.angle_rad] * 6)  # what the file says, in SI

    proc = recal("predict", "--model", model_file, "--joints", "joints.csv", "--out", "pose.csv", cwd=cell.dir)
    # an identified model says which configurations lie outside the joint ranges it was measured
    # in (issue 25, case 3); a nominal model records none, and says nothing
    said = proc.stderr.startswith("warning: ") and "lie outside the joint ranges the identification" in proc.stderr
    assert proc.returncode == 0 and (said if model_file.startswith("identified") else proc.stderr == ""), proc.stderr
    header, vals = read_csv(cell.dir / "pose.csv")
    assert header == ["x", "y", "z", "qw", "qx", "qy", "qz"]
    T = fk(model, q_si)
    assert np.allclose(vals[:, :3] * u.length_m, T[:, :3, 3], atol=1e-9)
    assert np.allclose(np.linalg.norm(vals[:, 3:], axis=1), 1.0, atol=1e-8)
    assert np.allclose(quat_to_matrix(vals[:, 3:]), T[:, :3, :3], atol=1e-8)

    proc = recal(
        "predict", "--model", model_file, "--joints", "joints.csv", "--target", "smr", "--out", "smr.csv", cwd=cell.dir
    )
    assert proc.returncode == 0, proc.stderr
    header, vals = read_csv(cell.dir / "smr.csv")
    assert header == ["x", "y", "z"]
    assert np.allclose(vals * u.length_m, target_positions(model, q_si, "smr"), atol=1e-9)


def test_identified_model_is_named_and_keeps_its_covariance(cell, identified):
    assert identified["mm"].returncode == 0
    doc = json.loads((cell.dir / "identified_mm.json").read_text())
    assert doc["name"] == "ur10e-identified"
    block = doc["identification"]
    assert block["identified_from"] == "ur10e-nominal" == block["nominal"]["name"]
    cov = block["covariance"]
    names = [p["name"] for p in block["parameters"]]
    assert cov["names"] == names and len(cov["kinds"]) == len(names)
    S = np.array(cov["matrix"])
    assert np.allclose(S, S.T) and np.all(np.linalg.eigvalsh(S) > 0)
    # SI whatever the file's units: the standard errors the block reports in mm and deg
    per_unit = {"length": MM_DEG.length_m, "angle": MM_DEG.angle_rad}
    se = np.array([p["std_error"] * per_unit[k] for p, k in zip(block["parameters"], cov["kinds"])])
    assert np.allclose(np.sqrt(np.diag(S)), se, rtol=1e-6)


def _joints_file(cell, model, name: str) -> np.ndarray:
    """Write ``cell.q_check`` in ``model``'s units; return them in SI."""
    q = joints_in(model.units, model, cell.q_check)
    _write(cell.dir / name, [f"q{i + 1}" for i in range(6)], [[repr(float(v)) for v in row] for row in q])
    return q * model.units.angle_rad


def test_predict_uncertainty_columns_are_honest(cell, identified):
    assert identified["mm"].returncode == identified["m"].returncode == 0
    out = {}
    for tag in ("mm", "m"):
        model = load_model(cell.dir / f"identified_{tag}.json")
        q_si = _joints_file(cell, model, f"joints_u_{tag}.csv")
        proc = recal(
            "predict",
            "--model",
            f"identified_{tag}.json",
            "--joints",
            f"joints_u_{tag}.csv",
            "--target",
            "smr",
            "--uncertainty",
            "--out",
            f"pred_u_{tag}.csv",
            cwd=cell.dir,
        )
        assert proc.returncode == 0, proc.stderr
        rows = [r for r in csv.reader((cell.dir / f"pred_u_{tag}.csv").open()) if r and not r[0].startswith("#")]
        assert rows[0] == ["x", "y", "z", "sigma_x", "sigma_y", "sigma_z", "u95", "flags"]
        # the bounds are marked where the identification's data never went (issue 25, case 3):
        # exactly the rows outside the joint ranges the 60 measured configurations covered
        ranges = np.array(
            json.loads((cell.dir / f"identified_{tag}.json").read_text())["identification"]["joint_ranges"]
        )
        q_file = q_si / model.units.angle_rad
        outside = np.any((q_file < ranges[:, 0]) | (q_file > ranges[:, 1]), axis=1)
        assert 0 < outside.sum() < len(outside)  # 50 random configurations: some beyond the 60's ranges
        assert [r[7] == "outside_calibrated_region" for r in rows[1:]] == outside.tolist()
        assert [r[7] for r in rows[1:] if r[7] != "outside_calibrated_region"] == [""] * int((~outside).sum())
        assert f"warning: {int(outside.sum())} of 50 configurations lie outside" in proc.stderr
        out[tag] = np.array([r[:7] for r in rows[1:]], dtype=float) * model.units.length_m  # SI
    mm, m = out["mm"], out["m"]
    assert np.allclose(mm, m, rtol=1e-6, atol=1e-12)  # the same in either unit
    sigma, u95 = mm[:, 3:6], mm[:, 6]
    assert np.all((sigma > 0) & (sigma < 0.03e-3))  # a few micrometres: 60 poses at 0.02 mm noise
    assert np.all(u95 >= np.sqrt(7.81) * sigma.max(axis=1) * (1 - 1e-6))  # 95 % radius of the largest axis
    # the radius holds against the truth (noise-free): the model's actual error is inside it
    err = np.linalg.norm(mm[:, :3] - target_positions(cell.truth, q_si, "smr"), axis=1)
    assert np.mean(err <= u95) >= 0.85, np.mean(err <= u95)

    proc = recal(
        "predict",
        "--model",
        "identified_mm.json",
        "--joints",
        "joints_u_mm.csv",
        "--uncertainty",
        "--out",
        "pose_u.csv",
        cwd=cell.dir,
    )
    assert proc.returncode == 0, proc.stderr
    rows = [r for r in csv.reader((cell.dir / "pose_u.csv").open()) if r and not r[0].startswith("#")]
    assert rows[0] == ["x", "y", "z", "qw", "qx", "qy", "qz", "sigma_x", "sigma_y", "sigma_z", "u95", "r95", "flags"]
    assert np.all(np.array([r[7:11] for r in rows[1:]], dtype=float) > 0)
    # the orientation's bound (issue 25): a position-only fit holds the tool's rotation and the last
    # joint's zero at 0.2 deg, so the bound is at least that (degrees: the model's angle unit)
    r95 = np.array([r[11] for r in rows[1:]], dtype=float)
    assert np.all((r95 > 0.2) & (r95 < 10.0)), r95


# --------------------------------------------------------------------------- bad input


def _table(cell) -> tuple[list[str], list[list[str]]]:
    rows = [r for r in csv.reader((cell.dir / "meas_mm.csv").open()) if r and not r[0].startswith("#")]
    return rows[0], rows[1:]


def _write(path: Path, header, rows) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def _drop(column):
    def make(cell, path):
        header, rows = _table(cell)
        k = header.index(column)
        _write(path, header[:k] + header[k + 1 :], [r[:k] + r[k + 1 :] for r in rows])

    return make


def _cell_value(row, column, value):
    def make(cell, path):
        header, rows = _table(cell)
        rows[row - 1][header.index(column)] = value
        _write(path, header, rows)

    return make


def _add_q7(cell, path):
    header, rows = _table(cell)
    _write(path, header[:6] + ["q7"] + header[6:], [r[:6] + ["0"] + r[6:] for r in rows])


def _partial_quaternion(cell, path):
    header, rows = _table(cell)
    quat = [["1", "0", "0", "0"] for _ in rows]
    quat[2][2] = ""  # row 3 has qw, qx, qz but no qy
    _write(path, header + ["qw", "qx", "qy", "qz"], [r + qv for r, qv in zip(rows, quat)])


def _empty(cell, path):
    path.write_text("")


def _missing(cell, path):
    pass


# (case, make the data file, [expected pieces of the stderr line besides the file name])
DATA_CASES = [
    ("no-x", _drop("x"), ["header", "column 'x'", "expected a column 'x'"]),
    ("no-q3", _drop("q3"), ["header", "column 'q3'", "expected q1..q6"]),
    ("text", _cell_value(4, "y", "abc"), ["row 4", "column 'y'", "expected a number", "'abc'"]),
    ("nan", _cell_value(2, "z", "NaN"), ["row 2", "column 'z'", "expected a finite number"]),
    ("inf", _cell_value(7, "q2", "inf"), ["row 7", "column 'q2'", "expected a finite number"]),
    # beyond what the model can use (was "SVD did not converge" with no row named); the API's
    # documents and task files answer the same (tests/service/test_limits.py)
    ("huge", _cell_value(3, "x", "1e308"), ["row 3", "column 'x'", "1e308 is beyond any robot cell"]),
    ("q7", _add_q7, ["header", "column 'q7'", "6 joints", "expected joint columns q1..q6"]),
    ("no-q6", _drop("q6"), ["header", "column 'q6'", "expected q1..q6"]),
    ("unknown-target", _cell_value(5, "target", "ball9"), ["row 5", "column 'target'", "'ball9'", "expected one of"]),
    ("partial-quaternion", _partial_quaternion, ["row 3", "column 'qy'", "expected a number"]),
    ("empty", _empty, ["empty", "expected a header"]),
    ("missing-file", _missing, ["cannot read"]),
]


def check_failure(proc, cell, names_file: str, expected: list[str], out: str) -> None:
    assert proc.returncode != 0
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    line = lines[0]
    assert names_file in line, line
    for piece in expected:
        assert piece in line, (piece, line)
    assert "Traceback" not in proc.stderr
    assert not (cell.dir / out).exists()
    assert not list(cell.dir.glob(f".{out}*")), "a temporary output file was left behind"


@pytest.mark.parametrize("case,make,expected", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_identify_bad_data(cell, case, make, expected):
    bad = cell.dir / f"bad_{case}.csv"
    make(cell, bad)
    out = f"out_{case}.json"
    proc = recal(
        "identify",
        "--model",
        "nominal_mm.json",
        "--data",
        bad.name,
        "--out",
        out,
        "--report",
        f"report_{case}.json",
        cwd=cell.dir,
    )
    check_failure(proc, cell, bad.name, expected, out)
    assert not (cell.dir / f"report_{case}.json").exists()


def test_identify_bad_validation_file_names_it(cell):
    _cell_value(9, "x", "1.2.3")(cell, cell.dir / "bad_holdout.csv")
    proc = recal(
        "identify",
        "--model",
        "nominal_mm.json",
        "--data",
        "meas_mm.csv",
        "--validate",
        "bad_holdout.csv",
        "--out",
        "out_val.json",
        cwd=cell.dir,
    )
    check_failure(proc, cell, "bad_holdout.csv", ["row 9", "column 'x'", "expected a number"], "out_val.json")


def _model_doc(cell) -> dict:
    return json.loads((cell.dir / "nominal_mm.json").read_text())


MODEL_CASES = [
    (
        "bad-alpha",
        lambda d: d["joints"][2].__setitem__("alpha", "ninety"),
        ["field 'joints[2].alpha'", "expected a finite number", "'ninety'"],
    ),
    ("short-base", lambda d: d.__setitem__("base", [0, 0, 0]), ["field 'base'", "expected a list of 6 numbers"]),
    ("no-format", lambda d: d.pop("format"), ["field 'format'", "expected 'recal.model/1'"]),
    ("bad-units", lambda d: d["units"].__setitem__("length", "cm"), ["field 'units.length'", "expected one of"]),
]


@pytest.mark.parametrize("case,edit,expected", MODEL_CASES, ids=[c[0] for c in MODEL_CASES])
def test_identify_malformed_model_names_the_field(cell, case, edit, expected):
    doc = _model_doc(cell)
    edit(doc)
    bad = cell.dir / f"model_{case}.json"
    bad.write_text(json.dumps(doc))
    proc = recal("identify", "--model", bad.name, "--data", "meas_mm.csv", "--out", f"out_{case}.json", cwd=cell.dir)
    check_failure(proc, cell, bad.name, expected, f"out_{case}.json")


def test_identify_invalid_json_names_line_and_column(cell):
    bad = cell.dir / "model_truncated.json"
    bad.write_text((cell.dir / "nominal_mm.json").read_text()[:200])
    proc = recal("identify", "--model", bad.name, "--data", "meas_mm.csv", "--out", "out_trunc.json", cwd=cell.dir)
    check_failure(proc, cell, bad.name, ["invalid JSON", "line ", "column ", "expected"], "out_trunc.json")


def test_identify_missing_model_file(cell):
    proc = recal(
        "identify", "--model", "absent.json", "--data", "meas_mm.csv", "--out", "out_absent.json", cwd=cell.dir
    )
    check_failure(proc, cell, "absent.json", ["cannot read"], "out_absent.json")


def test_identify_unwritable_output_fails_before_work(cell):
    proc = recal(
        "identify",
        "--model",
        "nominal_mm.json",
        "--data",
        "meas_mm.csv",
        "--out",
        "no/such/dir/m.json",
        "--report",
        "rep_unwritable.json",
        cwd=cell.dir,
    )
    assert proc.returncode != 0
    assert proc.stderr.count("\n") == 1 and "no/such/dir/m.json" in proc.stderr and "does not exist" in proc.stderr
    assert not (cell.dir / "rep_unwritable.json").exists()


def test_predict_unknown_target_names_the_model_field(cell):
    header, rows = _table(cell)
    _write(cell.dir / "joints_only.csv", header[:6], [r[:6] for r in rows])
    proc = recal(
        "predict",
        "--model",
        "nominal_mm.json",
        "--joints",
        "joints_only.csv",
        "--target",
        "ball9",
        "--out",
        "pred_t.csv",
        cwd=cell.dir,
    )
    check_failure(proc, cell, "nominal_mm.json", ["field 'targets'", "'ball9'", "expected one of smr"], "pred_t.csv")


def test_predict_uncertainty_needs_a_stored_covariance(cell):
    header, rows = _table(cell)
    _write(cell.dir / "joints_only2.csv", header[:6], [r[:6] for r in rows])
    proc = recal(
        "predict",
        "--model",
        "nominal_mm.json",
        "--joints",
        "joints_only2.csv",
        "--uncertainty",
        "--out",
        "pred_nocov.csv",
        cwd=cell.dir,
    )
    assert proc.returncode == 2
    check_failure(
        proc,
        cell,
        "nominal_mm.json",
        ["field 'identification.covariance'", "no parameter covariance", "--uncertainty"],
        "pred_nocov.csv",
    )


JOINT_CASES = [c for c in DATA_CASES if c[0] in ("no-q3", "inf", "q7", "empty")]


@pytest.mark.parametrize("case,make,expected", JOINT_CASES, ids=[c[0] for c in JOINT_CASES])
def test_predict_bad_joints(cell, case, make, expected):
    bad = cell.dir / f"badjoints_{case}.csv"
    make(cell, bad)
    proc = recal(
        "predict", "--model", "nominal_mm.json", "--joints", bad.name, "--out", f"pred_{case}.csv", cwd=cell.dir
    )
    check_failure(proc, cell, bad.name, expected, f"pred_{case}.csv")


# --------------------------------------------------------------------------- start-up


def _modules_after(code: str, cwd: Path) -> dict:
    probe = (
        "import json, sys\n"
        f"{code}\n"
        f"print(json.dumps({{'web': sorted({{m.split('.')[0] for m in sys.modules}} & set({WEB_STACK!r})), "
        "'numpy': 'numpy' in sys.modules}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", probe], cwd=cwd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_cli_module_imports_nothing_heavy(cell):
    # `recal` itself is argparse and a table of verbs; a verb's module is imported when it runs
    seen = _modules_after("import service.cli", cell.dir)
    assert seen == {"web": [], "numpy": False}


def test_math_verbs_do_not_import_the_web_stack(cell):
    code = (
        "from service.cli import main\n"
        "import contextlib, io\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    assert main(['identify', '--model', 'nominal_mm.json', '--data', 'meas_mm.csv', '--out', 'probe.json']) == 0\n"
        "    assert main(['predict', '--model', 'probe.json', '--joints', 'meas_mm.csv', '--target', 'smr',"
        " '--out', 'probe.csv']) == 0\n"
    )
    seen = _modules_after(code, cell.dir)
    assert seen["numpy"] is True  # the probe really ran the verbs
    assert seen["web"] == []


def test_help_does_not_import_the_web_stack(cell):
    seen = _modules_after(
        "from service.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass", cell.dir
    )
    assert seen["web"] == []


# --------------------------------------------------------------------------- the model does not explain the data


def test_identify_exits_3_when_the_model_does_not_explain_the_data(cell):
    """A tracker five times noisier than stated (--sigma): the model and the report are written,
    the status is 3 and one line says why."""
    rng = np.random.default_rng(21)
    noisy = simulate_measurements(
        cell.truth, random_configurations(cell.nominal, 60, rng), rng, sigma_m=100e-6, targets=("smr",)
    )
    write_measurements(cell.dir / "noisy_mm.csv", cell.nominal, noisy, MM_DEG)
    proc = recal(
        "identify",
        "--model",
        "nominal_mm.json",
        "--data",
        "noisy_mm.csv",
        "--sigma",
        "0.02",
        "--out",
        "noisy_identified.json",
        "--report",
        "noisy_report.json",
        cwd=cell.dir,
    )
    assert proc.returncode == 3, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "the model does not explain the data: residual RMS" in last and "expected" in last, last
    assert (cell.dir / "noisy_identified.json").exists()
    report = json.loads((cell.dir / "noisy_report.json").read_text())
    assert report["consistency"]["consistent"] is False and report["consistency"]["level"] == 0.001
    assert report["cross_validation"]["folds"] == 5
    assert report["complete"]["count"] == 30


def test_identify_two_rows_exit_2_with_the_rows_needed(cell):
    lines = (cell.dir / "meas_mm.csv").read_text().splitlines()
    (cell.dir / "two_rows.csv").write_text("\n".join(lines[:4]) + "\n")  # comment, header, two rows
    proc = recal("identify", "--model", "nominal_mm.json", "--data", "two_rows.csv", "--out", "two.json", cwd=cell.dir)
    assert proc.returncode == 2, proc.stderr
    assert "two_rows.csv" in proc.stderr and "no redundancy" in proc.stderr and "measure at least" in proc.stderr
    assert not (cell.dir / "two.json").exists()
