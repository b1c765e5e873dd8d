"""Task files of `recal compensate` (service.taskfiles): the task CSV of contracts §5 and
Universal Robots URScript programs (targets found, everything else byte for byte)."""

from __future__ import annotations

import csv
import io
import math
import re

import numpy as np
import pytest

from calibration import robots
from calibration.kinematics import fk
from calibration.transforms import matrix_to_quat, rotvec_to_matrix
from service.files import InputError
from service.programs.urscript import parse as parse_urscript
from service.taskfiles import format_task, is_script, matrix_to_pose_ur, pose_to_matrix_ur, read_task

UR = robots.nominal("ur10e")  # mm and degrees


def write(tmp_path, text, name="task.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


# =============================================================================== task CSV


def test_read_task_poses_and_taught_rows_in_si(tmp_path):
    q = np.radians([[10, -80, 90, -100, 70, 20], [-30, -100, 60, -50, -80, 0]])
    T = fk(UR, q)
    quat = matrix_to_quat(T[:, :3, :3])
    rows = ["name,x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6"]
    for i in range(2):
        rows.append(
            f"P{i},"
            + ",".join(f"{v:.9f}" for v in T[i, :3, 3] * 1000)
            + ","
            + ",".join(f"{v:.12f}" for v in quat[i])
            + ","
            + ",".join(f"{v:.6f}" for v in np.degrees(q[i]))
        )
    rows.append("taught,,,,,,,," + ",".join(f"{v:.6f}" for v in np.degrees(q[0])))
    task = read_task(write(tmp_path, "# a comment\n" + "\n".join(rows) + "\n"), UR)
    assert len(task) == 3
    np.testing.assert_array_equal(task.has_pose, [True, True, False])
    np.testing.assert_array_equal(task.has_q, [True, True, True])
    np.testing.assert_allclose(task.T_world_tool[:2], T, atol=1e-9)
    np.testing.assert_allclose(task.q[2], q[0], atol=1e-9)
    assert task.where(2) == {"row": 3, "line": 5}


@pytest.mark.parametrize(
    "text, match",
    [
        ("x,y,z,qw,qx,qy\n1,2,3,1,0,0\n", r"task\.csv: missing column 'qz'"),
        ("x,y,z,qw,qx,qy,qz\n1,2,3,1,0,,0\n", r"task\.csv, row 1 \(line 2\), column 'qy': expected a number"),
        (
            "x,y,z,qw,qx,qy,qz\n1,2,3,1,0,0,0\n1,2,abc,1,0,0,0\n",
            r"row 2 \(line 3\), column 'z': expected a number, got 'abc'",
        ),
        ("x,y,z,qw,qx,qy,qz\n1,2,3,0.5,0,0,0\n", r"row 1 \(line 2\), column 'qw': the quaternion has norm 0.5"),
        ("q1,q2,q3,q4,q5,q6,q7\n1,2,3,4,5,6,7\n", r"column 'q7': the model has 6 joints"),
        ("q1,q2,q4,q5,q6\n1,2,3,4,5\n", r"missing joint column 'q3'"),
        ("name,speed\nA,1\n", r"expected the columns x, y, z, qw, qx, qy, qz .* and/or q1\.\.q6"),
        (
            "name,x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6\nA,,,,,,,,,,,,,\n",
            r"row 1 \(line 2\), column 'x': the row has neither",
        ),
        ("x,y,z,qw,qx,qy,qz\n", r"has a header but no data rows"),
    ],
)
def test_bad_task_files_name_file_row_and_column(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        read_task(write(tmp_path, text), UR)


def test_format_task_replaces_only_its_columns_and_keeps_the_others_text(tmp_path):
    text = "name,x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6,note\nA,100.50,2,3,-1,0,0,0,1,2,3,4,5,6,keep me\n"
    task = read_task(write(tmp_path, text), UR)
    q = np.radians([[1.5, 2.5, 3.5, 4.5, 5.5, 6.5]])
    T = np.eye(4)[None].copy()
    T[0, :3, 3] = [0.2, 0.3, 0.4]
    out = format_task(task, UR, "joints", q, T, np.array([True]), np.array([2e-9]), ["near_singular"])
    rows = list(csv.reader(io.StringIO(out)))
    assert rows[0] == [
        "name",
        "x",
        "y",
        "z",
        "qw",
        "qx",
        "qy",
        "qz",
        "q1",
        "q2",
        "q3",
        "q4",
        "q5",
        "q6",
        "note",
        "converged",
        "residual",
        "flags",
    ]
    assert rows[1][:8] == ["A", "100.50", "2", "3", "-1", "0", "0", "0"]  # text as it was
    np.testing.assert_allclose([float(v) for v in rows[1][8:14]], [1.5, 2.5, 3.5, 4.5, 5.5, 6.5])
    assert rows[1][14:] == ["keep me", "1", "2e-06", "near_singular"]  # residual in mm
    out = format_task(task, UR, "targets", q, T, np.array([False]), np.array([0.0]), [""])
    rows = list(csv.reader(io.StringIO(out)))
    np.testing.assert_allclose([float(v) for v in rows[1][1:8]], [200, 300, 400, -1, 0, 0, 0])  # qw sign kept
    assert rows[1][8:14] == ["1", "2", "3", "4", "5", "6"] and rows[1][15:17] == ["0", "0"]


def test_format_task_appends_the_columns_a_taught_task_lacks(tmp_path):
    task = read_task(write(tmp_path, "q1,q2,q3,q4,q5,q6,converged\n1,2,3,4,5,6,0\n"), UR)
    T = fk(UR, np.radians([[1, 2, 3, 4, 5, 6]]))
    out = format_task(task, UR, "targets", task.q, T, np.array([True]), np.array([0.0]), [""])
    header = out.splitlines()[0].split(",")
    assert header == [
        "q1",
        "q2",
        "q3",
        "q4",
        "q5",
        "q6",
        "x",
        "y",
        "z",
        "qw",
        "qx",
        "qy",
        "qz",
        "converged",
        "residual",
        "flags",
    ]


# =============================================================================== URScript


PROGRAM = (
    b"def prog():\r\n"
    b"  # Waypoint 1: p[1, 2, 3] in a comment stays, \xe9 (latin-1) too\r\n"
    b"  global Waypoint_1_p=p[.12, -.43, .32, -.001, 3.116, .039]\r\n"
    b"  global Waypoint_1_q=[-1.6, -1.72, -2.2, -0.8, 1.59, -0.03]\r\n"
    b"\tglobal  Home_q =  [0,-1.57,  1.57,-1.57,-1.57,0]   # home 1.57\r\n"
    b"  movej(get_inverse_kin(Waypoint_1_p, qnear=Waypoint_1_q), a=1.39, v=1.04)\r\n"
    b"  movel(Waypoint_1_p, a=1.2, v=0.25, r=0.01)\r\n"
    b"  movej( Home_q ,a=1.4,v=1.05)\n"
    b"  movel(p[0.4,  -0.2,0.3,0,3.14159,0], a=1.2, v=0.25)   # odd spacing\r\n"
    b"  movep([0.1,-1.5,1.4,-1.5,-1.6,0.2], a=1, v=0.1, r=0.002)\r\n"
    b"  movel(pose_trans(Waypoint_1_p, p[0,0,-0.05,0,0,0]), a=1, v=0.1)\r\n"
    b'  textmsg("movel(p[9,9,9,9,9,9]) # not code")\r\n'
    b"  movej([1,2,3], a=1)\r\n"
    b"  movel(Nowhere)\r\n"
    b"  movec(p[0.3,0.1,0.3,0,3.14,0], p[0.3,0.2,0.3,0,3.14,0], a=1, v=0.1, r=0)\r\n"
    b"end"  # no line ending at the end of the file
)


def test_urscript_targets_are_found_with_their_lines(tmp_path):
    path = tmp_path / "prog.script"
    path.write_bytes(PROGRAM)
    s = parse_urscript(path)
    got = [
        (
            t.line,
            t.move,
            t.pose.name if t.pose else None,
            t.joints.name if t.joints else None,
            "pose" if t.pose else "joints",
        )
        for t in s.targets
    ]
    assert got == [
        (6, "movej", "Waypoint_1_p", "Waypoint_1_q", "pose"),  # get_inverse_kin: pose and its qnear
        (8, "movej", None, "Home_q", "joints"),
        (9, "movel", None, None, "pose"),
        (10, "movep", None, None, "joints"),
        (15, "movec", None, None, "pose"),
        (15, "movec", None, None, "pose"),
    ]
    np.testing.assert_allclose(s.targets[0].pose.values, [0.12, -0.43, 0.32, -0.001, 3.116, 0.039])
    assert s.targets[0].pose.line == 3 and s.targets[0].joints.line == 4
    left = [(u.line, u.reason) for u in s.uninterpreted]
    assert (11, "the target is computed by an expression") in left
    assert any(ln == 11 and "uses target variable Waypoint_1_p" in r for ln, r in left)
    assert (13, "expected a joint vector of 6 numbers") in left
    assert (14, "target variable Nowhere is not assigned in this file") in left
    assert all(ln != 12 for ln, _ in left)  # a move inside a string is not code
    assert s.line_text(11) == "  movel(pose_trans(Waypoint_1_p, p[0,0,-0.05,0,0,0]), a=1, v=0.1)"


def _numbers_masked(line: bytes) -> bytes:
    return re.sub(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", b"#", line)


def test_urscript_rewrite_changes_only_the_target_numbers(tmp_path):
    path = tmp_path / "prog.script"
    path.write_bytes(PROGRAM)
    s = parse_urscript(path)
    reps, lits = {}, {}
    for t in s.targets:
        for lit in (t.pose, t.joints):
            if lit is not None:
                reps[id(lit)], lits[id(lit)] = lit.values + 0.0012345, lit
    out = s.rewrite(reps, lits)
    a, b = PROGRAM.splitlines(keepends=True), out.splitlines(keepends=True)
    assert len(a) == len(b) and out.count(b"\r\n") == PROGRAM.count(b"\r\n") and not out.endswith(b"\n")
    changed = {3, 4, 5, 9, 10, 15}
    for ln, (x, y) in enumerate(zip(a, b), start=1):
        if ln in changed:
            assert x != y and _numbers_masked(x) == _numbers_masked(y), ln
        else:
            assert x == y, ln
    # parameters, comments (with their numbers) and odd bytes untouched
    assert b"a=1.39, v=1.04)\r\n" in out and b"# home 1.57\r\n" in out and b"p[1, 2, 3] in a comment stays, \xe9" in out
    assert b"  movel(p[0.4012345,  -0.1987655,0.3012345,0.0012345,3.1428245,0.0012345], a=1.2, v=0.25)" in out
    # nothing to replace: the very same bytes
    assert s.rewrite({}, {}) == PROGRAM


def test_urscript_pose_conversion_keeps_the_rotation_vector_style():
    pose = np.array([[0.1, -0.2, 0.3, 0.0, -3.14, 0.0], [0.1, 0.2, 0.3, 0.01, 3.1, -0.05], [0, 0, 0.5, 0.3, 0.2, 0.1]])
    T = pose_to_matrix_ur(pose)
    np.testing.assert_allclose(T[:, :3, :3], rotvec_to_matrix(pose[:, 3:]))
    back = matrix_to_pose_ur(T, like=pose)
    np.testing.assert_allclose(back, pose, atol=1e-12)
    # near pi the equivalent vector on the original's side is chosen
    plain = matrix_to_pose_ur(T)
    assert np.linalg.norm(plain[0, 3:]) <= math.pi


def test_script_suffixes():
    assert is_script("a/prog.script") and is_script("P.URSCRIPT") and not is_script("task.csv")
