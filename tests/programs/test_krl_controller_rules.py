"""KRL targets as a KUKA controller moves to them (issue 24), on the KR 16-like library arm with
every link in error: an inline target without S and T takes the configuration the controller
would use (LIN/CIRC: the start configuration, the previous target's; PTP: the solution nearest
the axes where the motion starts), and S bits beyond 0-2 (bit 4: taught on an absolutely
accurate robot) are kept as written, not read as a branch."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibration.kinematics import fk
from service.programs import krl

from .helpers import frame_of, models, pose_error, reached, recal
from .test_krl import abc, status_turn

# planned joints (deg): XA, the inline LIN, XB and the inline PTP on one branch (S 6, T 26); the
# other wrist (A4 + 180°, -A5, A6 - 180°: S 2, T 34) is nearer the arm's zero
Q = {
    "XA": [20, -80, 100, -110, -40, 100],
    "lin": [25, -75, 95, -120, -45, 110],
    "XB": [30, -70, 90, -130, -50, 120],
    "ptp": [35, -65, 85, -140, -55, 130],
}


def inline(T):
    p, a = T[:3, 3] * 1e3, abc(T[:3, :3])
    return "{X %.3f, Y %.3f, Z %.3f, A %.4f, B %.4f, C %.4f}" % (*p, *a)


def e6pos(T, S, Tb):
    p, a = T[:3, 3] * 1e3, abc(T[:3, :3])
    return "{X %.3f,Y %.3f,Z %.3f,A %.4f,B %.4f,C %.4f,S %d,T %d,E1 0.0,E2 0.0}" % (*p, *a, S, Tb)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("krlrules")
    nominal, true = models(d, "kuka")
    X = {k: fk(nominal, np.radians([q]))[0] for k, q in Q.items()}
    S, Tb = status_turn(Q["XA"])
    assert (S, Tb) == (6, 26) and status_turn(Q["XB"]) == (6, 26)
    src = f"DEF rules( )\nPTP XA\nLIN {inline(X['lin'])} C_DIS\nLIN XB\nPTP {inline(X['ptp'])}\nEND\n"
    # XB written with S bit 4 set (22 = 6 + 16): a point taught on an absolutely accurate robot
    dat = f"DEFDAT rules\nDECL E6POS XA={e6pos(X['XA'], 6, 26)}\nDECL E6POS XB={e6pos(X['XB'], 22, 26)}\nENDDAT\n"
    (d / "rules.src").write_text(src)
    (d / "rules.dat").write_text(dat)
    r = recal(
        "compensate",
        "--model",
        "identified.json",
        "--task",
        "rules.src",
        "--out",
        "out.src",
        "--report",
        "r.json",
        cwd=d,
    )
    return d, nominal, true, r


def test_inline_targets_without_s_and_t_take_the_controllers_solution_and_reach_their_poses(run):
    d, nominal, true, r = run
    assert r.returncode == 0, r.stderr
    M = frame_of(true, nominal)
    old, new = krl.parse(d / "rules.src"), krl.parse(d / "out.src")
    inl = [(a, b) for a, b in zip(old.targets, new.targets) if a.name is None]
    assert [a.move for a, _ in inl] == ["LIN", "PTP"]
    for (t0, t1), key in zip(inl, ("lin", "ptp")):
        q_plan = np.radians([Q[key]])
        X_d = np.linalg.inv(M) @ t0.P[None]
        before = pose_error(reached(true, nominal, t0.P[None], q_plan), X_d)
        dp, da = pose_error(reached(true, nominal, t1.P[None], q_plan), X_d)
        assert before[0][0] > 1e-3  # the arm's error, uncompensated
        assert dp[0] < 1e-5 and math.degrees(da[0]) < 0.005, (key, dp, math.degrees(da[0]))
    rep = json.loads((d / "r.json").read_text())
    rows = {p["line"]: p for p in rep["points"] if p["kind"] == "pose" and p["variable"] is None}
    for line in (3, 5):
        assert rows[line]["configuration"]["solution"] == {"S": 6, "T": 26}, rows[line]
        assert rows[line]["flags"] == []


def test_s_bits_beyond_0_to_2_are_kept_as_written_not_a_branch(run):
    d, _nominal, _true, _r = run
    rep = json.loads((d / "r.json").read_text())
    xb = next(p for p in rep["points"] if p["variable"] == "XB")
    assert xb["flags"] == [] and xb["configuration"]["written"] == {"S": 22, "T": 26}
    assert ",S 22,T 26," in (d / "out.dat").read_text()
