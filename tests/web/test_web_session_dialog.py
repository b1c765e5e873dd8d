"""A question the session page asks is withdrawn when the session moves on (issue 27): "Pause the
session?" stayed open after the session had completed; now it closes, and a notice says why."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")


def test_pause_question_is_withdrawn_when_the_session_completes(page, web, tmp_path):
    from calibration import robots
    from calibration.simulate import perturbed
    from service.client import Api
    from service.files import save_model
    from service.processes import start_fake_cell

    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = dataclasses.replace(perturbed(nominal, np.random.default_rng(2)), base=np.array([1.5, -0.4, 0.2, 0, 0, 1]))
    save_model(tmp_path / "nominal.json", nominal)
    save_model(tmp_path / "truth.json", truth)
    # about a pose a second (the demo's pace): the session runs while the page asks
    cell = start_fake_cell(tmp_path / "truth.json", f"{NET}.84", time_scale=0.15, log_path=tmp_path / "cell.log")
    try:
        with web.service_with_technician(tmp_path / "svc") as (url, token, _engine, _settings):
            api = Api(url, token)
            doc = json.loads((tmp_path / "nominal.json").read_text())
            cell_id = api.call("POST", "/cells", {"name": "c", "model": doc, "devices": cell.ready})["id"]
            s = api.call("POST", f"/cells/{cell_id}/sessions", {"kind": "verify", "count": 6})
            web.sign_in_at(page, url, token)
            page.goto(f"{url}/#/sessions/{s['id']}")
            page.click("#pause")  # shown while the session runs
            page.wait_for_selector("dialog.confirm[open]")
            assert api.wait_session(s["id"], 120)["state"] == "completed"
            page.wait_for_selector("dialog.confirm", state="detached", timeout=15_000)  # withdrawn, not answered
            assert "nothing to pause" in page.inner_text("#notices")
            assert api.call("GET", f"/sessions/{s['id']}")["state"] == "completed"
            page.wait_for_selector("#pause", state="detached")
    finally:
        cell.stop()
