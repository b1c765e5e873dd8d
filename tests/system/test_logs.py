"""Logs an operator can use (issue 27): the service's log (what `recal demo` keeps as service.log)
is one format, JSON lines by default, uvicorn's own lines included, and holds the access lines,
the sessions' states (aborted, completed, paused by a device fault), the refusals (401, 422) with
their reasons, and no secret; `RECAL_LOG_FORMAT=text` gives the same records as text lines."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest

from service.client import ApiError
from service.processes import free_port, start_service

WRONG_TOKEN = "rc_NotATokenOfThisService0123456789abcdefghij"


def _status(url: str, token: str | None) -> int:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def _lines(path) -> list[dict]:
    text = path.read_text()
    assert text.strip(), f"{path} is empty"
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        try:
            out.append(json.loads(line))
        except ValueError:
            pytest.fail(f"{path}, line {n} is not a JSON object: {line!r}")
    return out


def test_the_service_log_holds_access_sessions_faults_and_refusals_without_secrets(stack, register):
    cell, fake = register(time_scale=0.2)
    api, url = stack.api(), stack.service.ready["url"]
    assert _status(f"{url}/api/v1/cells", None) == 401
    assert _status(f"{url}/api/v1/cells", WRONG_TOKEN) == 401
    with pytest.raises(ApiError) as refused:
        api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "bogus", "count": 3})
    assert refused.value.status == 422
    aborted = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 5})
    assert api.wait_session(aborted["id"], 60, measured=1)["state"] == "running"
    assert api.call("POST", f"/sessions/{aborted['id']}/abort")["state"] == "aborted"
    done = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 3})
    assert api.wait_session(done["id"], 120)["state"] == "completed"
    fake.stop()  # the cell's devices are gone: the next session pauses, a device fault
    faulted = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": 3})
    assert api.wait_session(faulted["id"], 120)["state"] == "paused"
    stack.stop()

    lines = _lines(stack.home / "service.log")
    assert all({"time", "level", "logger", "message"} <= line.keys() for line in lines)
    assert any(line["logger"].startswith("uvicorn") for line in lines), "uvicorn's lines are not in the log"
    access = [line for line in lines if line["logger"] == "recal.access"]
    unauthorized = [a for a in access if a["status"] == 401]
    assert len(unauthorized) == 2 and all(a["level"] == "warning" and a["detail"] for a in unauthorized)
    invalid = [a for a in access if a["status"] == 422]
    assert len(invalid) == 1 and "kind" in invalid[0]["detail"]
    assert any(a["status"] == 201 and a["route"] == "/api/v1/cells/{cell_id}/sessions" for a in access)
    states = {(s["session"], s["state"]): s for s in lines if s["logger"] == "recal.sessions" and "state" in s}
    assert (aborted["id"], "aborted") in states and (done["id"], "completed") in states
    paused = states[(faulted["id"], "paused")]
    assert paused["level"] == "warning" and "devices" in paused["reason"], paused
    text = (stack.home / "service.log").read_text()
    assert WRONG_TOKEN not in text and not any(t in text for t in stack.tokens.values())


def test_text_lines_on_request(tmp_path):
    service = start_service(tmp_path, free_port(), env={"RECAL_LOG_FORMAT": "text"}, log_path=tmp_path / "service.log")
    try:
        assert _status(f"{service.ready['url']}/api/v1/cells", WRONG_TOKEN) == 401
    finally:
        service.stop()
    lines = (tmp_path / "service.log").read_text().splitlines()
    assert lines and not any(line.startswith("{") for line in lines), lines
    assert any(" INFO uvicorn.error: " in line for line in lines), lines  # uvicorn's, in the same format
    refusal = [line for line in lines if " WARNING recal.access: GET /api/v1/cells 401: " in line]
    assert len(refusal) == 1 and "status=401" in refusal[0] and WRONG_TOKEN not in "\n".join(lines)


def test_an_unknown_log_format_is_refused_in_one_line(tmp_path):
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "recal", "serve", "--port", str(free_port())],
        env={**__import__("os").environ, "RECAL_HOME": str(tmp_path), "RECAL_LOG_FORMAT": "xml"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (
        done.returncode == 2
        and done.stderr.strip() == "recal serve: RECAL_LOG_FORMAT: expected one of json, text, got 'xml'"
    )
