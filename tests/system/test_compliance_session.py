"""A pose session with two payloads against the real service and a simulated cell whose arm
sags under gravity: the session loop changes the payload through the robot's own interface (UR
``set_payload``, which makes the simulated arm sag under it) between the two halves of the
plan, and the cell's compliant model identifies the joints' compliance itself, shown against
the rigid model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.compliance import default_section, with_section
from calibration.model import model_to_dict
from calibration.simulate import SAGGING_ARMS, sagging
from service.client import ApiError
from service.files import load_model, save_model
from service.processes import start_fake_cell

from .conftest import next_host


def test_pose_session_with_two_payloads_identifies_the_joint_compliance(stack, models, tmp_path):
    nominal = load_model(models["nominal"])
    truth = sagging(models["truth_model"], "cobot", frames_of=nominal)
    save_model(tmp_path / "sagging.json", truth)
    host = next_host()
    fake = start_fake_cell(tmp_path / "sagging.json", host, extra=[], log_path=stack.home / f"cell-{host}.log")
    stack.cells.append(fake)
    api = stack.api("technician")
    doc = model_to_dict(with_section(nominal, default_section(nominal)))
    cell = api.call("POST", "/cells", {"name": "sagging", "model": doc, "devices": fake.ready})
    s = api.call(
        "POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": 60, "payloads": [[0], [10, 0, 0, 100]]}
    )  # kg, mm in the tool frame
    s = api.wait_session(s["id"], 240)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    params = {p["name"]: p for p in cal["report"]["parameters"]}
    for joint, c in SAGGING_ARMS["cobot"]["compliance"].items():
        k = params[f"compliance.{joint}.k"]  # determined: the two payloads separate it from the arm's weight
        assert k["unit"] == "deg/(N·m)"
        assert k["value"] == pytest.approx(np.rad2deg(c), rel=0.1)
    result = stack.api("viewer").call("GET", f"/calibrations/{s['calibration_id']}/result")
    comp = result["report"]["compliance"]
    assert comp["cv_rms_compliant"] < 0.2 * comp["cv_rms_rigid"]


def test_payloads_only_for_pose_and_verify_sessions(stack, models):
    api = stack.api("technician")
    cell = api.call(
        "POST", "/cells", {"name": "plain", "model": json.loads(models["nominal"].read_text()), "devices": {}}
    )
    with pytest.raises(ApiError) as exc:
        api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "circle", "count": 12, "payloads": [[5]]})
    assert exc.value.status == 422
    with pytest.raises(ApiError) as exc:
        api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": 12, "payloads": [[-1]]})
    assert exc.value.status == 422
