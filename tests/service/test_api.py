"""The REST API in process (TestClient): auth on every route, validation errors, cells,
dry-run sessions, the store's migrations. Sessions that move a robot run against the
simulated cell in tests/system/."""

from __future__ import annotations

import re
import time

import pytest
from fastapi.testclient import TestClient

from calibration.robots import nominal_document
from service.api.app import create_app
from service.settings import Settings

from .conftest import auth


def _model(targets=None) -> dict:
    doc = nominal_document("ur5e")
    doc["targets"] = targets or {"smr": [0, 0, 50]}
    return doc


@pytest.fixture
def client(settings, tokens):
    with TestClient(create_app(settings)) as c:
        yield c


def _cell(client, tokens, name="cell-1", **extra):
    body = {"name": name, "model": _model(), "devices": {"tracker": "socket://127.0.0.1:1", "rtde": "127.0.0.19"}}
    body.update(extra)
    r = client.post("/api/v1/cells", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 201, r.text
    return r.json()


def _wait_state(client, tokens, sid, states, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = client.get(f"/api/v1/sessions/{sid}", headers=auth(tokens["viewer"])).json()
        if s["state"] in states:
            return s
        time.sleep(0.05)
    raise AssertionError(f"session {sid} did not reach {states}: {s}")


def test_health_needs_no_token(client):
    assert client.get("/api/v1/health").json() == {"status": "ok"}


def _routes() -> list[tuple[str, str]]:
    """Every API route (method, path) the app has, from its OpenAPI document: a route added
    later is checked too."""
    paths = create_app(Settings()).openapi()["paths"]
    return [(m.upper(), p) for p, ops in paths.items() for m in ops]


PUBLIC = ("/api/v1/health", "/api/v1/ready")  # for load balancers: no token, nothing of a cell's
# POSTs that change nothing: a viewer watching a session asks for its event stream's ticket.
READING_POSTS = (("POST", "/api/v1/sessions/{session_id}/events/ticket"),)
MUTATING = [(m, p) for m, p in _routes() if m in ("POST", "PUT", "PATCH", "DELETE") and (m, p) not in READING_POSTS]
READING = [(m, p) for m, p in _routes() if (m == "GET" and p not in PUBLIC) or (m, p) in READING_POSTS]


def _concrete(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "1", path)


def test_every_route_needs_a_token_and_viewers_may_not_change_anything(client, tokens):
    assert ("POST", "/api/v1/cells/{cell_id}/devices/test") in MUTATING
    assert ("POST", "/api/v1/sessions/{session_id}/run") in MUTATING and len(MUTATING) >= 13
    wrong = []
    for method, path in MUTATING + READING:
        url = _concrete(path)
        for headers in ({}, auth("rc_not-a-token")):
            r = client.request(method, url, json={}, headers=headers)
            if r.status_code != 401:
                wrong.append(f"{method} {path} {'bad token' if headers else 'no token'}: {r.status_code}")
        if (method, path) in MUTATING:
            r = client.request(method, url, json={}, headers=auth(tokens["viewer"]))
            if r.status_code != 403:
                wrong.append(f"{method} {path} viewer: {r.status_code}")
    assert not wrong, "\n".join(wrong)


def test_job_token_may_not_register_cells_or_tokens(client, tokens):
    r = client.post("/api/v1/cells", json={"name": "x", "model": _model()}, headers=auth(tokens["job"]))
    assert r.status_code == 403
    r = client.post("/api/v1/tokens", json={"role": "admin"}, headers=auth(tokens["technician"]))
    assert r.status_code == 403


def test_register_and_read_a_cell(client, tokens):
    cell = _cell(client, tokens)
    got = client.get(f"/api/v1/cells/{cell['id']}", headers=auth(tokens["viewer"])).json()
    assert got["name"] == "cell-1" and got["model"]["convention"] == "dh" and got["last_calibration_id"] is None
    r = client.post("/api/v1/cells", json={"name": "cell-1", "model": _model()}, headers=auth(tokens["admin"]))
    assert r.status_code == 409


def test_a_bad_model_names_the_field(client, tokens):
    doc = _model()
    doc["joints"][2]["alpha"] = "ninety"
    r = client.post("/api/v1/cells", json={"name": "c", "model": doc}, headers=auth(tokens["admin"]))
    assert r.status_code == 422
    assert r.json()["detail"]["field"] == "body.model.joints[2].alpha"


@pytest.mark.parametrize(
    "body,field",
    [
        ({"kind": "dance"}, "body.kind"),
        ({"kind": "pose", "count": "many"}, "body.count"),
        ({"kind": "pose", "count": 0}, "body.count"),
        ({"kind": "pose", "device": "laser"}, "body.device"),
        ({"kind": "pose", "surprise": 1}, "body.surprise"),
        ({"kind": "pose", "target": "nope"}, "body.target"),
    ],
)
def test_session_request_validation_names_the_field(client, tokens, body, field):
    cell = _cell(client, tokens)
    r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 422, r.text
    assert field in str(r.json()["detail"])


def test_unknown_resources_are_404(client, tokens):
    h = auth(tokens["viewer"])
    for path in (
        "/api/v1/cells/99",
        "/api/v1/sessions/99",
        "/api/v1/calibrations/99",
        "/api/v1/sessions/99/measurements",
    ):
        assert client.get(path, headers=h).status_code == 404


def test_dry_run_plans_and_checks_without_devices(client, tokens):
    cell = _cell(client, tokens)
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions",
        json={"kind": "pose", "count": 12, "dry_run": True},
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 201
    s = _wait_state(client, tokens, r.json()["id"], ("completed", "failed"))
    assert s["state"] == "completed" and s["measured"] == 0
    info = s["plan_info"]
    assert info["dry_run"] and info["configurations"] == 12 and info["limits_checked"]


def test_allowed_region_is_enforced_in_the_plan(client, tokens):
    region = [[-90, 90], [-120, -30], [-100, 100], [-180, 0], [-90, 90], [-180, 180]]
    cell = _cell(client, tokens, allowed_region=region)
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions",
        json={"kind": "pose", "count": 20, "dry_run": True},
        headers=auth(tokens["technician"]),
    )
    s = _wait_state(client, tokens, r.json()["id"], ("completed", "failed"))
    for (lo, hi), (a, b) in zip(region, s["plan_info"]["joint_ranges_deg"]):
        assert lo - 1e-9 <= a and b <= hi + 1e-9


def test_device_fault_at_open_pauses_with_the_reason(client, tokens):
    # The cell's devices point at addresses where nothing listens: the session pauses, says why.
    cell = _cell(client, tokens)
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 5}, headers=auth(tokens["technician"])
    )
    s = _wait_state(client, tokens, r.json()["id"], ("paused", "failed"), timeout_s=30)
    assert s["state"] == "paused" and "devices" in s["reason"]
    # a second session cannot start while... the first is paused, so it may; but not while running
    audit = client.get("/api/v1/audit", headers=auth(tokens["admin"])).json()
    assert any(a["action"] == "start session" and a["actor"] == "technician-user" for a in audit)


def test_tokens_created_by_admin_work_and_can_be_revoked(client, tokens):
    r = client.post("/api/v1/tokens", json={"role": "viewer", "name": "tablet"}, headers=auth(tokens["admin"]))
    assert r.status_code == 201
    new = r.json()
    assert client.get("/api/v1/me", headers=auth(new["token"])).json() == {"name": "tablet", "role": "viewer"}
    client.delete(f"/api/v1/tokens/{new['id']}", headers=auth(tokens["admin"]))
    assert client.get("/api/v1/me", headers=auth(new["token"])).status_code == 401


def test_openapi_document_lists_the_contract_paths(client):
    paths = client.get("/openapi.json").json()["paths"]
    for p in (
        "/api/v1/health",
        "/api/v1/cells",
        "/api/v1/cells/{cell_id}/sessions",
        "/api/v1/sessions/{session_id}",
        "/api/v1/sessions/{session_id}/resume",
        "/api/v1/sessions/{session_id}/measurements",
        "/api/v1/sessions/{session_id}/events",
        "/api/v1/calibrations/{calibration_id}",
        "/api/v1/calibrations/{calibration_id}/compensate",
    ):
        assert p in paths


@pytest.mark.parametrize(
    "env,needle",
    [
        ({"RECAL_MAX_JOINT_SPEED": "30"}, "RECAL_MAX_JOINT_SPEED: expected 0.001 to 3.14 rad/s, got 30.0"),
        ({"RECAL_MAX_JOINT_ACCEL": "nan"}, "RECAL_MAX_JOINT_ACCEL"),
        ({"RECAL_MAX_JOINT_SPEED": "-1"}, "RECAL_MAX_JOINT_SPEED"),
        ({"RECAL_SETTLE_S": "fast"}, "RECAL_SETTLE_S: expected a number"),
    ],
)
def test_absurd_settings_stop_the_service_at_startup(monkeypatch, capsys, tmp_path, env, needle):
    from service.cli import main

    monkeypatch.setenv("RECAL_HOME", str(tmp_path))
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert main(["serve", "--port", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("recal serve: environment variable") and needle in err and "\n" not in err
