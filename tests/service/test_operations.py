"""What an operator's tools read (issue 12): readiness (database and runner), Prometheus
metrics, one structured log line per request without secrets, and the API documentation served
from the service's own files."""

from __future__ import annotations

import json
import logging

from prometheus_client.parser import text_string_to_metric_families

from .conftest import auth, register_cell


def test_ready_checks_the_database_and_the_runner(idle_app):
    with idle_app() as client:
        r = client.get("/api/v1/ready")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["ready"] is True and set(body["checks"]) == {"database", "runner"}
        assert all(c["ok"] for c in body["checks"].values())
        client.app.state.engine.dispose()
        client.app.state.engine.url  # noqa: B018 - the same engine, pointed nowhere below
        from service.store import make_engine

        real = client.app.state.engine
        client.app.state.engine = make_engine("postgresql+psycopg://nobody@127.0.0.1:1/none")  # nothing listens
        try:
            r = client.get("/api/v1/ready")
        finally:
            client.app.state.engine = real
        assert r.status_code == 503
        assert r.json()["ready"] is False and r.json()["checks"]["database"]["ok"] is False
        assert client.get("/api/v1/health").status_code == 200  # alive, not ready


def _samples(text: str) -> dict:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out.setdefault(s.name, []).append((s.labels, s.value))
    return out


def test_metrics_count_requests_sessions_measurements_and_verified_accuracy(idle_app, tokens, stored_session):
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "metered")["id"]
        client.patch(f"/api/v1/cells/{cell}", json={"drift_threshold": 0.05}, headers=auth(tokens["technician"]))
        pose, _ = stored_session(cell, seed=2)
        verify, _ = stored_session(cell, kind="verify", seed=3, n=12)
        for _ in range(3):
            assert client.get(f"/api/v1/sessions/{pose}", headers=auth(tokens["viewer"])).status_code == 200
            assert client.get(f"/api/v1/sessions/{pose}/live", headers=auth(tokens["viewer"])).status_code == 200
        r = client.get("/metrics")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        m = _samples(r.text)
        counts = {
            lab["route"]: v
            for lab, v in m["recal_request_duration_seconds_count"]
            if lab["method"] == "GET" and lab["status"] == "200"
        }
        assert counts["/api/v1/sessions/{session_id}"] == 3  # by route template, never by id
        assert counts["/api/v1/sessions/{session_id}/live"] == 3  # the page cache's answers too
        assert dict((lab["state"], v) for lab, v in m["recal_sessions"]) == {"completed": 2}
        assert m["recal_measurements"][0][1] == 30 + 12
        v = client.get(f"/api/v1/sessions/{verify}", headers=auth(tokens["viewer"])).json()["plan_info"]["verify"]
        ((labels, vmax),) = m["recal_cell_verified_max"]
        assert labels == {"cell": "metered", "unit": "mm"} and vmax == v["max"]
        assert m["recal_cell_verified_rms"][0][1] == v["rms"]
        assert m["recal_cell_drift_ratio"][0][1] == v["max"] / 0.05


def test_one_structured_log_line_per_request_without_secrets(idle_app, tokens, caplog):
    with idle_app() as client, caplog.at_level(logging.INFO, logger="recal.access"):
        caplog.clear()
        client.get("/api/v1/me", headers=auth(tokens["viewer"]))
        client.get(f"/api/v1/cells?token={tokens['admin']}&site=x")  # a token in a URL is refused, and not logged
        records = [r for r in caplog.records if r.name == "recal.access"]
        lines = [r.fields for r in records]
    assert [(x["method"], x["route"], x["status"]) for x in lines] == [
        ("GET", "/api/v1/me", 200),
        ("GET", "/api/v1/cells", 401),
    ]
    assert lines[1]["query"] == "token=%2A%2A%2A&site=x" and lines[0]["duration_ms"] >= 0
    # the refusal is a warning, with its reason
    assert [r.levelname for r in records] == ["INFO", "WARNING"] and lines[1]["detail"].startswith("missing token")
    assert not any(t in caplog.text for t in tokens.values())


def test_the_api_documentation_is_served_from_the_services_own_files(idle_app):
    with idle_app() as client:
        page = client.get("/docs")
        assert page.status_code == 200
        assert "cdn" not in page.text.lower() and "http" not in page.text.split("<body>")[1].split("openapi")[0]
        for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
            assert f"/docs/assets/{asset}" in page.text
            assert client.get(f"/docs/assets/{asset}").status_code == 200
        doc = client.get("/openapi.json").json()
        assert doc["components"]["securitySchemes"]["bearer"] == {
            "type": "http",
            "scheme": "bearer",
            "description": doc["components"]["securitySchemes"]["bearer"]["description"],
        }
        abort = doc["paths"]["/api/v1/sessions/{session_id}/abort"]["post"]
        assert abort["security"] == [{"bearer": []}]
        assert {"200", "401", "403", "404", "409", "422", "503"} <= set(abort["responses"])
        assert abort["responses"]["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ValidationProblem")
        assert "HTTPValidationError" not in json.dumps(doc)


def test_the_pages_cached_answers_follow_changes_and_refuse_unknown_callers(idle_app, tokens):
    with idle_app() as client:
        v = auth(tokens["viewer"])
        assert client.get("/api/v1/overview", headers=v).json()["total"] == 0
        register_cell(client, tokens["technician"], "new")  # a change: seen at once, not after the cache's time
        assert client.get("/api/v1/overview", headers=v).json()["total"] == 1
        assert client.get("/api/v1/overview", headers=auth("rc_unknown")).status_code == 401
        assert client.get("/api/v1/cells/1/summary", headers=v).status_code == 200
        assert client.get("/api/v1/cells/1/summary", headers=auth("rc_unknown")).status_code == 401
        assert client.get("/api/v1/cells/1/summary").status_code == 401
        # the overview says who asks, whatever another reader asked a moment before
        assert client.get("/api/v1/overview", headers=auth(tokens["admin"])).json()["me"]["role"] == "admin"
        assert client.get("/api/v1/overview", headers=v).json()["me"]["role"] == "viewer"
