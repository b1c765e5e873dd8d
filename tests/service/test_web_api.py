"""The endpoints behind the technician's web page, in process (TestClient): the page itself,
the overview and history (paged, without reports), the result (errors before and after,
predicted accuracy over the workspace), downloads, the certificate (JSON and PDF), the
connection test, a dry run's plan and running exactly that plan, and a session's live data.
Calibrations come from simulated measurements stored as a session would store them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sqlmodel import Session, select
from urdf_check import assert_urdf_is_predict, in_file_units

from calibration.simulate import random_configurations
from service.files import load_model
from service.models import RunSession
from service.store import make_engine

from .conftest import auth, register_cell


@pytest.fixture
def client(idle_app, tokens):
    with idle_app() as c:
        yield c


def _cell(client, tokens, name="web-cell") -> dict:
    return register_cell(client, tokens["technician"], name)


def test_the_page_offers_every_export_the_api_has(client):
    """Each format of the download route has its button on the result page (issue 26: the UR
    calibration YAML had none), served as the browser gets it."""
    from service.api.routes.results import DOWNLOADS

    js = client.get("/web/js/views/result.js")
    assert js.status_code == 200
    for fmt in DOWNLOADS:
        assert f"/download/{fmt}`" in js.text, fmt


def test_the_page_is_served_at_the_root(client):
    r = client.get("/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert '<script type="module" src="/web/js/main.js">' in r.text
    js = client.get("/web/js/main.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"]
    assert client.get("/web/app.css").status_code == 200
    assert client.get("/web/../models.py").status_code == 404
    assert client.get("/web/js/nothing.js").status_code == 404
    # the API still answers JSON 404s, and the OpenAPI document does not list the page
    assert client.get("/api/v1/cells/999", headers=auth("x")).status_code == 401
    assert "/web/{path}" not in client.get("/openapi.json").json()["paths"]


def test_result_certificate_downloads_and_comparison(client, stored_session, tokens, tmp_path):
    cell = _cell(client, tokens)
    first = stored_session(cell["id"], seed=2)[1]
    second = stored_session(cell["id"], seed=3)[1]
    v = auth(tokens["viewer"])

    r = client.get(f"/api/v1/calibrations/{second}/result", headers=v)
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["previous_id"] == first
    e = res["errors"]
    assert e["available"] and len(e["pose"]) == 30 and len(e["after"]["xyz"]) == 30
    # after: the identified model fits to the instrument's noise; before: the prior's model
    assert e["after"]["stats"]["rms"] < 0.06
    assert "prior" in e["before"]["model"]
    ws = res["workspace"]
    assert ws["available"] and ws["samples"] == len(ws["radius95"]) == len(ws["points"])
    assert 0 < ws["stats95"]["mean"] < 1.0
    assert res["report"]["unidentifiable"] and res["report"]["parameters"]

    first_res = client.get(f"/api/v1/calibrations/{first}/result", headers=v).json()
    assert first_res["previous_id"] is None
    assert first_res["errors"]["before"]["stats"]["rms"] > 10 * first_res["errors"]["after"]["stats"]["rms"]
    assert "nominal" in first_res["errors"]["before"]["model"]

    cert = client.get(f"/api/v1/calibrations/{second}/certificate", headers=v).json()
    assert cert["cell"]["name"] == "web-cell" and cert["operator"] == "technician-user"
    assert cert["accuracy"]["after"]["n"] == 30 and cert["accuracy"]["before"]["rms"] > cert["accuracy"]["after"]["rms"]
    checks = {c["name"]: c["passed"] for c in cert["checks"]}
    assert checks["identification converged"] and checks["every planned configuration measured"]
    assert checks["hold-out verification on fresh configurations"] is None  # none run
    assert all(
        p["expanded_uncertainty"] == pytest.approx(2 * p["std_error"], rel=1e-3)
        for p in cert["parameters"]
        if p["std_error"]
    )
    pdf = client.get(f"/api/v1/calibrations/{second}/certificate.pdf", headers=v)
    assert pdf.status_code == 200 and pdf.content[:4] == b"%PDF"
    assert cert["number"] in pdf.headers["content-disposition"]

    downloads = {}
    for fmt, needle in (
        ("model", '"format": "recal.model/1"'),
        ("urdf", "<robot"),
        ("dh-csv", "theta"),
        ("dh-md", "|"),
        ("ur-calibration", "  wrist_3:\n"),
    ):
        d = client.get(f"/api/v1/calibrations/{second}/download/{fmt}", headers=v)
        assert d.status_code == 200, (fmt, d.text)
        assert needle in d.text and "attachment" in d.headers["content-disposition"]
        downloads[fmt] = d.text
    # the URDF, read by yourdfpy, is recal predict of the model downloaded beside it
    (tmp_path / "model.json").write_text(downloads["model"])
    (tmp_path / "cell.urdf").write_text(downloads["urdf"])
    # a calibrated UR is named by its kinematics, not its model name (issue 26): UR's joint names
    names = "ur"
    assert "shoulder_pan_joint" in downloads["urdf"], json.loads(downloads["model"])["name"]
    q = in_file_units(
        tmp_path / "model.json",
        random_configurations(load_model(tmp_path / "model.json"), 10, np.random.default_rng(3)),
    )
    assert_urdf_is_predict(tmp_path / "cell.urdf", tmp_path / "model.json", q, tmp_path, names=names)
    assert client.get(f"/api/v1/calibrations/{second}/download/step", headers=v).status_code == 404
    assert client.get(f"/api/v1/calibrations/{second}/result").status_code == 401

    hist = client.get(f"/api/v1/cells/{cell['id']}/history?limit=1", headers=v).json()
    assert hist["total"] == 2 and [i["id"] for i in hist["items"]] == [second]
    ov = client.get("/api/v1/overview", headers=v).json()
    assert ov["me"]["role"] == "viewer"
    mine = next(c for c in ov["cells"] if c["id"] == cell["id"])
    assert [t["id"] for t in mine["trend"]] == [first, second] and mine["last"]["id"] == second


def test_plan_of_a_dry_run_then_run_exactly_that_plan(client, settings, tokens):
    cell = _cell(client, tokens, "plan-cell")
    t = auth(tokens["technician"])
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 25, "dry_run": True}, headers=t
    )
    dry = r.json()
    # the stub orchestrator moves nothing: run the dry run the way the orchestrator does
    from service.orchestrator import run_session

    engine = make_engine(settings.effective_database_url)
    assert run_session(engine, settings, dry["id"]) == "completed"
    engine.dispose()
    plan = client.get(f"/api/v1/sessions/{dry['id']}/plan", headers=auth(tokens["viewer"])).json()
    assert plan["configurations"] == 25 and plan["check"]["ok"]
    assert len(plan["joints"]) == 6 and all(len(j["values"]) == 25 for j in plan["joints"])
    assert plan["predicted"]["rms"] > 0 and plan["estimated_duration_s"] > 0
    # a viewer may not run it; a technician may, but the cell has no tracker
    assert client.post(f"/api/v1/sessions/{dry['id']}/run", headers=auth(tokens["viewer"])).status_code == 403
    r = client.post(f"/api/v1/sessions/{dry['id']}/run", headers=t)
    assert r.status_code == 422 and "tracker" in r.text
    client.patch(
        f"/api/v1/cells/{cell['id']}", json={"devices": {"tracker": "socket://127.0.0.1:9", "rtde": "x"}}, headers=t
    )
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        shown = db.get(RunSession, dry["id"]).plan
    r = client.post(f"/api/v1/sessions/{dry['id']}/run", headers=t)
    assert r.status_code == 201, r.text
    run = r.json()
    assert run["planned"] == 25 and not run["dry_run"] and run["plan_info"]["from_dry_run"] == dry["id"]
    with Session(engine) as db:
        assert db.get(RunSession, run["id"]).plan == shown
    engine.dispose()
    # only one session drives a cell; a session that is not a dry run cannot be "run"
    assert client.post(f"/api/v1/sessions/{dry['id']}/run", headers=t).status_code == 409
    assert client.post(f"/api/v1/sessions/{run['id']}/run", headers=t).status_code == 409
    live = client.get(f"/api/v1/sessions/{run['id']}/live", headers=auth(tokens["viewer"])).json()
    assert live["measured"] == 0 and live["planned"] == 25
    # the connection test does not open devices a session is using
    test = client.post(f"/api/v1/cells/{cell['id']}/devices/test", headers=t).json()
    assert all(r["skipped"] for r in test["results"]) and "driving this cell" in test["results"][0]["answer"]


def test_connection_test_reports_each_device_and_its_error(client, tokens):
    cell = _cell(client, tokens, "unreachable")
    t = auth(tokens["technician"])
    client.patch(
        f"/api/v1/cells/{cell['id']}",
        json={"devices": {"tracker": "socket://127.0.0.1:9", "modbus": "127.0.0.1:9"}},
        headers=t,
    )
    assert client.post(f"/api/v1/cells/{cell['id']}/devices/test", headers=auth(tokens["viewer"])).status_code == 403
    r = client.post(f"/api/v1/cells/{cell['id']}/devices/test?timeout_s=2", headers=t)
    assert r.status_code == 200
    res = r.json()
    assert not res["ok"]
    assert {x["device"] for x in res["results"]} == {"laser tracker", "robot (Modbus TCP)"}
    assert all(x["ok"] is False and x["error"] for x in res["results"])
    last = client.get(f"/api/v1/cells/{cell['id']}/devices/test", headers=auth(tokens["viewer"])).json()
    assert last["last"]["results"] == res["results"]


def test_library_robots(client, tokens):
    v = auth(tokens["viewer"])
    names = [r["name"] for r in client.get("/api/v1/library/robots", headers=v).json()]
    assert "ur10e" in names
    assert client.get("/api/v1/library/robots/ur10e", headers=v).json()["format"] == "recal.model/1"
    assert client.get("/api/v1/library/robots/nope", headers=v).status_code == 404


def test_showing_the_plan_stores_no_session(client, settings, tokens):
    # "Show the plan" (a dry run) is a plan to confirm: the cell's sessions never list it, and
    # showing a plan again replaces the previous one instead of adding a session each time
    from service.orchestrator import run_session

    cell = _cell(client, tokens, "plans-only")
    t = auth(tokens["technician"])
    engine = make_engine(settings.effective_database_url)
    ids = []
    for _ in range(3):
        dry = client.post(
            f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 5, "dry_run": True}, headers=t
        ).json()
        assert run_session(engine, settings, dry["id"]) == "completed"
        ids.append(dry["id"])
    with Session(engine) as db:
        stored = [r.id for r in db.exec(select(RunSession).where(RunSession.cell_id == cell["id"])).all()]
    engine.dispose()
    assert stored == ids[-1:] and len(set(ids)) == 3  # a replaced plan's id is never given to the next
    v = auth(tokens["viewer"])
    assert client.get(f"/api/v1/cells/{cell['id']}/sessions", headers=v).json() == []
    assert client.get(f"/api/v1/cells/{cell['id']}/session-list", headers=v).json()["items"] == []
    assert client.get(f"/api/v1/sessions/{ids[-1]}/plan", headers=v).json()["configurations"] == 5
