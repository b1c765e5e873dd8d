"""Issue 22's smaller defects (case 8), each as found: credential-looking query values in the
access log, a pose session's count (cap, docs and strict integers), PATCH's nulls in the OpenAPI
document, a payload and a KRL number beyond what the model can use."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import pytest

import service.kinds  # noqa: F401 (each kind's module fills MAX_COUNT as it registers its rules)
from service.models import MAX_COUNT

from .conftest import auth, register_cell
from .test_limits import live  # noqa: F401 (the service served by uvicorn on loopback)

DOCS = Path(__file__).resolve().parents[2] / "docs" / "service.md"
TASK = "q1,q2,q3,q4,q5,q6\n10,-80,90,-100,70,20\n"


def test_credential_looking_query_values_are_not_logged(idle_app, tokens, caplog):
    secret = "s3cr3t-value"
    names = ["auth", "authorization", "Authorization", "access_token", "apiKey", "api-key", "x_password", "ticket"]
    with idle_app() as client, caplog.at_level(logging.INFO, logger="recal.access"):
        caplog.clear()
        query = "&".join(f"{n}={secret}" for n in names)
        client.get(f"/api/v1/cells?{query}&site=plant-2", headers=auth(tokens["viewer"]))
        lines = [r.fields for r in caplog.records if r.name == "recal.access"]  # the line's fields (service/logs.py)
    assert len(lines) == 1 and secret not in caplog.text
    logged = dict(pair.split("=", 1) for pair in lines[0]["query"].split("&"))
    assert logged == {**{n: "%2A%2A%2A" for n in names}, "site": "plant-2"}  # what is not a secret stays


def _documented_caps() -> dict[str, int]:
    text = DOCS.read_text()
    table = text[text.index("| kind | what it does | result | `count` at most |") :].split("\n\n")[0]
    return {
        m.group(1): int(m.group(2))
        for m in re.finditer(r"^\| `(\w+)` \|.*\| (\d+)(?: \(× repeats\))? \|$", table, re.M)
    }


def test_the_documented_count_caps_are_the_codes():
    assert _documented_caps() == MAX_COUNT


@pytest.mark.parametrize("count", [True, "10", 10.0, MAX_COUNT["pose"] + 1])
def test_a_pose_sessions_count_is_a_json_integer_within_the_cap(idle_app, tokens, count):
    with idle_app() as c:
        cell = register_cell(c, tokens["technician"], "counted")["id"]
        h = auth(tokens["technician"])
        r = c.post(f"/api/v1/cells/{cell}/sessions", json={"kind": "pose", "count": count, "dry_run": True}, headers=h)
        assert r.status_code == 422 and r.json()["detail"].startswith("body.count"), r.text
        r = c.post(f"/api/v1/cells/{cell}/sessions", json={"kind": "verify", "count": 3, "repeats": True}, headers=h)
        assert r.status_code == 422 and "body.repeats" in r.json()["detail"], r.text
        r = c.post(
            f"/api/v1/cells/{cell}/sessions",
            json={"kind": "pose", "count": MAX_COUNT["pose"], "dry_run": True},
            headers=h,
        )
        assert r.status_code == 201 and r.json()["planned"] in (0, MAX_COUNT["pose"]), r.text


def test_patch_fields_the_service_refuses_as_null_are_not_nullable_in_the_openapi_document(idle_app, tokens):
    with idle_app() as c:
        doc = c.get("/openapi.json").json()
        schema = doc["paths"]["/api/v1/cells/{cell_id}"]["patch"]["requestBody"]["content"]["application/json"][
            "schema"
        ]
        props = doc["components"]["schemas"][schema["$ref"].split("/")[-1]]["properties"]
        for field in ("name", "model", "devices", "site"):
            assert "null" not in json.dumps(props[field]), (field, props[field])
            assert "default" not in props[field], (field, props[field])
        for field in ("allowed_region", "drift_threshold"):  # these may be null: null clears them
            assert {"type": "null"} in props[field]["anyOf"]
        cell = register_cell(c, tokens["technician"], "patched")["id"]
        r = c.patch(f"/api/v1/cells/{cell}", json={"site": "hall-3"}, headers=auth(tokens["technician"]))
        assert r.status_code == 200 and r.json()["site"] == "hall-3" and r.json()["name"] == "patched"


def test_a_payload_beyond_the_documented_bound_is_refused(calibrated, tokens):
    client, _, cal = calibrated
    h = auth(tokens["job"])
    for payload in ("1e200,0,0,0", "5,0,0,2e9", "1e10"):
        r = client.post(f"/api/v1/calibrations/{cal}/compensate?payload={payload}", content=TASK, headers=h)
        assert r.status_code == 422 and "query.payload" in r.text and "1e+09" in r.text, (payload, r.text)
    assert (
        client.post(f"/api/v1/calibrations/{cal}/compensate?payload=5,0,0,100", content=TASK, headers=h).status_code
        == 200
    )


def test_a_krl_target_beyond_any_cell_is_refused_as_urscript_is(calibrated, tokens):
    client, _, cal = calibrated
    h = auth(tokens["job"])
    krl = "DEF t( )\nPTP {X 1e200, Y 0, Z 500, A 0, B 90, C 0}\nEND\n"
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=t.src", content=krl, headers=h)
    assert r.status_code == 422 and "t.src, line 2: PTP: expected a number from -1e+09 to 1e+09" in r.text, r.text
    script = "def prog():\n  movel(p[1e197, 0.1, 0.4, 0, 3.14, 0], a=1.2, v=0.25)\nend\n"
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=prog.script", content=script, headers=h)
    assert r.status_code == 422 and "prog.script, line 2" in r.text, r.text


@pytest.mark.parametrize("megabytes", [4, 40])
def test_a_plain_client_sending_a_body_over_the_limit_reads_the_413(live, tokens, megabytes):  # noqa: F811
    """http.client (as requests) sends the whole body before it reads the answer: the service
    reads it (discarding it) and answers 413, instead of closing on an unread body, which the
    client saw as a connection reset."""
    import http.client

    body = b"q1,q2,q3,q4,q5,q6\n" + b"1,2,3,4,5,6\n" * (megabytes * 1024 * 1024 // 12)
    conn = http.client.HTTPConnection(*live, timeout=60)
    conn.request(
        "POST",
        "/api/v1/calibrations/1/compensate",
        body=body,
        headers={"Authorization": f"Bearer {tokens['job']}", "Content-Type": "text/csv"},
    )
    r = conn.getresponse()
    assert r.status == 413 and "RECAL_MAX_TASK_BYTES" in json.loads(r.read())["detail"]
    assert r.getheader("connection") == "close"
    conn.close()
