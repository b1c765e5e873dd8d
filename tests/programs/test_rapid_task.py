"""RAPID tool and work-object data declared outside the program's module (issue 24), on the
IRB 4600-like library arm with every link in error: a system module (``user.sys``) declares the
tooldata, passed with ``--module``; the wobjdata is given with ``--work-object``. The program
module alone is refused, naming the move and what to pass. The compensated targets reach their
poses on the simulated true robot; the system module is read, not rewritten."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from calibration.kinematics import fk
from calibration.transforms import matrix_to_pose
from service.programs import rapid
from service.programs.frames import Frames

from .helpers import frame_of, models, pose_error, reached, recal
from .test_rapid import TOOL, UFRAME, T_tool, T_wobj, confdata, robtarget

Q = {"p10": [20, 10, -20, 30, 50, -40], "p20": [25, 20, -10, -40, 60, 70]}
SYS = (
    "%%%\r\n  VERSION:1\r\n  LANGUAGE:ENGLISH\r\n%%%\r\n\r\nMODULE user(SYSMODULE)\r\n"
    "  ! the cell's tools, as a backup keeps them\r\n"
    "  PERS tooldata tGripper:=[TRUE,[[10.5,-3,150],[0.9961947,0,0.0871557,0]],[2.5,[0,0,80],[1,0,0,0],0,0,0]];\r\n"
    "  LOCAL PERS tooldata tHidden:=[TRUE,[[0,0,1],[1,0,0,0]],[1,[0,0,1],[1,0,0,0],0,0,0]];\r\n"
    "ENDMODULE\r\n"
)
WOBJ = "wFixture=" + ",".join(str(v) for v in UFRAME[0] + UFRAME[1])


def test_tool_from_another_module_and_work_object_from_the_command_line(tmp_path):
    nominal, true = models(tmp_path, "abb")
    assert TOOL[0] == [10.5, -3.0, 150.0]  # the system module's tGripper is the test's tool
    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(T_tool()))
    rt = {k: robtarget(np.linalg.inv(T_wobj()) @ fk(nom_t, np.radians([q]))[0], confdata(q)) for k, q in Q.items()}
    mod = (
        "MODULE Job\n"
        f"  CONST robtarget p10:={rt['p10']};\n"
        f"  CONST robtarget p20:={rt['p20']};\n"
        "  PROC main()\n"
        "    MoveJ p10, v1000, z50, tGripper\\WObj:=wFixture;\n"
        "    MoveL p20, v200, fine, tGripper\\WObj:=wFixture;\n"
        "  ENDPROC\nENDMODULE\n"
    )
    (tmp_path / "job.mod").write_text(mod)
    (tmp_path / "user.sys").write_bytes(SYS.encode())
    base = ("compensate", "--model", "identified.json", "--task", "job.mod", "--out", "out.mod")
    r = recal(*base, cwd=tmp_path)  # the module alone: refused, saying what to pass
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == (
        "recal compensate: job.mod, line 5: MoveJ: tooldata tGripper is not declared in this module; pass the "
        "module that declares it (--module SYSMOD.sys) or --tool-frame tGripper=X,Y,Z,Q1,Q2,Q3,Q4"
    )
    r = recal(*base, "--module", "user.sys", "--work-object", WOBJ, "--report", "r.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "user.sys").read_bytes() == SYS.encode()
    rows = json.loads((tmp_path / "r.json").read_text())["points"]
    assert {p["frames"] for p in rows} == {"tool tGripper (user.sys), wobj wFixture (--work-object)"}
    fr = Frames.from_options([], [], modules=[str(tmp_path / "user.sys")], rapid=True, wobjs=[WOBJ])
    old = rapid.parse(tmp_path / "job.mod", frames=fr)
    new = rapid.parse(tmp_path / "out.mod", frames=fr)
    true_t = dataclasses.replace(true, tool=matrix_to_pose(T_tool()))
    M, W = frame_of(true, nominal), T_wobj()
    for t0, t1 in zip(old.targets, new.targets):
        q = np.radians([Q[t0.name]])
        X_d = np.linalg.inv(M) @ (W @ t0.P)[None]
        assert pose_error(reached(true_t, nom_t, (W @ t0.P)[None], q), X_d)[0][0] > 2e-4
        dp, da = pose_error(reached(true_t, nom_t, (W @ t1.P)[None], q), X_d)
        assert dp[0] < 1e-5 and math.degrees(da[0]) < 0.005


def test_a_local_declaration_of_another_module_is_not_seen(tmp_path):
    (tmp_path / "user.sys").write_text(SYS)
    (tmp_path / "m.mod").write_text(
        "MODULE m\n  PROC main()\n    MoveAbsJ [[0,0,0,0,30,0],[9E9,9E9,9E9,9E9,9E9,9E9]], v1, fine, tHidden;\n"
        "  ENDPROC\nENDMODULE\n"
    )
    import pytest

    from service.files import InputError

    fr = Frames.from_options([], [], modules=[str(tmp_path / "user.sys")], rapid=True)
    with pytest.raises(
        InputError, match=r"m\.mod, line 3: MoveAbsJ: tooldata tHidden is not declared in this module nor"
    ):
        rapid.parse(tmp_path / "m.mod", frames=fr)
