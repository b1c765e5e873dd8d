"""No token in any URL or log (issue 12): a whole session through the API and the page's event
stream (opened with a single-use ticket, as service/web/js/api.js does), then every line the
service wrote (its log file: uvicorn's and Recal's loggers) is read: no token and no ticket of
the session appears in it, while the structured request lines are there."""

from __future__ import annotations

import http.client
import json
import time
from urllib.parse import urlsplit

import pytest


def _stream(url: str, path: str, headers: dict | None = None):
    u = urlsplit(url)
    c = http.client.HTTPConnection(u.hostname, u.port, timeout=120)
    c.request("GET", path, headers=headers or {})
    return c, c.getresponse()


@pytest.fixture
def stack(tmp_path, db_url):
    """The service at log level info: every line it can write about requests is written."""
    from service.processes import start_service

    from .conftest import Stack

    s = Stack(tmp_path, db_url, {"RECAL_SETTLE_S": "0"})
    s.service = start_service(s.home, s.port, env=s.env, log_path=s.home / "service.log", log_level="info")
    yield s
    s.stop()
    for c in s.cells:
        c.stop()


def test_a_whole_session_with_its_event_stream_leaves_no_secret_in_the_log(stack, register):
    cell, _ = register()
    api = stack.api("technician")
    url = stack.service.ready["url"]
    s = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": 14})
    # the page's way: a ticket for this session's stream, in the stream's URL
    ticket = api.call("POST", f"/sessions/{s['id']}/events/ticket")["ticket"]
    conn, r = _stream(url, f"/api/v1/sessions/{s['id']}/events?ticket={ticket}")
    assert r.status == 200 and r.getheader("content-type").startswith("text/event-stream")
    states = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = r.fp.readline().decode()
        if not line:
            break
        if line.startswith("data: "):
            states.append(json.loads(line[6:])["state"])
            if states[-1] in ("completed", "failed", "aborted", "paused"):
                break
    conn.close()
    assert states[-1] == "completed", states
    # a ticket serves one connection, and only its session's stream
    _, again = _stream(url, f"/api/v1/sessions/{s['id']}/events?ticket={ticket}")
    assert again.status == 401
    # a token in the URL is not accepted (and, below, not written down either)
    _, in_url = _stream(url, f"/api/v1/sessions/{s['id']}?token={stack.tokens['admin']}")
    assert in_url.status == 401
    viewer = stack.api("viewer")
    viewer.call("GET", f"/sessions/{s['id']}/measurements")
    cal = viewer.call("GET", f"/sessions/{s['id']}")["calibration_id"]
    viewer.call("GET", f"/calibrations/{cal}/result")
    stack.stop()  # everything the service wrote, to its last line
    log = (stack.home / "service.log").read_text()
    secrets = [*stack.tokens.values(), ticket]
    assert not [t for t in secrets if t in log], "a token or ticket was written to the service's log"
    lines = [json.loads(line) for line in log.splitlines() if line.strip()]  # JSON lines (service/logs.py)
    access = [line for line in lines if line["logger"] == "recal.access"]
    routes = {(a["method"], a["route"], a["status"]) for a in access}
    assert ("GET", "/api/v1/sessions/{session_id}/events", 200) in routes
    assert ("GET", "/api/v1/sessions/{session_id}/events", 401) in routes
    assert ("POST", "/api/v1/cells/{cell_id}/sessions", 201) in routes
    assert any(a["query"] == "token=%2A%2A%2A" for a in access)
