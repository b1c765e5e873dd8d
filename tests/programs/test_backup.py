"""`recal compensate --task DIR --out OUTDIR` on controller backups written for this test (issue
24): a KUKA archive (KRC/R1/Program/*.src with .dat, KRC/R1/System/$config.dat giving the
program's TOOL_DATA and BASE_DATA) and an ABB backup (RAPID/TASK1/PROGMOD with the program,
SYSMOD with the module declaring its tool and work object). Each comes back in the same layout:
every file that is not a program byte for byte, every program byte for byte outside its targets'
numbers, and the targets compensated exactly as the single-program run compensates them."""

from __future__ import annotations

import json
import re

from .helpers import models, recal, skeleton
from .test_krl import BASE2, TOOL1
from .test_krl import program as krl_program
from .test_rapid import program as rapid_program


def _tree(root):
    return {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _compensated(report, key="variable"):
    return {(p["file"].rsplit("/", 1)[-1], p[key], p["line"]): p["compensated"] for p in report["points"]}


def test_a_kuka_archive_comes_back_in_its_layout(tmp_path):
    nominal, _ = models(tmp_path, "kuka")
    src, dat = krl_program(nominal)
    arc = tmp_path / "archive"
    (arc / "KRC/R1/Program").mkdir(parents=True)
    (arc / "KRC/R1/System").mkdir(parents=True)
    (arc / "KRC/R1/Program/recal_test.src").write_bytes(src)
    (arc / "KRC/R1/Program/recal_test.dat").write_bytes(dat)
    config = (
        "DEFDAT $CONFIG\nDECL FRAME TOOL_DATA[16]\nTOOL_DATA[1]={X %s,Y %s,Z %s,A %s,B %s,C %s}\n" % TOOL1
        + "DECL FRAME BASE_DATA[32]\nBASE_DATA[2]={X %s,Y %s,Z %s,A %s,B %s,C %s}\nENDDAT\n" % BASE2
    ).encode()
    (arc / "KRC/R1/System/$config.dat").write_bytes(config)
    (arc / "am.ini").write_bytes(b"[Version]\r\nVersion=KRC4\r\n")
    # a program without targets, as every archive has: copied as it is
    (arc / "KRC/R1/cell.src").write_bytes(
        b"DEF CELL ( )\r\n  INIT\r\n  LOOP\r\n    P00 (#EXT_PGNO,#PGNO_GET,DMY[],0 )\r\n  ENDLOOP\r\nEND\r\n"
    )
    r = recal("compensate", "--model", "identified.json", "--task", "archive", "--out", "out", "--report", "b.json", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    before, after = _tree(arc), _tree(tmp_path / "out")
    assert set(before) == set(after)
    for rel in before:
        assert skeleton(after[rel]) == skeleton(before[rel]), rel
        if rel.suffix.lower() not in (".src", ".dat") or rel.name == "$config.dat":
            assert after[rel] == before[rel], rel
    assert after != before
    # the single program run with the same frames (from the same $config.dat)
    (tmp_path / "config.dat").write_bytes(config)
    (tmp_path / "recal_test.src").write_bytes(src)
    (tmp_path / "recal_test.dat").write_bytes(dat)
    one = recal("compensate", "--model", "identified.json", "--task", "recal_test.src", "--out", "o.src", "--config-dat", "config.dat", "--report", "one.json", cwd=tmp_path)  # fmt: skip
    assert one.returncode == 0, one.stderr
    assert after[arc.joinpath("KRC/R1/Program/recal_test.dat").relative_to(arc)] == (tmp_path / "o.dat").read_bytes()
    rep = json.loads((tmp_path / "b.json").read_text())
    assert rep["layout"] == "kuka"
    assert [f["file"] for f in rep["files"]] == ["KRC/R1/Program/recal_test.src", "KRC/R1/cell.src"]
    assert {p["file"] for p in rep["points"]} == {"KRC/R1/Program/recal_test.src", "KRC/R1/Program/recal_test.dat"}
    assert _compensated(rep) == _compensated(json.loads((tmp_path / "one.json").read_text()))


def test_an_abb_backup_resolves_the_tool_in_its_system_module(tmp_path):
    nominal, _ = models(tmp_path, "abb")
    data = rapid_program(nominal)
    lines = data.split(b"\r\n")
    decl = [ln for ln in lines if b"tooldata tGun" in ln or b"wobjdata wTable" in ln]
    assert len(decl) == 2
    prog = b"\r\n".join(ln for ln in lines if ln not in decl)
    sysmod = b"MODULE user(SYSMODULE)\r\n" + b"\r\n".join(decl) + b"\r\nENDMODULE\r\n"
    bk = tmp_path / "backup"
    (bk / "RAPID/TASK1/PROGMOD").mkdir(parents=True)
    (bk / "RAPID/TASK1/SYSMOD").mkdir(parents=True)
    (bk / "SYSPAR").mkdir()
    (bk / "RAPID/TASK1/PROGMOD/prog.mod").write_bytes(prog)
    (bk / "RAPID/TASK1/SYSMOD/user.sys").write_bytes(sysmod)
    (bk / "SYSPAR/MOC.cfg").write_bytes(b"MOC:CFG_1.0:6:0::\r\n")
    r = recal("compensate", "--model", "identified.json", "--task", "backup", "--out", "out", "--report", "b.json", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    before, after = _tree(bk), _tree(tmp_path / "out")
    assert set(before) == set(after)
    for rel in before:
        assert skeleton(after[rel]) == skeleton(before[rel]), rel
        if rel.name != "prog.mod":
            assert after[rel] == before[rel], rel
    # the single module with its declarations in it: the same targets' numbers
    (tmp_path / "whole.mod").write_bytes(data)
    one = recal("compensate", "--model", "identified.json", "--task", "whole.mod", "--out", "o.mod", "--report", "one.json", cwd=tmp_path)  # fmt: skip
    assert one.returncode == 0, one.stderr
    rep = json.loads((tmp_path / "b.json").read_text())
    assert rep["layout"] == "abb"
    got = {(p["variable"], p["move"]): p["compensated"] for p in rep["points"]}
    want = {
        (p["variable"], p["move"]): p["compensated"] for p in json.loads((tmp_path / "one.json").read_text())["points"]
    }
    assert got == want and len(got) >= 5
    assert all("(user.sys)" in p["frames"] for p in rep["points"] if "tGun" in p["frames"])


def test_a_folder_of_fanuc_programs_with_frames_given(tmp_path):
    from .test_fanuc_tp import UF1, UT1
    from .test_fanuc_tp import program as tp_program

    nominal, _ = models(tmp_path, "fanuc")
    data = tp_program(nominal)
    (tmp_path / "tp/sub").mkdir(parents=True)
    (tmp_path / "tp/sub/recal_test.ls").write_bytes(data)
    (tmp_path / "tp/notes.txt").write_bytes(b"cell 3\n")
    frames = ("--base-frame", "1=" + ",".join(map(str, UF1)), "--tool-frame", "1=" + ",".join(map(str, UT1)))
    r = recal("compensate", "--model", "identified.json", "--task", "tp", "--out", "out", *frames, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    (tmp_path / "recal_test.ls").write_bytes(data)
    one = recal("compensate", "--model", "identified.json", "--task", "recal_test.ls", "--out", "o.ls", *frames, cwd=tmp_path)  # fmt: skip
    assert one.returncode == 0, one.stderr
    assert (tmp_path / "out/sub/recal_test.ls").read_bytes() == (tmp_path / "o.ls").read_bytes() != data
    assert (tmp_path / "out/notes.txt").read_bytes() == b"cell 3\n"
    r = recal("compensate", "--model", "identified.json", "--task", "tp", "--out", "out", *frames, cwd=tmp_path)
    assert r.returncode == 2 and "expected a new or empty folder" in r.stderr


def sysframe_va(uf1, ut1) -> bytes:
    """A SYSFRAME.VA written for this test in the layout a Fanuc backup writes (service.programs.
    fanuc_frames): group 1's user frame 1 and tool frame 1, frames never set (Uninitialized), and a
    second group's frame that must not be read."""

    def element(g, n, v, comment=""):
        return (
            f"    [{g},{n}] = {comment}\r\n  Group: {g}   Config: N D B, 0, 0, 0\r\n"
            f"  X: {v[0]:9.3f}   Y: {v[1]:9.3f}   Z: {v[2]:9.3f}\r\n"
            f"  W: {v[3]:9.3f}   P: {v[4]:9.3f}   R: {v[5]:9.3f}\r\n"
        )

    return (
        "[*SYSTEM*]$MNUFRAME  Storage: SHADOW  Access: RW  : ARRAY[2,9] OF POSITION\r\n"
        + element(1, 1, uf1)
        + "    [1,2] = '' Uninitialized\r\n"
        + element(2, 1, (5, 5, 5, 0, 0, 0))
        + "[*SYSTEM*]$MNUFRAMENUM  Storage: SHADOW  Access: RW  : ARRAY[2] OF BYTE\r\n  [1] = 1\r\n"
        + "[*SYSTEM*]$MNUTOOL  Storage: SHADOW  Access: RW  : ARRAY[2,10] OF POSITION\r\n"
        + element(1, 1, ut1, "'GRIPPER'")
        + "    [1,2] = '' Uninitialized\r\n"
    ).encode()


def test_a_fanuc_backup_takes_its_frames_from_the_controllers_frame_data(tmp_path):
    """The user and tool frames come from the backup's SYSFRAME.VA ($MNUFRAME[1,1], $MNUTOOL[1,1]):
    the same bytes as the single program run with those frames given (before, the backup run
    refused the program: UF 1 not given). A frame the data leaves Uninitialized is refused,
    naming the line and the frame, not taken as the null frame."""
    from .test_fanuc_tp import UF1, UT1
    from .test_fanuc_tp import program as tp_program

    nominal, _ = models(tmp_path, "fanuc")
    data = tp_program(nominal)
    (tmp_path / "bk").mkdir()
    (tmp_path / "bk/recal_test.ls").write_bytes(data)
    (tmp_path / "bk/SYSFRAME.VA").write_bytes(sysframe_va(UF1, UT1))
    r = recal("compensate", "--model", "identified.json", "--task", "bk", "--out", "out", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    frames = ("--base-frame", "1=" + ",".join(map(str, UF1)), "--tool-frame", "1=" + ",".join(map(str, UT1)))
    (tmp_path / "recal_test.ls").write_bytes(data)
    one = recal("compensate", "--model", "identified.json", "--task", "recal_test.ls", "--out", "o.ls", *frames, cwd=tmp_path)  # fmt: skip
    assert one.returncode == 0, one.stderr
    assert (tmp_path / "out/recal_test.ls").read_bytes() == (tmp_path / "o.ls").read_bytes() != data
    assert (tmp_path / "out/SYSFRAME.VA").read_bytes() == sysframe_va(UF1, UT1)
    # a program on tool frame 2, which the controller never set: refused, naming line and frame
    bad = data.replace(b"UF : 1, UT : 1,", b"UF : 1, UT : 2,", 1)
    (tmp_path / "bk/recal_test.ls").write_bytes(bad)
    r = recal("compensate", "--model", "identified.json", "--task", "bk", "--out", "out2", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert re.search(r"recal_test\.ls, line \d+: .*UT 2 is not given", r.stderr), r.stderr
    assert not (tmp_path / "out2").exists()
