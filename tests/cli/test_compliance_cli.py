"""Joint compliance under gravity as a user runs it (contracts §2, §3, §6): the real `recal`
console script in a subprocess, on files written here from a simulated cobot that sags under
its own weight and a 10 kg payload, measured with and without the payload."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from urdf_check import assert_urdf_is_predict, in_file_units

from calibration import robots
from calibration.kinematics import target_positions
from calibration.model import Units, model_to_dict
from calibration.simulate import SAGGING_ARMS, perturbed, random_configurations, sagging, simulate_measurements
from service.files import load_model

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
MM_DEG = Units("mm", "deg")
PAYLOAD = SAGGING_ARMS["cobot"]["payload"]  # 10 kg, 100 mm out along the tool z axis


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=120)


def write_measurements(path: Path, data, *, payload_columns: bool = True) -> None:
    header = [f"q{i + 1}" for i in range(6)] + ["x", "y", "z", "target"]
    if payload_columns:
        header += ["payload_kg", "payload_x", "payload_y", "payload_z"]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for k in range(len(data)):
            row = [f"{v:.12g}" for v in np.rad2deg(data.q[k])] + [f"{v:.12g}" for v in data.p_world[k] * 1e3] + ["smr"]
            if payload_columns:
                pl = data.payload[k]
                row += ["" if pl[0] == 0 else f"{pl[0]:g}"] + [f"{v * 1e3:.12g}" for v in pl[1:]]
            w.writerow(row)


@dataclasses.dataclass
class Cell:
    dir: Path
    truth: object
    q: np.ndarray


@pytest.fixture(scope="module")
def cell(tmp_path_factory) -> Cell:
    d = tmp_path_factory.mktemp("compliance")
    rng = np.random.default_rng(4)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = sagging(perturbed(nominal, rng, base_length_m=0.5, base_angle_rad=0.3), "cobot", frames_of=nominal)
    (d / "nominal.json").write_text(json.dumps(model_to_dict(nominal, units=MM_DEG)))

    def measure(n):
        q = random_configurations(nominal, n, rng)
        pay = np.array([PAYLOAD if i % 2 else (0.0, 0.0, 0.0, 0.0) for i in range(n)])
        return simulate_measurements(truth, q, rng, sigma_m=20e-6, targets=("smr",), payload=pay)

    write_measurements(d / "meas.csv", measure(120))
    write_measurements(d / "holdout.csv", measure(300))
    q = random_configurations(nominal, 20, rng)
    with (d / "joints.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)])
        w.writerows(np.rad2deg(q).tolist())
    return Cell(d, truth, q)


@pytest.fixture(scope="module")
def auto(cell):
    return recal(
        "identify",
        "--model",
        "nominal.json",
        "--data",
        "meas.csv",
        "--validate",
        "holdout.csv",
        "--out",
        "id.json",
        "--report",
        "report.json",
        "--compliance",
        "auto",
        cwd=cell.dir,
    )


def test_identify_auto_adds_compliance_and_reports_cross_validation(cell, auto):
    assert auto.returncode == 0, auto.stderr
    lines = auto.stdout.splitlines()
    cv_line = next(line for line in lines if line.startswith("compliance (5-fold cross-validation)"))
    assert "compliance of j2, j3 added" in cv_line
    rep = json.loads((cell.dir / "report.json").read_text())
    cv = rep["compliance"]["cross_validation"]
    assert cv["rms_compliant"] < 0.1 * cv["rms_rigid"]  # mm
    # each fold is fitted on 96 rows: its error is the noise plus that of ~30 parameters fitted
    # without it (with the reflector on the flange axis, j5.a and j5.alpha only to 0.4 mm and
    # 0.13 deg: freed since issue 14, where they were held biased); the hold-out check is below
    assert cv["rms_compliant"] < 1.2 * np.sqrt(3) * 0.02
    assert rep["validation"]["rms"] < 1.1 * np.sqrt(3) * 0.02
    units = {p["name"]: p["unit"] for p in rep["parameters"]}
    assert units["compliance.j2.k"] == "deg/(N·m)" and units["compliance.j2.j6.m"] == "deg/mm"
    doc = json.loads((cell.dir / "id.json").read_text())
    assert doc["compliance"]["joints"] == ["j2", "j3"]
    c = SAGGING_ARMS["cobot"]["compliance"]["j2"]
    assert doc["compliance"]["terms"]["j2.k"] == pytest.approx(np.rad2deg(c), rel=0.03)
    assert "compliance.j2.k" in doc["identification"]["covariance"]["names"]


def test_identify_gravity_with_chosen_joints_runs_no_cross_validation(cell):
    proc = recal(
        "identify",
        "--model",
        "nominal.json",
        "--data",
        "meas.csv",
        "--out",
        "g.json",
        "--compliance",
        "gravity",
        "--compliance-joints",
        "j2",
        cwd=cell.dir,
    )
    # the cobot sags at j3 too: j2 alone cannot explain the data, and identify says so (exit 3,
    # issue 14) after writing the model it was asked for
    assert proc.returncode == 3, proc.stderr
    assert "the model does not explain the data" in proc.stderr
    assert json.loads((cell.dir / "g.json").read_text())["compliance"]["joints"] == ["j2"]
    assert "cross-validation" not in proc.stdout


def test_predict_and_compensate_take_the_task_payload(cell, auto):
    assert auto.returncode == 0, auto.stderr
    model = load_model(cell.dir / "id.json")
    for args, payload in (([], None), (["--payload", "10,0,0,100"], np.array(PAYLOAD))):
        proc = recal(
            "predict",
            "--model",
            "id.json",
            "--joints",
            "joints.csv",
            "--target",
            "smr",
            "--out",
            "pred.csv",
            *args,
            cwd=cell.dir,
        )
        assert proc.returncode == 0, proc.stderr
        rows = np.array(list(csv.reader((cell.dir / "pred.csv").open()))[1:], dtype=float) * 1e-3
        truth = target_positions(cell.truth, cell.q, "smr", payload=payload)
        assert np.sqrt(np.mean(np.sum((rows - truth) ** 2, axis=1))) < 50e-6  # where the sagging robot is
        assert np.allclose(rows, target_positions(model, cell.q, "smr", payload=payload), atol=1e-9)
    with (cell.dir / "task.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)])
        w.writerows(np.rad2deg(cell.q[:5]).tolist())
    outs = []
    for args in ([], ["--payload", "10,0,0,100"]):
        proc = recal("compensate", "--model", "id.json", "--task", "task.csv", "--out", "c.csv", *args, cwd=cell.dir)
        assert proc.returncode == 0, proc.stderr
        outs.append(np.array([r[:6] for r in list(csv.reader((cell.dir / "c.csv").open()))[1:]], dtype=float))
    # the payload makes the arm sag more, so the commands differ (by hundredths of a degree)
    assert 1e-3 < np.abs(outs[0] - outs[1]).max() < 0.5


def test_export_urdf_says_compliance_is_left_out(cell, auto):
    assert auto.returncode == 0, auto.stderr
    proc = recal("export", "--model", "id.json", "--format", "urdf", "--out", "id.urdf", cwd=cell.dir)
    assert proc.returncode == 0
    warn = [line for line in proc.stderr.splitlines() if "compliance" in line]
    assert len(warn) == 1 and "rigid part" in warn[0]
    assert (cell.dir / "id.urdf").read_text().count("<joint ") >= 6
    # the rigid part: recal predict of the identified model without its compliance section
    doc = json.loads((cell.dir / "id.json").read_text())
    assert doc.pop("compliance")
    (cell.dir / "id-rigid.json").write_text(json.dumps(doc))
    q = in_file_units(
        cell.dir / "id.json", random_configurations(load_model(cell.dir / "id.json"), 10, np.random.default_rng(9))
    )
    assert_urdf_is_predict(cell.dir / "id.urdf", cell.dir / "id-rigid.json", q, cell.dir, names="ur")


@pytest.mark.parametrize(
    "args, expected",
    [
        (
            ["predict", "--model", "id.json", "--joints", "joints.csv", "--out", "bad.csv", "--payload", "10,1"],
            "--payload: expected KG or KG,X,Y,Z",
        ),
        (
            [
                "identify",
                "--model",
                "nominal.json",
                "--data",
                "meas.csv",
                "--out",
                "bad.csv",
                "--compliance",
                "gravity",
                "--compliance-joints",
                "j9",
            ],
            "--compliance-joints: no joint 'j9'",
        ),
        (
            [
                "identify",
                "--model",
                "nominal.json",
                "--data",
                "meas.csv",
                "--out",
                "bad.csv",
                "--compliance",
                "auto",
                "--gravity",
                "0,0",
            ],
            "--gravity: expected three numbers",
        ),
    ],
)
def test_bad_payload_and_compliance_flags_fail_in_one_line(cell, auto, args, expected):
    proc = recal(*args, cwd=cell.dir)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and expected in proc.stderr
    assert not (cell.dir / "bad.csv").exists()


def test_negative_payload_mass_names_row_and_column(cell):
    lines = (cell.dir / "meas.csv").read_text().splitlines()
    head = lines[0].split(",")
    row = lines[3].split(",")
    row[head.index("payload_kg")] = "-2"
    (cell.dir / "neg.csv").write_text("\n".join([lines[0], lines[1], lines[2], ",".join(row)]) + "\n")
    proc = recal("identify", "--model", "nominal.json", "--data", "neg.csv", "--out", "bad.json", cwd=cell.dir)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "neg.csv, row 3 (line 4), column 'payload_kg'" in proc.stderr and ">= 0 kg" in proc.stderr
    assert not (cell.dir / "bad.json").exists()


# --------------------------------------------------------------------------- residual maps

CENTRE = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
REGION = np.stack([CENTRE - np.deg2rad(40), CENTRE + np.deg2rad(40)], axis=1)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A sagging cobot measured in one region of its workspace with its payload on; the rigid
    model identified with a residual map."""
    d = tmp_path_factory.mktemp("residual_map")
    rng = np.random.default_rng(8)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = sagging(perturbed(nominal, rng, base_length_m=0.5, base_angle_rad=0.3), "cobot", frames_of=nominal)
    (d / "nominal.json").write_text(json.dumps(model_to_dict(nominal, units=MM_DEG)))
    data = simulate_measurements(
        truth,
        random_configurations(nominal, 200, rng, limits=REGION),
        rng,
        sigma_m=20e-6,
        targets=("smr",),
        payload=np.array(PAYLOAD),
    )
    write_measurements(d / "meas.csv", data)
    proc = recal(
        "identify", "--model", "nominal.json", "--data", "meas.csv", "--out", "id.json", "--residual-map", "auto", cwd=d
    )
    q = np.vstack([random_configurations(nominal, 6, rng, limits=REGION), CENTRE + np.deg2rad([150, 0, 0, 0, 0, 0])])
    return d, truth, q, proc


def test_identify_keeps_a_map_that_helps_and_predict_flags_outside(mapped):
    d, truth, q, proc = mapped
    # a rigid model of a sagging arm: even with the map, what is left (about 0.11 mm
    # cross-validated) is far above the tracker's noise, so identify writes the model and the map
    # and exits 3 (issue 14: the model does not explain the data)
    assert proc.returncode == 3, proc.stderr
    assert "the model does not explain the data" in proc.stderr
    line = next(x for x in proc.stdout.splitlines() if x.startswith("residual map (5-fold nested cross-validation"))
    assert "kept" in line and all(f in line for f in ("none", "map", "transmission", "trees"))
    doc = json.loads((d / "id.json").read_text())
    assert doc["residual_map"]["family"] in ("map", "transmission", "trees")
    with (d / "joints.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)])
        w.writerows(np.rad2deg(q).tolist())
    p = recal("predict", "--model", "id.json", "--joints", "joints.csv", "--target", "smr", "--out", "p.csv", cwd=d)
    assert p.returncode == 0, p.stderr
    rows = list(csv.reader((d / "p.csv").open()))
    assert rows[0] == ["x", "y", "z", "flags"]
    flags = [r[3] for r in rows[1:]]
    # the last configuration turns the base where nothing was measured: outside the map, and
    # outside the joint ranges the identification saw (said on stderr)
    assert flags[-1] == "outside_mapped_region;outside_calibrated_region"
    assert sum("outside_mapped_region" in f for f in flags) <= 2
    assert "lie outside the joint ranges the identification measured" in p.stderr
    xyz = np.array([r[:3] for r in rows[1:]], dtype=float) * 1e-3
    parametric = target_positions(load_model(d / "id.json"), q, "smr")
    true = target_positions(truth, q, "smr", payload=np.array(PAYLOAD))
    inside = np.array(["outside_mapped_region" not in f for f in flags])
    # inside, the map brings the prediction closer to where the robot really is; outside it does nothing
    assert np.mean(np.linalg.norm(xyz - true, axis=1)[inside]) < 0.7 * np.mean(
        np.linalg.norm(parametric - true, axis=1)[inside]
    )
    assert np.allclose(xyz[~inside], parametric[~inside], atol=1e-9)


def test_identify_leaves_out_a_map_that_does_not_help(mapped):
    d = mapped[0]
    proc = recal(
        "identify",
        "--model",
        "nominal.json",
        "--data",
        "meas.csv",
        "--out",
        "idc.json",
        "--compliance",
        "gravity",
        "--residual-map",
        "auto",
        cwd=d,
    )
    assert proc.returncode == 0, proc.stderr
    assert "no gain of 5 % or more: left out" in proc.stdout
    assert "residual_map" not in json.loads((d / "idc.json").read_text())


def test_compensate_aims_the_parametric_model_at_the_goal_minus_the_map(mapped):
    from calibration.residual_map import from_model

    d, truth, q, proc = mapped
    assert proc.returncode == 3, proc.stderr  # written, see test_identify_keeps_a_map_that_helps_...
    model = load_model(d / "id.json")
    goal = target_positions(truth, q, None, payload=np.array(PAYLOAD))  # tool origin: where the robot must go
    from calibration.kinematics import fk
    from calibration.transforms import matrix_to_quat

    quat = matrix_to_quat(fk(truth, q, np.array(PAYLOAD))[:, :3, :3])
    with (d / "task.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", "z", "qw", "qx", "qy", "qz"] + [f"q{i + 1}" for i in range(6)])
        for k in range(len(goal)):
            w.writerow([*(goal[k] * 1e3), *quat[k], *np.rad2deg(q[k])])
    c = recal("compensate", "--model", "id.json", "--task", "task.csv", "--out", "c.csv", cwd=d)
    assert c.returncode == 0, c.stderr
    rows = list(csv.reader((d / "c.csv").open()))
    head = rows[0]
    qc = np.deg2rad(np.array([[r[head.index(f"q{i + 1}")] for i in range(6)] for r in rows[1:]], dtype=float))
    flags = [r[head.index("flags")] for r in rows[1:]]
    corr, inside = from_model(model).evaluate(qc)
    reached = fk(model, qc)[:, :3, 3] + corr
    ok = inside & np.array(["outside_mapped_region" not in f for f in flags])
    assert ok.sum() >= 4
    assert np.abs(reached - goal)[ok].max() < 1e-6
    assert "outside_mapped_region" in flags[-1].split(";")  # the base turned where nothing was measured
    assert np.linalg.norm(fk(model, qc[-1:])[0, :3, 3] - goal[-1]) < 1e-6  # the parametric model alone there


def test_demo_shows_rigid_and_compliant_side_by_side(tmp_path):
    proc = recal("demo", "--offline", "--sag", "cobot", "--poses", "100", "--dir", tmp_path / "demo", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    line = next(x for x in proc.stdout.splitlines() if x.startswith("rigid against compliant"))
    rigid, compliant = (float(v) for v in line.split("RMS ")[1].split(" mm;")[0].split(" mm against "))
    floor = np.sqrt(3) * 0.02
    assert compliant < 1.15 * floor < 3 * floor < rigid
    assert "payload_kg" in (tmp_path / "demo" / "measurements.csv").read_text().splitlines()[1]


def test_accuracy_applies_the_residual_map(mapped):
    d, truth, _, proc = mapped
    assert proc.returncode == 3, proc.stderr  # written, see test_identify_keeps_a_map_that_helps_...
    rng = np.random.default_rng(12)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    held = simulate_measurements(
        truth,
        random_configurations(nominal, 150, rng, limits=REGION),
        rng,
        sigma_m=20e-6,
        targets=("smr",),
        payload=np.array(PAYLOAD),
    )
    write_measurements(d / "held.csv", held)
    doc = json.loads((d / "id.json").read_text())
    (d / "nomap.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual_map"}))
    rms = {}
    for name in ("id.json", "nomap.json"):
        a = recal("accuracy", "--model", name, "--data", "held.csv", "--out", f"acc-{name}", cwd=d)
        assert a.returncode == 0, a.stderr
        rms[name] = json.loads((d / f"acc-{name}").read_text())["errors"]["rms"]
    assert rms["id.json"] < 0.7 * rms["nomap.json"]
