"""`recal compensate` on a KUKA KRL program written for this test (a .src and its .dat):
declarations in the .dat (one with two targets, an array element, an FDAT), an inline form fold
(a comment that looks like a move) whose body selects the frames through FDAT_ACT, $TOOL/$BASE
assignments, inline targets, a relative move and an expression use. Frames come from a
$config.dat and --tool-frame. The compensated targets bring a simulated true robot to the poses
the program means; every other byte of both files is unchanged."""

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
from service.programs import krl

from .arms import arm
from .helpers import compare_with_csv_path, frame_of, models, numbers, pose_error, reached, recal, skeleton

Q = {  # planned joints (deg)
    "XP1": [10, -80, 100, 20, 40, -30],
    "XP2": [20, -70, 80, -30, 60, 45],
    "XP3": [30, -60, -10, 40, -50, 10],
    "XP4[2]": [40, -75, 95, 170, 35, -200],
    "inline1": [-20, -85, 110, 10, 50, 0.5],
    "inline2": [-35, -95, 120, -60, 70, 30],
}
TOOL1 = (5.0, -2.0, 180.0, 0.0, 30.0, 0.0)  # X, Y, Z, A, B, C
BASE2 = (1000.0, -500.0, 200.0, 30.0, 0.0, 0.0)


def kuka_frame(v):
    """X, Y, Z, A, B, C (mm, deg; R = Rz(A)·Ry(B)·Rx(C)) written out here with rpy (rx=C, ry=B, rz=A)."""
    return homogeneous(rpy_to_matrix(np.radians([v[5], v[4], v[3]])), np.array(v[:3]) * 1e-3)


def abc(R):
    """KUKA A, B, C (deg) of R, computed here: B = -asin(r31), A = atan2(r21, r11), C = atan2(r32, r33)."""
    return np.degrees([math.atan2(R[1, 0], R[0, 0]), -math.asin(R[2, 0]), math.atan2(R[2, 1], R[2, 2])])


def status_turn(q_deg):
    """S and T of the KUKA-like arm, from its geometry (tests/programs/arms.py): the A1 frame turns
    by -A1 (gain -1); φ = atan(35/670), where the wrist root point is in line with A2 and A3."""
    q = np.radians(q_deg)
    T = fk(arm("kuka"), q[None])[0]
    w = T[:3, 3] - 0.115 * T[:3, 2]
    overhead = w[0] * math.cos(-q[0]) + w[1] * math.sin(-q[0]) - 0.0 < 0
    phi = math.degrees(math.atan2(35, 670))
    S = int(overhead) + 2 * (q_deg[2] >= phi) + 4 * (math.sin(q[4]) < 0)
    return S, sum(1 << i for i in range(6) if q_deg[i] < 0)


def e6pos(T, q):
    S, Tb = status_turn(q)
    p, a = T[:3, 3] * 1e3, abc(T[:3, :3])
    return "{X %.3f,Y %.3f,Z %.3f,A %.4f,B %.4f,C %.4f,S %d,T %d,E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}" % (
        *p,
        *a,
        S,
        Tb,
    )


def program(nominal):
    tool = kuka_frame(TOOL1)
    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
    B = kuka_frame(BASE2)
    pos = {}
    for name, q in Q.items():
        if name == "inline2":
            pos[name] = fk(nominal, np.radians([q]))[0]
        else:
            pos[name] = np.linalg.inv(B) @ fk(nom_t, np.radians([q]))[0]
    inline = {k: e6pos(pos[k], Q[k]).split(",S ")[0].replace(",", ", ") + "}" for k in ("inline1", "inline2")}
    src = (
        "\n".join(
            [
                "&ACCESS RVP",
                "&REL 3",
                "DEF recal_test( )",
                "; written for Recal's tests. Not a move: LIN {X 1, Y 2, Z 3, A 0, B 0, C 0}",
                "; Greifer geöffnet, 90° gedreht (Windows-1252, as KUKA's editor writes: not UTF-8)",
                ";FOLD INI;%{PE}",
                "  ;FOLD BASISTECH INI",
                "    BAS (#INITMOV,0 )",
                "  ;ENDFOLD",
                ";ENDFOLD",
                "PTP XHOME1",
                ";FOLD PTP P1 Vel=100 % PDAT1 Tool[1] Base[2];%{PE}%R 8.3.31,%MKUKATPBASIS,%CMOVE,%VPTP,%P 1:PTP, 2:P1",
                "$BWDSTART=FALSE",
                "PDAT_ACT=PPDAT1",
                "FDAT_ACT=FP1",
                "BAS(#PTP_PARAMS,100)",
                "PTP XP1 ",
                ";ENDFOLD",
                "LIN XP2 C_DIS",
                "CIRC XP3, XP4[2] C_DIS\t; arc",
                f"LIN {inline['inline1']} C_DIS ; inline, TOOL_DATA[1] and BASE_DATA[2]",
                "$TOOL = $NULLFRAME",
                "$BASE=$NULLFRAME",
                f"LIN {inline['inline2']}",
                "LIN_REL {Z 10}",
                "XP2.Z = XP2.Z + 10",
                "END",
            ]
        )
        + "\n"
    )
    dat = "\r\n".join(
        [
            "&ACCESS RVP",
            "&REL 3",
            "DEFDAT recal_test",
            ";FOLD EXTERNAL DECLARATIONS;%{PE}%V3.2.0,%MKUKATPBASIS,%CEXT,%VCOMMON,%P",
            ";ENDFOLD (EXTERNAL DECLARATIONS)",
            "; DECL E6POS XOLD={X 1,Y 2,Z 3,A 0,B 0,C 0,S 2,T 2} (a comment)",
            "DECL E6AXIS XHOME1={A1 0.0,A2 -90.0,A3 90.0,A4 0.0,A5 30.0,A6 0.0,E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}",
            f"DECL E6POS XP1={e6pos(pos['XP1'], Q['XP1'])} ; Übergabe – Lage ±0,5 mm",
            'DECL FDAT FP1={TOOL_NO 1,BASE_NO 2,IPO_FRAME #BASE,POINT2[] " ",TQ_STATE FALSE}',
            "DECL PDAT PPDAT1={VEL 100.000,ACC 100.000,APO_DIST 100.000,APO_MODE #CDIS}",
            f"DECL E6POS XP2={e6pos(pos['XP2'], Q['XP2'])},XP3={e6pos(pos['XP3'], Q['XP3'])}",
            "DECL E6POS XP4[3]",
            f"XP4[2]={e6pos(pos['XP4[2]'], Q['XP4[2]'])}",
            "ENDDAT",
            "",
        ]
    )
    return src.encode("cp1252"), dat.encode("cp1252")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("krl")
    nominal, true = models(d, "kuka")
    src, dat = program(nominal)
    (d / "recal_test.src").write_bytes(src)
    (d / "recal_test.dat").write_bytes(dat)
    (d / "config.dat").write_text(
        "DEFDAT $CONFIG\nDECL FRAME BASE_DATA[32]\nBASE_DATA[2]={X %s,Y %s,Z %s,A %s,B %s,C %s}\nENDDAT\n" % BASE2
    )
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "recal_test.src",
        "--out",
        "out.src",
        "--config-dat",
        "config.dat",
        "--tool-frame",
        "1=" + ",".join(map(str, TOOL1)),
        "--report",
        "rep.json",
        cwd=d,
    )
    return d, nominal, true, src, dat, r


def test_both_files_keep_every_byte_but_the_targets_numbers(run):
    d, _nominal, _true, src, dat, r = run
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 7 points (KRL): 7 converged"), r.stdout
    assert "wrote out.src, out.dat" in r.stdout
    out_src, out_dat = (d / "out.src").read_bytes(), (d / "out.dat").read_bytes()
    assert skeleton(out_src) == skeleton(src) and skeleton(out_dat) == skeleton(dat)
    assert out_dat.count(b"\r\n") == dat.count(b"\r\n")
    # Windows-1252 bytes (not UTF-8) as read, in a comment line and after a target on its line
    assert b"ge\xf6ffnet, 90\xb0" in out_src and b"\xdcbergabe \x96 Lage \xb10,5 mm\r\n" in out_dat
    for a, b in zip(src.splitlines() + dat.splitlines(), out_src.splitlines() + out_dat.splitlines()):
        if a.lstrip().startswith(b";") or b"FDAT" in a or b"PDAT" in a or b"_REL" in a:
            assert a == b
    st = re.compile(rb",S \d+,T \d+,E1[^}]*")  # status, turn and external axes as written
    assert st.findall(out_dat) == st.findall(dat) and len(st.findall(dat)) == 4
    changed = [(a, b) for a, b in zip(numbers(src + dat), numbers(out_src + out_dat)) if a != b]
    assert 30 <= len(changed) <= 6 * 7
    assert "XP2.Z = XP2.Z + 10" in r.stderr and "LIN_REL moves relative" in r.stderr


def test_compensated_targets_bring_the_true_robot_to_the_program_poses(run):
    d, nominal, true, _src, _dat, _r = run
    M = frame_of(true, nominal)
    old = krl.parse(d / "recal_test.src", frames=_frames(d))
    new = krl.parse(d / "out.src", frames=_frames(d))
    assert [t.name for t in old.targets] == [t.name for t in new.targets]
    errs, before, cases = [], [], {}
    names = {t.name or ("inline1" if t.frames.startswith("tool TOOL") else "inline2") for t in old.targets}
    assert names == set(Q) | {"XHOME1"}
    for t0, t1 in zip(old.targets, new.targets):
        if t0.kind != "pose":
            continue
        key = t0.name or ("inline1" if t0.frames.startswith("tool TOOL") else "inline2")
        framed = key != "inline2"
        tool = kuka_frame(TOOL1) if framed else np.eye(4)
        B = kuka_frame(BASE2) if framed else np.eye(4)
        nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
        true_t = dataclasses.replace(true, tool=matrix_to_pose(tool))
        q_plan = np.radians([Q[key]])
        planned = np.linalg.inv(B) @ fk(nom_t, q_plan)[0]
        assert np.abs(t0.P[:3, 3] - planned[:3, 3]).max() < 1e-6  # the parser reads what was written
        X_d = np.linalg.inv(M) @ (B @ t0.P)[None]
        errs.append(pose_error(reached(true_t, nom_t, (B @ t1.P)[None], q_plan), X_d))
        before.append(pose_error(reached(true_t, nom_t, (B @ t0.P)[None], q_plan), X_d))
        cases.setdefault("tool1" if framed else "flange", (true_t, nom_t, []))[2].append((X_d[0], q_plan[0], B @ t1.P))
    assert min(b[0][0] for b in before) > 2e-4
    assert max(e[0][0] for e in errs) < 2e-6 and max(e[1][0] for e in errs) < 5e-7
    # the task CSV's targets mode (`recal compensate --mode targets`) on the same desired poses,
    # its targets sent to the same controller: the program's targets are the CSV's to the rounding
    # of the written numbers (3 decimals of mm, 5 of a degree), and reach as close
    prog_dp, prog_da, csv_dp, csv_da, diff_dp, diff_da = compare_with_csv_path(d, cases)
    assert csv_dp < 1e-8 and csv_da < 1e-7
    assert diff_dp < 2e-6 and diff_da < 5e-7
    assert prog_dp < csv_dp + 2e-6 and prog_da < csv_da + 5e-7


def _frames(d):
    from service.programs.frames import Frames

    return Frames.from_options(["1=" + ",".join(map(str, TOOL1))], [], str(d / "config.dat"))


def test_report_and_configuration(run):
    d, *_ = run
    rep = json.loads((d / "rep.json").read_text())
    assert rep["mode"] == "krl"
    rows = [p for p in rep["points"] if p["kind"] == "pose"]
    stated = [p for p in rows if p["configuration"]["written"] is not None]
    assert len(stated) == 4  # the .dat's E6POS; the inline targets write no S and T
    assert all(p["configuration"]["written"] == p["configuration"]["solution"] for p in stated)
    assert {p["configuration"]["written"]["S"] & 2 for p in stated} == {0, 2}  # both elbows (A3 vs φ)
    assert {p["file"].rsplit("/", 1)[-1] for p in rep["points"]} == {"recal_test.src", "recal_test.dat"}
    xp1 = next(p for p in rows if p["variable"] == "XP1")
    assert xp1["frames"] == "tool TOOL_DATA[1] (--tool-frame), base BASE_DATA[2] ($config.dat)"


@pytest.mark.parametrize(
    "src, dat, message",
    [
        (
            "DEF t( )\n$TOOL = TOOL_DATA[3]\nLIN XP1\nEND\n",
            "DEFDAT t\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0,C 0}\nENDDAT\n",
            r"t\.src, line 3: TOOL_DATA\[3\] is selected here but not given: pass --tool-frame 3=X,Y,Z,A,B,C",
        ),
        (
            "DEF t( )\nLIN XP1\nEND\n",
            "DEFDAT t\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0}\nENDDAT\n",
            r"t\.dat, line 2: E6POS XP1: expected component C",
        ),
        (
            "DEF t( )\nPTP XA\nEND\n",
            "DEFDAT t\nDECL E6AXIS XA={A1 0,A2 -90,A3 9O,A4 0,A5 0,A6 0}\nENDDAT\n",
            r"t\.dat, line 2: E6AXIS XA: component A3: expected a number, got '9O'",
        ),
        (
            "DEF t( )\n$TOOL = MYTOOL\nLIN XP1\nEND\n",
            "DEFDAT t\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0,C 0}\nENDDAT\n",
            r"t\.src, line 3: \$TOOL = MYTOOL: Recal cannot resolve this tool frame",
        ),
    ],
)
def test_bad_programs_name_file_line_and_token(tmp_path, src, dat, message):
    (tmp_path / "t.src").write_text(src)
    (tmp_path / "t.dat").write_text(dat)
    with pytest.raises(InputError, match=message):
        krl.parse(tmp_path / "t.src")


def test_bad_program_on_the_command_line_exits_2_and_writes_neither_file(run, tmp_path):
    d, *_ = run
    (tmp_path / "t.src").write_text("DEF t( )\nLIN XP1\nEND\n")
    (tmp_path / "t.dat").write_text("DEFDAT t\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0}\nENDDAT\n")
    r = recal("compensate", "--model", d / "identified.json", "--task", "t.src", "--out", "o.src", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == "recal compensate: t.dat, line 2: E6POS XP1: expected component C"
    assert not (tmp_path / "o.src").exists() and not (tmp_path / "o.dat").exists()


def test_a_target_out_of_reach_in_its_written_configuration_is_flagged_and_left_as_written(run, tmp_path):
    """XP1 written with S 0 (the other elbow) and its T: the nominal arm has no solution with
    both, so the target is not flipped to the one it has (S 2): left as written, flagged."""
    d, nominal, *_ = run
    q = Q["XP1"]
    S, Tb = status_turn(q)
    assert (S, Tb) == (2, 34)
    line = e6pos(fk(nominal, np.radians([q]))[0], q).replace(",S 2,", ",S 0,")
    (tmp_path / "t.src").write_text("DEF t( )\nLIN XP1\nEND\n")
    dat = "DEFDAT t\nDECL E6POS XP1=" + line + "\nENDDAT\n"
    (tmp_path / "t.dat").write_text(dat)
    r = recal(
        "compensate",
        "--model",
        d / "identified.json",
        "--task",
        "t.src",
        "--out",
        "o.src",
        "--report",
        "r.json",
        cwd=tmp_path,
    )
    assert r.returncode == 3, r.stderr  # written, with a shortfall the last line names
    assert r.stderr.strip().splitlines()[-1] == (
        "recal compensate: 1 of 1 targets not compensated (1 unreachable, left as written): "
        "t.dat, line 2 (XP1) (rows in r.json)"
    )
    row = json.loads((tmp_path / "r.json").read_text())["points"][0]
    assert sorted(row["flags"]) == ["branch_change", "unreachable"] and row["compensated"] is None
    assert row["configuration"] == {"written": {"S": 0, "T": 34}, "solution": {"S": 2, "T": 34}}
    assert (tmp_path / "o.dat").read_text() == dat


def test_inline_ptp_axis_and_circ_auxiliary_and_end_points(run, tmp_path):
    """Targets written in the moves: a PTP to an axis aggregate, a CIRC through an auxiliary point
    to an end point (no S and T: the solutions nearest the previous target's, as the controller
    moves from there). Each is compensated in place; the true robot reaches what each means."""
    d, nominal, true, *_ = run
    M = frame_of(true, nominal)
    q_ptp, q_aux, q_end = [10, -80, 100, 20, 40, -30], [15, -78, 98, 22, 42, -28], [20, -75, 95, 25, 45, -25]

    def inline(q):
        T = fk(nominal, np.radians([q]))[0]
        p, a = T[:3, 3] * 1e3, abc(T[:3, :3])
        return "{X %.3f, Y %.3f, Z %.3f, A %.4f, B %.4f, C %.4f}" % (*p, *a)

    axis = "{A1 %.1f, A2 %.1f, A3 %.1f, A4 %.1f, A5 %.1f, A6 %.1f}" % tuple(q_ptp)
    src = f"DEF t( )\n; PTP {axis}\nPTP {axis} C_PTP\nCIRC {inline(q_aux)}, {inline(q_end)} C_DIS ; arc\nEND\n"
    (tmp_path / "t.src").write_text(src)
    (tmp_path / "t.dat").write_text("DEFDAT t\nENDDAT\n")
    r = recal("compensate", "--model", d / "identified.json", "--task", "t.src", "--out", "o.src", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 3 points (KRL): 3 converged"), r.stdout
    out = (tmp_path / "o.src").read_text()
    assert skeleton(out.encode()) == skeleton(src.encode()) and out.splitlines()[1] == src.splitlines()[1]
    old, new = krl.parse(tmp_path / "t.src"), krl.parse(tmp_path / "o.src")
    assert [(t.kind, t.move, t.line) for t in new.targets] == [
        ("joints", "PTP", 3),
        ("pose", "CIRC", 4),
        ("pose", "CIRC", 4),
    ]
    X_d = np.linalg.inv(M) @ fk(nominal, np.radians([q_ptp]))
    dp, da = pose_error(fk(true, new.targets[0].q[None]), X_d)
    assert dp[0] < 2e-6 and da[0] < 5e-7
    for t0, t1, q in zip(old.targets[1:], new.targets[1:], (q_aux, q_end)):
        X_d = np.linalg.inv(M) @ t0.P[None]
        dp, da = pose_error(reached(true, nominal, t1.P[None], np.radians([q])), X_d)
        assert dp[0] < 2e-6 and da[0] < 5e-7
        before = pose_error(reached(true, nominal, t0.P[None], np.radians([q])), X_d)[0][0]
        assert before > 2e-4


def test_pos_and_axis_declarations_and_status_written_in_binary(tmp_path):
    """POS and AXIS are read as E6POS and E6AXIS are; S and T written as KRL's bit strings."""
    (tmp_path / "t.src").write_text("DEF t( )\nPTP XA\nLIN XP1\nEND\n")
    (tmp_path / "t.dat").write_text(
        "DEFDAT t\nDECL AXIS XA={A1 0.0,A2 -90.0,A3 90.0,A4 0.0,A5 30.0,A6 0.0}\n"
        "DECL POS XP1={X 900.0,Y 0.0,Z 1200.0,A 0.0,B 90.0,C 0.0,S 'B010',T 'B100010'}\nENDDAT\n"
    )
    prog = krl.parse(tmp_path / "t.src")
    assert [(t.name, t.kind, t.line) for t in prog.targets] == [("XA", "joints", 2), ("XP1", "pose", 3)]
    np.testing.assert_allclose(np.degrees(prog.targets[0].q), [0, -90, 90, 0, 30, 0])
    assert prog.targets[1].config == (2, 34)
    np.testing.assert_allclose(prog.targets[1].P[:3, 3], [0.9, 0.0, 1.2])
