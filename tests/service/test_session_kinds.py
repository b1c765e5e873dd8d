"""The table of session kinds (service.kinds): every kind the API accepts has one entry, and a
configuration the cell cannot run is refused when the session is started, naming the field,
with nothing stored (before, a CMM session without tooling balls or a joint session on a joint
without an encoder moved the robot to its first configuration and failed there)."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient
from sqlmodel import Session, select

from calibration.robots import nominal_document
from service.api.app import create_app
from service.kinds import KINDS, kind_of
from service.models import RunSession, SessionCreate
from service.store import make_engine

from .conftest import auth

NOWHERE = "127.0.0.19"  # nothing listens there: nothing may be opened by a refused start
CAN = {"interface": "socketcand", "channel": "vcan0", "host": NOWHERE, "port": 29536}


def test_every_kind_the_api_accepts_is_in_the_table():
    # the request's schema lists the table's kinds (the kinds register themselves with the rows)
    accepted = SessionCreate.model_json_schema()["properties"]["kind"]["enum"]
    assert accepted == list(KINDS)
    with pytest.raises(ValueError, match="Input should be 'pose', 'verify', 'circle' or 'joint'"):
        SessionCreate(kind="sweep")
    assert all(kind_of(name).name == name for name in accepted)
    with pytest.raises(ValueError, match="unknown session kind 'sweep'"):
        kind_of("sweep")


@pytest.fixture
def client(settings, tokens):
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def _cell(client, tokens, devices: dict, targets: dict) -> dict:
    doc = nominal_document("ur5e")
    doc["targets"] = targets
    r = client.post(
        "/api/v1/cells",
        json={"name": f"cell-{len(devices)}-{len(targets)}", "model": doc, "devices": devices},
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 201, r.text
    return r.json()


CASES = [
    # (devices, targets, request, field, words of the message)
    ({"rtde": NOWHERE, "cmm": f"tcp://{NOWHERE}:1294"}, {"smr": [0, 0, 50]}, {"kind": "pose", "device": "cmm"},
     "body.device", "three tooling balls"),
    ({"rtde": NOWHERE, "tracker": f"socket://{NOWHERE}:9"}, {"smr": [0, 0, 50]}, {"kind": "pose", "device": "cmm"},
     "body.device", "no CMM"),
    ({"rtde": NOWHERE, "cmm": f"tcp://{NOWHERE}:1294"}, {"smr": [0, 0, 50]}, {"kind": "verify"},
     "body.device", "no laser tracker"),
    ({"modbus": f"{NOWHERE}:502", "tracker": f"socket://{NOWHERE}:9"}, {"smr": [0, 0, 50]},
     {"kind": "pose", "payloads": [[2.0]]}, "body.payloads", "controller that takes one"),
    ({"rtde": NOWHERE, "can": CAN, "encoders": {"1": 11, "2": 12}}, {},
     {"kind": "joint", "joints": [2, 3]}, "body.joints", "joint 3; the cell has them on joint 1, 2"),
    ({"rtde": NOWHERE, "can": CAN, "encoders": {"1": 11}}, {}, {"kind": "joint"},
     "body.joints", "joint 2, 3, 4, 5, 6"),
    ({"rtde": NOWHERE, "tracker": f"socket://{NOWHERE}:9"}, {"smr": [0, 0, 50]}, {"kind": "joint"},
     "body.kind", "no reference encoders"),
]  # fmt: skip


@pytest.mark.parametrize("devices,targets,request_body,field,words", CASES)
def test_a_session_the_cell_cannot_run_is_refused_at_the_start(
    client, tokens, settings, devices, targets, request_body, field, words
):
    cell = _cell(client, tokens, devices, targets)
    r = client.post(
        f"/api/v1/cells/{cell['id']}/sessions", json={"count": 14, **request_body}, headers=auth(tokens["technician"])
    )
    assert r.status_code == 422, r.text
    assert field in r.text and words in r.text, r.text
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        assert db.exec(select(RunSession).where(RunSession.cell_id == cell["id"])).all() == []
    engine.dispose()


def test_a_dry_run_shows_the_plan_on_any_cell_but_running_it_is_checked(client, tokens):
    # Showing a plan moves nothing: it needs no instrument. Running it is a start like any other.
    cell = _cell(client, tokens, {"rtde": NOWHERE, "tracker": f"socket://{NOWHERE}:9"}, {"smr": [0, 0, 50]})
    t = auth(tokens["technician"])
    dry = client.post(
        f"/api/v1/cells/{cell['id']}/sessions",
        json={"kind": "verify", "count": 5, "device": "cmm", "dry_run": True},
        headers=t,
    ).json()
    deadline = time.monotonic() + 60
    while (got := client.get(f"/api/v1/sessions/{dry['id']}", headers=t).json())["state"] != "completed":
        assert got["state"] in ("planned", "running") and time.monotonic() < deadline, got
        time.sleep(0.05)
    r = client.post(f"/api/v1/sessions/{dry['id']}/run", headers=t)
    assert r.status_code == 422 and "no CMM" in r.text, r.text
