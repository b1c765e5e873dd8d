"""No request gives a 500: every route's path ids, query parameters and JSON bodies swept with
oversized, negative, non-finite, empty and mistyped values (the routes enumerated from the app,
so that new ones are swept too); cell fields validated with the field at fault; session counts
capped; abort during planning; a session left planned by a stop; replacing a nominal model."""

from __future__ import annotations

import re
import time

import pytest
from fastapi.testclient import TestClient
from sqlmodel import Session, select

from calibration.robots import nominal_document
from service.api.app import create_app
from service.models import MAX_COUNT, AuditEntry, RunSession
from service.store import make_engine

from .conftest import auth

HUGE = "99999999999999999999999"


def _model(**changes) -> dict:
    doc = nominal_document("ur5e")
    doc["targets"] = {"smr": [0, 0, 50]}
    doc.update(changes)
    return doc


UNREACHABLE = {"tracker": "socket://127.0.0.1:9", "rtde": "127.0.0.19"}  # nothing listens there


def _register(client, tokens, name="cell", **extra) -> dict:
    body = {"name": name, "model": _model(), "devices": UNREACHABLE, **extra}
    r = client.post("/api/v1/cells", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture
def quiet_client(idle_app, tokens):
    with idle_app(raise_server_exceptions=False) as c:
        yield c


@pytest.fixture
def client(settings, tokens):
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def _fill(path: str, ids: dict[str, str], override: dict[str, str] | None = None) -> str:
    def value(m):
        name = m.group(1)
        return (override or {}).get(name, ids.get(name, "1"))

    return re.sub(r"\{([^}]+)\}", value, path)


def test_no_request_gives_a_500(quiet_client, tokens, stored_session):
    c, h = quiet_client, auth(tokens["admin"])
    cell = _register(c, tokens, allowed_region=[[-170, 170]] * 6)
    _, cal = stored_session(cell["id"], seed=2, n=25)
    task = c.post(
        f"/api/v1/cells/{cell['id']}/tasks",
        headers=h,
        json={"name": "t.csv", "content": "q1,q2,q3,q4,q5,q6\n10,-80,90,-100,70,20\n"},
    ).json()
    comp = c.post(
        f"/api/v1/calibrations/{cal}/compensate", headers=h, content="q1,q2,q3,q4,q5,q6\n10,-80,90,-100,70,20\n"
    ).headers["x-recal-compensation"]
    session = c.post(
        f"/api/v1/cells/{cell['id']}/sessions", headers=h, json={"kind": "verify", "count": 3, "dry_run": True}
    ).json()
    spare = c.post("/api/v1/tokens", headers=h, json={"role": "viewer"}).json()
    ids = {
        "cell_id": str(cell["id"]),
        "session_id": str(session["id"]),
        "calibration_id": str(cal),
        "other_id": str(cal),
        "compensation_id": comp,
        "task_id": str(task["id"]),
        "token_id": str(spare["id"]),
        "fmt": "model",
        "name": "ur5e",
    }
    paths = c.get("/openapi.json").json()["paths"]
    assert "/api/v1/cells/{cell_id}/devices/test" in paths and "/api/v1/sessions/{session_id}/run" in paths
    failures = []

    def probe(method, url, content=None):
        headers = h if content is None else {**h, "Content-Type": "application/json"}
        r = c.request(method, url, headers=headers, content=content)
        if r.status_code >= 500:
            failures.append(f"{method} {url} {(content or '')[:40]}: {r.status_code} {r.text[:200]}")
        return r

    for path, ops in paths.items():
        params = re.findall(r"\{([^}]+)\}", path)
        for method, op in ops.items():
            method = method.upper()
            streams = path.endswith("/events")
            for p in params:
                for bad in (HUGE, "-" + HUGE, "0", "-1", "nan", "1e3", "%20"):
                    r = probe(method, _fill(path, ids, {p: bad}))
                    if p.endswith("_id") and bad in (HUGE, "-" + HUGE):
                        assert r.status_code == 422 and f"path.{p}" in r.json()["detail"], (path, bad, r.text)
            if streams:
                continue  # a stream of a real session runs until the session ends
            for q in [x["name"] for x in op.get("parameters", []) if x["in"] == "query"]:
                for bad in (HUGE, "-" + HUGE, "nan", "inf", "-1", "", "x"):
                    probe(method, _fill(path, ids) + f"?{q}={bad}")
            if "requestBody" in op:
                for body in ("{}", "[]", '"x"', '{"name": NaN, "model": {"a": Infinity}}', "{", "null"):
                    probe(method, _fill(path, ids), content=body)
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize(
    "extra,field",
    [
        ({"allowed_region": [[-90, 90]] * 5}, "body.allowed_region"),
        ({"allowed_region": [[-90, 90]] * 2 + [[30, -30]] + [[-90, 90]] * 3}, "body.allowed_region[2]"),
        ({"allowed_region": [[-90, 90, 0]] + [[-90, 90]] * 5}, "body.allowed_region[0]"),
        ({"allowed_region": [[400, 500]] + [[-90, 90]] * 5}, "body.allowed_region[0]"),
        ({"site": ""}, "body.site"),
        ({"site": "  "}, "body.site"),
        ({"name": " padded"}, "body.name"),
        ({"drift_threshold": 0}, "body.drift_threshold"),
    ],
)
def test_cell_fields_are_validated_naming_the_field(quiet_client, tokens, extra, field):
    body = {"name": "c", "model": _model(), "devices": {}, **extra}
    r = quiet_client.post("/api/v1/cells", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert field == (detail["field"] if isinstance(detail, dict) else detail.split(":")[0]), detail
    # the same through PATCH of a cell that is fine
    cell = _register(quiet_client, tokens, name="fine")
    r = quiet_client.patch(f"/api/v1/cells/{cell['id']}", json=extra, headers=auth(tokens["technician"]))
    assert r.status_code == 422, r.text


@pytest.mark.parametrize(
    "raw,field",
    [
        (
            '"allowed_region": [[-90, NaN], [-90, 90], [-90, 90], [-90, 90], [-90, 90], [-90, 90]]',
            "body.allowed_region[0][1]",
        ),
        ('"drift_threshold": Infinity', "body.drift_threshold"),
        ('"devices": {"tracker": NaN}', "body.devices"),
    ],
)
def test_non_finite_numbers_are_refused(quiet_client, tokens, raw, field):
    import json

    body = '{"name": "c", "model": ' + json.dumps(_model()) + ", " + raw + "}"
    r = quiet_client.post(
        "/api/v1/cells", content=body, headers={**auth(tokens["technician"]), "Content-Type": "application/json"}
    )
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(field + ":"), r.json()["detail"]


def test_patch_refuses_nulls_and_a_taken_name(quiet_client, tokens):
    a = _register(quiet_client, tokens, name="a")
    _register(quiet_client, tokens, name="b")
    t = auth(tokens["technician"])
    for field in ("name", "site", "devices", "model"):
        r = quiet_client.patch(f"/api/v1/cells/{a['id']}", json={field: None}, headers=t)
        assert r.status_code == 422 and f"body.{field}" in r.text, r.text
    assert quiet_client.patch(f"/api/v1/cells/{a['id']}", json={"name": "b"}, headers=t).status_code == 409
    r = quiet_client.patch(
        f"/api/v1/cells/{a['id']}", json={"allowed_region": None, "drift_threshold": None}, headers=t
    )
    assert r.status_code == 200 and r.json()["allowed_region"] is None


@pytest.mark.parametrize(
    "body,field",
    [
        ({"kind": "pose", "count": 100000}, "body.count"),
        ({"kind": "pose", "count": MAX_COUNT["pose"] + 1}, "body.count"),
        ({"kind": "circle", "count": MAX_COUNT["circle"] + 1}, "body.count"),
        ({"kind": "verify", "count": 50, "repeats": 11}, "body.repeats"),
        ({"kind": "pose", "repeats": 3}, "body.repeats"),
        ({"kind": "joint", "joints": [1, 7]}, "body.joints[1]"),
        ({"kind": "circle", "joints": [2, 2]}, "body.joints[1]"),
    ],
)
def test_session_counts_are_capped(quiet_client, tokens, body, field):
    cell = _register(quiet_client, tokens)
    r = quiet_client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={**body, "dry_run": True}, headers=auth(tokens["technician"])
    )
    assert r.status_code == 422, r.text
    assert field in str(r.json()["detail"])


def test_abort_while_planning_ends_the_session_aborted(client, tokens):
    # The largest pose session plans for seconds; the abort stops it between two phases of the
    # planning (before, planning ran to its end and the session never became aborted).
    cell = _register(client, tokens)
    t = auth(tokens["technician"])
    s = client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": MAX_COUNT["pose"]}, headers=t
    ).json()
    t0 = time.monotonic()
    r = client.post(f"/api/v1/sessions/{s['id']}/abort", headers=t)
    assert r.status_code == 200
    deadline = time.monotonic() + 60
    while (got := client.get(f"/api/v1/sessions/{s['id']}", headers=t).json())["state"] in ("planned", "running"):
        assert time.monotonic() < deadline, got
        time.sleep(0.05)
    assert got["state"] == "aborted" and got["measured"] == 0, got
    assert got["planned"] == MAX_COUNT["pose"] and got["plan_info"] is None  # stopped before its plan was stored
    print(f"aborted while planning, {time.monotonic() - t0:.1f} s after the request")
    # the cell is free again
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3, "dry_run": True}, headers=t
    )
    assert r.status_code == 201


def test_a_session_left_planned_by_a_stop_does_not_hold_its_cell(idle_app, settings, tokens):
    with idle_app() as c:
        cell = _register(c, tokens)
        t = auth(tokens["technician"])
        left = c.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3}, headers=t).json()
        assert left["state"] == "planned"  # nobody runs it (the process "stops" during planning)
        assert (
            c.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3}, headers=t).status_code
            == 409
        )
    with idle_app() as c:  # the next start
        got = c.get(f"/api/v1/sessions/{left['id']}", headers=t).json()
        assert got["state"] == "interrupted" and "planned" in got["reason"]
        r = c.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3}, headers=t)
        assert r.status_code == 201, r.text


def test_replacing_the_nominal_model(quiet_client, settings, tokens, stored_session):
    c, t = quiet_client, auth(tokens["technician"])
    cell = _register(c, tokens, allowed_region=[[-170, 170]] * 6)
    _, first = stored_session(cell["id"], seed=2, n=25)
    assert c.get(f"/api/v1/calibrations/{first}", headers=t).json()["nominal_version"] == 1
    new = _model(tool=[0, 0, 100, 0, 0, 0], name="ur5e-with-tool")
    # validated as at registration, the cell's region checked against it
    bad = _model()
    bad["joints"][1]["a"] = "far"
    r = c.patch(f"/api/v1/cells/{cell['id']}", json={"model": bad}, headers=t)
    assert r.status_code == 422 and r.json()["detail"]["field"] == "body.model.joints[1].a"
    five = _model()
    five["joints"] = five["joints"][:5]
    r = c.patch(f"/api/v1/cells/{cell['id']}", json={"model": five}, headers=t)
    assert r.status_code == 422 and r.json()["detail"]["field"] == "body.allowed_region", r.text
    # refused while a session drives the cell
    s = c.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3}, headers=t).json()
    assert c.patch(f"/api/v1/cells/{cell['id']}", json={"model": new}, headers=t).status_code == 409
    c.post(f"/api/v1/sessions/{s['id']}/abort", headers=t)
    r = c.patch(f"/api/v1/cells/{cell['id']}", json={"model": new}, headers=t)
    assert r.status_code == 200, r.text
    assert r.json()["model"]["name"] == "ur5e-with-tool" and r.json()["model_version"] == 2
    # calibrations of the old nominal are history now: none is current, none serves as prior
    assert r.json()["last_calibration_id"] is None
    _, second = stored_session(cell["id"], seed=3, n=25)
    cal = c.get(f"/api/v1/calibrations/{second}", headers=t).json()
    assert cal["nominal_version"] == 2 and cal["report"]["prior"] is None
    assert c.get(f"/api/v1/cells/{cell['id']}", headers=t).json()["last_calibration_id"] == second
    # the old calibration's result still compares it with the nominal it was identified from
    before = c.get(f"/api/v1/calibrations/{first}/result", headers=t).json()["errors"]["before"]
    assert "identified from (version 1)" in before["model"]
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        edits = [
            a
            for a in db.exec(select(AuditEntry).where(AuditEntry.action == "edit cell")).all()
            if "old_model" in (a.detail or {})
        ]
    engine.dispose()
    assert len(edits) == 1 and edits[0].detail["old_model"]["name"] == _model()["name"]
    assert edits[0].detail["old_model_version"] == 1


def test_a_session_planned_for_a_replaced_nominal_does_not_resume(quiet_client, settings, tokens):
    c, t = quiet_client, auth(tokens["technician"])
    cell = _register(c, tokens)
    s = c.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "verify", "count": 3}, headers=t).json()
    from service.session_loop import run_session

    engine = make_engine(settings.effective_database_url)
    assert run_session(engine, settings, s["id"]) == "paused"  # planned, then no devices
    with Session(engine) as db:
        assert db.get(RunSession, s["id"]).plan_info["nominal_version"] == 1
    engine.dispose()
    assert c.patch(f"/api/v1/cells/{cell['id']}", json={"model": _model(name="other")}, headers=t).status_code == 200
    r = c.post(f"/api/v1/sessions/{s['id']}/resume", headers=t)
    assert r.status_code == 409 and "replaced" in r.text
