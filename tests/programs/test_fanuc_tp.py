"""`recal compensate` on a Fanuc TP program (.ls) written for this test: Cartesian positions in
two user frames and tools, a joint position (J3 from the horizon, through the model's coupling),
a second motion group left untouched, an instruction continued on the next line, a commented-out
move and a comment that looks like a position. The compensated positions bring a simulated true
robot to the poses the program means; every other byte is unchanged."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.transforms import homogeneous, matrix_to_pose, rpy_to_matrix
from service.files import InputError
from service.programs import fanuc_tp

from .arms import arm
from .helpers import compare_with_csv_path, frame_of, models, numbers, pose_error, reached, recal, skeleton

Q = {  # planned joints (deg), Fanuc readings
    1: [10, 10, -10, 20, -60, 30],
    2: [-20, 25, 5, -40, -45, 200],
    3: [30, -10, 20, 190, 50, -20],
    5: [5, 40, 60, 10, -70, 0],
}
UF1 = (800.0, -300.0, 150.0, 0.0, 0.0, -30.0)  # X, Y, Z, W, P, R
UT1 = (0.0, 10.0, 220.0, 0.0, -20.0, 0.0)


def fanuc_frame(v):
    """X, Y, Z, W, P, R (mm, deg; fixed X, Y, Z: R = Rz(R)·Ry(P)·Rx(W)): rpy (rx=W, ry=P, rz=R)."""
    return homogeneous(rpy_to_matrix(np.radians(v[3:])), np.array(v[:3]) * 1e-3)


def wpr(R):
    """W, P, R (deg) of R, computed here."""
    return np.degrees([math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0]), math.atan2(R[1, 0], R[0, 0])])


def config(q_deg):
    """Fanuc CONFIG of the Fanuc-like arm from its geometry (tests/programs/arms.py): F where
    J5 > 0; U while the elbow angle J2 + J3 is below the stretched 90° - atan(150/860); T while
    the wrist centre is ahead of J1 along the arm's heading; turn numbers of J1, J4, J6."""
    q = np.radians(q_deg)
    T = fk(arm("fanuc"), q[None])[0]
    w = T[:3, 3] - 0.100 * T[:3, 2]
    front = w[0] * math.cos(q[0]) + w[1] * math.sin(q[0]) >= 0
    up = q_deg[1] + q_deg[2] < 90 - math.degrees(math.atan2(150, 860))
    turns = [math.floor((q_deg[i] + 180) / 360) for i in (0, 3, 5)]
    return f"{'F' if q_deg[4] > 0 else 'N'} {'U' if up else 'D'} {'T' if front else 'B'}, " + ", ".join(map(str, turns))


def cartesian(T, q, uf, ut):
    x, y, z = T[:3, 3] * 1e3
    w, p, r = wpr(T[:3, :3])
    return [
        f"\tUF : {uf}, UT : {ut},\t\tCONFIG : '{config(q)}',",
        f"\tX = {x:9.3f}  mm,\tY = {y:9.3f}  mm,\tZ = {z:9.3f}  mm,",
        f"\tW = {w:9.3f} deg,\tP = {p:9.3f} deg,\tR = {r:9.3f} deg",
    ]


def program(nominal):
    tool = fanuc_frame(UT1)
    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
    U = fanuc_frame(UF1)
    P1 = np.linalg.inv(U) @ fk(nom_t, np.radians([Q[1]]))[0]
    P2 = np.linalg.inv(U) @ fk(nom_t, np.radians([Q[2]]))[0]
    P3 = fk(nominal, np.radians([Q[3]]))[0]  # UF 0, UT 0
    lines = [
        "/PROG  RECAL_TEST",
        "/ATTR",
        "OWNER\t\t= MNEDITOR;",
        'COMMENT\t\t= "written for Recal";',
        "DEFAULT_GROUP\t= 1,1,*,*,*;",
        "/MN",
        "   1:  UFRAME_NUM=1 ;",
        "   2:  UTOOL_NUM=1 ;",
        "   3:J P[1] 100% FINE    ;",
        "   4:L P[2:approach] 500mm/sec CNT50    ;",
        "   5:  ! looks like one: X = 1.000 mm, W = 0.000 deg ;",
        "   6:C P[3]    ",
        "    :  P[5] 300mm/sec FINE    ;",
        "   7:  //L P[9] 100mm/sec FINE    ;",
        "/POS",
        "P[1]{",
        "   GP1:",
        *cartesian(P1, Q[1], 1, 1),
        "};",
        'P[2:"approach"]{',
        "   GP1:",
        *cartesian(P2, Q[2], 1, 1),
        "   GP2:",
        "\tUF : 1, UT : 1,",
        "\tJ1=   120.000  mm",
        "};",
        "P[3]{",
        "   GP1:",
        *cartesian(P3, Q[3], 0, 0),
        "};",
        "P[5]{",
        "   GP1:",
        "\tUF : 1, UT : 1,",
        "\tJ1= %10.3f deg,\tJ2= %10.3f deg,\tJ3= %10.3f deg," % tuple(Q[5][:3]),
        "\tJ4= %10.3f deg,\tJ5= %10.3f deg,\tJ6= %10.3f deg," % tuple(Q[5][3:]),
        "\tE1= %10.3f  mm" % 55.5,
        "};",
        "/END",
        "",
    ]
    return "\r\n".join(lines).encode("ascii")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("tp")
    nominal, true = models(d, "fanuc")
    data = program(nominal)
    (d / "recal_test.ls").write_bytes(data)
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "recal_test.ls",
        "--out",
        "out.ls",
        "--base-frame",
        "1=" + ",".join(map(str, UF1)),
        "--tool-frame",
        "1=" + ",".join(map(str, UT1)),
        "--report",
        "rep.json",
        cwd=d,
    )
    return d, nominal, true, data, r


def test_every_byte_but_the_positions_numbers_is_unchanged(run):
    d, _nominal, _true, data, r = run
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 4 points (Fanuc TP): 4 converged"), r.stdout
    out = (d / "out.ls").read_bytes()
    assert skeleton(out) == skeleton(data)
    pos = data.index(b"/POS")
    assert out[:pos] == data[:pos]  # /ATTR and /MN as they were
    conf = re.compile(rb"CONFIG : '[^']*'")
    assert conf.findall(out) == conf.findall(data)
    assert b"J1=   120.000  mm" in out and b"E1=     55.500  mm" in out  # group 2 and the extended axis
    changed = [(a, b) for a, b in zip(numbers(data), numbers(out)) if a != b]
    assert 18 <= len(changed) <= 24
    # written precision: millimetres were written with 3 decimals, enough (kept); degrees with 3,
    # fewer than the 5 a compensation needs (base.MIN_DECIMALS)
    unit = re.compile(rb"\b([XYZWPR]|J\d)\s*=\s*(-?\d+\.(\d+))\s*(mm|deg)")
    got = [(m[0], len(m[2]), m[3]) for m in unit.findall(out[out.index(b"/POS") :])]
    assert got and all(d == (3 if u == b"mm" else 5) for _, d, u in got), got


def test_compensated_positions_bring_the_true_robot_to_the_program_poses(run):
    d, nominal, true, _data, _r = run
    from service.programs.frames import Frames

    M = frame_of(true, nominal)
    fr = Frames.from_options(["1=" + ",".join(map(str, UT1))], ["1=" + ",".join(map(str, UF1))])
    old = fanuc_tp.parse(d / "recal_test.ls", frames=fr)
    new = fanuc_tp.parse(d / "out.ls", frames=fr)
    errs, before, cases = [], [], {}
    for t0, t1 in zip(old.targets, new.targets):
        n = int(t0.name[2:-1])
        if t0.kind == "joints":
            X_d = np.linalg.inv(M) @ fk(nominal, np.radians([Q[n]]))
            # the same pose without the model's coupling: the uncoupled chain at the joint angles
            # Fanuc's readings mean (J3 from the horizon: joint 3 = -(J2 + J3); J4..J6 turn the
            # other way), contracts §2
            a = np.radians(Q[n])
            angles = np.array([a[0], a[1], -(a[1] + a[2]), -a[3], -a[4], -a[5]])
            uncoupled = dataclasses.replace(nominal, coupling=None)
            np.testing.assert_allclose(fk(uncoupled, angles[None]), fk(nominal, np.radians([Q[n]])), atol=1e-12)
            assert np.abs(fk(uncoupled, a[None])[0, :3, 3] - fk(nominal, a[None])[0, :3, 3]).max() > 0.1
            dp, da = pose_error(fk(true, t1.q[None]), X_d)
            assert dp[0] < 2e-6 and da[0] < 5e-7
            continue
        framed = n != 3
        tool = fanuc_frame(UT1) if framed else np.eye(4)
        U = fanuc_frame(UF1) if framed else np.eye(4)
        nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
        true_t = dataclasses.replace(true, tool=matrix_to_pose(tool))
        q_plan = np.radians([Q[n]])
        planned = np.linalg.inv(U) @ fk(nom_t, q_plan)[0]
        assert np.abs(t0.P[:3, 3] - planned[:3, 3]).max() < 1e-6
        X_d = np.linalg.inv(M) @ (U @ t0.P)[None]
        errs.append(pose_error(reached(true_t, nom_t, (U @ t1.P)[None], q_plan), X_d))
        before.append(pose_error(reached(true_t, nom_t, (U @ t0.P)[None], q_plan), X_d))
        cases.setdefault("ut1" if framed else "ut0", (true_t, nom_t, []))[2].append((X_d[0], q_plan[0], U @ t1.P))
    assert min(b[0][0] for b in before) > 2e-4
    # written 3 decimals of mm and of a degree: compensated ones get 3 and 5 (base.MIN_DECIMALS)
    assert max(e[0][0] for e in errs) < 2e-6 and max(e[1][0] for e in errs) < 5e-7
    # the task CSV's targets mode (`recal compensate --mode targets`) on the same desired poses,
    # its targets sent to the same controller: the program's targets are the CSV's to the rounding
    # of the written numbers, and reach as close
    prog_dp, prog_da, csv_dp, csv_da, diff_dp, diff_da = compare_with_csv_path(d, cases)
    assert csv_dp < 1e-8 and csv_da < 1e-7
    assert diff_dp < 2e-6 and diff_da < 5e-7
    assert prog_dp < csv_dp + 2e-6 and prog_da < csv_da + 5e-7


def test_report(run):
    d, *_ = run
    rep = json.loads((d / "rep.json").read_text())
    assert rep["mode"] == "fanuc-tp"
    rows = {p["variable"]: p for p in rep["points"]}
    for k in ("P[1]", "P[2]", "P[3]"):
        assert rows[k]["configuration"]["written"] == rows[k]["configuration"]["solution"]
        assert rows[k]["flags"] == []
    assert rows["P[2]"]["configuration"]["written"] == "N U T, 0, 0, 1"  # J6 = 200°: one turn
    assert rows["P[3]"]["configuration"]["written"].startswith("F")
    assert rows["P[1]"]["frames"] == "UF 1, UT 1"


@pytest.mark.parametrize(
    "body, message",
    [
        (
            "\tUF : 0, UT : 0,\t\tCONFIG : 'N U T, 0, 0, 0',\r\n\tX = 1.0 mm, Y = 2.0 mm, Z = 3.0 mm,\r\n"
            "\tW = 0.0 deg, P = 0.0 deg\r\n",
            r"prog\.ls, line 7: P\[1\]: expected component R",
        ),
        (
            "\tUF : 2, UT : 1,\t\tCONFIG : 'N U T, 0, 0, 0',\r\n\tX = 1.0 mm, Y = 2.0 mm, Z = 3.0 mm,\r\n"
            "\tW = 0.0 deg, P = 0.0 deg, R = 0.0 deg\r\n",
            r"prog\.ls, line 5: P\[1\]: UF 2 is not given: pass --base-frame 2=",
        ),
        (
            "\tUF : 0, UT : 0,\t\tCONFIG : 'N X T, 0, 0, 0',\r\n\tX = 1.0 mm, Y = 2.0 mm, Z = 3.0 mm,\r\n"
            "\tW = 0.0 deg, P = 0.0 deg, R = 0.0 deg\r\n",
            r"line 5: P\[1\]: CONFIG: expected 'F\|N U\|D T\|B",
        ),
    ],
)
def test_bad_programs_name_file_line_and_token(tmp_path, body, message):
    p = tmp_path / "prog.ls"
    p.write_bytes(("/PROG X\r\n/POS\r\nP[1]{\r\n   GP1:\r\n" + body + "};\r\n/END\r\n").encode())
    with pytest.raises(InputError, match=message):
        fanuc_tp.parse(p)


def test_bad_program_on_the_command_line_exits_2_without_output(run, tmp_path):
    d, *_ = run
    (tmp_path / "prog.ls").write_bytes(
        b"/PROG X\r\n/POS\r\nP[1]{\r\n   GP1:\r\n\tUF : 0, UT : 0,\t\tCONFIG : 'N U T, 0, 0, 0',\r\n"
        b"\tX = 1.0 mm, Y = 2.0 mm, Z = 3.0 mm,\r\n\tW = 0.0 deg, P = 0.0 deg\r\n};\r\n/END\r\n"
    )
    r = recal("compensate", "--model", d / "identified.json", "--task", "prog.ls", "--out", "out.ls", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith("recal compensate: prog.ls, line 7: P[1]: expected component R")
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out.ls").exists()


@pytest.mark.parametrize(
    "written, reachable",
    [
        ("N D T, 0, 0, 0", True),  # the elbow down: the arm reaches P[1] so too, and stays so
        ("F U T, 0, 0, 0", True),  # the wrist flipped
        ("N U T, 1, 0, 0", False),  # J1 a turn further: beyond its 170° limit
    ],
)
def test_the_written_configuration_is_kept_or_the_position_flagged_and_left_as_written(
    run, tmp_path, written, reachable
):
    """P[1]'s pose written in another configuration: compensated in that one (never moved to the
    configuration it was planned in), or, where the nominal arm cannot reach the pose so, left
    as written and flagged."""
    d, nominal, *_ = run
    T = fk(nominal, np.radians([Q[1]]))[0]
    lines = cartesian(T, Q[1], 0, 0)
    assert "'N U T, 0, 0, 0'" in lines[0]
    lines[0] = lines[0].replace("'N U T, 0, 0, 0'", f"'{written}'")
    data = "\r\n".join(
        ["/PROG  T", "/MN", "   1:J P[1] 100% FINE    ;", "/POS", "P[1]{", "   GP1:", *lines, "};", "/END", ""]
    )
    (tmp_path / "t.ls").write_text(data, newline="")
    r = recal(
        "compensate",
        "--model",
        d / "identified.json",
        "--task",
        "t.ls",
        "--out",
        "o.ls",
        "--report",
        "r.json",
        cwd=tmp_path,
    )
    # written either way; left as written is a shortfall: exit 3, the line naming the target
    assert r.returncode == (0 if reachable else 3), r.stderr
    if not reachable:
        assert r.stderr.strip().splitlines()[-1] == (
            "recal compensate: 1 of 1 targets not compensated (1 unreachable, left as written): "
            "t.ls, line 5 (P[1]) (rows in r.json)"
        )
    row = json.loads((tmp_path / "r.json").read_text())["points"][0]
    out = (tmp_path / "o.ls").read_bytes()
    if reachable:
        assert row["flags"] == [] and row["configuration"] == {"written": written, "solution": written}
        assert out != data.encode() and skeleton(out) == skeleton(data.encode())
    else:
        assert sorted(row["flags"]) == ["branch_change", "unreachable"] and row["compensated"] is None
        assert row["configuration"] == {"written": written, "solution": "N U T, 0, 0, 0"}
        assert out == data.encode()


def test_turn_numbers_count_j1_j4_j6(run, tmp_path):
    """J4 at 190° (past a half turn, within the M-20iA-like arm's ±200°): the controller writes
    'N U T, 0, 1, 0' (turns of J1, J4, J6; docs/compensation.md §7). Read that way the target is
    reached; read as J4, J5, J6 it was flagged unreachable. The J4, J5, J6 reading's string
    'N U T, 1, 0, 0' asks for a J1 turn the arm (±170°) cannot make: left alone, flagged."""
    d, nominal, true, *_ = run
    q = [20, 10, -20, 190, -40, 30]
    assert config(q) == "N U T, 0, 1, 0"
    X = fk(nominal, np.radians([q]))[0]
    rows = {}
    for written in ("N U T, 0, 1, 0", "N U T, 1, 0, 0"):
        lines = cartesian(X, q, 0, 0)
        lines[0] = lines[0].replace(config(q), written)
        text = "\r\n".join(
            ["/PROG  TURNS", "/MN", "   1:J P[1] 100% FINE    ;", "/POS", "P[1]{", "   GP1:", *lines, "};", "/END", ""]
        )
        (tmp_path / "turns.ls").write_text(text)
        r = recal(
            "compensate", "--model", d / "identified.json", "--task", "turns.ls", "--out", "out.ls", "--report", "r.json",
            cwd=tmp_path,
        )  # fmt: skip
        rows[written] = (json.loads((tmp_path / "r.json").read_text())["points"][0], r)
        (tmp_path / f"{written[-7:].replace(', ', '')}.ls").write_bytes((tmp_path / "out.ls").read_bytes())
    row, r = rows["N U T, 0, 1, 0"]
    assert row["flags"] == [] and row["configuration"]["solution"] == "N U T, 0, 1, 0", row
    t0 = fanuc_tp.parse(tmp_path / "turns.ls").targets[0]
    t1 = fanuc_tp.parse(tmp_path / "010.ls").targets[0]
    X_d = np.linalg.inv(frame_of(true, nominal)) @ t0.P[None]
    dp, da = pose_error(reached(true, nominal, t1.P[None], np.radians([q])), X_d)
    assert dp[0] < 1e-5 and math.degrees(da[0]) < 0.005
    row, r = rows["N U T, 1, 0, 0"]
    assert "unreachable" in row["flags"] and row["compensated"] is None


def test_uf_f_and_ut_f_take_the_frames_uframe_num_and_utool_num_select(tmp_path):
    """``UF : F`` / ``UT : F``: the frames active at run time, which /MN fixes with UFRAME_NUM=1 and
    UTOOL_NUM=1 before its first motion: P[1] is read in user frame 1 and tool frame 1, as when
    written ``UF : 1, UT : 1`` (it was refused before). Where a motion comes before the
    selection, the active frame is the controller's: refused, naming the line and why."""
    from service.programs.frames import Frames

    from .arms import arm

    data = program(arm("fanuc"))
    frames = Frames.from_options(["1=" + ",".join(map(str, UT1))], ["1=" + ",".join(map(str, UF1))])
    (tmp_path / "n.ls").write_bytes(data)
    (tmp_path / "f.ls").write_bytes(data.replace(b"UF : 1, UT : 1,", b"UF : F, UT : F,", 1))
    numbered, active = (
        fanuc_tp.parse(tmp_path / "n.ls", frames=frames),
        fanuc_tp.parse(tmp_path / "f.ls", frames=frames),
    )
    a, b = numbered.targets[0], active.targets[0]
    np.testing.assert_array_equal(a.T_work, b.T_work)
    np.testing.assert_array_equal(a.T_tool, b.T_tool)
    assert b.frames == "UF 1 (F: UFRAME_NUM=1), UT 1 (F: UTOOL_NUM=1)", b.frames
    late = data.replace(b"UF : 1, UT : 1,", b"UF : F, UT : F,", 1).replace(
        b"   1:  UFRAME_NUM=1 ;\r\n   2:  UTOOL_NUM=1 ;\r\n   3:J P[1]",
        b"   1:J P[1] 100% FINE ;\r\n   2:  UFRAME_NUM=1 ;\r\n   3:  UTOOL_NUM=1 ;\r\n   4:J P[1]",
    )
    (tmp_path / "late.ls").write_bytes(late)
    with pytest.raises(InputError, match=r"line \d+: P\[1\]: UF : F .*: a motion comes before UFRAME_NUM=1"):
        fanuc_tp.parse(tmp_path / "late.ls", frames=frames)
