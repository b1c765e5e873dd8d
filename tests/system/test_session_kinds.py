"""Circle-point and joint-level sessions against the real service and a simulated cell."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.model import model_from_dict
from service.files import save_model


@pytest.fixture
def geared_models(models, tmp_path):
    """The system-test truth with gear eccentricity and a gain error on joints 1 and 2."""
    truth = models["truth_model"]
    joints = list(truth.joints)
    joints[0] = dataclasses.replace(joints[0], gain=1.0003, harmonic=(np.deg2rad(0.03), 3.0, 0.5))
    joints[1] = dataclasses.replace(joints[1], gain=0.9998, harmonic=(np.deg2rad(0.02), 5.0, -1.0))
    geared = dataclasses.replace(truth, joints=tuple(joints))
    save_model(tmp_path / "geared.json", geared)
    return {**models, "truth": tmp_path / "geared.json", "truth_model": geared}


def test_joint_session_finds_gain_and_gear_eccentricity(stack, geared_models, register):
    cell, _fake = register(truth=geared_models["truth"])
    api = stack.api()
    s = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "joint", "count": 60, "joints": [1, 2]})
    s = api.wait_session(s["id"], 120)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    assert cal["kind"] == "joint"
    truth = geared_models["truth_model"]
    for j in (1, 2):
        fit = cal["report"]["joints"][str(j)]
        gain, (amp, freq, phase) = truth.joints[j - 1].gain, truth.joints[j - 1].harmonic
        assert fit["frequency"] == pytest.approx(freq)
        assert fit["gain"] == pytest.approx(gain, abs=2e-5)
        assert fit["amplitude"] == pytest.approx(amp, rel=0.1)
        assert np.angle(np.exp(1j * (fit["phase"] - phase))) == pytest.approx(0.0, abs=0.15)
    model = model_from_dict(cal["model"])
    assert model.joints[0].harmonic is not None and model.joints[0].gain == pytest.approx(1.0003, abs=2e-5)


def test_circle_session_gives_the_joint_axes(stack, models, register):
    cell, _ = register()
    api = stack.api()
    s = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "circle", "count": 12})
    s = api.wait_session(s["id"], 120)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert s["measured"] == 6 * 12
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    assert cal["kind"] == "cpa"
    model = model_from_dict(cal["model"])
    truth = models["truth_model"]
    from calibration.cpa import axis_lines

    # The sweeps hold the other joints at the signature (readings 0 here, inside the limits):
    # there every measured axis lies on the truth's, to a few thousandths of a degree.
    signature = np.zeros((1, 6))
    d_true, _ = axis_lines(truth, signature)
    d_model, _ = axis_lines(model, signature)
    angles = np.degrees(np.arccos(np.clip(np.sum(d_true * d_model, axis=-1), -1, 1)))[0]
    assert np.all(angles[:5] < 0.02), angles
    # the reflector sits on joint 6's axis: its circle is tiny, and the report says so
    assert any("joint 6" in w and "radius" in w for w in cal["report"]["warnings"])
