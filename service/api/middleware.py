"""What every request passes through, as plain ASGI (no per-request thread hop, no body copy):

- :class:`BodyLimit`: request bodies beyond the route's limit (``Settings.max_task_bytes`` for
  task files, ``Settings.max_import_bytes`` for a measurement import, ``Settings.max_body_bytes``
  for everything else) answered 413 with a message,
  before the body is read (a declared ``Content-Length``) or as soon as it passes the limit
  (chunked uploads). A 50 MB task file once held the service for 5 minutes and 1.6 GB.
- :class:`RequestLog`: one structured line per request on the ``recal.access`` logger (its
  ``fields``: method, route, status, duration, client; for a refusal (4xx, a warning) or an error
  (5xx) the answer's ``detail``), with no secret: query values named like a secret are replaced
  by ``***``; the ``Authorization`` header is never read here (service/logs.py redacts anything
  token-like besides). Its duration also feeds
  the request-latency histogram of ``/metrics`` (service/api/metrics.py).
"""

from __future__ import annotations

import asyncio
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
TASK_ROUTES = (
    re.compile(r"^/api/v1/calibrations/[^/]+/compensate$"),
    re.compile(r"^/api/v1/calibrations/[^/]+/compensate-backup$"),
    re.compile(r"^/api/v1/cells/[^/]+/tasks$"),
)
IMPORT_ROUTE = re.compile(r"^/api/v1/cells/[^/]+/measurements$")  # the import of an external CSV
# A query parameter whose name contains any of these (case and separators aside) is written
# ``***``: ``auth=`` and ``authorization=`` were once logged verbatim (issue 22).
SECRET_KEYS = ("token", "ticket", "auth", "pass", "pwd", "secret", "key", "credential", "signature", "cookie")


def secret_like(name: str) -> bool:
    """Whether the query parameter ``name`` looks like it carries a credential."""
    folded = "".join(ch for ch in name.lower() if ch.isalnum())
    return any(word in folded for word in SECRET_KEYS)


class BodyTooLarge(RecalError, HTTPException):
    """A request body beyond its route's limit: answered 413."""

    def __init__(self, limit: int, setting: str):
        super().__init__(
            413,
            f"request body too large: at most {limit} bytes on this route (the service's {setting} setting)",
            headers={"Connection": "close"},
        )


def _header(scope, name: bytes) -> str | None:
    for k, v in scope.get("headers") or ():
        if k == name:
            return v.decode("latin-1")
    return None


class BodyLimit:
    def __init__(self, app, settings):
        self.app, self.settings = app, settings

    def limit_for(self, path: str) -> tuple[int, str]:
        if IMPORT_ROUTE.match(path):
            return self.settings.max_import_bytes, "RECAL_MAX_IMPORT_BYTES"
        if any(r.match(path) for r in TASK_ROUTES):
            return self.settings.max_task_bytes, "RECAL_MAX_TASK_BYTES"
        return self.settings.max_body_bytes, "RECAL_MAX_BODY_BYTES"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit, setting = self.limit_for(scope["path"])
        declared = _header(scope, b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > limit:
            if int(declared) <= DRAIN_BYTES and not _expects_continue(scope):
                await _drain(receive, DRAIN_BYTES)
            return await _send_json(
                send, 413, {"detail": BodyTooLarge(limit, setting).detail}, extra=[(b"connection", b"close")]
            )
        seen = 0

        async def limited():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:  # chunked, or more than declared: stop keeping it here
                    if message.get("more_body", False):
                        await _drain(receive, DRAIN_BYTES - seen)
                    raise BodyTooLarge(limit, setting)
            return message

        await self.app(scope, limited, send)


# How much of a body beyond its limit is read (and thrown away) before the 413. A client such as
# Python's http.client or requests sends the whole body before it reads the answer: closing the
# connection on an unread body reset it, and the client saw a connection reset instead of the
# 413. Beyond this (or when the client waits for "100 Continue" and so sends nothing unasked),
# the 413 is sent at once and the connection closed.
DRAIN_BYTES = 64 * 1024 * 1024


def _expects_continue(scope) -> bool:
    return (_header(scope, b"expect") or "").strip().lower() == "100-continue"


async def _drain(receive, budget: int) -> None:
    """Read and discard the request's body until its end or ``budget`` bytes."""
    while budget > 0:
        message = await receive()
        if message["type"] != "http.request":
            return
        budget -= len(message.get("body", b""))
        if not message.get("more_body", False):
            return


async def _send_json(send, status: int, doc: dict, extra: list | None = None) -> None:
    body = json.dumps(doc).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *(extra or []),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def redacted_query(query: str) -> str:
    """The query string with every secret-like parameter's value replaced by ``***``."""
    if not query:
        return ""
    pairs = parse_qsl(query, keep_blank_values=True)
    return urlencode([(k, "***" if secret_like(k) else v) for k, v in pairs])


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
        refusal = bytearray()  # a 4xx/5xx answer's body (its "detail"): why, in the log

        async def sending(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            elif message["type"] == "http.response.body" and status >= 400 and len(refusal) < REFUSAL_BYTES:
                refusal.extend(message.get("body", b"")[: REFUSAL_BYTES - len(refusal)])
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            elapsed = time.perf_counter() - t0
            route = route_of(scope)
            if self.observe is not None:
                self.observe(scope["method"], route, status, elapsed)
            # refusals (4xx) are warnings and server errors errors: an operator's log at
            # --log-level warning still shows every 401, 403, 409, 422
            level = logging.INFO if status < 400 else logging.WARNING if status < 500 else logging.ERROR
            if access_log.isEnabledFor(level):
                client = scope.get("client")
                query = redacted_query(scope.get("query_string", b"").decode("latin-1"))
                fields = {
                    "method": scope["method"],
                    "path": scope["path"],
                    "query": query or None,
                    "route": route,
                    "status": status,
                    "duration_ms": round(elapsed * 1e3, 2),
                    "client": f"{client[0]}:{client[1]}" if client else None,
                }
                if status >= 400:
                    fields["detail"] = _detail(bytes(refusal))
                access_log.log(
                    level,
                    "%s %s %d%s",
                    scope["method"],
                    scope["path"],
                    status,
                    f": {fields['detail']}" if status >= 400 and fields["detail"] else "",
                    extra={"fields": fields},
                )


REFUSAL_BYTES = 2048  # of a refusal's body, for its detail in the access log


def _detail(body: bytes) -> str | None:
    """A refusal's reason: its JSON body's ``detail`` (a message, or the fields at fault), or its
    text, cut to a few hundred characters."""
    text = body.decode("utf-8", errors="replace")
    try:
        detail = json.loads(text).get("detail")
    except (ValueError, AttributeError):
        detail = text
    if detail is None:
        return None
    out = detail if isinstance(detail, str) else json.dumps(detail, separators=(",", ":"))
    return out[:500]


# The routes the technician's page polls (service/web/js/views) whose answers are computed from
# several queries and the models (residuals, predicted accuracy): answered from a short-lived
# cache. The session's own status (GET /sessions/{id}) is not here: it is one indexed read
# already, and what jobs wait on.
PAGE_ROUTES = tuple(
    re.compile(p)
    for p in (
        r"^/api/v1/overview$",
        r"^/api/v1/cells/[^/]+/summary$",
        r"^/api/v1/cells/[^/]+/history$",
        r"^/api/v1/cells/[^/]+/session-list$",
        r"^/api/v1/cells/[^/]+/drift$",
        r"^/api/v1/sessions/[^/]+/measurements$",
        r"^/api/v1/sessions/[^/]+/live$",
        r"^/api/v1/calibrations/[^/]+/result$",
        r"^/api/v1/calibrations/[^/]+/comparison$",
    )
)


class PageCache:
    """Answers of the page's polled routes (:data:`PAGE_ROUTES`), kept ``ttl_s`` seconds per
    route and query, served to callers whose token the token cache verified in the last 2 s and
    whose role may read (every reader sees the same answers, except the overview's ``me``: that
    one is kept per token). A caller not in the token cache goes to the route, which checks it.

    Why: 50 pages polling their routes asked the service for the same few answers hundreds of
    times a second, each a dozen queries and some kinematics; the p99 was 2.8 s (issue 12). Now
    each answer is computed at most once per ``ttl_s``: requests arriving while it is being
    computed wait for that one computation instead of starting their own, and once it is older
    than ``ttl_s`` (but not ``2 * ttl_s``) it is still answered while one background computation
    replaces it. Any request that may
    change something (not GET, HEAD or OPTIONS) empties the cache, before and after it, so what
    a caller did is seen at once; what a running session commits is seen within ``ttl_s``."""

    def __init__(self, app, ttl_s: float = 0.5):
        self.app, self.ttl_s = app, ttl_s
        self._entries: dict[tuple, tuple[float, list[dict], object]] = {}  # key: (fresh until, answer, route)
        self._inflight: dict[tuple, asyncio.Future] = {}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        if scope["method"] not in ("GET", "HEAD", "OPTIONS"):
            self._entries.clear()
            try:
                return await self.app(scope, receive, send)
            finally:
                self._entries.clear()
        if scope["method"] != "GET" or not any(r.match(scope["path"]) for r in PAGE_ROUTES):
            return await self.app(scope, receive, send)
        from ..store import hash_token
        from .deps import PERMISSIONS, token_cache

        auth = _header(scope, b"authorization") or ""
        plain = auth[7:].strip() if auth.lower().startswith("bearer ") else ""
        tok = token_cache(scope["app"]).get(hash_token(plain)) if plain else None
        if tok is None or tok.role not in PERMISSIONS["read"]:
            return await self.app(scope, receive, send)  # not known to be a reader yet: the routes decide
        # Every reader gets the same answer, but the overview's, which says who is asking.
        key = (scope["path"], scope.get("query_string", b""), tok.id if scope["path"].endswith("/overview") else None)
        now = time.monotonic()
        hit = self._entries.get(key)
        if hit is not None:
            scope["route"] = hit[2]  # for the request log and metrics, as if routed
        if hit is not None and now < hit[0]:
            return await _replay(send, hit[1])
        running = self._inflight.get(key)
        if hit is not None and now < hit[0] + self.ttl_s:
            # Stale by less than ttl_s: answer it now and have it computed again once, in the
            # background, rather than make every poll arriving meanwhile wait for the computation.
            if running is None:
                self._inflight[key] = asyncio.get_running_loop().create_future()
                asyncio.get_running_loop().create_task(self._compute(dict(scope), key, _no_body, None))
            return await _replay(send, hit[1])
        if running is not None:  # the same answer is being computed: wait for it
            messages = await asyncio.shield(running)
            if messages is not None:
                return await _replay(send, messages)
            return await self.app(scope, receive, send)
        self._inflight[key] = asyncio.get_running_loop().create_future()
        await self._compute(scope, key, receive, send)

    async def _compute(self, scope, key, receive, send) -> None:
        """Run the route for ``key``'s future (already in ``_inflight``), forwarding its answer to
        ``send`` (None: a background refresh) and keeping it when it is a 200."""
        future = self._inflight[key]
        messages: list[dict] = []

        async def capture(message):
            messages.append(message)
            if send is not None:
                await send(message)

        ok = False
        try:
            await self.app(scope, receive, capture)
            ok = bool(messages) and messages[0].get("status") == 200
        except Exception:  # a background refresh has nobody to tell; a request re-raises
            if send is not None:
                raise
        finally:
            del self._inflight[key]
            future.set_result(messages if ok else None)
            if ok:
                if len(self._entries) > 2000:  # drop the expired ones
                    now = time.monotonic()
                    self._entries = {k: v for k, v in self._entries.items() if v[0] + self.ttl_s > now}
                self._entries[key] = (time.monotonic() + self.ttl_s, messages, scope.get("route"))
            elif send is None:
                self._entries.pop(key, None)  # the route now refuses (gone, or the caller): no stale answer


async def _no_body():
    return {"type": "http.request", "body": b"", "more_body": False}


async def _replay(send, messages: list[dict]) -> None:
    for message in messages:
        await send(message)
