"""Robot programs compensated through a model's residual correction (issue 28: "Compensation
applies it too: joints, targets and programs").

The true arm here is an ABB-like arm with errors in every link *and* harmonic-drive transmission
errors: at a reading ``q`` it is the identified geometry at ``q + δq(q)``. The identified model
file carries that geometry and the transmission as its correction (what `recal identify
--residual-map auto` stores when the transmission family wins). The RAPID module of
test_rapid.py (a tool 150 mm out, a work object, joint and inline targets), compensated with it
and sent to a controller that knows only the nominal model, must bring the true arm, transmission
and all, to the poses the program means; the same module compensated with the geometry alone
misses them by the transmission's error. A smooth map or boosted trees correct only the point they
were measured at: a program whose targets use another tool says so in the report's notes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from calibration.kinematics import fk
from calibration.model import model_to_dict
from calibration.simulate import harmonic_drive_errors
from calibration.transforms import matrix_to_pose
from calibration.transmission import JointTransmission, TransmissionCorrection
from calibration.transmission import to_dict as transmission_section
from service.files import save_model
from service.programs import rapid

from .helpers import frame_of, models, pose_error, recal
from .test_rapid import Q, T_tool, T_wobj, program


def _pose_error(X, T):
    """6 errors of pose ``T`` against ``X`` (4, 4): position, and the rotation's small-angle vector."""
    dR = X[:3, :3] @ T[:3, :3].T
    return np.concatenate(
        [X[:3, 3] - T[:3, 3], 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])]
    )


def _solve_nominal(nom_t, X, q_planned):
    """The nominal controller's joints for command ``X`` (4, 4): Newton on the nominal model from
    the planned joints, with a finite-difference Jacobian written here."""
    q = q_planned.copy()
    for _ in range(30):
        T = fk(nom_t, q[None])[0]
        e = _pose_error(X, T)
        if np.linalg.norm(e) < 1e-13:
            break
        J = np.stack([_pose_error(fk(nom_t, (q + 1e-7 * np.eye(6)[i])[None])[0], T) / 1e-7 for i in range(6)], axis=1)
        q = q + np.linalg.lstsq(J, e, rcond=None)[0]
    return q


@pytest.fixture(scope="module")
def corrected(tmp_path_factory):
    d = tmp_path_factory.mktemp("program-correction")
    nominal, true = models(d, "abb")
    tx = harmonic_drive_errors(nominal, np.random.default_rng(7))
    lo = np.array([j.lower for j in nominal.joints])
    hi = np.array([j.upper for j in nominal.joints])
    region = JointTransmission(tx.ratios, tx.coefficients, lo, hi)
    section = transmission_section(TransmissionCorrection(true, true, region), true)
    save_model(
        d / "corrected.json", true, {"identification": {"nominal": model_to_dict(nominal)}, "residual_map": section}
    )
    assert json.loads((d / "corrected.json").read_text())["residual_map"]["family"] == "transmission"
    (d / "prog.mod").write_bytes(program(nominal))
    runs = {}
    for name in ("corrected", "identified"):
        r = recal("compensate", "--model", f"{name}.json", "--task", "prog.mod", "--out", f"{name}.mod", "--report", f"{name}.json.rep", cwd=d)  # fmt: skip
        runs[name] = r
    return d, nominal, true, tx, runs


def _true_errors(d, nominal, true, tx, out_name):
    """Position and angle errors of the true arm (transmission included) sent each pose target
    of ``out_name`` by the nominal controller, against the pose the written target means."""
    M = frame_of(true, nominal)
    old = rapid.parse(d / "prog.mod")
    new = rapid.parse(d / out_name)
    dps, das = [], []
    for t0, t1 in zip(old.targets, new.targets):
        if t0.kind != "pose":
            continue
        tool = T_tool() if t0.name else np.eye(4)
        W = T_wobj() if t0.name else np.eye(4)
        nom_t = dataclasses.replace(nominal, tool=matrix_to_pose(tool))
        true_t = dataclasses.replace(true, tool=matrix_to_pose(tool))
        q_cmd = _solve_nominal(nom_t, W @ t1.P, np.radians(Q[t0.name or "inline"]))
        reached = fk(true_t, (q_cmd + tx.joint_errors(q_cmd[None])[0])[None])
        dp, da = pose_error(reached, (np.linalg.inv(M) @ (W @ t0.P))[None])
        dps.append(dp[0])
        das.append(da[0])
    return np.array(dps), np.array(das)


def test_a_program_through_the_transmission_puts_the_true_arm_on_its_poses(corrected):
    d, nominal, true, tx, runs = corrected
    for r in runs.values():
        assert r.returncode == 0, r.stderr
    dp, _da = _true_errors(d, nominal, true, tx, "corrected.mod")
    dp_geo, _ = _true_errors(d, nominal, true, tx, "identified.mod")
    assert len(dp) == 6
    # to the rounding of the written numbers (2 decimals of mm in this module, 7 of the quaternion)
    assert dp.max() < 0.01e-3, dp
    assert dp_geo.max() > 5 * dp.max() and dp_geo.max() > 0.02e-3, dp_geo  # the geometry alone misses
    report = json.loads((d / "corrected.json.rep").read_text())
    assert not any("residual" in n for n in report["summary"]["notes"])  # the transmission moves with the tool
    assert report["summary"]["flags"].get("outside_mapped_region", 0) == 0


def test_a_correction_of_one_point_says_which_targets_use_another_tool(corrected):
    d, _nominal, _true, _tx, _runs = corrected
    doc = json.loads((d / "corrected.json").read_text())
    q_deg = np.array([Q[k] for k in Q], dtype=float)
    doc["residual_map"] = {  # a smooth map of nothing (zero coefficients) around the planned joints
        "format": "recal.residual_map/1",
        "family": "map",
        "configurations": q_deg.tolist(),
        "coefficients": np.zeros((len(q_deg), 3)).tolist(),
        "length_scale": 1.0,
        "ridge": 1e-6,
    }
    (d / "map.json").write_text(json.dumps(doc))
    r = recal("compensate", "--model", "map.json", "--task", "prog.mod", "--out", "map.mod", "--report", "map.rep", cwd=d)  # fmt: skip
    assert r.returncode in (0, 3), r.stderr
    notes = json.loads((d / "map.rep").read_text())["summary"]["notes"]
    note = next(n for n in notes if n.startswith("the residual correction (smooth map)"))
    # the tGun targets (five, on lines 20-24 of the module) use another tool than the model's
    assert "5 target(s) with another tool" in note, note
