"""The UR controller's own kinematics kept by the cell (issue 16): read when a session starts on
a UR cell over RTDE, versioned, shown with the cell, recorded in the calibration, used as the
nominal model of compensation; a changed factory calibration is a new version and a warning."""

from __future__ import annotations

import json

import numpy as np

from calibration.kinematics import fk
from calibration.model import model_from_dict
from fakes.world import draw_factory_calibration
from service.processes import start_fake_cell
from service.stored_compensation import compensate_text

from .conftest import next_host

SCRIPT = """def task():
  movel(p[0.400, -0.200, 0.350, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
  movel(p[0.450, -0.150, 0.300, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
end
"""


def _same_kinematics(doc: dict, factory_seed: int) -> float:
    """Worst flange position difference (m) between ``doc`` and the fake's factory model."""
    q = np.random.default_rng(2).uniform(-np.pi, np.pi, (100, 6))
    expected = fk(draw_factory_calibration("ur5e", factory_seed).model(), q)
    return float(np.max(np.linalg.norm(fk(model_from_dict(doc), q)[:, :3, 3] - expected[:, :3, 3], axis=1)))


def test_sessions_read_keep_and_version_the_controllers_kinematics(stack, models, register):
    cell, fake = register(fake_args=["--factory-seed", "3"])
    api = stack.api()
    s = api.wait_session(api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": 30})["id"], 120)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert s["plan_info"]["controller_model"] == {"version": 1, "changed": False, "warning": None, "moved_mm": None}
    cm = api.call("GET", f"/cells/{cell['id']}/controller-model")
    assert cm["version"] == 1 and cm["session_id"] == s["id"] and cm["check_um"] < 1.0
    assert _same_kinematics(cm["model"], 3) < 1e-6
    summary = api.call("GET", f"/cells/{cell['id']}/summary")
    assert summary["controller_model"]["version"] == 1

    # the calibration records what the controller computes with; compensation uses it
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    assert cal["model"]["identification"]["controller"]["name"] == "ur5e-controller"
    out = api.call("POST", f"/calibrations/{s['calibration_id']}/compensate?name=task.script", raw=SCRIPT)
    through = {
        name: compensate_text(SCRIPT, name="task.script", model_doc=cal["model"], nominal_doc=doc)[0]
        for name, doc in (("controller", cm["model"]), ("published", cell["model"]))
    }
    assert out == through["controller"] and out != through["published"]

    # the same controller: nothing new
    s2 = api.wait_session(api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 4})["id"], 60)
    assert s2["state"] == "completed", (s2["state"], s2.get("reason"))
    assert s2["plan_info"]["controller_model"]["changed"] is False, s2["plan_info"]["controller_model"]
    assert api.call("GET", f"/cells/{cell['id']}/controller-model")["version"] == 1

    # the controller's factory calibration replaced: a new version and a warning
    host = fake.ready["rtde"]
    fake.stop()
    stack.cells.append(start_fake_cell(models["truth"], host, extra=["--factory-seed", "4"]))
    s3 = api.wait_session(api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 4})["id"], 60)
    assert s3["state"] == "completed", (s3["state"], s3.get("reason"))
    info = s3["plan_info"]["controller_model"]
    assert info["version"] == 2 and info["changed"] is True and info["moved_mm"] > 0.1
    assert "changed since version 1" in info["warning"]
    cm = api.call("GET", f"/cells/{cell['id']}/controller-model")
    assert cm["version"] == 2 and [h["version"] for h in cm["history"]] == [2, 1]
    assert _same_kinematics(cm["model"], 4) < 1e-6


def test_over_modbus_a_session_fits_the_controllers_kinematics_from_its_tcp_registers(stack, models):
    """A UR cell driven over Modbus only: no forward-kinematics query, so the session reads UR's
    TCP-pose registers (0.1 mm, 1 mrad) at each configuration it measures and fits the
    controller's model from them: far closer to what the controller computes than the published
    table, kept as version 1 and used by compensation."""
    host = next_host()
    fake = start_fake_cell(models["truth"], host, extra=["--factory-seed", "3", "--no-cmm", "--no-can", "--no-emscon"])
    stack.cells.append(fake)
    devices = {"modbus": fake.ready["modbus"], "tracker": fake.ready["tracker"]}  # no rtde
    cell = stack.api().call(
        "POST",
        "/cells",
        {"name": "modbus-cell", "model": json.loads(models["nominal"].read_text()), "devices": devices},
    )
    api = stack.api()
    s = api.wait_session(api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": 30})["id"], 120)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    info = s["plan_info"]["controller_model"]
    assert info["version"] == 1 and info["from_registers"] is True and info["changed"] is False, info
    cm = api.call("GET", f"/cells/{cell['id']}/controller-model")
    assert cm["version"] == 1 and cm["from_registers"] is True and cm["session_id"] == s["id"]
    assert "TCP-pose registers" in cm["model"]["controller"]["method"]
    # what the controller computes, over the whole joint space: the fit within a few tenths of a
    # millimetre (UR's 1 mrad joint registers), the published table millimetres off
    q = np.random.default_rng(2).uniform(-np.pi, np.pi, (200, 6))
    factory = fk(draw_factory_calibration("ur5e", 3).model(), q)[:, :3, 3]

    def rms(doc):
        return float(np.sqrt(np.mean(np.sum((fk(model_from_dict(doc), q)[:, :3, 3] - factory) ** 2, axis=1))))

    published = {**cell["model"], "base": [0.0] * 6, "tool": [0.0] * 6}
    assert rms(cm["model"]) < 0.3e-3 and rms(published) > 4 * rms(cm["model"]), (rms(cm["model"]), rms(published))

    # compensation goes through it
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    out = api.call("POST", f"/calibrations/{s['calibration_id']}/compensate?name=task.script", raw=SCRIPT)
    assert out == compensate_text(SCRIPT, name="task.script", model_doc=cal["model"], nominal_doc=cm["model"])[0]

    # the next session: the registers agree with the stored model, nothing new
    s2 = api.wait_session(api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 4})["id"], 60)
    assert s2["state"] == "completed", (s2["state"], s2.get("reason"))
    info2 = s2["plan_info"]["controller_model"]  # (a check within the registers' resolution: changed None)
    assert info2["version"] == 1 and info2["warning"] is None, info2
    assert info2["tcp_registers_mm"] < info2["tolerance_mm"], info2
    assert api.call("GET", f"/cells/{cell['id']}/controller-model")["version"] == 1
