"""``recal identify --residual-map auto`` on an arm with joint transmission errors, then ``recal
predict`` applying the stored correction inside its region and flagging the rest (issue 28)."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from calibration import robots
from calibration.model import Units, model_to_dict
from calibration.simulate import harmonic_drive_errors, perturbed, random_configurations, simulate_measurements
from service.files import load_model

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
CENTRE = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
REGION = np.stack([CENTRE - np.deg2rad(60), CENTRE + np.deg2rad(60)], axis=1)


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_identify_stores_the_transmission_correction_and_predict_applies_it(tmp_path):
    rng = np.random.default_rng(21)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nominal, rng, base_length_m=0.5, base_angle_rad=0.3)
    tx = harmonic_drive_errors(nominal, rng)
    (tmp_path / "nominal.json").write_text(json.dumps(model_to_dict(nominal, units=Units("mm", "deg"))))
    data = simulate_measurements(
        truth,
        random_configurations(nominal, 800, rng, limits=REGION),
        rng,
        sigma_m=10e-6,
        targets=("smr",),
        transmission=tx,
    )
    with (tmp_path / "meas.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)] + ["x", "y", "z", "target"])
        for k in range(len(data)):
            w.writerow([*np.rad2deg(data.q[k]).tolist(), *(data.p_world[k] * 1e3).tolist(), "smr"])
    proc = recal(
        "identify", "--model", "nominal.json", "--data", "meas.csv", "--out", "id.json", "--sigma", "0.01",
        "--report", "r.json", "--residual-map", "auto", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode in (0, 3), proc.stderr  # 3: the geometric model alone does not explain the data
    line = next(x for x in proc.stdout.splitlines() if x.startswith("residual map (5-fold nested cross-validation"))
    assert "kept transmission" in line
    doc = json.loads((tmp_path / "id.json").read_text())
    assert doc["residual_map"]["format"] == "recal.residual_transmission/1"
    report = json.loads((tmp_path / "r.json").read_text())["residual_map"]
    fams = report["families"]
    assert fams["transmission"]["rms"] < 0.7 * fams["none"]["rms"]  # mm, each family's CV error
    assert len(report["learning_curve"]) == 3 and all(p["rms"] > 0 for p in report["learning_curve"])
    # predict: inside the region, the stored correction; outside (a joint beyond its measured
    # range), the geometric model alone and the row flagged
    inner = REGION + np.deg2rad([2.0, -2.0])  # within what 800 random configurations of REGION span
    q = random_configurations(nominal, 40, rng, limits=inner)
    q[-5:, 1] = REGION[1, 1] + np.deg2rad(20)
    with (tmp_path / "joints.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)])
        w.writerows(np.rad2deg(q).tolist())
    p = recal(
        "predict", "--model", "id.json", "--joints", "joints.csv", "--target", "smr", "--out", "p.csv", cwd=tmp_path
    )
    assert p.returncode == 0, p.stderr
    rows = list(csv.reader((tmp_path / "p.csv").open()))
    assert rows[0] == ["x", "y", "z", "flags"]
    xyz = np.array([r[:3] for r in rows[1:]], dtype=float) * 1e-3
    outside = np.array(["outside_mapped_region" in r[3] for r in rows[1:]])
    assert outside[-5:].all() and not outside[:-5].any()
    true = simulate_measurements(truth, q, rng, sigma_m=0.0, targets=("smr",), transmission=tx).p_world
    model = load_model(tmp_path / "id.json")
    from calibration.kinematics import target_positions

    geometric = target_positions(model, q, "smr")
    err_pred = np.linalg.norm(xyz - true, axis=1)
    err_geo = np.linalg.norm(geometric - true, axis=1)
    assert np.sqrt(np.mean(err_pred[~outside] ** 2)) < 0.3 * np.sqrt(np.mean(err_geo[~outside] ** 2))
    assert np.allclose(xyz[outside], geometric[outside], atol=1e-9)  # the geometric model alone there
