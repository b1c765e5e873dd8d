"""The register form (issue 27): no robot is chosen for the technician (the library's first,
alphabetically, was the default), and an endpoint line with a key the service does not know is
refused in the API's own words ("did you mean 'emscon'?"), with nothing filled in."""

from __future__ import annotations

import json
import os

from calibration.robots import nominal_document
from service.client import Api, ApiError

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")


def test_the_register_form_chooses_no_robot_and_refuses_an_unknown_key_as_the_api_does(page, web, tmp_path):
    with web.service_with_technician(tmp_path) as (url, token, _engine, _settings):
        line = {"ready": True, "rtde": f"{NET}.2", "tracker": f"socket://{NET}.2:10001", "emscom": f"{NET}.2:700"}
        try:  # what the API says of the same devices
            Api(url, token).call("POST", "/cells", {"name": "x", "model": nominal_document("ur10e"), "devices": line})
            raise AssertionError("the API took an unknown device key")
        except ApiError as exc:
            api_says = json.loads(exc.detail)["detail"]
        assert api_says["field"] == "body.devices.emscom" and "did you mean 'emscon'?" in api_says["message"]

        web.sign_in_at(page, url, token)
        page.goto(f"{url}/#/cells/new")
        page.wait_for_selector("#endpoint-line")
        assert page.input_value("#model-source") == ""  # no robot chosen
        assert page.locator("#model-source option:checked").inner_text() == "choose the robot…"
        page.fill("#cell-name", "line 4")
        page.click("#save-cell")
        assert page.inner_text("#form-error") == "Choose the robot first (Robot model)."

        page.fill("#endpoint-line", json.dumps(line))
        page.click("#fill-from-line")
        said = page.inner_text("#endpoint-line-error")
        assert said.startswith('The line\'s "emscom": ' + api_says["message"]), (said, api_says)
        assert page.input_value("#dev-rtde") == "" and page.input_value("#dev-tracker") == ""  # nothing filled in
        assert page.inner_text("#endpoint-line-status") == ""

        # a key too far from every known one: no suggestion, as the API gives none
        page.fill("#endpoint-line", json.dumps({"rtde": f"{NET}.2", "zzz": 1}))
        page.click("#fill-from-line")
        assert "unknown key (expected one of ready, rtde" in page.inner_text("#endpoint-line-error")

        # the line without the typo fills the fields, and the robot chosen registers the cell
        del line["emscom"]
        page.fill("#endpoint-line", json.dumps(line))
        page.click("#fill-from-line")
        assert page.input_value("#dev-rtde") == line["rtde"] and page.inner_text("#endpoint-line-error") == ""
        page.select_option("#model-source", "lib:ur10e")
        page.click("#save-cell")
        page.wait_for_selector("h1:has-text('line 4')")
        cells = Api(url, token).call("GET", "/cells")
        assert [c["name"] for c in cells] == ["line 4"] and cells[0]["devices"]["rtde"] == line["rtde"]
