"""The technician's web page in a real (headless) browser against the real service and a
simulated cell: sign in, register a cell (from the endpoint line, with inline checks), test its
connections, plan and start a pose session, watch it (it pauses on a protective stop, is
resumed), open the result, download the model, URDF and DH table, compensate a URScript program,
a KUKA .src with its .dat and a task CSV with flagged points, print the certificate (before and after a verify session);
a session interrupted by a crash of the service, resumed, paused and aborted; a second
calibration after a crash shows what moved; a viewer cannot start a session; pages stay fast
with a thousand stored calibrations and page through many cells; a portrait tablet."""

from __future__ import annotations

import json
import os
import re
import socket
import time

import numpy as np
import pytest

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")


pytestmark = pytest.mark.slow

URSCRIPT = """def pick_and_place():
  # taught in PolyScope
  global home_q = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
  movej(home_q, a=1.2, v=0.5)
  movel(p[0.600, -0.200, 0.400, 0.0, 3.1416, 0.0], a=0.8, v=0.2)
  movel(p[0.650, -0.150, 0.350, 0.0, 3.1416, 0.0], a=0.8, v=0.1)
  movej([0.3, -1.2, 1.4, -1.8, -1.5708, 0.2], a=1.2, v=0.5)
end
"""


def unlock_protective_stop(host: str) -> str:
    """What the technician does at the teach pendant: release the protective stop (UR dashboard)."""
    with socket.create_connection((host, 29999), timeout=5) as s:
        f = s.makefile("rw", newline="\n")
        f.readline()  # greeting
        f.write("unlock protective stop\n")
        f.flush()
        return f.readline().strip()


def confirm(page, expected_title: str) -> None:
    dlg = page.locator("dialog.confirm")
    dlg.wait_for()
    assert expected_title in dlg.locator("h2").inner_text()
    dlg.locator("[data-action=confirm]").click()


def test_technician_calibrates_a_cell_from_the_page(page, stack, web, tmp_path):
    shot, sign_in, api = web.shot, web.sign_in, web.api
    # --- sign in
    page.goto(stack.url + "/")
    page.wait_for_selector("#token")
    shot(page, "01-sign-in")
    page.fill("#token", "rc_not-a-token")
    page.click("#sign-in")
    page.wait_for_selector("text=This token is not valid")
    sign_in(page, stack)
    assert page.inner_text("#role") == "technician"
    shot(page, "02-cells-empty")

    # --- register a cell: the nominal model from a file, the devices from the fake cell's line
    page.click("#register-cell")
    page.fill("#cell-name", "line 3 UR10e")
    page.fill("#cell-site", "plant A")
    page.select_option("#model-source", "file")
    page.set_input_files("#model-file", str(stack.nominal_path))
    page.wait_for_selector("#model-info:has-text('targets: smr')")
    page.wait_for_selector("#enc-6")  # a row of node ids per joint of the model
    page.fill("#endpoint-line", "not json")
    page.click("#fill-from-line")
    assert "Not an endpoint line" in page.inner_text("#endpoint-line-error")
    page.fill("#endpoint-line", json.dumps(stack.cell_ready))
    page.click("#fill-from-line")
    assert page.input_value("#dev-rtde") == stack.cell_ready["rtde"]
    assert page.input_value("#dev-tracker") == stack.cell_ready["tracker"]
    assert page.input_value("#dev-emscon") == stack.cell_ready["emscon"]  # the Leica tracker sessions use
    assert page.input_value("#dev-can-port") == str(stack.cell_ready["can"]["port"])
    assert page.input_value("#enc-2") == str(stack.cell_ready["encoders"]["2"])
    assert page.input_value("#res-1") == str(stack.cell_ready["resolvers"]["1"])
    # inline checks: a wrong field says what it expects, and nothing is registered
    page.fill("#dev-modbus", f"{NET}.81")
    page.fill("#region-lo-2", "10")
    page.fill("#region-hi-2", "-10")
    page.fill("#res-2", str(stack.cell_ready["encoders"]["1"]))  # a node id used twice
    page.fill("#cell-drift", "0.1")
    page.click("#save-cell")
    assert "HOST:PORT" in page.inner_text("#dev-modbus-error")
    assert "above the lower end" in page.inner_text("#region-hi-2-error")
    assert "already the joint 1 reference encoder" in page.inner_text("#res-2-error")
    assert "need attention" in page.inner_text("#form-error")
    shot(page, "03-register-cell-checks")
    page.fill("#dev-modbus", stack.cell_ready["modbus"])
    page.fill("#res-2", "")
    page.fill("#region-lo-2", "")
    page.fill("#region-hi-2", "")
    page.click("#save-cell")
    page.wait_for_url(re.compile(r"#/cells/\d+$"))
    cell_id = int(page.url.rsplit("/", 1)[1])
    page.wait_for_selector("h1:has-text('line 3 UR10e')")
    cell = api(stack, "GET", f"/cells/{cell_id}")
    assert cell["devices"] == {k: v for k, v in stack.cell_ready.items() if k != "ready"}, cell["devices"]
    assert cell["allowed_region"] is None

    # --- edit it
    page.click("#edit-cell")
    page.wait_for_selector("#save-cell")
    assert page.input_value("#enc-1") == str(stack.cell_ready["encoders"]["1"])
    page.fill("#cell-site", "plant B")
    page.click("#save-cell")
    page.wait_for_selector("text=site plant B")

    # --- test the connections: every device answers, each encoder and resolver on its own
    page.click("#test-devices")
    page.locator("table.device-test tbody tr").first.wait_for()
    text = page.inner_text("table.device-test")
    assert "ERROR" not in text, text
    for what in (
        "robot (UR RTDE)",
        "laser tracker",
        "CMM (I++ DME)",
        "reference encoder, joint 1",
        "reference encoder, joint 2",
        "resolver, joint 1",
    ):
        assert what in text, what
    assert "SIM-LT" in text  # the line-protocol tracker's *IDN? answer
    assert "Leica, emScon 3.8.400" in text  # the emScon server's GetSystemStatus
    encoder2 = page.inner_text("table.device-test tr:has-text('reference encoder, joint 2')")
    assert re.search(r"-1\d\d\.\d{4}°", encoder2) and "counts" in encoder2 and "per count" in encoder2, encoder2
    assert "no heartbeat" not in text or "alive" in text, text  # a state that is said, is explained
    notices = page.locator("#notices .notice")
    if notices.count():  # a success notice never covers the buttons
        n, b = notices.first.bounding_box(), page.locator("#start-session").bounding_box()
        assert n["y"] + n["height"] <= b["y"] or b["y"] + b["height"] <= n["y"], (n, b)
    shot(page, "04-cell-devices-tested")

    # --- plan a pose session (a dry run: nothing moves), look at it, confirm
    page.click("#start-session")
    page.wait_for_selector("#plan")
    page.fill("#count", "24")
    page.select_option("#target", "smr")
    page.click("#plan")
    page.wait_for_selector("#plan-check")
    assert page.inner_text("#plan-check").startswith("✓")
    assert "95th percentile" in page.inner_text("#predicted")
    assert "random configurations" in page.inner_text("#predicted-note")
    # what these poses cannot determine, and which kind of measurement would (issue 27)
    assert "orientation measurements" in page.inner_text("#plan-shortfall")
    assert page.locator("svg[aria-label='joint ranges']").count() == 1
    shot(page, "05-session-plan")
    page.click("#confirm-start")
    confirm(page, "Start the session?")
    page.wait_for_url(re.compile(r"#/sessions/\d+$"))
    session_id = int(page.url.rsplit("/", 1)[1])

    # --- watch it: the robot protective-stops at its 6th move, the session pauses with the reason
    page.wait_for_selector("#stop-banner", timeout=60_000)
    banner = page.inner_text("#stop-banner")
    assert "Paused" in banner and "protective stop" in banner.lower(), banner
    # the live residual plot is drawn at the page's next poll after the pause (slow on a loaded machine)
    page.wait_for_selector("#residuals svg", timeout=60_000)
    state = api(stack, "GET", f"/sessions/{session_id}").get("device_state")
    devices = page.inner_text("#device-state")
    if state:  # the devices' own state, as the session last saw it
        assert state["robot"]["state"] in devices and "As of" in devices, (state, devices)
    else:
        assert "stopped (paused)" in devices, devices
    assert re.search(r"Last reading\s+pose \d+ at \S*\d:\d\d:\d\d", devices), devices  # to the second
    shot(page, "06-session-paused-on-fault")
    assert unlock_protective_stop(stack.cell_host).startswith("Protective stop releasing")
    page.click("#resume")
    confirm(page, "Resume the session?")
    page.wait_for_function("document.querySelector('#state').innerText.trim() !== 'paused'")
    page.wait_for_function(
        "(() => { const m = /(\\d+) of (\\d+)/.exec(document.querySelector('#progress').innerText);"
        " return m && +m[1] >= 8 && +m[1] < +m[2]; })()",
        timeout=60_000,
    )
    shot(page, "07-session-running")
    page.wait_for_selector("#open-result", timeout=90_000)
    assert "24 of 24" in page.inner_text("#progress")
    shot(page, "08-session-completed")

    # --- the result
    page.click("#open-result")
    page.wait_for_selector("#summary")
    calibration_id = int(page.url.rsplit("/", 1)[1])
    summary = page.inner_text("#summary")
    for label in ("Before", "After (fitted poses)", "Predicted error", "95th percentile at random configurations"):
        assert label in summary, summary
    for label in (
        "histogram of errors before",
        "histogram of errors after",
        "per-pose errors before and after",
        "residuals against pose",
        "workspace map from above",
    ):
        assert page.locator(f"svg[aria-label='{label}']").count() == 1, label
    bins = page.eval_on_selector_all(
        "svg[aria-label='histogram of errors before'] rect title", "ts => ts.map(t => +t.textContent.split(': ').pop())"
    )
    assert bins[0] > 0 and bins[-1] > 0 and sum(bins) == 24, bins  # no empty bar at either end
    assert page.locator("table.params tbody tr").count() > 10
    assert "same motion" in page.inner_text("table.unidentifiable")
    assert "not determined" in page.inner_text("#numerical-notes")  # what the warnings mean
    assert "first calibration" in page.inner_text("#compare")
    shot(page, "09-result")

    # --- downloads: the model file, the URDF and the DH table
    def download(button: str) -> str:
        with page.expect_download() as dl:
            page.click(button)
        path = tmp_path / dl.value.suggested_filename
        dl.value.save_as(path)
        return path

    model = json.loads(download("#download-model").read_text())
    assert model["format"] == "recal.model/1" and len(model["joints"]) == 6
    urdf = download("#download-urdf")
    assert urdf.suffix == ".urdf" and "<robot" in urdf.read_text() and "<joint" in urdf.read_text()
    ur_yaml = download("#download-ur-calibration")
    assert ur_yaml.name.endswith(".yaml") and "kinematics:\n  shoulder:" in ur_yaml.read_text()
    dh = download("#download-dh").read_text().splitlines()
    assert any(r.startswith("joint,type,theta,d,a,alpha") for r in dh) and sum(r.startswith("j") for r in dh) == 7, dh

    # --- compensate a URScript program: per-point flags shown, the compensated file downloaded
    prog = tmp_path / "pick_and_place.script"
    prog.write_text(URSCRIPT)
    page.set_input_files("#task-file", str(prog))
    page.click("#compensate")
    page.wait_for_selector("#compensated", timeout=30_000)
    page.evaluate("document.querySelector('#compensated').closest('.card').scrollIntoView()")
    shot(page, "10-compensated", full_page=False)
    out = download("#download-compensated")
    assert out.name == "pick_and_place-compensated.script"
    compensated = out.read_text()
    assert compensated != URSCRIPT and "def pick_and_place():" in compensated

    # --- a KUKA program: its .src and .dat chosen together, both compensated files downloaded
    (tmp_path / "job.src").write_text("DEF job( )\nPTP XP1\nPTP {A1 5, A2 -90, A3 80, A4 -60, A5 70, A6 0}\nEND\n")
    dat = "DEFDAT job\nDECL E6AXIS XP1={A1 10.0,A2 -80.0,A3 90.0,A4 -100.0,A5 70.0,A6 20.0,E1 0.0}\nENDDAT\n"
    (tmp_path / "job.dat").write_text(dat)
    page.set_input_files("#task-file", [str(tmp_path / "job.src"), str(tmp_path / "job.dat")])
    page.click("#compensate")
    page.wait_for_selector("#compensated:has-text('job-compensated.src')", timeout=30_000)
    assert download("#download-compensated").name == "job-compensated.src"
    out_dat = download("#download-compensated-1")
    assert (
        out_dat.name == "job-compensated.dat"
        and out_dat.read_text() != dat
        and "DECL E6AXIS XP1={" in out_dat.read_text()
    )

    # --- a task CSV with a point outside the calibrated joint ranges and one at a wrist singularity
    ranges = model["identification"]["joint_ranges"]
    from calibration.ik import pose_and_jacobian, singular_values
    from calibration.model import model_from_dict

    nominal = model_from_dict(json.loads(stack.nominal_path.read_text()))
    q = np.array([m["q"] for m in api(stack, "GET", f"/sessions/{session_id}/measurements")])
    farthest = np.argmax(singular_values(nominal, pose_and_jacobian(nominal, q)[2])[:, -1])
    inside = [round(float(v), 4) for v in np.rad2deg(q[farthest])]  # the measured one farthest from a singularity
    outside = [ranges[0][1] + 25 if ranges[0][1] < 330 else ranges[0][0] - 25, *inside[1:]]
    singular = [*inside[:4], 0.0, inside[5]]
    task = tmp_path / "task.csv"
    rows = (",".join(map(str, q)) for q in (inside, outside, singular))
    task.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(rows) + "\n")
    page.set_input_files("#task-file", str(task))
    page.click("#compensate")
    page.wait_for_selector("#compensated:has-text('task-compensated.csv')", timeout=30_000)
    flags = page.locator("table.compensation tbody tr td.flags").all_inner_texts()
    assert len(flags) == 3 and flags[0] == "—", flags
    assert "outside calibrated region" in flags[1] and "near singular" in flags[2], flags
    assert "extrapolated" in page.inner_text("#flag-meanings")
    page.evaluate("document.querySelector('#compensated').closest('.card').scrollIntoView()")
    shot(page, "10b-compensated-task-flags", full_page=False)

    # --- the certificate: no hold-out check yet, so it says which checks were not run
    page.click("#open-certificate")
    page.wait_for_selector("#certificate")
    cert = page.inner_text("#certificate")
    # the instrument that measured: the Leica tracker on emScon (the simulated cell's default)
    for what in (
        "line 3 UR10e",
        "ur10e",
        "laser tracker",
        "emScon 3.8.400",
        "technician-anna",
        "Before calibration",
        "After calibration, in-sample",
        "identification converged",
        "j2.a",
        "No hold-out check yet",
    ):
        assert what in cert, what
    verdict = page.inner_text("#verdict")
    assert "Not run: hold-out verification" in verdict and "All checks passed" not in verdict, verdict

    # ... a verify session after the calibration (through the API, as the nightly job would): the
    # certificate quotes its fresh configurations as the hold-out accuracy
    verify = api(
        stack,
        "POST",
        f"/cells/{cell_id}/sessions",
        {"kind": "verify", "count": 8, "device": "tracker", "target": "smr"},
    )
    deadline = time.monotonic() + 90
    while (v := api(stack, "GET", f"/sessions/{verify['id']}"))["state"] not in ("completed", "failed", "aborted"):
        assert time.monotonic() < deadline, v
        time.sleep(0.3)
    assert v["state"] == "completed", v
    page.reload()
    page.wait_for_selector("#certificate tr.holdout")
    cert = page.inner_text("#certificate")
    assert f"After calibration, hold-out (verify session {verify['id']})" in cert, cert
    assert "Not run" not in page.inner_text("#verdict")
    assert re.search(r"✓ passed\s+hold-out verification on fresh configurations", cert), cert
    # conditioning judged by the positions predicted, not the raw condition number (issue 25)
    assert re.search(r"✓ passed\s+identified parameters predict positions precisely over the workspace", cert), cert
    assert "Predicted: predicted position error" in cert
    shot(page, "11-certificate")
    page.emulate_media(media="print")
    page.pdf(path=str(tmp_path / "printed.pdf"), format="A4")
    shot(page, "12-certificate-print-view")
    page.emulate_media(media="screen")
    assert (tmp_path / "printed.pdf").read_bytes()[:4] == b"%PDF"
    pdf = download("#download-pdf")
    assert pdf.read_bytes()[:4] == b"%PDF" and pdf.stat().st_size > 2000

    # --- the cell page shows the UR controller's own kinematics, read when the sessions started
    page.goto(f"{stack.url}/#/cells/{cell_id}")
    controller_card = page.locator("section.card:has(h2:has-text('Controller kinematics'))")
    controller_card.wait_for()
    text = controller_card.inner_text()
    assert "-controller, version 1" in text and "µm" in text and "first read" in text, text

    # --- a session interrupted by a crash of the service, resumed, paused and aborted from the page
    def plan_and_start(count: int) -> int:
        page.goto(f"{stack.url}/#/cells/{cell_id}/start")
        page.wait_for_selector("#plan")
        page.fill("#count", str(count))
        page.click("#plan")
        page.wait_for_selector("#confirm-start:not([disabled])")
        page.click("#confirm-start")
        confirm(page, "Start the session?")
        page.wait_for_url(re.compile(r"#/sessions/\d+$"))
        return int(page.url.rsplit("/", 1)[1])

    plan_and_start(40)
    page.wait_for_function("/^[1-9]\\d* of/.test(document.querySelector('#progress')?.innerText)")  # running
    stack.crash_and_restart_service()
    page.wait_for_selector("#stop-banner:has-text('Interrupted')", timeout=30_000)
    assert "the service stopped" in page.inner_text("#stop-banner")
    assert "not connected" in page.inner_text("#device-state")  # what the devices said before is only the last known
    shot(page, "13-session-interrupted")
    page.click("#resume")
    confirm(page, "Resume the session?")
    page.wait_for_function("document.querySelector('#state').innerText.trim() === 'running'")
    page.click("#pause")
    confirm(page, "Pause the session?")
    page.wait_for_selector("#stop-banner:has-text('Paused')")
    assert page.locator("#resume").count() == 1
    shot(page, "13b-session-paused")
    page.click("#abort")
    confirm(page, "Abort the session?")
    page.wait_for_selector("#stop-banner:has-text('Aborted')")
    assert page.locator("#resume").count() == 0
    shot(page, "13c-session-aborted")

    # --- a crash bent link 3 (the cell's devices now reach that robot): the next calibration
    # shows which parameters moved beyond their uncertainty, the base and tool included
    page.goto(f"{stack.url}/#/cells/{cell_id}/edit")
    page.fill("#endpoint-line", json.dumps(stack.crashed_cell_ready))
    page.click("#fill-from-line")
    page.click("#save-cell")
    page.wait_for_selector("text=site plant B")
    plan_and_start(16)
    page.wait_for_selector("#open-result", timeout=90_000)
    page.click("#open-result")
    page.wait_for_selector("#moved-count")
    moved = page.inner_text("#moved-count")
    assert "moved beyond their uncertainty" in moved and "j3.a" in moved, moved
    assert page.locator("table.compare tr.moved:has-text('j3.a')").count() == 1
    compare = page.inner_text("table.compare")
    assert "base.tx" in compare and f"calibration {calibration_id}" in page.inner_text("#compare"), compare
    page.evaluate("document.querySelector('#compare').closest('.card').scrollIntoView()")
    shot(page, "14-result-compared-with-previous", full_page=False)

    s = api(stack, "GET", f"/sessions/{session_id}")
    assert s["state"] == "completed" and s["calibration_id"] == calibration_id


def test_viewer_cannot_start_a_session(page, stack, web):
    shot, sign_in, register_cell_by_api = web.shot, web.sign_in, web.register_cell_by_api
    cell_id = register_cell_by_api(stack, "viewer's view")
    sign_in(page, stack, "viewer")
    assert page.inner_text("#role") == "viewer"
    assert page.locator("#register-cell").count() == 0
    page.goto(f"{stack.url}/#/cells/{cell_id}")
    page.wait_for_selector('h1:has-text("viewer\'s view")')
    assert page.locator("#start-session").count() == 0
    assert page.locator("#test-devices").count() == 0
    assert page.locator("#edit-cell").count() == 0
    shot(page, "20-viewer-cell")
    page.goto(f"{stack.url}/#/cells/{cell_id}/start")
    page.wait_for_selector("#no-start")
    assert page.locator("#plan").count() == 0
    # ... and the API refuses a viewer anyway
    status = page.evaluate(
        """async ([id, token]) => (await fetch(`/api/v1/cells/${id}/sessions`, {method: 'POST',
        headers: {Authorization: `Bearer ${token}`, 'Content-Type': 'application/json'},
        body: JSON.stringify({kind: 'pose', count: 10})})).status""",
        [cell_id, stack.tokens["viewer"]],
    )
    assert status == 403


def test_the_cell_form_describes_and_checks_devices_with_the_services_schema(page, stack, web):
    """The device fields are labelled, explained and checked from GET /schemas/devices: a wrong
    value is refused in the service's words; a stored document with a key from before the
    service checked them says it is left out, and saving it registers what the schema allows."""
    from sqlmodel import Session

    from service.models import Cell
    from service.settings import Settings
    from service.store import make_engine

    schema = web.api(stack, "GET", "/schemas/devices")
    props = schema["properties"]
    web.sign_in(page, stack)
    page.goto(f"{stack.url}/#/cells/new")
    page.wait_for_selector("#dev-modbus")
    # the ball's radius is entered in mm (the API's metres converted at the page)
    assert page.inner_text("label[for=dev-cmm-ball]") == "CMM tooling ball radius (mm)"
    assert props["cmm_ball_radius_m"]["default"] == 0.0125
    assert page.get_attribute("#dev-cmm-ball", "placeholder") == "12.5"
    # every device the registry serves has its field, labelled with the schema's title
    for entry in schema["x-devices"]:
        if entry["page"] != "can":
            assert page.inner_text(f"label[for=dev-{entry['key']}]") == props[entry["key"]]["title"]
    page.fill("#dev-modbus", "robot-7")
    page.fill("#dev-cmm-ball", "125")  # beyond 100 mm
    page.fill("#dev-tracker", "tracker-pc:10001")
    assert page.inner_text("label[for=dev-emscon]") == props["emscon"]["title"]  # the Leica tracker
    page.fill("#dev-emscon", "tracker-ctrl:port")
    page.click("#save-cell")
    assert page.inner_text("#dev-modbus-error") == "expected " + props["modbus"]["anyOf"][0]["x-expected"]
    assert "HOST:PORT of the emScon server" in page.inner_text("#dev-emscon-error")
    assert "(0.5–100)" in page.inner_text("#dev-cmm-ball-error")
    assert "socket://HOST:PORT" in page.inner_text("#dev-tracker-error")
    web.shot(page, "05-register-cell-schema-checks")

    model = json.loads(stack.nominal_path.read_text())
    engine = make_engine(Settings(home=stack.home).effective_database_url)
    with Session(engine) as db:  # registered before the service checked the keys
        old = Cell(name="old devices", model=model, devices={"rtde": f"{NET}.89", "note": "line 3"})
        db.add(old)
        db.commit()
        cell_id = old.id
    engine.dispose()
    page.goto(f"{stack.url}/#/cells/{cell_id}/edit")
    page.wait_for_selector("#devices-unknown")
    assert "note" in page.inner_text("#devices-unknown")
    page.fill("#dev-cmm-ball", "10")  # mm
    page.click("#save-cell")
    page.wait_for_url(re.compile(rf"#/cells/{cell_id}$"))
    page.wait_for_selector("#test-devices")
    assert web.api(stack, "GET", f"/cells/{cell_id}")["devices"] == {"rtde": f"{NET}.89", "cmm_ball_radius_m": 0.01}


def test_pages_stay_fast_with_a_thousand_calibrations(page, stack, web):
    """A cell with 1000 stored calibrations (reports of full size): the overview and the cell's
    page load quickly (they never load all the reports); the overview shows the cells page by page."""
    from sqlmodel import Session

    from service.models import Calibration, Cell, utcnow
    from service.settings import Settings
    from service.store import make_engine

    shot, sign_in, register_cell_by_api = web.shot, web.sign_in, web.register_cell_by_api
    cell_id = register_cell_by_api(stack, "busy cell")
    names = [f"j{i}.{f}" for i in range(1, 7) for f in ("theta", "d", "a", "alpha")]
    report = {
        "success": True,
        "rows": 40,
        "message": "converged",
        "parameters": [{"name": n, "unit": "mm", "value": 1.0, "change": 0.01, "std_error": 0.001} for n in names],
        "unidentifiable": [],
        "correlation": {"names": names, "matrix": [[0.1] * len(names)] * len(names)},
        "residuals": {"rms": 0.03, "max": 0.06},
    }
    model = json.loads(stack.nominal_path.read_text())
    engine = make_engine(Settings(home=stack.home).effective_database_url)
    with Session(engine) as db:
        for k in range(1000):  # as the store keeps them: each put in use in its turn (schema v9), the last current
            db.add(
                Calibration(
                    cell_id=cell_id,
                    kind="pose",
                    model=model,
                    report=report,
                    rms=0.03 + 0.01 * (k % 7) / 7,
                    nominal_version=1,
                    activated_at=utcnow(),
                )
            )
        for k in range(30):  # more cells than one page of the overview holds
            db.add(Cell(name=f"spare cell {k + 1:02d}", site="plant C", model=model, devices={}))
        db.commit()
    engine.dispose()
    quiet_id = register_cell_by_api(stack, "quiet cell")
    sign_in(page, stack)

    def load(cid: int, selector: str) -> float:
        page.goto(f"{stack.url}/#/")
        page.wait_for_selector(".cell-card")
        t = time.monotonic()
        page.goto(f"{stack.url}/#/cells/{cid}")
        page.wait_for_selector(selector)
        return time.monotonic() - t

    quiet_s = load(quiet_id, "#test-devices")
    busy_s = load(cell_id, "table.calibrations tbody tr")
    assert "of 1000" in page.inner_text(".pager")
    shot(page, "30-cell-with-1000-calibrations")
    t = time.monotonic()
    page.goto(f"{stack.url}/#/")
    page.wait_for_selector(f"[data-cell='{cell_id}'] .accuracy:has-text('not verified yet')")
    overview_s = time.monotonic() - t
    cells_total = web.api(stack, "GET", "/overview?limit=1")["total"]
    pager = page.inner_text("#overview-pager")
    assert f"of {cells_total}" in pager and page.locator(".cell-card").count() == 30, pager
    page.click("#next-page")
    page.wait_for_selector("#prev-page")
    assert page.locator(".cell-card").count() == cells_total - 30
    assert "spare cell 30" in page.inner_text(".cell-grid")
    # compared with a cell without calibrations on the same (possibly busy) machine
    assert busy_s < 2 * quiet_s + 1.5 and overview_s < 2 * quiet_s + 1.5, (quiet_s, busy_s, overview_s)
    assert busy_s < 10 and overview_s < 10


def test_page_fits_a_portrait_tablet(page, stack, web):
    """The overview, a cell's page and a result on a tablet held upright: no sideways scrolling,
    no figure sticking out of its card, the trend labelled along its time axis."""
    shot, sign_in, TABLET = web.shot, web.sign_in, web.tablet
    page.set_viewport_size({"width": TABLET["height"], "height": TABLET["width"]})
    sign_in(page, stack)
    page.wait_for_selector(".cell-card")
    fits = "document.documentElement.scrollWidth <= window.innerWidth + 1"
    assert page.evaluate(fits)
    assert web.overflowing(page) == []
    shot(page, "40-portrait-cells")
    cells = {c["name"]: c for c in web.api(stack, "GET", "/overview")["cells"]}
    cell = cells.get("line 3 UR10e") or next(iter(cells.values()))
    page.goto(f"{stack.url}/#/cells/{cell['id']}")
    page.wait_for_selector("#test-devices")
    assert page.evaluate(fits)
    assert web.overflowing(page) == []
    if len(cell["verified"]) > 1:
        ticks = page.locator("svg[aria-label='accuracy trend'] g.axes text:not(.label)").all_text_contents()
        assert len([t for t in ticks if ":" in t]) >= 2, ticks  # times along the x axis, not one lone "1"
        tips = page.locator("svg[aria-label='accuracy trend'] circle title").all_text_contents()
        assert all(t.startswith("calibration ") and " verified " in t for t in tips), tips
        assert len(tips) == len(cell["verified"]), tips
    shot(page, "41-portrait-cell")
    if cell["last"]:
        page.goto(f"{stack.url}/#/calibrations/{cell['last']['id']}")
        page.wait_for_selector("#compare table, #compare p")
        assert page.evaluate(fits)
        assert web.overflowing(page) == []
        widths = page.eval_on_selector_all(".stat .value", "vs => vs.map(v => [v.scrollWidth, v.clientWidth])")
        assert widths and all(sw <= cw for sw, cw in widths), widths
        shot(page, "42-portrait-result")


def _wait_done(api, stack, session_id: int, timeout_s: float = 90) -> dict:
    deadline = time.monotonic() + timeout_s
    while (s := api(stack, "GET", f"/sessions/{session_id}"))["state"] not in (
        "completed",
        "failed",
        "aborted",
        "paused",
    ):
        assert time.monotonic() < deadline, s
        time.sleep(0.2)
    assert s["state"] == "completed", s
    return s


def js_num(v: float, digits: int = 3) -> str:
    """A figure as the page's ``num`` writes it (service/web/js/ui.js)."""
    import math

    if v == 0:
        return "0"
    d = max(0, digits - 1 - math.floor(math.log10(abs(v))))
    return f"{v:.{min(d, 8)}f}"


TEXT_OUTSIDE_DETAILS = """() => { const c = document.querySelector('#app, main, body').cloneNode(true);
  c.querySelectorAll('details#details').forEach((d) => d.remove()); return c.textContent; }"""


def test_figures_and_banners_say_what_happened_in_a_technicians_words(page, stack, web, tmp_path):
    """The nominal model's check leads with the robot's own error (placed where it fits best), in
    mm; a calibration says "Calibrated", its mathematics folded into details; "Show the plan"
    stores no session; the cell card's accuracy is the verified one; an error toast names the
    file, not "body"."""
    shot, sign_in, api = web.shot, web.sign_in, web.api
    doc = json.loads(stack.nominal_path.read_text())
    # the second simulated cell (no injected fault) under a name of its own
    cell_id = api(
        stack, "POST", "/cells", {"name": "words and figures", "model": doc, "devices": stack.crashed_cell_ready}
    )["id"]
    nominal = _wait_done(
        api,
        stack,
        api(stack, "POST", f"/cells/{cell_id}/sessions", {"kind": "verify", "count": 6, "target": "smr"})["id"],
    )
    v = nominal["plan_info"]["verify"]
    sign_in(page, stack)
    page.goto(f"{stack.url}/#/sessions/{nominal['id']}")
    page.wait_for_selector("#done-banner")
    banner = page.inner_text("#done-banner")
    assert banner.startswith("Not calibrated yet.") and "Completed" not in banner, banner
    assert "banner-warn" in page.get_attribute("#done-banner", "class")
    registered, raw = js_num(v["registered"]["rms"]), js_num(v["rms"])
    assert f"{registered} mm RMS" in banner and banner.index(registered) < banner.index(raw), banner
    shot(page, "50-nominal-verified")

    # "Show the plan" twice, then run the second plan: no dry run is left among the sessions
    page.goto(f"{stack.url}/#/cells/{cell_id}/start")
    page.wait_for_selector("#plan")
    page.fill("#count", "14")  # a first calibration needs 13 (issue 14: spare equations to check the fit)
    for _ in range(2):
        shown = page.query_selector("#confirm-start")
        page.click("#plan")
        if shown is not None:  # the new plan replaces the one shown
            shown.wait_for_element_state("hidden")
        page.wait_for_selector("#confirm-start:not([disabled])")
    page.click("#confirm-start")
    confirm(page, "Start the session?")
    page.wait_for_url(re.compile(r"#/sessions/\d+$"))
    page.wait_for_selector("#open-result", timeout=90_000)
    done = page.inner_text("#done-banner")
    assert done.startswith("Calibrated.") and "14 poses" in done, done
    with page.expect_download() as dl:  # the session's measurements, as `recal identify` reads them
        page.click("#download-measurements")
    csv_path = tmp_path / dl.value.suggested_filename
    dl.value.save_as(csv_path)
    rows = [ln for ln in csv_path.read_text().splitlines() if not ln.startswith("#")]
    assert rows[0].startswith("q1,q2,q3,q4,q5,q6,x,y,z") and len(rows) == 15, rows[:2]
    sessions = api(stack, "GET", f"/cells/{cell_id}/sessions")
    assert [s["kind"] for s in sessions] == ["pose", "verify"] and not any(s["dry_run"] for s in sessions), sessions

    # the result: the identification's terms are in a closed "details" fold
    page.click("#open-result")
    page.wait_for_selector("#summary")
    assert page.get_attribute("details#details", "open") is None
    outside = page.evaluate(TEXT_OUTSIDE_DETAILS)
    for term in ("ftol", "χ²", "chi2", "Hayati"):
        assert term not in outside, term
    page.click("details#details summary")
    assert "χ² / dof" in page.inner_text("details#details")
    # a bad task file: the toast names the file, row and column, not the request's "body"
    bad = tmp_path / "bad-task.csv"
    bad.write_text("q1,q2,q3,q4,q5,q6\n0,abc,0,0,0,0\n")
    page.set_input_files("#task-file", str(bad))
    page.click("#compensate")
    toast = page.locator("#toasts .notice-error").last
    toast.wait_for()
    text = toast.inner_text()
    assert text.startswith("bad-task.csv, row 1") and "column 'q2'" in text and not text.startswith("body"), text

    # after a verify session, the cell card's accuracy is its result (fresh configurations)
    check = _wait_done(
        api,
        stack,
        api(stack, "POST", f"/cells/{cell_id}/sessions", {"kind": "verify", "count": 6, "target": "smr"})["id"],
    )
    rms = check["plan_info"]["verify"]["rms"]
    summary = api(stack, "GET", f"/cells/{cell_id}/summary")
    assert summary["accuracy"]["session_id"] == check["id"] and summary["accuracy"]["rms"] == rms
    order = [c["id"] for c in api(stack, "GET", "/overview?limit=500")["cells"]]
    page.goto(f"{stack.url}/#/page/{order.index(cell_id) // 30 + 1}")  # the overview shows 30 cells a page
    card = page.locator(f".cell-card[data-cell='{cell_id}'] .accuracy")
    card.wait_for()
    assert card.locator(".big").inner_text() == f"{js_num(rms)} mm"
    assert "fresh configurations" in card.inner_text()
    page.goto(f"{stack.url}/#/cells/{cell_id}")
    page.wait_for_selector("#last-calibration")
    assert "fresh configurations" in page.inner_text("#last-calibration >> xpath=..")
    shot(page, "51-cell-verified-accuracy")

    # the register form claims no endpoint line from `make demo`
    page.goto(f"{stack.url}/#/cells/new")
    page.wait_for_selector("#endpoint-line")
    assert "make demo" not in page.inner_text("main, body")
