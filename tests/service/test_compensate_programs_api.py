"""Robot programs through the compensation route: a KRL program's .src and .dat posted together
as multipart/form-data come back as JSON with both files compensated; a RAPID module posted as
the body (like a task CSV) comes back as text. The task CSV request is unchanged
(tests/service/test_compensate_api.py)."""

from __future__ import annotations

import re

import numpy as np

from calibration.kinematics import fk
from calibration.model import model_from_dict

from .conftest import auth

NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
SRC = "DEF job( )\n; PTP {A1 1, A2 2} is a comment\nPTP XHOME\nPTP XP1\nEND\n"
DAT = (
    "DEFDAT job\r\nDECL E6AXIS XHOME={A1 10.0,A2 -80.0,A3 90.0,A4 -100.0,A5 70.0,A6 20.0,E1 0.0}\r\n"
    "DECL E6AXIS XP1={A1 -30.0,A2 -100.0,A3 60.0,A4 -50.0,A5 -80.0,A6 0.0,E1 12.5}\r\nENDDAT\r\n"
)


def test_a_krl_program_and_its_dat_as_multipart(calibrated, tokens):
    client, cell, cal = calibrated
    files = [("program", ("job.src", SRC.encode(), "text/plain")), ("dat", ("job.dat", DAT.encode(), "text/plain"))]
    r = client.post(f"/api/v1/calibrations/{cal}/compensate", files=files, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    out = r.json()["files"]
    assert [f["name"] for f in out] == ["job.src", "job.dat"]
    assert out[0]["text"] == SRC  # the .src holds no target's number
    dat = out[1]["text"]
    assert NUMBER.sub("#", dat) == NUMBER.sub("#", DAT) and dat.count("\r\n") == DAT.count("\r\n")
    assert "E1 12.5}" in dat  # external axes untouched
    # the joint commands bring the identified robot where the nominal joints meant (same frame fit
    # as the command's)
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    nominal = model_from_dict(client.get(f"/api/v1/cells/{cell}", headers=auth(tokens["viewer"])).json()["model"])
    import dataclasses

    from calibration.compensation import nominal_world_frame
    from calibration.transforms import invert, matrix_to_pose, pose_to_matrix
    from service.task_compensation import calibrated_range_of

    M = nominal_world_frame(model, nominal, calibrated_range_of(model))[0]
    # no $TOOL in the program: the flange ($NULLFRAME), with the identified tool's correction kept
    flange = dataclasses.replace(nominal, tool=np.zeros(6))
    model = dataclasses.replace(
        model, tool=matrix_to_pose(pose_to_matrix(model.tool) @ invert(pose_to_matrix(nominal.tool)))
    )
    q_old = np.radians([[float(v) for v in re.findall(r"A\d (-?[\d.]+)", line)[:6]] for line in DAT.splitlines()[1:3]])
    q_new = np.radians([[float(v) for v in re.findall(r"A\d (-?[\d.]+)", line)[:6]] for line in dat.splitlines()[1:3]])
    X_d = np.linalg.inv(M) @ fk(flange, q_old)
    assert np.abs(fk(model, q_new)[:, :3, 3] - X_d[:, :3, 3]).max() < 2e-6
    assert np.abs(q_new - q_old).max() > 1e-5  # corrected
    report = client.get(
        f"/api/v1/compensations/{r.headers['x-recal-compensation']}/report", headers=auth(tokens["viewer"])
    ).json()["report"]
    assert {p["file"] for p in report["points"]} == {"job.dat"}
    assert report["files"][0]["name"] == "job.dat"


def test_a_rapid_module_as_the_body_and_a_bad_one(calibrated, tokens):
    client, _, cal = calibrated
    mod = (
        "MODULE m\n  ! MoveAbsJ [[1,2,3,4,5,6],[9E9,9E9,9E9,9E9,9E9,9E9]], v1, fine, tool0;\n  PROC main()\n"
        "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tool0;\n"
        "  ENDPROC\nENDMODULE\n"
    )
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=m.mod", content=mod, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain")
    assert NUMBER.sub("#", r.text) == NUMBER.sub("#", mod) and r.text != mod
    bad = mod.replace("[[10,-80,90,-100,70,20]", "[[10,-80,90,-100,70]")
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=m.mod", content=bad, headers=auth(tokens["job"]))
    assert r.status_code == 422
    assert r.json()["detail"]["message"].startswith(
        "m.mod, line 4: jointtarget (inline): robot axes: expected 6 values"
    )


def test_programs_not_in_utf8_come_back_byte_for_byte(calibrated, tokens):
    """A KRL program written in Windows-1252 (as KUKA's editor writes it) and a RAPID module with
    a Latin-1 comment: every byte that is not a target's number comes back as it was, the
    multipart answer with ``"encoding": "iso-8859-1"``, the body with its charset."""
    client, _, cal = calibrated
    src = "DEF job( )\n; Greifer geöffnet, 90° gedreht\nPTP XHOME\nEND\n".encode("cp1252")
    dat = DAT.replace("ENDDAT", "; Übergabe – Lage ±0,5 mm\r\nENDDAT").encode("cp1252")
    files = [("program", ("job.src", src, "text/plain")), ("dat", ("job.dat", dat, "text/plain"))]
    r = client.post(f"/api/v1/calibrations/{cal}/compensate", files=files, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    out = r.json()["files"]
    assert [(f["name"], f["encoding"]) for f in out] == [("job.src", "iso-8859-1"), ("job.dat", "iso-8859-1")]
    assert out[0]["text"].encode("iso-8859-1") == src
    out_dat = out[1]["text"].encode("iso-8859-1")
    assert NUMBER.sub("#", out_dat.decode("iso-8859-1")) == NUMBER.sub("#", dat.decode("iso-8859-1"))
    assert b"\xdcbergabe \x96 Lage \xb10,5 mm\r\nENDDAT" in out_dat and out_dat != dat

    mod = (
        "MODULE m\n  ! Schweißnaht, Düse\n  PROC main()\n"
        "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tool0;\n"
        "  ENDPROC\nENDMODULE\n"
    ).encode("latin-1")
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=m.mod", content=mod, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "text/plain; charset=iso-8859-1"
    assert r.content != mod and re.sub(rb"[-\d.]+", b"#", r.content) == re.sub(rb"[-\d.]+", b"#", mod)
    assert b"! Schwei\xdfnaht, D\xfcse\n" in r.content


def test_a_fanuc_tp_program_as_the_body(calibrated, tokens):
    client, _, cal = calibrated
    ls = (
        "/PROG  JOB\r\n/MN\r\n   1:J P[1] 100% FINE    ;\r\n   2:  ! J1= 1.000 deg ;\r\n/POS\r\nP[1]{\r\n   GP1:\r\n"
        "\tUF : 0, UT : 0,\r\n\tJ1=    10.000 deg,\tJ2=   -80.000 deg,\tJ3=    90.000 deg,\r\n"
        "\tJ4=  -100.000 deg,\tJ5=    70.000 deg,\tJ6=    20.000 deg\r\n};\r\n/END\r\n"
    )
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=job.ls", content=ls, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    assert r.text != ls and NUMBER.sub("#", r.text) == NUMBER.sub("#", ls)
    assert r.text.split("/POS")[0] == ls.split("/POS", maxsplit=1)[0]  # the comment that looks like a position
    bad = ls.replace(",\tJ6=    20.000 deg", "")
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=job.ls", content=bad, headers=auth(tokens["job"]))
    assert r.status_code == 422
    assert r.json()["detail"]["message"].startswith("job.ls, line ")


def test_targets_not_compensated_are_counted_as_the_cli_exit_3(calibrated, tokens):
    """A task CSV whose second row is 5 m out of reach: the compensated file comes back (200) and
    X-Recal-Not-Compensated says 1, the stored report's rows naming it; 0 when all are done."""
    client, _, cal = calibrated
    good = "x,y,z,qw,qx,qy,qz\n400,100,500,0,1,0,0\n"
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?mode=targets", content=good, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    assert r.headers["x-recal-not-compensated"] == "0"
    r = client.post(
        f"/api/v1/calibrations/{cal}/compensate?mode=targets",
        content=good + "5000,100,500,0,1,0,0\n",
        headers=auth(tokens["job"]),
    )
    assert r.status_code == 200, r.text
    assert r.headers["x-recal-not-compensated"] == "1"
    report = client.get(
        f"/api/v1/compensations/{r.headers['x-recal-compensation']}/report", headers=auth(tokens["viewer"])
    ).json()["report"]
    assert [p["converged"] for p in report["points"]] == [True, False]
    assert report["summary"]["not_compensated"] == 1


def test_a_rapid_module_with_the_system_module_that_declares_its_tool(calibrated, tokens):
    """A RAPID program posted with the task's system module (multipart): the tooldata it declares
    is the move's tool; the program alone is refused, saying to post the module with it."""
    client, _, cal = calibrated
    mod = (
        "MODULE job\n  PROC main()\n"
        "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tGripper;\n"
        "  ENDPROC\nENDMODULE\n"
    )
    sys_mod = "MODULE user(SYSMODULE)\n  PERS tooldata tGripper:=[TRUE,[[0,0,200],[1,0,0,0]],[1,[0,0,50],[1,0,0,0],0,0,0]];\nENDMODULE\n"
    files = [
        ("program", ("job.mod", mod.encode(), "text/plain")),
        ("sys", ("user.sys", sys_mod.encode(), "text/plain")),
    ]
    r = client.post(f"/api/v1/calibrations/{cal}/compensate", files=files, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    out = r.json()["files"]
    assert out[0]["name"] == "job.mod" and NUMBER.sub("#", out[0]["text"]) == NUMBER.sub("#", mod)
    assert out[0]["text"] != mod
    report = client.get(
        f"/api/v1/compensations/{r.headers['x-recal-compensation']}/report", headers=auth(tokens["viewer"])
    ).json()["report"]
    assert report["points"][0]["frames"] == "tool tGripper (user.sys), wobj wobj0"
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=job.mod", content=mod, headers=auth(tokens["job"]))
    assert r.status_code == 422
    assert (
        "tooldata tGripper is not declared in this module; pass the module that declares it (post it with"
        in (r.json()["detail"]["message"])
    )
