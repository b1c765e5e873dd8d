"""The technician's web page in a real (headless) browser against the real service and a
simulated cell: sign in, register a cell, test its connections, plan and start a pose session,
watch it (it pauses on a protective stop, is resumed), open the result, download the URDF,
compensate a URScript program, print the certificate; a viewer cannot start a session; pages
stay fast with a thousand stored calibrations."""

from __future__ import annotations

import json
import re
import socket
import time

import pytest


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
    page.fill("#cell-devices", json.dumps(stack.cell_ready))
    page.fill("#cell-drift", "0.1")
    shot(page, "03-register-cell")
    page.click("#save-cell")
    page.wait_for_url(re.compile(r"#/cells/\d+$"))
    cell_id = int(page.url.rsplit("/", 1)[1])
    page.wait_for_selector("h1:has-text('line 3 UR10e')")

    # --- edit it
    page.click("#edit-cell")
    page.wait_for_selector("#save-cell")
    page.fill("#cell-site", "plant B")
    page.click("#save-cell")
    page.wait_for_selector("text=site plant B")

    # --- test the connections: every device answers
    page.click("#test-devices")
    rows = page.locator("table.device-test tbody tr")
    rows.first.wait_for()
    text = page.inner_text("table.device-test")
    assert "ERROR" not in text, text
    for what in ("robot (UR RTDE)", "laser tracker", "CMM (I++ DME)", "reference encoder, joint 1"):
        assert what in text
    assert "SIM-LT" in text  # the tracker's *IDN? answer
    shot(page, "04-cell-devices-tested")

    # --- plan a pose session (a dry run: nothing moves), look at it, confirm
    page.click("#start-session")
    page.wait_for_selector("#plan")
    page.fill("#count", "24")
    page.select_option("#target", "smr")
    page.click("#plan")
    page.wait_for_selector("#plan-check")
    assert page.inner_text("#plan-check").startswith("✓")
    assert "RMS" in page.inner_text("#predicted")
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
    page.wait_for_selector("#residuals svg")
    shot(page, "06-session-paused-on-fault")
    assert unlock_protective_stop(stack.cell_host).startswith("Protective stop releasing")
    page.click("#resume")
    confirm(page, "Resume the session?")
    page.wait_for_function("document.querySelector('#state').innerText.trim() !== 'paused'")
    page.wait_for_function("(() => { const m = /(\\d+) of (\\d+)/.exec(document.querySelector('#progress').innerText);"
                           " return m && +m[1] >= 8 && +m[1] < +m[2]; })()", timeout=60_000)
    shot(page, "07-session-running")
    page.wait_for_selector("#open-result", timeout=90_000)
    assert "24 of 24" in page.inner_text("#progress")
    shot(page, "08-session-completed")

    # --- the result
    page.click("#open-result")
    page.wait_for_selector("#summary")
    summary = page.inner_text("#summary")
    assert "Before" in summary and "After" in summary and "Predicted" in summary
    for label in ("histogram of errors before", "histogram of errors after", "per-pose errors before and after",
                  "residuals against pose", "workspace map from above"):
        assert page.locator(f"svg[aria-label='{label}']").count() == 1, label
    assert page.locator("table.params tbody tr").count() > 10
    assert "same motion" in page.inner_text("table.unidentifiable")
    assert "first calibration" in page.inner_text("#compare")
    shot(page, "09-result")

    # --- downloads: the URDF
    with page.expect_download() as dl:
        page.click("#download-urdf")
    urdf = tmp_path / dl.value.suggested_filename
    dl.value.save_as(urdf)
    assert urdf.suffix == ".urdf"
    assert "<robot" in urdf.read_text() and "<joint" in urdf.read_text()

    # --- compensate a URScript program: per-point flags shown, the compensated file downloaded
    prog = tmp_path / "pick_and_place.script"
    prog.write_text(URSCRIPT)
    page.set_input_files("#task-file", str(prog))
    page.click("#compensate")
    page.wait_for_selector("#compensated", timeout=30_000)
    page.evaluate("document.querySelector('#compensated').closest('.card').scrollIntoView()")
    shot(page, "10-compensated", full_page=False)
    with page.expect_download() as dl:
        page.click("#download-compensated")
    out = tmp_path / dl.value.suggested_filename
    dl.value.save_as(out)
    assert out.name == "pick_and_place-compensated.script"
    compensated = out.read_text()
    assert compensated != URSCRIPT and "def pick_and_place():" in compensated

    # --- the certificate: printable page, the browser's print to PDF, and the service's PDF
    page.click("#open-certificate")
    page.wait_for_selector("#certificate")
    cert = page.inner_text("#certificate")
    for what in ("line 3 UR10e", "ur10e", "laser tracker", "SIM-LT", "technician-anna", "Before calibration",
                 "After calibration", "identification converged", "j2.a"):
        assert what in cert, what
    shot(page, "11-certificate")
    page.emulate_media(media="print")
    page.pdf(path=str(tmp_path / "printed.pdf"), format="A4")
    shot(page, "12-certificate-print-view")
    page.emulate_media(media="screen")
    assert (tmp_path / "printed.pdf").read_bytes()[:4] == b"%PDF"
    with page.expect_download() as dl:
        page.click("#download-pdf")
    pdf = tmp_path / "cert.pdf"
    dl.value.save_as(pdf)
    assert pdf.read_bytes()[:4] == b"%PDF" and pdf.stat().st_size > 2000

    # --- abort a session (with a confirmation), then a second calibration and the comparison
    def plan_and_start(count: int) -> None:
        page.goto(f"{stack.url}/#/cells/{cell_id}/start")
        page.wait_for_selector("#plan")
        page.fill("#count", str(count))
        page.click("#plan")
        page.wait_for_selector("#confirm-start:not([disabled])")
        page.click("#confirm-start")
        confirm(page, "Start the session?")
        page.wait_for_url(re.compile(r"#/sessions/\d+$"))

    plan_and_start(40)
    page.click("#abort")
    confirm(page, "Abort the session?")
    page.wait_for_selector("#stop-banner:has-text('Aborted')")
    shot(page, "13-session-aborted")
    plan_and_start(16)
    page.wait_for_selector("#open-result", timeout=90_000)
    page.click("#open-result")
    page.wait_for_selector("#moved-count")
    assert "calibration" in page.inner_text("#compare")
    assert page.locator("table.compare tbody tr").count() > 5
    page.evaluate("document.querySelector('#compare').closest('.card').scrollIntoView()")
    shot(page, "14-result-compared-with-previous", full_page=False)

    s = api(stack, "GET", f"/sessions/{session_id}")
    assert s["state"] == "completed" and s["calibration_id"]


def test_viewer_cannot_start_a_session(page, stack, web):
    shot, sign_in, register_cell_by_api = web.shot, web.sign_in, web.register_cell_by_api
    cell_id = register_cell_by_api(stack, "viewer's view")
    sign_in(page, stack, "viewer")
    assert page.inner_text("#role") == "viewer"
    assert page.locator("#register-cell").count() == 0
    page.goto(f"{stack.url}/#/cells/{cell_id}")
    page.wait_for_selector("h1:has-text(\"viewer's view\")")
    assert page.locator("#start-session").count() == 0
    assert page.locator("#test-devices").count() == 0
    assert page.locator("#edit-cell").count() == 0
    shot(page, "20-viewer-cell")
    page.goto(f"{stack.url}/#/cells/{cell_id}/start")
    page.wait_for_selector("#no-start")
    assert page.locator("#plan").count() == 0
    # ... and the API refuses a viewer anyway
    status = page.evaluate("""async ([id, token]) => (await fetch(`/api/v1/cells/${id}/sessions`, {method: 'POST',
        headers: {Authorization: `Bearer ${token}`, 'Content-Type': 'application/json'},
        body: JSON.stringify({kind: 'pose', count: 10})})).status""", [cell_id, stack.tokens["viewer"]])
    assert status == 403


def test_pages_stay_fast_with_a_thousand_calibrations(page, stack, web):
    """A cell with 1000 stored calibrations (reports of full size): the overview and the cell's
    page load quickly (they never load all the reports)."""
    from sqlmodel import Session

    from service.models import Calibration
    from service.settings import Settings
    from service.store import make_engine

    shot, sign_in, register_cell_by_api = web.shot, web.sign_in, web.register_cell_by_api
    cell_id = register_cell_by_api(stack, "busy cell")
    names = [f"j{i}.{f}" for i in range(1, 7) for f in ("theta", "d", "a", "alpha")]
    report = {"success": True, "rows": 40, "message": "converged",
              "parameters": [{"name": n, "unit": "mm", "value": 1.0, "change": 0.01, "std_error": 0.001} for n in names],
              "unidentifiable": [], "correlation": {"names": names, "matrix": [[0.1] * len(names)] * len(names)},
              "residuals": {"rms": 0.03, "max": 0.06}}
    model = json.loads(stack.nominal_path.read_text())
    engine = make_engine(Settings(home=stack.home).effective_database_url)
    with Session(engine) as db:
        for k in range(1000):
            db.add(Calibration(cell_id=cell_id, kind="pose", model=model, report=report, rms=0.03 + 0.01 * (k % 7) / 7))
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
    page.wait_for_selector(f"[data-cell='{cell_id}'] svg.spark polyline")
    overview_s = time.monotonic() - t
    # compared with a cell without calibrations on the same (possibly busy) machine
    assert busy_s < 2 * quiet_s + 1.5 and overview_s < 2 * quiet_s + 1.5, (quiet_s, busy_s, overview_s)
    assert busy_s < 10 and overview_s < 10


def test_page_fits_a_portrait_tablet(page, stack, web):
    """The overview and a cell's page on a tablet held upright (no sideways scrolling)."""
    shot, sign_in, TABLET = web.shot, web.sign_in, web.tablet
    page.set_viewport_size({"width": TABLET["height"], "height": TABLET["width"]})
    sign_in(page, stack)
    page.wait_for_selector(".cell-card")
    fits = "document.documentElement.scrollWidth <= window.innerWidth + 1"
    assert page.evaluate(fits)
    shot(page, "40-portrait-cells")
    cells = {c["name"]: c for c in web.api(stack, "GET", "/overview")["cells"]}
    cell = cells.get("line 3 UR10e") or next(iter(cells.values()))
    page.goto(f"{stack.url}/#/cells/{cell['id']}")
    page.wait_for_selector("#test-devices")
    assert page.evaluate(fits)
    shot(page, "41-portrait-cell")
    if cell["last"]:
        page.goto(f"{stack.url}/#/calibrations/{cell['last']['id']}")
        page.wait_for_selector("#summary")
        assert page.evaluate(fits)
        shot(page, "42-portrait-result")
