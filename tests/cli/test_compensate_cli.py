"""`recal compensate` as a user runs it: the real console script, in a subprocess, on files
written here (contracts §5, §6).

The identified robot is what `recal identify` writes for a UR (Hayati links, small errors in
every link, the base where the tracker sees it, the nominal model and the calibrated joint ranges
recorded in its `identification` block). Outputs are checked against the library's forward
kinematics, not against the command's own report.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration import robots
from calibration.conventions import hayati_for_parallel_axes
from calibration.ik import geometric_jacobian, inverse_kinematics, singular_values
from calibration.kinematics import fk
from calibration.model import model_to_dict
from calibration.parameters import apply_step, candidate_parameters
from calibration.transforms import matrix_to_quat, pose_to_matrix, quat_to_matrix
from service.files import load_model, save_model
from service.taskfiles import pose_to_matrix_ur

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]
MM = 1e-3
DEG = math.pi / 180
NUMBER_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")


def recal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*RECAL, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=120)


def identified_like(nominal, seed, base=(1800.0, -600.0, 300.0, 0.1, -0.2, 130.0)):
    rng = np.random.default_rng(seed)
    m, _ = hayati_for_parallel_axes(nominal)
    params = candidate_parameters(m, base=False, tool=False)
    sig = [0.5e-3 if p.kind == "length" else 0.1 * DEG if p.name.endswith(".theta") else 0.05 * DEG for p in params]
    m = apply_step(m, params, rng.normal(0.0, sig))
    b = np.array(base, dtype=float)
    return dataclasses.replace(m, base=np.concatenate([b[:3] * MM, b[3:] * DEG]), name=f"ur10e-identified-{seed}")


def task_q(rng, n):
    q = rng.uniform(-170, 170, (n, 6))
    q[:, 1] = rng.uniform(-150, -30, n)
    q[:, 2] = rng.uniform(30, 150, n) * rng.choice([-1, 1], n)
    q[:, 4] = rng.uniform(30, 150, n) * rng.choice([-1, 1], n)
    return q  # degrees


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("compensate")
    nominal = robots.nominal("ur10e")  # mm, deg
    ident = identified_like(nominal, 1)
    ranges = [[-175.0, 175.0], [-155.0, -25.0], [-155.0, 155.0], [-175.0, 175.0], [-155.0, 155.0], [-175.0, 175.0]]
    save_model(d / "nominal.json", nominal)
    save_model(
        d / "identified.json", ident, {"identification": {"nominal": model_to_dict(nominal), "joint_ranges": ranges}}
    )
    save_model(d / "bare.json", ident)  # records nothing
    save_model(d / "robot_a.json", identified_like(nominal, 2))
    rng = np.random.default_rng(3)
    q = task_q(rng, 40)
    # desired poses: where the robot was planned to be, in the world of the identified model
    from calibration.compensation import nominal_world_frame

    M, _ = nominal_world_frame(ident, nominal, np.radians(ranges))
    X = np.linalg.inv(M) @ fk(nominal, np.radians(q))
    quat = matrix_to_quat(X[:, :3, :3])
    lines = ["# planned off line", "name,x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6"]
    for i in range(len(q)):
        joints = ",".join(f"{v:.10f}" for v in q[i]) if i % 4 else ",,,,,"  # every 4th: pose only
        lines.append(
            f"P{i},"
            + ",".join(f"{v:.10f}" for v in X[i, :3, 3] / MM)
            + ","
            + ",".join(f"{v:.15f}" for v in quat[i])
            + ","
            + joints
        )
    (d / "task.csv").write_text("\n".join(lines) + "\n")
    (d / "taught.csv").write_text(
        "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(f"{v:.10f}" for v in r) for r in q[:10]) + "\n"
    )
    return d, nominal, ident, q, X, M


def read_out(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def col(header, rows, names):
    return np.array([[float(r[header.index(c)]) for c in names] for r in rows])


Q = [f"q{i}" for i in range(1, 7)]
POSE = ["x", "y", "z", "qw", "qx", "qy", "qz"]


def test_joints_mode_commands_reach_the_task_poses(files):
    d, _nominal, ident, q, X, _M = files
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "task.csv",
        "--out",
        "out.csv",
        "--report",
        "rep.json",
        cwd=d,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 40 points (joints mode): 40 converged")
    header, rows = read_out(d / "out.csv")
    assert header == ["name", *POSE, *Q, "converged", "residual", "flags"]
    assert all(row[header.index("converged")] == "1" for row in rows)
    qc = col(header, rows, Q) * DEG
    reached = fk(ident, qc)
    assert np.abs(reached[:, :3, 3] - X[:, :3, 3]).max() < 1e-6  # 1 µm
    np.testing.assert_allclose(reached[:, :3, :3], X[:, :3, :3], atol=1e-8)
    # a small correction on the planned branch and turns (rows with q), or the nearest solution
    planned = np.array([i % 4 != 0 for i in range(40)])
    clean = planned & np.array([row[-1] == "" for row in rows])
    assert clean.sum() > 20
    corr = np.abs(qc[clean] - q[clean] * DEG)
    assert corr.max() < 5.0 * DEG and np.median(corr) < 0.3 * DEG  # larger only near singularities
    # the pose columns are the input's text
    src = (d / "task.csv").read_text().splitlines()[2].split(",")
    assert rows[0][:8] == src[:8]
    report = json.loads((d / "rep.json").read_text())
    assert report["mode"] == "joints" and report["summary"]["converged"] == 40
    assert report["points"][1]["row"] == 2 and report["points"][1]["line"] == 4
    assert report["calibrated_region"][1] == [-155.0, -25.0]
    assert set(report["points"][0]) >= {"converged", "residual", "residual_angle", "correction", "flags", "sigma_min"}


def test_targets_mode_through_the_nominal_controller(files):
    """No --nominal: the identified model records the one it came from. The corrected targets,
    given to the nominal closed form (the controller), bring the identified robot to the task."""
    d, nominal, ident, q, X, _M = files
    r = recal(
        "compensate", "--model", "identified.json", "--task", "task.csv", "--out", "tgt.csv", "--mode", "targets", cwd=d
    )
    assert r.returncode == 0, r.stderr
    header, rows = read_out(d / "tgt.csv")
    assert header == ["name", *POSE, *Q, "converged", "residual", "flags"]
    assert all(row[header.index("converged")] == "1" for row in rows)
    P = col(header, rows, POSE)
    T = np.broadcast_to(np.eye(4), (len(P), 4, 4)).copy()
    T[:, :3, :3] = quat_to_matrix(P[:, 3:])
    T[:, :3, 3] = P[:, :3] * MM
    planned = np.array([i % 4 != 0 for i in range(40)])
    ctrl = inverse_kinematics(nominal, T[planned], q[planned] * DEG)
    reached = fk(ident, ctrl.q)
    assert np.abs(reached[:, :3, 3] - X[planned, :3, 3]).max() < 1e-6
    # the q columns (the planned configuration) are kept as they were
    np.testing.assert_allclose(col(header, [rw for rw, p in zip(rows, planned) if p], Q), q[planned], atol=1e-9)


def test_taught_joints_replayed_on_another_robot(files):
    d, _nominal, ident, q, _X, _M = files
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "taught.csv",
        "--out",
        "taught_out.csv",
        "--taught-on",
        "robot_a.json",
        cwd=d,
    )
    assert r.returncode == 0, r.stderr
    header, rows = read_out(d / "taught_out.csv")
    assert header == [*Q, "converged", "residual", "flags"]
    qb = col(header, rows, Q) * DEG
    robot_a = load_model(d / "robot_a.json")
    target = fk(robot_a, q[:10] * DEG)
    assert np.abs(fk(ident, qb)[:, :3, 3] - target[:, :3, 3]).max() < 1e-6
    assert np.abs(fk(ident, q[:10] * DEG)[:, :3, 3] - target[:, :3, 3]).max() > 0.5e-3  # it needed correcting


def test_outside_the_calibrated_region_is_flagged(files):
    d, *_ = files
    (d / "wide.csv").write_text("q1,q2,q3,q4,q5,q6\n10,-170,90,-90,90,0\n10,-90,90,-90,90,0\n")
    r = recal("compensate", "--model", "identified.json", "--task", "wide.csv", "--out", "wide_out.csv", cwd=d)
    assert r.returncode == 0, r.stderr
    _header, rows = read_out(d / "wide_out.csv")
    assert rows[0][-1] == "outside_calibrated_region" and rows[1][-1] == ""


def test_urscript_program_is_rewritten_byte_for_byte_except_its_targets(files):
    d, nominal, ident, _q, _X, M = files
    p0 = [0.55, -0.35, 0.42, 0.01, 3.12, 0.03]
    q0 = (np.radians([-40, -100, 90, -80, -90, 10])).tolist()
    prog = (
        "def job():\r\n"
        "  # approach   (2 targets below)\r\n"
        f"  global Waypoint_1_p=p[{p0[0]}, {p0[1]},{p0[2]}, {p0[3]}, {p0[4]}, {p0[5]}]\r\n"
        f"  global Waypoint_1_q=[{', '.join(f'{v:.6f}' for v in q0)}]\r\n"
        "  movej(get_inverse_kin(Waypoint_1_p, qnear=Waypoint_1_q), a=1.39, v=1.04)\r\n"
        f"  movej([{','.join(f'{v:.5f}' for v in q0)}],  a=1.4, v=1.05, r=0)\r\n"
        "  movel(pose_trans(Waypoint_1_p, p[0, 0, -0.05, 0, 0, 0]), a=1.2, v=0.25)\r\n"
        "end\r\n"
    ).encode()
    (d / "job.script").write_bytes(prog)
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "job.script",
        "--out",
        "job_out.script",
        "--report",
        "job.json",
        cwd=d,
    )
    assert r.returncode == 0, r.stderr
    out = (d / "job_out.script").read_bytes()
    a, b = prog.split(b"\r\n"), out.split(b"\r\n")
    assert len(a) == len(b)
    for ln, (x, y) in enumerate(zip(a, b), start=1):
        assert (x != y) == (ln in (3, 4, 6)), ln
    assert b"), a=1.39, v=1.04)\r\n" in out and b"],  a=1.4, v=1.05, r=0)\r\n" in out
    # the line it cannot interpret is reported with its number and text, on stderr and in the report
    assert "line 7: not compensated (the target is computed by an expression): movel(pose_trans(" in r.stderr
    report = json.loads((d / "job.json").read_text())
    assert [u["line"] for u in report["uninterpreted"]] == [7, 7]
    # the new pose, given to the nominal controller in the waypoint's branch, brings the identified
    # robot where the program meant (the pose in the base frame, through the fitted frame)
    line3 = out.split(b"\r\n")[2].decode()
    new = np.array([float(v) for v in line3[line3.index("p[") + 2 : line3.index("]")].split(",")])
    new_q = np.array([float(v) for v in out.split(b"\r\n")[3].decode().split("[")[1].rstrip("]").split(",")])
    X_meant = np.linalg.inv(M) @ pose_to_matrix(nominal.base) @ pose_to_matrix_ur(p0)
    ctrl = inverse_kinematics(nominal, pose_to_matrix(nominal.base) @ pose_to_matrix_ur(new)[None], np.array(q0))
    np.testing.assert_allclose(ctrl.q[0], new_q, atol=1e-8)  # the qnear is the controller's solution
    assert np.linalg.norm(fk(ident, ctrl.q)[0, :3, 3] - X_meant[:3, 3]) < 1e-6
    # the joint target: the identified robot reaches where the nominal would have been
    line6 = out.split(b"\r\n")[5].decode()
    qj = np.array([float(v) for v in line6[line6.index("[") + 1 : line6.index("]")].split(",")])
    meant = np.linalg.inv(M) @ fk(nominal, np.round(np.array(q0), 5))
    assert np.linalg.norm(fk(ident, qj)[0, :3, 3] - meant[0, :3, 3]) < 1e-6


@pytest.mark.parametrize(
    "name, content, args, match",
    [
        (
            "bad.csv",
            "x,y,z,qw,qx,qy,qz\n1,2,3,1,0,0,0\n1,2,oops,1,0,0,0\n",
            [],
            r"bad\.csv, row 2 \(line 3\), column 'z': expected a number, got 'oops'",
        ),
        ("short.csv", "x,y,z,qw,qx,qy\n1,2,3,1,0,0\n", [], r"short\.csv: missing column 'qz'"),
        # was a traceback, and the output written all the same
        (
            "huge.csv",
            "x,y,z,qw,qx,qy,qz\n1,2,3,1,0,0,0\n1e308,2,3,1,0,0,0\n",
            [],
            r"huge\.csv, row 2 \(line 3\), column 'x': 1e308 is beyond any robot cell",
        ),
        (
            "empty.script",
            'def f():\n  textmsg("hello")\n  movel(pose_trans(a, b))\nend\n',
            [],
            r"empty\.script, line 3: no movej/movel/movep/movec target could be interpreted: 1 line\(s\) left alone \(line "
            r"3\), the first because the target is computed by an expression; --report R\.json lists each with its text",
        ),
        (
            "nomove.script",
            'def f():\n  textmsg("hello")\nend\n',
            [],
            r"nomove\.script: no movej/movel/movep/movec call "
            r"found",
        ),
        (
            "ok.csv",
            "x,y,z,qw,qx,qy,qz\n800,100,500,0,1,0,0\n",
            ["--mode", "targets", "--model", "bare.json"],
            r"bare\.json: targets mode needs the nominal model the controller uses: give --nominal",
        ),
    ],
)
def test_bad_input_is_one_line_and_no_output_file(files, name, content, args, match):
    d, *_ = files
    (d / name).write_text(content)
    out = d / f"{name}.out"
    model = [] if "--model" in args else ["--model", "identified.json"]
    r = recal("compensate", *model, "--task", name, "--out", out.name, *args, cwd=d)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recal compensate: ")
    import re

    assert re.search(match, lines[0]), lines[0]
    assert not out.exists()


def test_identify_then_compensate_uses_what_identify_recorded(tmp_path):
    """`recal identify` records the nominal model and the joint ranges of its data; `recal
    compensate` then needs no --nominal, and flags a point outside the measured ranges."""
    from calibration.simulate import perturbed, simulate_measurements

    rng = np.random.default_rng(8)
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = dataclasses.replace(
        perturbed(nominal, rng),
        base=np.array([1.5, 0.4, 0.2, 0.0, 0.0, 2.0]),
        targets={"smr": np.array([0.0, 0.0, 0.05])},
    )
    q = np.radians(task_q(rng, 50))
    q[:, 0] = rng.uniform(-1.5, 1.5, 50)  # joint 1 measured over ±86° only
    data = simulate_measurements(truth, q, rng, sigma_m=10e-6, targets=("smr",))
    save_model(tmp_path / "nominal.json", nominal)
    rows = ["q1,q2,q3,q4,q5,q6,x,y,z,target"] + [
        ",".join(f"{v:.9f}" for v in np.degrees(qi)) + "," + ",".join(f"{v:.6f}" for v in p / MM) + ",smr"
        for qi, p in zip(data.q, data.p_world)
    ]
    (tmp_path / "meas.csv").write_text("\n".join(rows) + "\n")
    r = recal("identify", "--model", "nominal.json", "--data", "meas.csv", "--out", "ident.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "ident.json").read_text())
    assert doc["identification"]["nominal"]["name"] == "ur10e-nominal"
    np.testing.assert_allclose(
        doc["identification"]["joint_ranges"][0], np.degrees([data.q[:, 0].min(), data.q[:, 0].max()]), atol=1e-6
    )
    (tmp_path / "task.csv").write_text("q1,q2,q3,q4,q5,q6\n10,-90,80,-80,90,0\n150,-90,80,-80,90,0\n")
    r = recal(
        "compensate",
        "--model",
        "ident.json",
        "--task",
        "task.csv",
        "--out",
        "out.csv",
        "--mode",
        "targets",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    # position-only data: the tool orientation stayed nominal, and the user is told so
    assert "note: the calibration did not determine the tool orientation (tool.rx" in r.stderr
    header, out = read_out(tmp_path / "out.csv")
    assert [row[-1] for row in out] == ["", "outside_calibrated_region"]
    ident = load_model(tmp_path / "ident.json")
    P = col(header, out, POSE)
    T = np.broadcast_to(np.eye(4), (2, 4, 4)).copy()
    T[:, :3, :3], T[:, :3, 3] = quat_to_matrix(P[:, 3:]), P[:, :3] * MM
    qt = np.radians([[10, -90, 80, -80, 90, 0], [150, -90, 80, -80, 90, 0]])
    ctrl = inverse_kinematics(robots.nominal("ur10e"), T, qt)
    from calibration.compensation import nominal_world_frame

    M, _ = nominal_world_frame(ident, robots.nominal("ur10e"), np.radians(doc["identification"]["joint_ranges"]))
    meant = np.linalg.inv(M) @ fk(robots.nominal("ur10e"), qt)
    assert np.abs(fk(ident, ctrl.q)[:, :3, 3] - meant[:, :3, 3]).max() < 1e-6


def test_an_output_that_cannot_be_written_fails_before_any_work(files):
    d, *_ = files
    r = recal("compensate", "--model", "identified.json", "--task", "task.csv", "--out", "no/such/dir/out.csv", cwd=d)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "recal compensate: no/such/dir/out.csv: cannot write: the folder 'no/such/dir' does not exist"
    ]


def test_a_program_without_targets_still_gets_the_report_its_error_points_to(files):
    """The hint of "no target could be interpreted" can be followed: with --report the lines left
    alone are listed there with their numbers; the compensated program is not written."""
    d, *_ = files
    (d / "calc.script").write_text(
        "def f():\n  p = get_actual_tcp_pose()\n  movel(pose_trans(p, t))\n  movej(get_inverse_kin(p))\nend\n"
    )
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "calc.script",
        "--out",
        "calc.out.script",
        "--report",
        "calc.json",
        cwd=d,
    )
    assert r.returncode == 2 and not (d / "calc.out.script").exists()
    assert r.stderr.strip().splitlines() == [
        "recal compensate: calc.script, line 2: no movej/movel/movep/movec target could be interpreted: 3 line(s) left "
        "alone (line 2, 3, 4), the first because p: a target computed by an expression is not compensated; the "
        "report lists each with its text and reason"
    ]
    report = json.loads((d / "calc.json").read_text())
    assert report["summary"]["points"] == 0 and report["points"] == []
    assert [(u["line"], u["text"]) for u in report["uninterpreted"]] == [
        (2, "p = get_actual_tcp_pose()"),
        (3, "movel(pose_trans(p, t))"),
        (4, "movej(get_inverse_kin(p))"),
    ]
    assert all(u["reason"] for u in report["uninterpreted"])


def test_pose_only_rows_on_a_robot_without_a_closed_form(tmp_path):
    """A PUMA 560 (no closed-form inverse in Recal) identified with small errors; a task of poses
    without joints. Joints mode: the numerical nominal inverse from --qnear (then the previous
    row's solution, then seeds over the joint limits) starts the correction, and every command
    brings the identified robot to its pose within 1 µm, inside the joint limits. Targets mode: the
    nominal controller's inverse of each corrected target brings it there too."""
    rng = np.random.default_rng(12)
    nominal = robots.nominal("puma560")  # inches, degrees
    m, _ = hayati_for_parallel_axes(nominal)
    params = candidate_parameters(m, base=False, tool=False)
    sig = [0.5e-3 if p.kind == "length" else 0.05 * DEG for p in params]
    ident = dataclasses.replace(apply_step(m, params, rng.normal(0.0, sig)), name="puma-identified")
    save_model(tmp_path / "ident.json", ident, {"identification": {"nominal": model_to_dict(nominal)}})
    lim = np.degrees(nominal.joint_limits)
    q = rng.uniform(np.maximum(lim[:, 0], -150) + 20, np.minimum(lim[:, 1], 150) - 20, (60, 6))
    # away from singular configurations, where the nominal robot may not reach the identified one's pose
    q = q[singular_values(ident, geometric_jacobian(ident, np.radians(q)))[:, -1] > 0.02][:30]
    X = fk(ident, np.radians(q))
    IN = 0.0254
    quat = matrix_to_quat(X[:, :3, :3])
    (tmp_path / "task.csv").write_text(
        "x,y,z,qw,qx,qy,qz\n"
        + "\n".join(
            ",".join(f"{v:.10f}" for v in X[i, :3, 3] / IN) + "," + ",".join(f"{v:.15f}" for v in quat[i])
            for i in range(len(q))
        )
        + "\n"
    )
    r = recal(
        "compensate",
        "--model",
        "ident.json",
        "--task",
        "task.csv",
        "--out",
        "out.csv",
        "--qnear",
        "0,-45,180,0,45,0",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 30 points (joints mode): 30 converged")
    header, rows = read_out(tmp_path / "out.csv")
    assert header == [*POSE, *Q, "converged", "residual", "flags"]
    qc = col(header, rows, Q) * DEG
    reached = fk(ident, qc)
    assert np.abs(reached[:, :3, 3] - X[:, :3, 3]).max() < 1e-6  # 1 µm
    np.testing.assert_allclose(reached[:, :3, :3], X[:, :3, :3], atol=1e-8)
    assert not any("joint_limit" in row[-1] or "unreachable" in row[-1] for row in rows)
    r = recal(
        "compensate",
        "--model",
        "ident.json",
        "--task",
        "task.csv",
        "--out",
        "targets.csv",
        "--mode",
        "targets",
        "--qnear",
        "0,-45,180,0,45,0",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    header, rows = read_out(tmp_path / "targets.csv")
    assert all(row[header.index("converged")] == "1" for row in rows)
    P = col(header, rows, POSE)
    T = np.broadcast_to(np.eye(4), (len(P), 4, 4)).copy()
    T[:, :3, :3], T[:, :3, 3] = quat_to_matrix(P[:, 3:]), P[:, :3] * IN
    ctrl = inverse_kinematics(nominal, T, qc)  # the controller, in the branch of the commands above
    assert np.abs(fk(ident, ctrl.q)[:, :3, 3] - X[:, :3, 3]).max() < 1e-6


def test_a_row_that_does_not_converge_exits_3_naming_it(files, tmp_path):
    """Row 3's pose is 5 m out of the UR10e's reach: the output is written with it flagged, and
    the exit status says not everything was done (3), the last line naming the row (issue 24:
    it exited 0 with 1,059 of 20,000 points not converged)."""
    d, _nominal, _ident, _q, _X, _M = files
    lines = (d / "task.csv").read_text().splitlines()[:6]
    far = lines[4].split(",")
    far[1] = "5000.0"
    lines[4] = ",".join(far)
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    r = recal("compensate", "--model", d / "identified.json", "--task", "t.csv", "--out", "o.csv", cwd=tmp_path)
    assert r.returncode == 3, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last == "recal compensate: 1 of 4 targets not compensated (1 unreachable): row 3", last
    header, rows = read_out(tmp_path / "o.csv")
    assert [row[header.index("converged")] for row in rows] == ["1", "1", "0", "1"]


@pytest.mark.parametrize(
    "name, content, expected",
    [
        # a RAPID system module (.sys): read as RAPID, not as a CSV ("row 9 (line 10): has 6 values")
        (
            "user.sys",
            "%%%\n  VERSION:1\n  LANGUAGE:ENGLISH\n%%%\n\nMODULE user(SYSMODULE)\n  PROC main()\n"
            "    MoveAbsJ [[10,-80,90,-100,70,20],[9E9,9E9,9E9,9E9,9E9,9E9]], v1000, fine, tool0;\n"
            "  ENDPROC\nENDMODULE\n",
            "(RAPID)",
        ),
        # a URScript saved without an extension
        ("program", "def prog():\n  movej([0.1, -1.2, 1.5, -1.9, -1.5, 0.2], a=1.2, v=0.25)\nend\n", "(URScript)"),
    ],
)
def test_the_format_comes_from_the_content_when_the_extension_says_nothing(files, tmp_path, name, content, expected):
    d, *_ = files
    (tmp_path / name).write_text(content)
    r = recal("compensate", "--model", d / "identified.json", "--task", name, "--out", "out", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert expected in r.stdout
    out = (tmp_path / "out").read_text()
    assert out != content and NUMBER_RE.sub("#", out) == NUMBER_RE.sub("#", content)


def test_a_file_whose_format_cannot_be_told_is_refused_naming_format(files, tmp_path):
    d, *_ = files
    (tmp_path / "job.txt").write_text("hello\n1 2 3\n")
    r = recal("compensate", "--model", d / "identified.json", "--task", "job.txt", "--out", "o.txt", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == (
        "recal compensate: job.txt: cannot tell its format from the extension (.txt) or the content: "
        "give --format csv|urscript|rapid|krl|fanuc-tp"
    )
    assert not (tmp_path / "o.txt").exists()


@pytest.mark.parametrize("tcp, flagged", [("p[0, 0, 0, 0, 0, 0]", False), ("p[0, 0, 0.1, 0, 0, 0]", True)])
def test_a_set_tcp_equal_to_the_models_tool_is_not_flagged(files, tcp, flagged):
    # issue 27: set_tcp(p[0,0,0,0,0,0]) is the identified model's own tool (the flange here): the
    # targets are compensated for exactly that TCP, so nothing is left alone; another TCP is flagged
    d, *_ = files
    prog = f"def job():\n  set_tcp({tcp})\n  movel(p[0.55, -0.35, 0.42, 0.01, 3.12, 0.03], a=1.2, v=0.25)\nend\n"
    (d / "tcp.script").write_text(prog)
    args = ["--model", "identified.json", "--task", "tcp.script", "--out", "tcp_out.script", "--report", "tcp.json"]
    r = recal("compensate", *args, cwd=d)
    report = json.loads((d / "tcp.json").read_text())
    assert [u["line"] for u in report["uninterpreted"]] == ([2] if flagged else [])
    assert ("line 2: not compensated (set_tcp changes the TCP" in r.stderr) == flagged
    assert r.returncode in ((0, 3) if flagged else (0,)), r.stderr
    assert (d / "tcp_out.script").read_text().splitlines()[1] == f"  set_tcp({tcp})"
