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


# --------------------------------------------------------------------------- a stub session kind

STUB_KIND = '''"""A stub kind: fresh configurations, measured as a verification is (docs/architecture.md)."""

from ..models import KindRules
from ..plans import random_inside
from .verify import Verify


class Stub(Verify):
    name = "stub"
    order = 90
    title = "Stub"
    summary = "a stub kind, for the worked example"
    heading = "Stub session"
    default_count = 5
    rules = KindRules(max_count=7, stores="verification")

    def plan(self, req):
        return random_inside(req.lim, req.count, req.rng, req.model)


KIND = Stub()
'''

USE_THE_STUB = """
import json
from service.kinds import KINDS, describe_kinds
from service.models import SessionCreate, kinds_that
from pydantic import ValidationError

SessionCreate(kind="stub", count=7)
try:
    SessionCreate(kind="stub", count=8)
    capped = False
except ValidationError as exc:
    capped = "at most 7 for a stub session" in str(exc)
print(json.dumps({
    "kinds": list(KINDS),
    "page": describe_kinds()[-1],
    "capped": capped,
    "verifications": kinds_that(lambda r: r.stores == "verification"),
    "enum": SessionCreate.model_json_schema()["properties"]["kind"]["enum"],
}))
"""


def test_a_stub_session_kind_is_its_module_alone(tmp_path):
    """Adding a kind, as docs/architecture.md says: one module in service/kinds/ (with its test and
    its docs). A copy of the packages with the stub added differs from this one by that file, and
    the request's schema, its caps, the store's verifications and the page's list (GET /kinds,
    describe_kinds) all have it."""
    import filecmp
    import json
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for package in ("calibration", "drivers", "fakes", "service"):
        shutil.copytree(root / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "service" / "kinds" / "stub.py").write_text(STUB_KIND)
    changed = [
        str(p.relative_to(tmp_path))
        for p in sorted(tmp_path.rglob("*.py"))
        if not (root / p.relative_to(tmp_path)).exists()
        or not filecmp.cmp(root / p.relative_to(tmp_path), p, shallow=False)
    ]
    assert changed == ["service/kinds/stub.py"]
    done = subprocess.run(
        [sys.executable, "-c", USE_THE_STUB], cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    assert seen["kinds"] == ["pose", "verify", "circle", "joint", "stub"] == seen["enum"]
    assert (
        seen["page"]["name"] == "stub" and seen["page"]["max_count"] == 7 and seen["page"]["heading"] == "Stub session"
    )
    assert seen["capped"]
    assert seen["verifications"] == ["verify", "stub"]


def test_the_page_reads_the_kinds_from_the_api(idle_app, tokens):
    from service.kinds import describe_kinds

    with idle_app() as client:
        r = client.get("/api/v1/kinds", headers=auth(tokens["viewer"]))
    assert r.status_code == 200, r.text
    assert r.json() == describe_kinds()
    assert [k["name"] for k in r.json()] == list(KINDS)
