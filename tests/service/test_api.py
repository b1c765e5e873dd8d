"""The REST API in process (TestClient): auth on every route, validation errors, cells,
dry-run sessions, the store's migrations. Sessions that move a robot run against the
simulated cell in tests/system/."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from calibration.robots import nominal_document
from service.api.app import create_app



def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _model(targets=None) -> dict:
    doc = nominal_document("ur5e")
    doc["targets"] = targets or {"smr": [0, 0, 50]}
    return doc


@pytest.fixture
def client(settings, tokens):
    with TestClient(create_app(settings)) as c:
        yield c


def _cell(client, tokens, name="cell-1", **extra):
    body = {"name": name, "model": _model(), "devices": {"tracker": "socket://127.0.0.1:1", "rtde": "127.0.0.9"}}
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


MUTATING = [
    ("post", "/api/v1/cells", {"name": "x", "model": {}}),
    ("patch", "/api/v1/cells/1", {"name": "y"}),
    ("post", "/api/v1/cells/1/sessions", {"kind": "pose"}),
    ("post", "/api/v1/sessions/1/resume", None),
    ("post", "/api/v1/sessions/1/pause", None),
    ("post", "/api/v1/sessions/1/abort", None),
    ("post", "/api/v1/calibrations/1/compensate", None),
    ("post", "/api/v1/cells/1/tasks", {"name": "t.csv", "content": "x"}),
    ("post", "/api/v1/cells/1/tasks/compensate", None),
    ("post", "/api/v1/tokens", {"role": "viewer"}),
    ("delete", "/api/v1/tokens/1", None),
]


@pytest.mark.parametrize("method,path,body", MUTATING)
def test_every_mutating_route_needs_a_token(client, method, path, body):
    r = client.request(method.upper(), path, json=body)
    assert r.status_code == 401
    r = client.request(method.upper(), path, json=body, headers=auth("rc_not-a-token"))
    assert r.status_code == 401


@pytest.mark.parametrize("method,path,body", MUTATING)
def test_viewers_may_not_change_anything(client, tokens, method, path, body):
    r = client.request(method.upper(), path, json=body, headers=auth(tokens["viewer"]))
    assert r.status_code == 403, r.text


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
    assert r.json()["detail"]["field"] == "model.joints[2].alpha"


@pytest.mark.parametrize("body,field", [
    ({"kind": "dance"}, "body.kind"),
    ({"kind": "pose", "count": "many"}, "body.count"),
    ({"kind": "pose", "count": 0}, "body.count"),
    ({"kind": "pose", "device": "laser"}, "body.device"),
    ({"kind": "pose", "surprise": 1}, "body.surprise"),
    ({"kind": "pose", "target": "nope"}, "body.target"),
])
def test_session_request_validation_names_the_field(client, tokens, body, field):
    cell = _cell(client, tokens)
    r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 422, r.text
    assert field in str(r.json()["detail"])


def test_unknown_resources_are_404(client, tokens):
    h = auth(tokens["viewer"])
    for path in ("/api/v1/cells/99", "/api/v1/sessions/99", "/api/v1/calibrations/99", "/api/v1/sessions/99/measurements"):
        assert client.get(path, headers=h).status_code == 404


def test_dry_run_plans_and_checks_without_devices(client, tokens):
    cell = _cell(client, tokens)
    r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 12, "dry_run": True},
                    headers=auth(tokens["technician"]))
    assert r.status_code == 201
    s = _wait_state(client, tokens, r.json()["id"], ("completed", "failed"))
    assert s["state"] == "completed" and s["measured"] == 0
    info = s["plan_info"]
    assert info["dry_run"] and info["configurations"] == 12 and info["limits_checked"]


def test_allowed_region_is_enforced_in_the_plan(client, tokens):
    region = [[-90, 90], [-120, -30], [-100, 100], [-180, 0], [-90, 90], [-180, 180]]
    cell = _cell(client, tokens, allowed_region=region)
    r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 20, "dry_run": True},
                    headers=auth(tokens["technician"]))
    s = _wait_state(client, tokens, r.json()["id"], ("completed", "failed"))
    for (lo, hi), (a, b) in zip(region, s["plan_info"]["joint_ranges_deg"]):
        assert lo - 1e-9 <= a and b <= hi + 1e-9


def test_device_fault_at_open_pauses_with_the_reason(client, tokens):
    # The cell's devices point at addresses where nothing listens: the session pauses, says why.
    cell = _cell(client, tokens)
    r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 5},
                    headers=auth(tokens["technician"]))
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
    for p in ("/api/v1/health", "/api/v1/cells", "/api/v1/cells/{cell_id}/sessions", "/api/v1/sessions/{session_id}",
              "/api/v1/sessions/{session_id}/resume", "/api/v1/sessions/{session_id}/measurements",
              "/api/v1/sessions/{session_id}/events", "/api/v1/calibrations/{calibration_id}",
              "/api/v1/calibrations/{calibration_id}/compensate"):
        assert p in paths
