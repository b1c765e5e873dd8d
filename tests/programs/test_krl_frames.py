"""KRL frames where KSS 8 puts them (issue 24), on the KR 16-like library arm with every link in
error: the spline inline form's ``WITH $TOOL = STOOL2(FP1), $BASE = SBASE(FP1.BASE_NO), ...``
selects the same frames as ``FDAT_ACT = FP1``; ``$config.dat``'s globals (``FHOME``, ``XHOME``)
are known with ``--config-dat``; a name declared without a value is reported as such; a frame
that cannot be resolved refuses the program, naming the line and the frame."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.transforms import matrix_to_pose
from service.files import InputError
from service.programs import krl
from service.programs.frames import Frames

from .helpers import frame_of, models, pose_error, reached, recal
from .test_krl import BASE2, TOOL1, e6pos, kuka_frame

Q1 = [10, -80, 100, 20, 40, -30]

CONFIG_DAT = (
    "DEFDAT $CONFIG PUBLIC\n"
    "DECL FRAME TOOL_DATA[16]\n"
    "TOOL_DATA[1]={X %s,Y %s,Z %s,A %s,B %s,C %s}\n"
    % TOOL1
    + "BASE_DATA[2]={X %s,Y %s,Z %s,A %s,B %s,C %s}\n" % BASE2
    + "DECL E6AXIS XHOME={A1 0.0,A2 -90.0,A3 90.0,A4 0.0,A5 0.0,A6 0.0,E1 0.0,E2 0.0}\n"
    'DECL FDAT FHOME={TOOL_NO 0,BASE_NO 0,IPO_FRAME #BASE,POINT2[] " "}\n'
    "ENDDAT\n"
)
HOME = ";FOLD SPTP HOME\n$BWDSTART = FALSE\nPDAT_ACT = PDEFAULT\nFDAT_ACT = FHOME\nBAS(#PTP_PARAMS, 100)\n$H_POS = XHOME\nSPTP XHOME\n;ENDFOLD\n"
WITH = (
    "SPTP XP1 WITH $TOOL = STOOL2(FP1), $BASE = SBASE(FP1.BASE_NO), $IPO_MODE = SIPO_MODE(FP1.IPO_FRAME), "
    "$LOAD = SLOAD(FP1.TOOL_NO), $ACC_AXIS = SACC_JNT(PPDAT1), $APO = SAPO_PTP(PPDAT1), "
    "$COLLMON_TOL_PRO[1] = USE_CM_PRO_VALUES(0)\n"
)
ACT = "FDAT_ACT = FP1\nBAS(#PTP_PARAMS, 100)\nSPTP XP1\n"


def write(d, name, body, xp1, fp1='DECL FDAT FP1={TOOL_NO 1,BASE_NO 2,IPO_FRAME #BASE,POINT2[] " "}\n'):
    (d / f"{name}.src").write_text(f"DEF {name}( )\n{HOME}{body}SPTP joint_pos_tgt\nEND\n")
    (d / f"{name}.dat").write_text(
        f"DEFDAT {name}\nDECL E6POS XP1={xp1}\n{fp1}DECL PDAT PPDAT1={{VEL 100,ACC 100}}\ndecl axis joint_pos_tgt\nENDDAT\n"
    )


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("krlframes")
    nominal, true = models(d, "kuka")
    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(kuka_frame(TOOL1)))
    P = np.linalg.inv(kuka_frame(BASE2)) @ fk(nom_t, np.radians([Q1]))[0]
    xp1 = e6pos(P, Q1)
    (d / "config.dat").write_text(CONFIG_DAT)
    write(d, "withs", WITH, xp1)
    write(d, "act", ACT, xp1)
    runs = {}
    for name in ("withs", "act"):
        runs[name] = recal(
            "compensate", "--model", "identified.json", "--task", f"{name}.src", "--out", f"{name}-out.src",
            "--config-dat", "config.dat", "--report", f"{name}.json", cwd=d,
        )  # fmt: skip
    return d, nominal, true, runs


def test_with_clause_frames_are_the_fdats_and_the_target_reaches_its_pose(cell):
    d, nominal, true, runs = cell
    for r in runs.values():
        assert r.returncode == 0, r.stderr
    rows = {n: {p["variable"]: p for p in json.loads((d / f"{n}.json").read_text())["points"]} for n in runs}
    frames = "tool TOOL_DATA[1] ($config.dat), base BASE_DATA[2] ($config.dat)"
    assert rows["withs"]["XP1"]["frames"] == rows["act"]["XP1"]["frames"] == frames
    assert rows["withs"]["XP1"]["compensated"] == rows["act"]["XP1"]["compensated"]
    # the true robot, sent the compensated XP1 through the nominal controller, reaches XP1's pose
    fr = Frames.from_options([], [], str(d / "config.dat"))
    t0 = next(t for t in krl.parse(d / "withs.src", frames=fr).targets if t.name == "XP1")
    t1 = next(t for t in krl.parse(d / "withs-out.src", frames=fr).targets if t.name == "XP1")
    tool, B = kuka_frame(TOOL1), kuka_frame(BASE2)
    nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
    true_t = dataclasses.replace(true, tool=matrix_to_pose(tool))
    X_d = np.linalg.inv(frame_of(true, nominal)) @ (B @ t0.P)[None]
    q = np.radians([Q1])
    assert pose_error(reached(true_t, nom_t, (B @ t0.P)[None], q), X_d)[0][0] > 2e-4
    dp, da = pose_error(reached(true_t, nom_t, (B @ t1.P)[None], q), X_d)
    assert dp[0] < 1e-5 and math.degrees(da[0]) < 0.005


def test_config_dat_globals_and_a_name_declared_without_value_are_reported_as_they_are(cell):
    d, _nominal, _true, _runs = cell
    rep = json.loads((d / "withs.json").read_text())
    why = {u["line"]: u["reason"] for u in rep["uninterpreted"]}
    assert "XHOME is a global of $config.dat" in why[8], why
    assert "JOINT_POS_TGT is declared without a value (AXIS" in why[11], why


@pytest.mark.parametrize(
    "body, fp1, message",
    [
        (
            WITH.replace("STOOL2(FP1)", "STOOL2(FP9)"),
            None,
            r"line 10: \$TOOL = STOOL2\(FP9\): FDAT FP9 is not declared",
        ),
        (
            WITH.replace("STOOL2(FP1)", "MYTOOL"),
            None,
            r"line 10: \$TOOL = MYTOOL: Recal cannot resolve this tool frame",
        ),
        (
            WITH,
            "DECL FDAT FP1={TOOL_NO 1,BASE_NO 2,IPO_FRAME #TCP}\n",
            r"line 10: \$IPO_MODE = SIPO_MODE\(FP1.IPO_FRAME\): #TCP \(an external TCP\)",
        ),
    ],
)
def test_a_frame_that_cannot_be_resolved_is_refused_naming_line_and_frame(tmp_path, body, fp1, message):
    (tmp_path / "config.dat").write_text(CONFIG_DAT)
    xp1 = "{X 1,Y 2,Z 3,A 0,B 0,C 0,S 2,T 2}"
    if fp1 is None:
        write(tmp_path, "t", body, xp1)
    else:
        write(tmp_path, "t", body, xp1, fp1)
    with pytest.raises(InputError, match=message):
        krl.parse(tmp_path / "t.src", frames=Frames.from_options([], [], str(tmp_path / "config.dat")))


def test_without_config_dat_the_home_fold_is_not_refused_and_says_what_to_pass(tmp_path):
    """FDAT_ACT = FHOME with no $config.dat: the axis target XHOME needs no Cartesian frame
    resolved to be reported; it is left alone, the reason naming --config-dat."""
    write(tmp_path, "t", "", "{X 1,Y 2,Z 3,A 0,B 0,C 0,S 2,T 2}")
    prog = krl.parse(tmp_path / "t.src")
    reasons = " ".join(u.reason for u in prog.uninterpreted)
    assert "--config-dat" in reasons and prog.targets == []


@pytest.mark.parametrize(
    "option",
    ["1=1,2,3\n4,5,6", "1=nan,0,0,0,0,0", "1=1,2,3,4,5", "1=1,2,3,4,5,inf"],
    ids=["break", "nan", "five", "inf"],
)
def test_a_frame_option_that_is_not_six_finite_numbers_exits_2_naming_the_option(tmp_path, option):
    """A pasted value with a line break once raised a traceback (the option's pattern matched
    nothing); NaN and infinity passed as numbers."""
    models(tmp_path, "kuka")
    write(tmp_path, "t", "PTP XP1\n", "{X 1,Y 2,Z 3,A 0,B 0,C 0,S 2,T 2}")
    r = recal("compensate", "--model", "identified.json", "--task", "t.src", "--out", "o.src", "--tool-frame", option, cwd=tmp_path)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert "--tool-frame" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o.src").exists()
