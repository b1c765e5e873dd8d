"""RAPID moves under ``ConfL\\Off`` / ``ConfJ\\Off`` (issue 24), on the ABB-like library arm with
every link in error: the controller does not hold the target's confdata, it takes the
configuration nearest the start, as for a KRL or TP target without configuration data. A
confdata that names another configuration (here axis 1 in the wrong quadrant) is kept as written,
the target compensated in the controller's solution (it was left as written, unreachable, exit 3)."""

from __future__ import annotations

import json
import math

import numpy as np

from calibration.kinematics import fk
from service.programs import rapid

from .helpers import frame_of, models, pose_error, reached, recal
from .test_rapid import confdata, robtarget

# planned joints (deg): the start (monitored), a MoveL under ConfL\Off, a MoveJ under ConfJ\Off
Q = {"pA": [20, 10, -20, 30, 50, -40], "pL": [24, 14, -24, 34, 46, -36], "pJ": [30, 5, -15, 40, 55, -30]}


def module(nominal, wrong: set, on: bool = False) -> str:
    rts = []
    for name, q in Q.items():
        conf = confdata(q)
        if name in wrong:
            conf[0] += 1  # axis 1 in the next quadrant: no solution of this pose there
        rts.append(f"  CONST robtarget {name}:=" + robtarget(fk(nominal, np.radians([q]))[0], conf, (3, 8)) + ";")
    conf_l = "ConfL \\On;" if on else "ConfL \\Off;"
    body = [
        "  PROC main()",
        "    MoveJ pA, v1000, fine, tool0;",
        f"    {conf_l}",
        "    ConfJ\\Off;",
        "    MoveL pL, v200, fine, tool0;",
        "    MoveJ pJ, v1000, fine, tool0;",
        "  ENDPROC",
    ]
    return "\n".join(["MODULE confoff", *rts, *body, "ENDMODULE", ""])


def test_targets_under_confl_off_and_confj_off_take_the_start_configuration_and_reach_their_poses(tmp_path):
    nominal, true = models(tmp_path, "abb")
    text = module(nominal, {"pL", "pJ"})
    (tmp_path / "m.mod").write_text(text)
    args = ["--model", "identified.json", "--task", "m.mod", "--out", "o.mod", "--report", "r.json"]
    r = recal("compensate", *args, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    M = frame_of(true, nominal)
    old, new = rapid.parse(tmp_path / "m.mod"), rapid.parse(tmp_path / "o.mod")
    assert [t.config_off for t in old.targets] == [False, True, True]
    for t0, t1 in zip(old.targets, new.targets):
        q_plan = np.radians([Q[t0.name]])
        X_d = np.linalg.inv(M) @ t0.P[None]
        before = pose_error(reached(true, nominal, t0.P[None], q_plan), X_d)
        dp, da = pose_error(reached(true, nominal, t1.P[None], q_plan), X_d)
        assert before[0][0] > 1e-3  # the arm's error, uncompensated
        assert dp[0] < 1e-5 and math.degrees(da[0]) < 0.005, (t0.name, dp, math.degrees(da[0]))
        assert t1.config_text == t0.config_text  # kept as written
    rows = {p["variable"]: p for p in json.loads((tmp_path / "r.json").read_text())["points"]}
    for name in ("pL", "pJ"):
        assert rows[name]["flags"] == [] and rows[name]["converged"], rows[name]
        assert rows[name]["configuration"]["solution"] == confdata(Q[name]), rows[name]


def test_with_confl_on_the_written_configuration_still_chooses(tmp_path):
    nominal, _ = models(tmp_path, "abb")
    text = module(nominal, {"pL"}, on=True)
    (tmp_path / "m.mod").write_text(text)
    r = recal("compensate", "--model", "identified.json", "--task", "m.mod", "--out", "o.mod", cwd=tmp_path)
    assert r.returncode == 3, r.stderr
    assert "1 of 3 targets not compensated (1 unreachable, left as written): m.mod, line 3 (pL)" in r.stderr
