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
import pytest

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


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    """A UR10e with every link in error and harmonic-drive transmission errors, measured on 800
    configurations of a region, identified with ``--residual-map auto``."""
    tmp_path = tmp_path_factory.mktemp("transmission")
    rng = np.random.default_rng(21)
    # the reflector at the tool origin (50 mm out from the flange): the point measured is the point
    # compensated
    ur = robots.nominal("ur10e")
    nominal = dataclasses.replace(ur, tool=ur.tool + np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0]))
    truth = perturbed(nominal, rng, base_length_m=0.5, base_angle_rad=0.3)
    tx = harmonic_drive_errors(nominal, rng)
    (tmp_path / "nominal.json").write_text(json.dumps(model_to_dict(nominal, units=Units("mm", "deg"))))
    data = simulate_measurements(
        truth,
        random_configurations(nominal, 800, rng, limits=REGION),
        rng,
        sigma_m=10e-6,
        targets=(None,),
        transmission=tx,
    )
    with (tmp_path / "meas.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)] + ["x", "y", "z"])
        for k in range(len(data)):
            w.writerow([*np.rad2deg(data.q[k]).tolist(), *(data.p_world[k] * 1e3).tolist()])
    _write_validation(tmp_path / "val.csv", nominal, truth, tx)
    # one identification serves every test (about 20 s): --validate only reads the hold-out file
    proc = recal(
        "identify", "--model", "nominal.json", "--data", "meas.csv", "--out", "id.json", "--sigma", "0.01",
        "--report", "r.json", "--residual-map", "auto", "--validate", "val.csv", cwd=tmp_path,
    )  # fmt: skip
    return tmp_path, rng, nominal, truth, tx, proc


def _write_validation(path: Path, nominal, truth, tx) -> None:
    """400 fresh configurations of the region measured as the data are (their own generator)."""
    rng = np.random.default_rng(195)
    held = simulate_measurements(
        truth,
        random_configurations(nominal, 400, rng, limits=REGION + np.deg2rad([2.0, -2.0])),
        rng,
        sigma_m=10e-6,
        targets=(None,),
        transmission=tx,
    )
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)] + ["x", "y", "z"])
        for k in range(len(held)):
            w.writerow([*np.rad2deg(held.q[k]).tolist(), *(held.p_world[k] * 1e3).tolist()])


def test_identify_stores_the_transmission_correction_and_predict_applies_it(identified):
    tmp_path, rng, nominal, truth, tx, proc = identified
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
    p = recal("predict", "--model", "id.json", "--joints", "joints.csv", "--out", "p.csv", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    rows = list(csv.reader((tmp_path / "p.csv").open()))
    assert rows[0] == ["x", "y", "z", "qw", "qx", "qy", "qz", "flags"]
    xyz = np.array([r[:3] for r in rows[1:]], dtype=float) * 1e-3
    outside = np.array(["outside_mapped_region" in r[7] for r in rows[1:]])
    assert outside[-5:].all() and not outside[:-5].any()
    true = simulate_measurements(truth, q, rng, sigma_m=0.0, targets=(None,), transmission=tx).p_world
    model = load_model(tmp_path / "id.json")
    from calibration.kinematics import target_positions

    geometric = target_positions(model, q, None)
    err_pred = np.linalg.norm(xyz - true, axis=1)
    err_geo = np.linalg.norm(geometric - true, axis=1)
    assert np.sqrt(np.mean(err_pred[~outside] ** 2)) < 0.3 * np.sqrt(np.mean(err_geo[~outside] ** 2))
    assert np.allclose(xyz[outside], geometric[outside], atol=1e-9)  # the geometric model alone there


def _task(path: Path, T_goal: np.ndarray, q_near: np.ndarray) -> None:
    from calibration.transforms import matrix_to_quat

    quat = matrix_to_quat(T_goal[:, :3, :3])
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", "z", "qw", "qx", "qy", "qz"] + [f"q{i + 1}" for i in range(6)])
        for k in range(len(T_goal)):
            w.writerow([*(T_goal[k, :3, 3] * 1e3), *quat[k], *np.rad2deg(q_near[k])])


def _compensated(path: Path):
    rows = list(csv.reader(path.open()))
    head = rows[0]
    q = np.deg2rad(np.array([[r[head.index(f"q{i + 1}")] for i in range(6)] for r in rows[1:]], dtype=float))
    return q, [r[head.index("flags")] for r in rows[1:]]


def test_compensation_through_the_transmission_puts_the_true_arm_on_the_targets(identified):
    from calibration.kinematics import fk

    tmp_path, rng, nominal, truth, tx, proc = identified
    assert proc.returncode in (0, 3), proc.stderr
    inner = REGION + np.deg2rad([5.0, -5.0])
    q_goal = random_configurations(nominal, 30, rng, limits=inner)
    T_goal = fk(truth, q_goal + tx.joint_errors(q_goal))  # where the tool must truly be
    _task(tmp_path / "task.csv", T_goal, q_goal)
    c = recal("compensate", "--model", "id.json", "--task", "task.csv", "--out", "c.csv", cwd=tmp_path)
    assert c.returncode == 0, c.stderr
    qc, flags = _compensated(tmp_path / "c.csv")
    assert not any(flags), flags
    reached = fk(truth, qc + tx.joint_errors(qc))[:, :3, 3]  # where the true arm goes at the commands
    err = np.linalg.norm(reached - T_goal[:, :3, 3], axis=1)
    doc = json.loads((tmp_path / "id.json").read_text())
    (tmp_path / "nomap.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual_map"}))
    c2 = recal("compensate", "--model", "nomap.json", "--task", "task.csv", "--out", "c2.csv", cwd=tmp_path)
    assert c2.returncode == 0, c2.stderr
    q2, _ = _compensated(tmp_path / "c2.csv")
    err2 = np.linalg.norm(fk(truth, q2 + tx.joint_errors(q2))[:, :3, 3] - T_goal[:, :3, 3], axis=1)
    assert err.max() < 0.01e-3, err.max()  # within 0.01 mm of every target (issue 28)
    assert err2.max() > 2 * err.max()  # the geometric model alone does not get there


def test_a_urscript_program_through_the_transmission_puts_the_true_arm_on_its_targets(identified, tmp_path):
    """A URScript program (pose targets with their qnear, as PolyScope writes them, and joint
    targets), compensated with the stored transmission correction and run by a controller that
    knows only the nominal model, brings the true arm (transmission included) within 0.01 mm of
    every target (issue 28: "Compensation applies it too: joints, targets and programs")."""
    import re

    from calibration.compensation import nominal_world_frame
    from calibration.ik import solve_ik
    from calibration.kinematics import fk
    from calibration.transforms import matrix_to_rotvec, pose_to_matrix, rotvec_to_matrix
    from service.task_compensation import calibrated_range_of

    d, rng, nominal, truth, tx, proc = identified
    assert proc.returncode in (0, 3), proc.stderr
    model = load_model(d / "id.json")
    # the nominal's world in the identified one's, as compensation fits it
    M = nominal_world_frame(model, nominal, calibrated_range_of(model))[0]
    B = pose_to_matrix(nominal.base)
    q_pose = random_configurations(nominal, 6, rng, limits=REGION + np.deg2rad([5.0, -5.0]))
    q_joint = random_configurations(nominal, 4, rng, limits=REGION + np.deg2rad([5.0, -5.0]))
    T_goal = fk(truth, q_pose + tx.joint_errors(q_pose))  # where the tool must truly be
    P = np.linalg.inv(B) @ M @ T_goal  # the targets in the nominal robot's base frame
    lines = ["def main():"]
    for k in range(len(P)):
        vals = [*P[k, :3, 3], *matrix_to_rotvec(P[k, :3, :3])]
        qnear = ", ".join(f"{v:.9f}" for v in q_pose[k])
        pose = ", ".join(f"{v:.9f}" for v in vals)
        lines.append(f"  movej(get_inverse_kin(p[{pose}], qnear=[{qnear}]), a=1.4, v=1.05)")
    for k in range(len(q_joint)):
        lines.append("  movej([" + ", ".join(f"{v:.9f}" for v in q_joint[k]) + "], a=1.4, v=1.05)")
    lines.append("end")
    (tmp_path / "prog.script").write_text("\n".join(lines) + "\n")
    for name in ("id.json", "nominal.json"):
        (tmp_path / name).write_text((d / name).read_text())
    c = recal("compensate", "--model", "id.json", "--nominal", "nominal.json", "--task", "prog.script", "--out", "out.script", cwd=tmp_path)  # fmt: skip
    assert c.returncode == 0, c.stderr + c.stdout
    assert "flagged" not in c.stdout, c.stdout  # every target inside the calibrated and corrected region
    out = (tmp_path / "out.script").read_text().splitlines()[1:-1]
    numbers = [np.array(re.findall(r"-?\d+\.\d+(?:e-?\d+)?", line)[:6], dtype=float) for line in out]
    # the nominal controller's inverse kinematics of the new pose near its qnear, then the true
    # arm there
    P_new = np.array([pose_to_matrix(np.r_[v[:3], 0, 0, 0]) for v in numbers[: len(P)]])
    P_new[:, :3, :3] = rotvec_to_matrix(np.array([v[3:] for v in numbers[: len(P)]]))
    ik = solve_ik(nominal, B @ P_new, q_pose, position_tol_m=1e-12, rotation_tol_rad=1e-12)
    assert ik.converged.all()
    reached = fk(truth, ik.q + tx.joint_errors(ik.q))[:, :3, 3]
    assert np.linalg.norm(reached - T_goal[:, :3, 3], axis=1).max() < 0.01e-3
    # movej: the pose the nominal joints meant, reached by the true arm at the new joints
    q_new = np.array(numbers[len(P) :])
    goal_j = (np.linalg.inv(M) @ fk(nominal, q_joint))[:, :3, 3]
    reached_j = fk(truth, q_new + tx.joint_errors(q_new))[:, :3, 3]
    assert np.linalg.norm(reached_j - goal_j, axis=1).max() < 0.01e-3
    # the same program through the geometry alone misses by the transmission's error
    doc = json.loads((d / "id.json").read_text())
    (tmp_path / "id.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual_map"}))
    c2 = recal("compensate", "--model", "id.json", "--nominal", "nominal.json", "--task", "prog.script", "--out", "geo.script", cwd=tmp_path)  # fmt: skip
    assert c2.returncode == 0, c2.stderr
    q_geo = np.array([re.findall(r"-?\d+\.\d+(?:e-?\d+)?", line)[:6] for line in (tmp_path / "geo.script").read_text().splitlines()[1 + len(P) : -1]], dtype=float)  # fmt: skip
    miss_geo = np.linalg.norm(fk(truth, q_geo + tx.joint_errors(q_geo))[:, :3, 3] - goal_j, axis=1)
    assert miss_geo.max() > 0.02e-3, miss_geo


def test_compensation_through_trees_settles_or_flags_every_point(identified, tmp_path):
    from calibration import residual_choice as RC
    from calibration import trees as TT
    from calibration.kinematics import fk
    from service.files import read_measurements

    d, rng, nominal, truth, tx, _proc = identified
    model = load_model(d / "id.json")
    data = read_measurements(str(d / "meas.csv"), model)
    trees = RC.fit_family("trees", model, model, data, {"sigma_m": 10e-6})
    doc = json.loads((d / "id.json").read_text())
    doc["residual_map"] = TT.to_dict(trees, model)
    (tmp_path / "trees.json").write_text(json.dumps(doc))
    q_goal = random_configurations(nominal, 40, rng, limits=REGION + np.deg2rad([5.0, -5.0]))
    T_goal = fk(truth, q_goal + tx.joint_errors(q_goal))
    _task(tmp_path / "task.csv", T_goal, q_goal)
    c = recal("compensate", "--model", "trees.json", "--task", "task.csv", "--out", "c.csv", cwd=tmp_path)
    assert c.returncode in (0, 3), c.stderr
    qc, flags = _compensated(tmp_path / "c.csv")
    m = load_model(tmp_path / "trees.json")
    corr, inside = trees.evaluate(qc)
    reached = fk(m, qc)[:, :3, 3] + corr  # where the corrected model puts the commands
    miss = np.linalg.norm(reached - T_goal[:, :3, 3], axis=1)
    flagged = np.array(["no_convergence" in f or "outside_mapped_region" in f for f in flags])
    assert inside[~flagged].all()
    assert np.all(miss[~flagged] < 5e-6), miss[~flagged].max()  # settled: on the goal
    assert np.all(miss[flagged & inside] > 1e-6)  # flagged only where it did not settle


def test_accuracy_judges_the_model_with_its_transmission_correction(identified):
    tmp_path, rng, nominal, truth, tx, proc = identified
    assert proc.returncode in (0, 3), proc.stderr
    held = simulate_measurements(
        truth,
        random_configurations(nominal, 200, rng, limits=REGION + np.deg2rad([5.0, -5.0])),
        rng,
        sigma_m=10e-6,
        targets=(None,),
        transmission=tx,
    )
    with (tmp_path / "held.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)] + ["x", "y", "z"])
        for k in range(len(held)):
            w.writerow([*np.rad2deg(held.q[k]).tolist(), *(held.p_world[k] * 1e3).tolist()])
    doc = json.loads((tmp_path / "id.json").read_text())
    (tmp_path / "geometric.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual_map"}))
    rms = {}
    for name in ("id.json", "geometric.json"):
        a = recal("accuracy", "--model", name, "--data", "held.csv", "--out", f"acc-{name}", cwd=tmp_path)
        assert a.returncode == 0, a.stderr
        report = json.loads((tmp_path / f"acc-{name}").read_text())
        rms[name] = report["errors"]["rms"]
        # every row inside the correction's region is counted as such; a model without one says nothing
        assert report.get("outside_mapped_region") == (0 if name == "id.json" else None)
    # with the correction only the tracker's noise is left (√3 · 0.01 mm), well under the geometric model's
    assert rms["id.json"] < 0.6 * rms["geometric.json"] and rms["id.json"] < 1.3 * np.sqrt(3) * 0.01


def _write_joints(path: Path, q: np.ndarray) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"q{i + 1}" for i in range(6)])
        w.writerows(np.rad2deg(q).tolist())


def _predicted_with_bounds(path: Path):
    rows = list(csv.reader(path.open()))
    head = rows[0]
    xyz = np.array([r[:3] for r in rows[1:]], dtype=float) * 1e-3
    u95 = np.array([r[head.index("u95")] for r in rows[1:]], dtype=float) * 1e-3
    flags = [r[head.index("flags")] for r in rows[1:]]
    return xyz, u95, flags


def test_u95_of_the_corrected_model_covers_95_percent_of_fresh_hold_out_errors_in_its_region(identified):
    """Honest bounds (issue 28): inside the correction's region ``recal predict --uncertainty``
    gives the bound of the corrected model (its cross-validated error, the instrument's noise
    taken out), and with the tracker's noise it covers about 95 % of the errors of fresh poses
    measured as the identification's were. Measured with this seed: 0.962 of the 980 poses inside (the
    bound against the noise-free truth: 1.000, the cross-validation's folds being a little worse
    than the final fit). Outside the region, the geometric model's bound, flagged."""
    from calibration.uncertainty import chi2_quantile

    tmp_path, _, nominal, truth, tx, proc = identified
    assert proc.returncode in (0, 3), proc.stderr
    rng = np.random.default_rng(95)
    sigma_m = 10e-6
    q = random_configurations(nominal, 1000, rng, limits=REGION + np.deg2rad([2.0, -2.0]))
    q[-20:, 2] = REGION[2, 1] + np.deg2rad(10)  # beyond the elbow's measured range
    held = simulate_measurements(truth, q, rng, sigma_m=sigma_m, targets=(None,), transmission=tx)
    _write_joints(tmp_path / "fresh.csv", q)
    doc = json.loads((tmp_path / "id.json").read_text())
    assert doc["residual_map"]["cross_validation"]["model_sigma_m"] > 0  # mm: stored by identify
    (tmp_path / "geometric.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual_map"}))
    out = {}
    for name in ("id.json", "geometric.json"):
        p = recal(
            "predict", "--model", name, "--joints", "fresh.csv", "--out", f"u-{name}.csv", "--uncertainty",
            cwd=tmp_path,
        )  # fmt: skip
        assert p.returncode == 0, p.stderr
        out[name] = _predicted_with_bounds(tmp_path / f"u-{name}.csv")
    xyz, u95, flags = out["id.json"]
    inside = np.array(["outside_mapped_region" not in f for f in flags])
    assert not inside[-20:].any() and inside[:-20].mean() > 0.97
    # a measured error is the model's and the tracker's: the bound of both (isotropic inside)
    bound = np.sqrt(u95**2 + chi2_quantile(0.95, 3) * sigma_m**2)
    err = np.linalg.norm(held.p_world - xyz, axis=1)
    coverage = float(np.mean(err[inside] <= bound[inside]))
    assert 0.90 <= coverage <= 0.99, coverage  # measured: 0.962 of 980 (u95 10.3 µm; geometric ~100 µm)
    # the corrected model's bound is its own, far tighter than the geometric model's there
    geo_xyz, geo_u95, _ = out["geometric.json"]
    assert np.median(u95[inside]) < 0.5 * np.median(geo_u95[inside])
    # outside: the geometric model's position and bound, flagged
    assert np.allclose(xyz[~inside], geo_xyz[~inside], atol=1e-9)
    assert np.allclose(u95[~inside], geo_u95[~inside], rtol=1e-9)


def test_identify_validate_reports_how_many_hold_out_errors_the_corrected_bound_covers(identified):
    """``recal identify --residual-map auto --validate`` states the share of hold-out rows inside
    the correction's region within the 95 % bound the stored model gives there (the one bound of
    ``recal predict --uncertainty``) plus the tracker's noise."""
    tmp_path, _, _, _, _, proc = identified
    assert proc.returncode in (0, 3), proc.stderr
    v = json.loads((tmp_path / "r.json").read_text())["residual_map"]["validation"]
    assert v["inside_share"] > 0.95
    assert 0.90 <= v["coverage_95"] <= 0.99, v  # measured: 0.975 of 400
    line = next(x for x in proc.stdout.splitlines() if x.startswith("residual map ("))
    assert f"{100 * v['coverage_95']:.1f} % of those within their 95 % bound" in line


def test_the_bound_of_a_file_without_the_stored_error_is_wider_and_a_bad_one_is_named(identified, tmp_path):
    """The bound inside the region is the σ whose 95 % radius is the held-out errors' own 95 %
    quantile (``model_sigma_95``), never below the RMS's σ (``model_sigma``). A model file written
    before ``model_sigma_95`` was stored gets ``model_sigma``; one written before that, the
    cross-validated RMS with the correction over √3 inside the region (the noise left in: wider,
    never narrower); a malformed figure is refused naming its field, before any output."""
    from calibration.model import model_from_dict
    from calibration.uncertainty import CovarianceError, stored_position_bound

    d, _rng, nominal, *_ = identified
    doc = json.loads((d / "id.json").read_text())
    cv = doc["residual_map"]["cross_validation"]
    assert cv["model_sigma_95_m"] >= cv["model_sigma_m"] > 0
    q = random_configurations(nominal, 20, np.random.default_rng(3), limits=REGION + np.deg2rad([5.0, -5.0]))
    C_new, inside = stored_position_bound(model_from_dict(doc), q)
    assert inside.all() and np.allclose(C_new, (cv["model_sigma_95_m"] * 1e-3) ** 2 * np.eye(3))
    older = json.loads(json.dumps(doc))
    del older["residual_map"]["cross_validation"]["model_sigma_95_m"]
    C_older, _ = stored_position_bound(model_from_dict(older), q)
    assert np.allclose(C_older, (cv["model_sigma_m"] * 1e-3) ** 2 * np.eye(3))
    old = json.loads(json.dumps(older))
    del old["residual_map"]["cross_validation"]["model_sigma_m"]
    C_old, _ = stored_position_bound(model_from_dict(old), q)
    assert np.allclose(C_old, (cv["rms_with_m"] * 1e-3 / np.sqrt(3)) ** 2 * np.eye(3))
    assert np.all(C_old[:, 0, 0] > C_older[:, 0, 0])
    bad95 = json.loads(json.dumps(doc))
    bad95["residual_map"]["cross_validation"]["model_sigma_95_m"] = "wide"
    with pytest.raises(CovarianceError) as exc:
        stored_position_bound(model_from_dict(bad95), q)
    assert exc.value.field == "residual_map.cross_validation.model_sigma_95_m"
    bad = json.loads(json.dumps(older))
    bad["residual_map"]["cross_validation"]["model_sigma_m"] = -1
    with pytest.raises(CovarianceError) as exc:
        stored_position_bound(model_from_dict(bad), q)
    assert exc.value.field == "residual_map.cross_validation.model_sigma_m"
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    _write_joints(tmp_path / "j.csv", q)
    p = recal("predict", "--model", "bad.json", "--joints", "j.csv", "--out", "o.csv", "--uncertainty", cwd=tmp_path)
    assert p.returncode == 2 and "residual_map.cross_validation.model_sigma_m" in p.stderr
    assert not (tmp_path / "o.csv").exists()
