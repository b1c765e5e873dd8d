"""Limits of what a request may carry (issue 12): bodies beyond the route's limit get 413 with
a message; numbers beyond what the model can use (1e200, 1e308) and text with NUL characters
get 422 naming the field and row, on SQLite and PostgreSQL alike, never a 500; and the client's
keep-alive connection survives them. Through a real server (uvicorn on loopback), so that the
connection is the one a client holds."""

from __future__ import annotations

import dataclasses
import http.client
import json
import threading
import time

import pytest


@pytest.fixture
def live(settings, tokens):
    """(host, port) of the service on ``settings`` (small body limits), served by uvicorn in a
    thread of this process."""
    import uvicorn

    from service.api.app import create_app
    from service.processes import free_port

    small = dataclasses.replace(settings, max_body_bytes=64 * 1024, max_task_bytes=128 * 1024)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(small), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the service did not start"
        time.sleep(0.02)
    yield ("127.0.0.1", port)
    server.should_exit = True
    thread.join(10)


class Conn:
    """One keep-alive connection; ``request`` says whether it was still the same socket."""

    def __init__(self, host, port, token):
        self.c = http.client.HTTPConnection(host, port, timeout=30)
        self.token = token
        self.sock = None

    def request(self, method, path, body=None, *, json_body=None, headers=None):
        h = {"Authorization": f"Bearer {self.token}", **(headers or {})}
        if json_body is not None:
            body = json.dumps(json_body).encode()
            h["Content-Type"] = "application/json"
        self.c.request(method, path, body=body, headers=h)
        r = self.c.getresponse()
        data = r.read()
        same = self.sock is None or self.c.sock is self.sock
        self.sock = self.c.sock
        return (
            r.status,
            (json.loads(data) if r.getheader("content-type", "").startswith("application/json") else data),
            same,
        )


def _model(target_z):
    from calibration.robots import nominal_document

    doc = nominal_document("ur10e")
    doc["targets"] = {"smr": [0, 0, target_z]}
    return doc


def test_numbers_beyond_the_model_and_nul_text_get_422_on_one_keep_alive_connection(live, tokens):
    c = Conn(*live, tokens["technician"])
    for value in (1e200, 1e308):
        status, body, same = c.request("POST", "/api/v1/cells", json_body={"name": f"c{value}", "model": _model(value)})
        assert status == 422 and same, body
        assert body["errors"][0]["field"] == "body.model"
        assert "model.targets.smr[2]: expected a number from -1e+09 to 1e+09" in body["detail"], body
    # inf is not JSON; the text a client may send anyway
    status, body, same = c.request(
        "POST",
        "/api/v1/cells",
        b'{"name": "i", "model": {"a": Infinity}}',
        headers={"Content-Type": "application/json"},
    )
    assert status == 422 and same, body
    for doc in (
        {"name": "a\x00b", "model": _model(50)},
        {"name": "ok", "site": "s\x00", "model": _model(50)},
        {"name": "ok", "model": {**_model(50), "name": "ur\x00"}},
    ):
        status, body, same = c.request("POST", "/api/v1/cells", json_body=doc)
        assert status == 422 and same, body
        assert "NUL" in body["detail"]
    status, body, _ = c.request("POST", "/api/v1/cells", json_body={"name": "ok", "model": _model(50)})
    assert status == 201, body
    cell = body["id"]
    for doc in ({"name": "t\x00", "content": "x\n"}, {"name": "t.csv", "content": "x,y\n1\x00,2\n"}):
        status, body, same = c.request("POST", f"/api/v1/cells/{cell}/tasks", json_body=doc)
        assert status == 422 and same and "NUL" in body["detail"], body
    status, body, same = c.request("GET", "/api/v1/cells?site=a%00b")
    assert status == 422 and same and body["errors"][0]["field"] == "query.site", body
    # the connection still serves
    status, body, same = c.request("GET", f"/api/v1/cells/{cell}")
    assert status == 200 and same


def test_a_compensation_row_beyond_the_model_names_row_and_column(live, tokens, stored_session, settings):
    c = Conn(*live, tokens["technician"])
    status, body, _ = c.request("POST", "/api/v1/cells", json_body={"name": "comp", "model": _model(50)})
    assert status == 201
    _, cal = stored_session(body["id"], seed=2)
    task = "name,x,y,z,qw,qx,qy,qz\nP1,800,100,500,0,1,0,0\nP2,1e308,100,500,0,1,0,0\n"
    status, body, same = c.request("POST", f"/api/v1/calibrations/{cal}/compensate?name=weld.csv", task.encode())
    assert status == 422 and same, body
    # the message recal compensate gives for the same file (tests/cli/test_compensate_cli.py)
    assert body["detail"] == {
        "field": "body",
        "message": "weld.csv, row 2 (line 3), column 'x': 1e308 is beyond any "
        "robot cell; expected a magnitude of at most 1e+08 in the "
        "model's units",
    }
    status, body, same = c.request("POST", f"/api/v1/calibrations/{cal}/compensate", b"x,y\n\x00\n")
    assert status == 422 and same and "NUL" in body["detail"]["message"]


def test_bodies_beyond_the_routes_limit_get_413_with_a_message(live, tokens):
    c = Conn(*live, tokens["technician"])
    big_doc = {"name": "big", "model": _model(50), "devices": {"note": "x" * 70_000}}
    status, body, _ = c.request("POST", "/api/v1/cells", json_body=big_doc)
    assert status == 413
    assert body["detail"] == (
        "request body too large: at most 65536 bytes on this route (the service's RECAL_MAX_BODY_BYTES setting)"
    )
    c = Conn(*live, tokens["technician"])
    status, body, _ = c.request("POST", "/api/v1/cells", json_body={"name": "small", "model": _model(50)})
    assert status == 201
    cell = body["id"]
    # task files have their own, larger limit: 100 kB passes the documents' limit...
    task = "name,q1,q2,q3,q4,q5,q6\n" + "P,1,2,3,4,5,6\n" * 7000
    assert 64 * 1024 < len(task) < 128 * 1024
    status, body, _ = c.request("POST", f"/api/v1/cells/{cell}/tasks", json_body={"name": "t.csv", "content": task})
    assert status == 201, body
    # ...and beyond it 413, declared or streamed (chunked: no Content-Length to go by)
    huge = task * 2
    status, body, _ = c.request("POST", "/api/v1/calibrations/1/compensate", huge.encode())
    assert status == 413 and "RECAL_MAX_TASK_BYTES" in body["detail"]
    c = Conn(*live, tokens["technician"])
    c.c.putrequest("POST", f"/api/v1/cells/{cell}/tasks")
    c.c.putheader("Authorization", f"Bearer {tokens['technician']}")
    c.c.putheader("Content-Type", "application/json")
    c.c.putheader("Transfer-Encoding", "chunked")
    c.c.endheaders()
    doc = json.dumps({"name": "t.csv", "content": huge}).encode()
    try:
        for k in range(0, len(doc), 16384):
            chunk = doc[k : k + 16384]
            c.c.send(b"%x\r\n%s\r\n" % (len(chunk), chunk))
        c.c.send(b"0\r\n\r\n")
    except (BrokenPipeError, ConnectionResetError):
        pass  # the service may answer and close before the whole body is sent
    r = c.c.getresponse()
    assert r.status == 413 and "RECAL_MAX_TASK_BYTES" in json.loads(r.read())["detail"]
