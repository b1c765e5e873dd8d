"""`recal compensate` on an ABB RAPID module written for this test: declarations (CONST, PERS,
VAR, LOCAL, TASK, an array of several targets), a statement continued over lines, a tool and a
work object declared in the module, inline targets, a target inside a comment, an expression
target, CRLF line endings and a byte that is not UTF-8. The compensated targets, sent to a
controller that knows only the nominal model, bring a simulated true robot to the poses the
program means; every byte that is not a target's number is unchanged."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from calibration.compensation import compensate_targets
from calibration.kinematics import fk
from calibration.transforms import homogeneous, matrix_to_quat, quat_to_matrix
from service.files import InputError
from service.programs import rapid

from .helpers import compare_with_csv_path, frame_of, models, numbers, pose_error, reached, recal, skeleton

DEG = math.pi / 180
Q = {  # planned joints (deg): the configurations the program was written for
    "pApp": [20, 10, -20, 30, 50, -40],
    "pWeld": [25, 20, -10, -40, 60, 70],
    "path{1}": [30, 15, -5, 10, 45, 100],
    "path{2}": [35, 18, 0, 200, -50, 20],
    "path{3}": [-40, 5, 10, -150, 70, -300],
    "inline": [-60, 30, -30, 5, 80, 10],
}
TOOL = np.array([[10.5, -3.0, 150.0], [0.9961947, 0.0, 0.0871557, 0.0]], dtype=object)
UFRAME = ([900.0, -250.0, 320.0], [0.9659258, 0.0, 0.0, 0.2588190])


def pose(p, q):
    return homogeneous(quat_to_matrix(np.array(q, float)), np.array(p, float) * 1e-3)


def T_tool():
    return pose(TOOL[0], TOOL[1])


def T_wobj():
    return pose(*UFRAME)


def confdata(q_deg):
    """ABB confdata written here from the ABB-like arm's geometry (tests/programs/arms.py), not
    from calibration.vendors: quadrants of axes 1, 4, 6; the wrist centre behind axis 1 when its
    horizontal reach along the arm's heading is negative; behind the lower arm when axis 3 is
    below the stretched angle -(90° - atan(175/960))."""
    q = np.radians(q_deg)
    from .arms import arm

    m = arm("abb")
    T = fk(m, q[None])[0]
    w = T[:3, 3] - 0.135 * T[:3, 2]
    back = w[0] * math.cos(q[0]) + w[1] * math.sin(q[0]) < 0
    behind = q_deg[2] < -(90 - math.degrees(math.atan2(175, 960)))
    return [math.floor(v / 90) for v in (q_deg[0], q_deg[3], q_deg[5])] + [4 * back + 2 * behind + (q_deg[4] < 0)]


def robtarget(T, conf, digits=(2, 7)):
    p = T[:3, 3] * 1e3
    quat = matrix_to_quat(T[:3, :3])
    return (
        "[["
        + ",".join(f"{v:.{digits[0]}f}" for v in p)
        + "],["
        + ",".join(f"{v:.{digits[1]}f}" for v in quat)
        + "],["
        + ",".join(str(c) for c in conf)
        + "],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]"
    )


def program(nominal):
    import dataclasses

    from calibration.transforms import matrix_to_pose

    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(T_tool()))
    W = T_wobj()
    rt = {}
    for name, q in Q.items():
        T = fk(nominal, np.radians([q]))[0] if name == "inline" else np.linalg.inv(W) @ fk(nom_t, np.radians([q]))[0]
        rt[name] = robtarget(T, confdata(q))
    weld = rt["pWeld"].split("],[")
    lines = [
        "%%%",
        "  VERSION:1",
        "%%%",
        "MODULE RecalTest",
        "  ! written for Recal's tests; not a target: MoveL [[1,2,3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]], v1, fine, tool0;",
        "  ! Gr\xfc\xdfe: a Latin-1 byte follows \udce9",
        "  PERS tooldata tGun:=[TRUE,[[10.5,-3,150],[0.9961947,0,0.0871557,0]],[2.5,[0,0,80],[1,0,0,0],0,0,0]];",
        '  TASK PERS wobjdata wTable:=[FALSE,TRUE,"",[[900,-250,320],[0.9659258,0,0,0.2588190]],[[0,0,0],[1,0,0,0]]];',
        f"  CONST robtarget pApp:={rt['pApp']};",
        f"  LOCAL CONST robtarget pWeld:={weld[0]}],",
        f"      [{weld[1]}],   ! orientation on its own line",
        f"      [{weld[2]}],[{weld[3]};",
        f"  VAR robtarget path{{3}}:=[{rt['path{1}']},\t{rt['path{2}']},",
        f"    {rt['path{3}']}];",
        "  CONST jointtarget jHome:=[[0,-10,20,0,60,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];",
        "  CONST robtarget pSpare:=[[1,2,3],[1,0,0,0],[0,0,0,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];",
        "",
        "  PROC main()",
        "    MoveAbsJ jHome\\NoEOffs, v1000, fine, tool0;",
        "    MoveJ pApp, v1000, z50, tGun\\WObj:=wTable;",
        "    TriggL pApp, v200, gunOn, z10, tGun\\WObj:=wTable;",
        "    MoveL pWeld, v200, fine, tGun \\WObj:=wTable;  ! weld start",
        "    MoveL Offs(pWeld,0,0,50), v200, z10, tGun\\WObj:=wTable;",
        "    MoveC path{1}, path{2}, v100, z5, tGun\\WObj:=wTable;",
        "    MoveL path{3}, v100, fine, tGun\\WObj:=wTable;",
        f"    MoveL {rt['inline']}, v500,",
        "          z10, tool0;",
        "    ! MoveL pApp, v100, fine, tool0;",
        "  ENDPROC",
        "ENDMODULE",
    ]
    return "\r\n".join(lines).encode("utf-8", "surrogateescape")  # no final newline


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("rapid")
    nominal, true = models(d, "abb")
    data = program(nominal)
    (d / "prog.mod").write_bytes(data)
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "prog.mod",
        "--out",
        "out.mod",
        "--report",
        "rep.json",
        cwd=d,
    )
    return d, nominal, true, data, r


def test_every_byte_but_the_targets_numbers_is_unchanged(run):
    d, _nominal, _true, data, r = run
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("compensated 7 points (RAPID): 7 converged"), r.stdout
    out = (d / "out.mod").read_bytes()
    assert skeleton(out) == skeleton(data)
    assert out.count(b"\r\n") == data.count(b"\r\n") and not out.endswith(b"\n")
    assert b"\xe9" in out  # the byte that is not UTF-8
    changed = [(a, b) for a, b in zip(numbers(data), numbers(out)) if a != b]
    assert 7 * 6 <= len(changed) <= 7 * 7  # positions, orientations and joints; nothing else
    for line_in, line_out in zip(data.split(b"\r\n"), out.split(b"\r\n")):
        if (
            line_in.strip().startswith(b"!")
            or b"tooldata" in line_in
            or b"wobjdata" in line_in
            or b"pSpare" in line_in
            or b"Offs" in line_in
        ):
            assert line_in == line_out
    # configurations and external axes as written
    conf = re.compile(rb"\],\s*\[(-?\d+,-?\d+,-?\d+,\d)\],\s*\[9E\+09")
    assert conf.findall(out) == conf.findall(data)
    warn = r.stderr
    assert "Offs(pWeld" in warn and "pSpare is not the target of a move" in warn
    assert "TriggL" not in warn  # pApp, same tool and work object as its MoveJ: one target


def test_compensated_targets_bring_the_true_robot_to_the_program_poses(run):
    """Sent to the nominal controller, the new targets put the true robot where the written ones
    mean, as closely as the task CSV's targets mode (1e-9 m) plus the rounding of the written
    numbers (3 decimals of mm, 8 of the quaternion)."""
    import dataclasses

    from calibration.transforms import matrix_to_pose

    d, nominal, true, _data, _r = run
    M = frame_of(true, nominal)
    old = rapid.parse(d / "prog.mod")
    new = rapid.parse(d / "out.mod")
    assert [t.name for t in old.targets] == [t.name for t in new.targets]
    errs, before, cases = [], [], {}
    for t0, t1 in zip(old.targets, new.targets):
        if t0.kind != "pose":
            continue
        tool = T_tool() if t0.name else np.eye(4)
        W = T_wobj() if t0.name else np.eye(4)
        nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
        true_t = dataclasses.replace(true, tool=matrix_to_pose(tool))
        q_plan = np.radians([Q[t0.name or "inline"]])
        X_d = np.linalg.inv(M) @ (W @ t0.P)[None]  # what the written target means, world frame
        # the parser reads what was written: the planned pose, to the written 2 decimals of mm
        planned = np.linalg.inv(W) @ fk(nom_t, q_plan)[0]
        assert np.abs(t0.P[:3, 3] - planned[:3, 3]).max() < 6e-6
        np.testing.assert_allclose(t0.P[:3, :3], planned[:3, :3], atol=1e-6)
        errs.append(pose_error(reached(true_t, nom_t, (W @ t1.P)[None], q_plan), X_d))
        before.append(pose_error(reached(true_t, nom_t, (W @ t0.P)[None], q_plan), X_d))
        # the same pose through the library call the task CSV's targets mode makes
        csv = compensate_targets(true_t, nom_t, X_d, q_plan, T_nominal_world=M)
        assert csv.residual_m[0] < 1e-9
        cases.setdefault("tGun" if t0.name else "tool0", (true_t, nom_t, []))[2].append((X_d[0], q_plan[0], W @ t1.P))
    dp = np.array([e[0][0] for e in errs])
    da = np.array([e[1][0] for e in errs])
    assert np.array([b[0][0] for b in before]).min() > 2e-4  # the true robot is 0.2 mm+ off uncompensated
    assert dp.max() < 2e-6 and da.max() < 5e-8
    # the task CSV's targets mode (`recal compensate --mode targets`) on the same desired poses,
    # its targets sent to the same controller: the program's targets are the CSV's to the rounding
    # of the written numbers (3 decimals of mm, 8 of the quaternion), and reach as close
    prog_dp, prog_da, csv_dp, csv_da, diff_dp, diff_da = compare_with_csv_path(d, cases)
    assert csv_dp < 1e-8 and csv_da < 1e-7
    assert diff_dp < 1e-6 and diff_da < 5e-8
    assert prog_dp < csv_dp + 1e-6 and prog_da < csv_da + 5e-8


def test_joint_target_reaches_the_pose_the_nominal_joints_meant(run):
    d, nominal, true, _data, _r = run
    M = frame_of(true, nominal)
    new = rapid.parse(d / "out.mod")
    j = next(t for t in new.targets if t.kind == "joints")
    X_d = np.linalg.inv(M) @ fk(nominal, np.radians([[0, -10, 20, 0, 60, 0]]))
    dp, da = pose_error(fk(true, j.q[None]), X_d)
    assert dp[0] < 2e-6 and da[0] < 5e-7  # 5 decimals of a degree


def test_report_rows(run):
    import json

    d, *_ = run
    rep = json.loads((d / "rep.json").read_text())
    assert rep["mode"] == "rapid" and rep["summary"]["points"] == 7
    rows = {p["variable"]: p for p in rep["points"]}
    assert rows["path{2}"]["configuration"]["written"] == rows["path{2}"]["configuration"]["solution"]
    assert rows["pWeld"]["frames"] == "tool tGun, wobj wTable"
    assert all(p["flags"] == [] or "branch_change" not in p["flags"] for p in rep["points"])


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "MODULE m\n  CONST robtarget p20:=[[1,2,3],[1,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
            "  PROC main()\n    MoveL p20, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n",
            r"prog\.mod, line 2: robtarget p20: expected 4 quaternion values, got 3",
        ),
        (
            "MODULE m\n  PROC main()\n    MoveL [[1,2,3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]], v100, fine,\n"
            "      tGlue;\n  ENDPROC\nENDMODULE\n",
            r"prog\.mod, line 3: MoveL: tooldata tGlue is not declared in this module; pass the module that declares it \(--module SYSMOD\.sys\) or --tool-frame tGlue=X,Y,Z,Q1,Q2,Q3,Q4",
        ),
        (
            "MODULE m\n  PROC main()\n    MoveJ [[1,2,3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]], v100, fine, tool0"
            "\\WObj:=wMoving;\n  ENDPROC\nENDMODULE\n",
            r"line 3: MoveJ: wobjdata wMoving is not declared",
        ),
        (
            "MODULE m\n  CONST robtarget p1:=[[1,2,x3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
            "  PROC main()\n    MoveL p1, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n",
            r"line 2: robtarget p1: position: expected a number, got 'x3'",
        ),
    ],
)
def test_bad_programs_name_file_line_and_token(tmp_path, text, message):
    p = tmp_path / "prog.mod"
    p.write_text(text)
    with pytest.raises(InputError, match=message):
        rapid.parse(p)


def test_bad_program_on_the_command_line_exits_2_without_output(run, tmp_path):
    d, *_ = run
    (tmp_path / "prog.mod").write_text(
        "MODULE m\n  CONST robtarget p20:=[[1,2,3],[1,0,0],[0,0,0,0],[9E9]];\n"
        "  PROC main()\n    MoveL p20, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n"
    )
    r = recal("compensate", "--model", d / "identified.json", "--task", "prog.mod", "--out", "out.mod", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == (
        "recal compensate: prog.mod, line 2: robtarget p20: expected 4 quaternion values, got 3"
    )
    assert not (tmp_path / "out.mod").exists()


def _one_target_module(nominal, q, conf):
    T = fk(nominal, np.radians([q]))[0]
    return (
        "MODULE m\n  CONST robtarget p1:=" + robtarget(T, conf, (3, 8)) + ";\n  PROC main()\n"
        "    MoveL p1, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n"
    )


def test_a_configuration_the_compensation_leaves_is_flagged_not_rewritten(run, tmp_path):
    """Axis 4 planned exactly at 90°: the written cf4 may say quadrant 0 or 1. The correction moves
    axis 4 to one side; the target whose cf4 names the other is flagged branch_change, and both
    keep their written configuration."""
    import json

    d, nominal, *_ = run
    q = [20, 10, -20, 90, 50, -40]
    flagged = []
    for cf4 in (0, 1):
        conf = confdata(q)
        conf[1] = cf4
        (tmp_path / f"q{cf4}.mod").write_text(_one_target_module(nominal, q, conf))
        r = recal(
            "compensate",
            "--model",
            d / "identified.json",
            "--task",
            f"q{cf4}.mod",
            "--out",
            f"o{cf4}.mod",
            "--report",
            f"r{cf4}.json",
            cwd=tmp_path,
        )
        assert r.returncode == 0, r.stderr
        assert f"[0,{cf4},-1,0]" in (tmp_path / f"o{cf4}.mod").read_text()
        row = json.loads((tmp_path / f"r{cf4}.json").read_text())["points"][0]
        flagged.append("branch_change" in row["flags"])
        assert row["configuration"]["written"][1] == cf4
    assert sorted(flagged) == [False, True]


def test_a_target_out_of_reach_in_its_written_configuration_is_left_as_written(run, tmp_path):
    d, nominal, *_ = run
    q = [20, 10, -20, 30, 50, -40]
    conf = confdata(q)
    conf[0] = 1  # axis 1 in 90°..180° with the wrist in front: not this pose
    text = _one_target_module(nominal, q, conf)
    (tmp_path / "m.mod").write_text(text)
    r = recal("compensate", "--model", d / "identified.json", "--task", "m.mod", "--out", "o.mod", cwd=tmp_path)
    assert r.returncode == 3, r.stderr  # written, with a shortfall: left as written
    assert "1 of 1 targets not compensated (1 unreachable, left as written): m.mod, line 2 (p1)" in r.stderr
    assert "unreachable 1" in r.stdout and "0 converged" in r.stdout
    assert (tmp_path / "o.mod").read_text() == text


def test_a_target_used_with_two_tools_is_left_alone_and_reported(tmp_path):
    p = tmp_path / "m.mod"
    p.write_text(
        "MODULE m\n  PERS tooldata tA:=[TRUE,[[0,0,100],[1,0,0,0]],[1,[0,0,1],[1,0,0,0],0,0,0]];\n"
        "  CONST robtarget p1:=[[900,0,900],[0,0,1,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
        "  PROC main()\n    MoveL p1, v100, fine, tool0;\n    MoveL p1, v100, fine, tA;\n  ENDPROC\n"
        "ENDMODULE\n"
    )
    prog = rapid.parse(p)
    assert prog.targets == []
    assert [(u.line, u.reason) for u in prog.uninterpreted] == [
        (3, "robtarget p1 is used with different tools or work objects (lines 5, 6): not compensated")
    ]


def test_format_option_and_nominal_option(run, tmp_path):
    """--format rapid reads a module whatever its extension (without it, a .txt module is told
    from its content, issue 24);
    --nominal gives the controller's model to an identified model that does not record it (the
    same output as the recorded one); without either the program is refused."""
    import json

    d, *_ = run
    (tmp_path / "prog.txt").write_bytes((d / "prog.mod").read_bytes())
    doc = json.loads((d / "identified.json").read_text())
    doc.pop("identification")
    (tmp_path / "bare.json").write_text(json.dumps(doc))
    args = ("--task", "prog.txt", "--out", "out.txt")
    r = recal("compensate", "--model", d / "identified.json", *args, cwd=tmp_path)
    assert r.returncode == 0 and "(RAPID)" in r.stdout, r.stderr
    assert (tmp_path / "out.txt").read_bytes() == (d / "out.mod").read_bytes()
    (tmp_path / "out.txt").unlink()
    r = recal("compensate", "--model", "bare.json", "--format", "rapid", *args, cwd=tmp_path)
    assert r.returncode == 2 and not (tmp_path / "out.txt").exists()
    assert (
        r.stderr.strip()
        .splitlines()[-1]
        .startswith(
            "recal compensate: bare.json: a robot program needs the nominal model its controller uses: give --nominal"
        )
    )
    r = recal(
        "compensate", "--model", "bare.json", "--nominal", d / "nominal.json", "--format", "rapid", *args, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out.txt").read_bytes() == (d / "out.mod").read_bytes()


@pytest.mark.parametrize("suffix", [".mod", ".modx", ".prg"])
def test_every_declaration_scope_and_module_extension(tmp_path, suffix):
    """PERS, TASK PERS, LOCAL PERS and LOCAL VAR declarations are targets as CONST ones are, in
    a .mod, .modx or .prg file."""
    from service.programs import format_of

    rest = "[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]"
    p = tmp_path / f"m{suffix}"
    p.write_text(
        f"MODULE m\n  PERS robtarget p1:=[[1200,0,1200],[0,0,1,0],[0,0,0,0],{rest}];\n"
        f"  TASK PERS robtarget p2:=[[1200,100,1200],[0,0,1,0],[0,0,0,0],{rest}];\n"
        f"  LOCAL PERS jointtarget j1:=[[0,0,0,0,30,0],{rest}];\n"
        f"  LOCAL VAR robtarget p3:=[[1200,-100,1200],[0,0,1,0],[-1,0,-1,0],{rest}];\n"
        "  PROC main()\n    MoveAbsJ j1, v100, fine, tool0;\n    MoveJ p1, v100, fine, tool0;\n"
        "    MoveL p2, v100, fine, tool0;\n    MoveL p3, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n"
    )
    assert format_of(p) == "rapid"
    prog = rapid.parse(p)
    assert [(t.name, t.kind, t.line) for t in prog.targets] == [
        ("p1", "pose", 2),
        ("p2", "pose", 3),
        ("j1", "joints", 4),
        ("p3", "pose", 5),
    ]
    assert prog.targets[3].config == (-1, 0, -1, 0) and prog.uninterpreted == []


@pytest.mark.parametrize(
    "q, flags",
    [
        ([20, 10, -20, 30, 0.2, -40], {"near_singular"}),  # axis 5 at 0.2°: the wrist singularity
        # axis 1 at -179.99°: the correction takes it past its -180° limit, out of quadrant -2
        ([-179.99, 10, -20, 30, 50, -40], {"joint_limit", "branch_change"}),
    ],
)
def test_report_rows_flag_near_singular_and_beyond_the_joint_limits(run, tmp_path, q, flags):
    import json

    d, nominal, *_ = run
    (tmp_path / "m.mod").write_text(_one_target_module(nominal, q, confdata(q)))
    r = recal(
        "compensate",
        "--model",
        d / "identified.json",
        "--task",
        "m.mod",
        "--out",
        "o.mod",
        "--report",
        "r.json",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    row = json.loads((tmp_path / "r.json").read_text())["points"][0]
    assert flags <= set(row["flags"]) and row["converged"], row
    assert row["configuration"]["written"] == confdata(q)
