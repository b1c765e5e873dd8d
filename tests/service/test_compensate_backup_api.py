"""A zipped controller backup through ``POST /calibrations/{id}/compensate-backup`` (issue 24):
the zip of the same layout comes back, every entry that is not a program byte for byte, each
program compensated as the single-program route compensates it, plus the report; targets not
compensated are counted in ``X-Recal-Not-Compensated``. A zip that would write outside its
folder (an absolute path, ``..``) or unpack beyond ``RECAL_MAX_INPUT_BYTES`` is refused before
anything is written; a viewer may not compensate; the work is audited."""

from __future__ import annotations

import io
import json
import re
import zipfile

import pytest

from .conftest import auth

NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
MOD = (
    "MODULE job\r\n  PROC main()\r\n"
    "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tGripper;\r\n"
    "    MoveAbsJ [[-30,-100,60,-50,-80,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, z10, tGripper;\r\n"
    "  ENDPROC\r\nENDMODULE\r\n"
)
SYS = "MODULE user(SYSMODULE)\n  PERS tooldata tGripper:=[TRUE,[[0,0,200],[1,0,0,0]],[1,[0,0,50],[1,0,0,0],0,0,0]];\nENDMODULE\n"
OTHER = {"BACKINFO/backinfo.txt": b"[BACKUP]\r\nSYSTEM=recal-test\r\n", "SYSPAR/MOC.cfg": b"MOC:CFG_1.0:6:0::\n"}


def backup_zip(extra: dict | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("RAPID/TASK1/PROGMOD/job.mod", MOD)
        zf.writestr("RAPID/TASK1/SYSMOD/user.sys", SYS)
        for name, data in {**OTHER, **(extra or {})}.items():
            zf.writestr(name, data)
    return buf.getvalue()


def post(client, cal, data: bytes, token: str):
    return client.post(
        f"/api/v1/calibrations/{cal}/compensate-backup?name=cell7.zip",
        content=data,
        headers={**auth(token), "Content-Type": "application/zip"},
    )


def test_an_abb_backup_zip_comes_back_in_its_layout_with_the_report(calibrated, tokens):
    client, _, cal = calibrated
    r = post(client, cal, backup_zip(), tokens["job"])
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/zip"
    assert r.headers["x-recal-not-compensated"] == "0"
    assert 'filename="cell7-compensated.zip"' in r.headers["content-disposition"]
    out = zipfile.ZipFile(io.BytesIO(r.content))
    names = out.namelist()
    assert names[:-1] == ["RAPID/TASK1/PROGMOD/job.mod", "RAPID/TASK1/SYSMOD/user.sys", *OTHER]
    assert names[-1] == "recal-compensation-report.json"
    for name, data in OTHER.items():
        assert out.read(name) == data
    assert out.read("RAPID/TASK1/SYSMOD/user.sys").decode() == SYS
    job = out.read("RAPID/TASK1/PROGMOD/job.mod").decode()
    assert job != MOD and NUMBER.sub("#", job) == NUMBER.sub("#", MOD)
    # the same as the single-program route gives for the module and its system module
    files = [("p", ("job.mod", MOD.encode(), "text/plain")), ("s", ("user.sys", SYS.encode(), "text/plain"))]
    one = client.post(f"/api/v1/calibrations/{cal}/compensate", files=files, headers=auth(tokens["job"]))
    assert one.status_code == 200, one.text
    assert one.json()["files"][0]["text"] == job
    report = json.loads(out.read("recal-compensation-report.json"))
    assert report["layout"] == "abb" and report["task"] == "cell7.zip"
    assert [f["file"] for f in report["files"]] == ["RAPID/TASK1/PROGMOD/job.mod"]
    assert [p["line"] for p in report["points"]] == [3, 4]
    assert {p["file"] for p in report["points"]} == {"RAPID/TASK1/PROGMOD/job.mod"}
    assert report["points"][0]["frames"].startswith("tool tGripper")
    audit = client.get("/api/v1/audit", headers=auth(tokens["admin"])).json()
    entries = audit if isinstance(audit, list) else audit.get("entries", audit.get("items", []))
    assert any(e["action"] == "compensate backup" and e["actor"] == "job-user" for e in entries), audit


@pytest.mark.parametrize(
    "name",
    ["../evil.mod", "/etc/evil", "RAPID/../../evil", "C:/evil", "..\\evil"],
)
def test_an_entry_outside_the_folder_is_refused(calibrated, tokens, name, tmp_path):
    client, _, cal = calibrated
    r = post(client, cal, backup_zip({name: b"x"}), tokens["job"])
    assert r.status_code == 422, r.text
    assert r.json()["detail"]["message"].startswith(f"zip entry {name!r}: an absolute path or '..'")


def test_a_zip_beyond_the_input_bound_is_refused_before_it_is_unpacked(calibrated, tokens, monkeypatch):
    client, _, cal = calibrated
    monkeypatch.setenv("RECAL_MAX_INPUT_BYTES", "1M")
    data = backup_zip({"bomb.bin": bytes(4 << 20)})  # 4 MiB of zeros: a few kB compressed
    assert len(data) < 64 * 1024
    r = post(client, cal, data, tokens["job"])
    assert r.status_code == 413, r.text
    assert "beyond the input bound of 1048576 bytes (RECAL_MAX_INPUT_BYTES)" in r.json()["detail"]["message"]


def test_bad_zips_and_roles(calibrated, tokens):
    client, _, cal = calibrated
    assert post(client, cal, backup_zip(), tokens["viewer"]).status_code == 403
    r = post(client, cal, b"not a zip", tokens["job"])
    assert r.status_code == 422 and "expected a zip of a controller backup" in r.json()["detail"]["message"]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("readme.txt", "no programs")
    r = post(client, cal, buf.getvalue(), tokens["job"])
    assert r.status_code == 422 and r.json()["detail"]["message"].startswith("the zip: expected a controller backup")
    assert post(client, 99999, backup_zip(), tokens["job"]).status_code == 404


def fanuc_zip(tool_frame: str) -> bytes:
    """A folder of Fanuc programs: one joint position in user frame 1 and tool frame 1, and the
    controller's frame data (SYSFRAME.VA, written for this test in a Fanuc backup's layout)."""
    ls = (
        "/PROG  JOB\r\n/MN\r\n   1:J P[1] 100% FINE    ;\r\n/POS\r\nP[1]{\r\n   GP1:\r\n\tUF : 1, UT : 1,\r\n"
        "\tJ1=    10.000 deg,\tJ2=   -20.000 deg,\tJ3=    30.000 deg,\r\n"
        "\tJ4=   -40.000 deg,\tJ5=    50.000 deg,\tJ6=   -60.000 deg\r\n};\r\n/END\r\n"
    )
    va = (
        "[*SYSTEM*]$MNUFRAME  Storage: SHADOW  Access: RW  : ARRAY[1,9] OF POSITION\r\n    [1,1] =\r\n"
        "  Group: 1   Config: N D B, 0, 0, 0\r\n  X:   800.000   Y:  -300.000   Z:   150.000\r\n"
        "  W:     0.000   P:     0.000   R:   -30.000\r\n"
        "[*SYSTEM*]$MNUTOOL  Storage: SHADOW  Access: RW  : ARRAY[1,10] OF POSITION\r\n" + tool_frame
    )
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("cell3/JOB.LS", ls)
        zf.writestr("cell3/SYSFRAME.VA", va)
    return buf.getvalue()


def test_a_fanuc_backup_zip_takes_its_frames_from_the_frame_data(calibrated, tokens):
    client, _, cal = calibrated
    tool = "    [1,1] = 'GUN'\r\n  Group: 1   Config: N D B, 0, 0, 0\r\n  X: 0.000   Y: 10.000   Z: 220.000\r\n  W: 0.000   P: -20.000   R: 0.000\r\n"
    r = post(client, cal, fanuc_zip(tool), tokens["job"])
    assert r.status_code == 200, r.text
    report = json.loads(zipfile.ZipFile(io.BytesIO(r.content)).read("recal-compensation-report.json"))
    assert report["layout"] == "fanuc" and [p["frames"] for p in report["points"]] == ["UF 1, UT 1"]
    # tool frame 1 never set on the controller: refused, naming the entry, its line and the frame
    r = post(client, cal, fanuc_zip("    [1,1] = '' Uninitialized\r\n"), tokens["job"])
    assert r.status_code == 422, r.text
    message = r.json()["detail"]["message"]
    assert message == (
        "cell3/JOB.LS, line 7: P[1]: UT 1 is not given: not set (or Uninitialized) in the backup's frame data "
        "(SYSFRAME.VA)"
    ), message


def test_a_kuka_archive_zip_comes_back_in_its_layout(calibrated, tokens):
    """A KUKA archive (KRC/R1/Program with a .src and its .dat, KRC/R1/System/$config.dat, am.ini):
    the .dat's targets compensated as the multipart route compensates the program, every other
    entry byte for byte (the .src holds no target's number)."""
    client, _, cal = calibrated
    src = "DEF job( )\r\nPTP XHOME\r\nPTP XP1\r\nEND\r\n"
    dat = (
        "DEFDAT job\r\nDECL E6AXIS XHOME={A1 10.0,A2 -80.0,A3 90.0,A4 -100.0,A5 70.0,A6 20.0,E1 0.0}\r\n"
        "DECL E6AXIS XP1={A1 -30.0,A2 -100.0,A3 60.0,A4 -50.0,A5 -80.0,A6 0.0,E1 12.5}\r\nENDDAT\r\n"
    )
    config = "DEFDAT $CONFIG\r\nDECL FRAME TOOL_DATA[16]\r\nENDDAT\r\n"
    entries = {
        "KRC/R1/Program/job.src": src,
        "KRC/R1/Program/job.dat": dat,
        "KRC/R1/System/$config.dat": config,
        "am.ini": "[Version]\r\nVersion=KRC4\r\n",
    }
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, text in entries.items():
            zf.writestr(name, text)
    r = post(client, cal, buf.getvalue(), tokens["job"])
    assert r.status_code == 200, r.text
    assert r.headers["x-recal-not-compensated"] == "0"
    out = zipfile.ZipFile(io.BytesIO(r.content))
    assert out.namelist() == [*entries, "recal-compensation-report.json"]
    for name in ("KRC/R1/Program/job.src", "KRC/R1/System/$config.dat", "am.ini"):
        assert out.read(name).decode() == entries[name], name
    new_dat = out.read("KRC/R1/Program/job.dat").decode()
    assert new_dat != dat and NUMBER.sub("#", new_dat) == NUMBER.sub("#", dat) and "E1 12.5}" in new_dat
    files = [("p", ("job.src", src.encode(), "text/plain")), ("d", ("job.dat", dat.encode(), "text/plain"))]
    one = client.post(f"/api/v1/calibrations/{cal}/compensate", files=files, headers=auth(tokens["job"]))
    assert one.status_code == 200, one.text
    assert one.json()["files"][1]["text"] == new_dat
    report = json.loads(out.read("recal-compensation-report.json"))
    assert report["layout"] == "kuka" and {p["file"] for p in report["points"]} == {"KRC/R1/Program/job.dat"}
