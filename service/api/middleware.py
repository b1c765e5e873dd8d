"""What every request passes through, as plain ASGI (no per-request thread hop, no body copy):

- :class:`BodyLimit`: request bodies beyond the route's limit (``Settings.max_task_bytes`` for
  task files, ``Settings.max_body_bytes`` for everything else) answered 413 with a message,
  before the body is read (a declared ``Content-Length``) or as soon as it passes the limit
  (chunked uploads). A 50 MB task file once held the service for 5 minutes and 1.6 GB.
- :class:`RequestLog`: one structured line per request on the ``recal.access`` logger (method,
  route, status, duration, client), with no secret: query values named like a secret are
  replaced by ``***``; the ``Authorization`` header is never read here. Its duration also feeds
  the request-latency histogram of ``/metrics`` (service/api/metrics.py).
"""

from __future__ import annotations

import json
import logging
import re
import time
from urllib.parse import parse_qsl, urlencode

from fastapi import HTTPException

from calibration.errors import RecalError

access_log = logging.getLogger("recal.access")

# Routes whose bodies are task files (a task CSV or URScript, raw or inside JSON), answered by
# ``max_task_bytes``; any other body by ``max_body_bytes``.
TASK_ROUTES = (re.compile(r"^/api/v1/calibrations/[^/]+/compensate$"), re.compile(r"^/api/v1/cells/[^/]+/tasks$"),
               re.compile(r"^/api/v1/cells/[^/]+/measurements/import$"))
SECRET_KEYS = {"token", "ticket", "access_token", "password", "secret", "key", "api_key"}


class BodyTooLarge(RecalError, HTTPException):
    """A request body beyond its route's limit: answered 413."""

    def __init__(self, limit: int, setting: str):
        super().__init__(413, f"request body too large: at most {limit} bytes on this route (the service's "
                              f"{setting} setting)", headers={"Connection": "close"})


def _header(scope, name: bytes) -> str | None:
    for k, v in scope.get("headers") or ():
        if k == name:
            return v.decode("latin-1")
    return None


class BodyLimit:
    def __init__(self, app, settings):
        self.app, self.settings = app, settings

    def limit_for(self, path: str) -> tuple[int, str]:
        if any(r.match(path) for r in TASK_ROUTES):
            return self.settings.max_task_bytes, "RECAL_MAX_TASK_BYTES"
        return self.settings.max_body_bytes, "RECAL_MAX_BODY_BYTES"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit, setting = self.limit_for(scope["path"])
        declared = _header(scope, b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > limit:
            return await _send_json(send, 413, {"detail": BodyTooLarge(limit, setting).detail},
                                    extra=[(b"connection", b"close")])
        seen = 0

        async def limited():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:  # chunked, or more than declared: stop reading here
                    raise BodyTooLarge(limit, setting)
            return message

        await self.app(scope, limited, send)


async def _send_json(send, status: int, doc: dict, extra: list | None = None) -> None:
    body = json.dumps(doc).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(extra or [])]})
    await send({"type": "http.response.body", "body": body})


def redacted_query(query: str) -> str:
    """The query string with every secret-like parameter's value replaced by ``***``."""
    if not query:
        return ""
    pairs = parse_qsl(query, keep_blank_values=True)
    return urlencode([(k, "***" if k.lower() in SECRET_KEYS else v) for k, v in pairs])


def route_of(scope) -> str:
    """The route's template (``/api/v1/sessions/{session_id}``), or ``unmatched``: a label with
    few values (the metrics), never an id or a query."""
    route = scope.get("route")
    template, regex = getattr(route, "path", None), getattr(route, "path_regex", None)
    if template is None or regex is None:
        return "unmatched"
    # An included router's route knows its path without the router's prefix ("/sessions/{id}"):
    # the prefix is what comes before the part of the request's path the route matched.
    path = scope["path"]
    k = 0
    while k != -1:
        if regex.match(path[k:]):
            return path[:k] + template
        k = path.find("/", k + 1)
    return template


class RequestLog:
    def __init__(self, app, observe=None):
        self.app, self.observe = app, observe

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = 500  # what the client gets when the app raises before answering

        async def sending(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            elapsed = time.perf_counter() - t0
            route = route_of(scope)
            if self.observe is not None:
                self.observe(scope["method"], route, status, elapsed)
            if access_log.isEnabledFor(logging.INFO):
                client = scope.get("client")
                query = redacted_query(scope.get("query_string", b"").decode("latin-1"))
                access_log.info(json.dumps({
                    "method": scope["method"], "path": scope["path"], "query": query or None, "route": route,
                    "status": status, "duration_ms": round(elapsed * 1e3, 2),
                    "client": f"{client[0]}:{client[1]}" if client else None}, separators=(",", ":")))
