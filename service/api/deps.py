"""Dependencies of the routes: the database session, the caller's token and role checks."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from datetime import datetime
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPBearer
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ..models import Token, utcnow
from ..runners import SessionRunner
from ..store import find_token, hash_token, issue_ticket, redeem_ticket


def get_db(request: Request) -> Iterator[Session]:
    with Session(request.app.state.engine) as db:
        yield db


DbSession = Annotated[Session, Depends(get_db)]


def get_runner(request: Request):
    return request.app.state.runner


SessionRunnerDep = Annotated[SessionRunner, Depends(get_runner)]


# The bearer scheme of the OpenAPI document (auto_error off: a missing token is our own 401 with
# its message). A token is only ever taken from the Authorization header, never from a URL (URLs
# end up in access logs, proxies' logs and browser history): the page's event stream, which
# cannot send headers, uses a short-lived single-use ticket instead (:class:`Tickets`).
bearer_scheme = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="An API token (`recal token create`), as `Authorization: Bearer <token>`.",
)


def _bearer(request: Request) -> str | None:
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return None


class TokenCache:
    """Tokens verified in the last ``ttl_s`` seconds, keyed by their hash, so that a page or a
    nightly job polling a session does not cost a database query per request. Revoking a token
    through this process forgets it at once; other API processes of a fleet see the revocation
    within ``ttl_s``. Unknown tokens are never cached (a token created a moment ago works)."""

    def __init__(self, ttl_s: float = 2.0):
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[float, Token]] = {}
        self._lock = threading.Lock()

    def get(self, token_hash: str) -> Token | None:
        with self._lock:
            hit = self._entries.get(token_hash)
        if hit is None or time.monotonic() - hit[0] > self.ttl_s:
            return None
        return hit[1]

    def put(self, token_hash: str, tok: Token) -> None:
        with self._lock:
            if len(self._entries) > 10_000:  # only live tokens are cached; drop the stale ones
                now = time.monotonic()
                self._entries = {k: v for k, v in self._entries.items() if now - v[0] <= self.ttl_s}
            self._entries[token_hash] = (time.monotonic(), tok)

    def forget(self, token_id: int) -> None:
        with self._lock:
            self._entries = {k: v for k, v in self._entries.items() if v[1].id != token_id}


def token_cache(app) -> TokenCache:
    cache = getattr(app.state, "token_cache", None)
    if cache is None:
        cache = app.state.token_cache = TokenCache()
    return cache


async def quick_read(request: Request, fn, *args):
    """``fn(engine, *args)``: a read of one or two indexed rows that every polled request makes
    (the caller's token, a session's progress). On SQLite it runs on the event loop: it takes a
    fraction of a millisecond on a local file, and a thread hop per request cost more than the
    query and put every request behind the GIL's 5 ms switch interval (half the throughput,
    bench/service.py). A networked database can stall (connection lost, server restarting), and
    must not stall the whole server: there it runs in the thread pool."""
    engine = request.app.state.engine
    if engine.dialect.name == "sqlite":
        return fn(engine, *args)
    return await run_in_threadpool(fn, engine, *args)


def _lookup_token(engine, plain: str) -> Token | None:
    with Session(engine) as db:
        tok = find_token(db, plain)
        return None if tok is None else Token(**tok.model_dump())  # detached: outlives the session


async def current_token(request: Request, _scheme: Annotated[object, Depends(bearer_scheme)] = None) -> Token:
    # async, and the database only on a cache miss: authentication is on every request, and a
    # thread hop plus a query per request was most of the cost of a polled GET (bench/service.py).
    plain = _bearer(request)
    if not plain:
        raise HTTPException(
            401, "missing token: send `Authorization: Bearer <token>`", headers={"WWW-Authenticate": "Bearer"}
        )
    cache, key = token_cache(request.app), hash_token(plain)
    tok = cache.get(key)
    if tok is None:
        tok = await quick_read(request, _lookup_token, plain)
        if tok is None:
            raise HTTPException(401, "unknown or revoked token", headers={"WWW-Authenticate": "Bearer"})
        cache.put(key, tok)
    return tok


CurrentToken = Annotated[Token, Depends(current_token)]

# What each role may do (contracts §9).
PERMISSIONS = {
    "read": {"viewer", "technician", "job", "admin"},
    "run": {"technician", "job", "admin"},  # start, pause, resume, abort sessions
    "compensate": {"technician", "job", "admin"},
    "cells": {"technician", "admin"},  # register and edit cells and their task files
    "admin": {"admin"},  # tokens, audit log
}


def require(permission: str):
    roles = PERMISSIONS[permission]

    async def check(tok: CurrentToken) -> Token:
        if tok.role not in roles:
            raise HTTPException(403, f"role {tok.role!r} may not do this (needs one of: {', '.join(sorted(roles))})")
        return tok

    return Depends(check)


Reader = Annotated[Token, require("read")]
SessionOperator = Annotated[Token, require("run")]
Compensator = Annotated[Token, require("compensate")]
CellEditor = Annotated[Token, require("cells")]
Admin = Annotated[Token, require("admin")]


class Tickets:
    """Short-lived, single-use tickets for the page's event stream (``EventSource`` cannot send
    an Authorization header). A ticket is issued to a caller who authenticated with their token,
    for one session's stream; it is good for ``ttl_s`` seconds and for one connection, and is
    stored only as its hash. A ticket in an access log is worthless: it was used up when the
    stream opened. Kept in the database (``store.issue_ticket``, ``store.redeem_ticket``), so
    that every API process of a fleet accepts a ticket any of them issued, once. ``clock``: the
    current UTC time (tests move it on to see a ticket expire)."""

    def __init__(self, ttl_s: float = 30.0, clock: Callable[[], datetime] = utcnow):
        self.ttl_s, self.clock = ttl_s, clock

    def issue(self, engine, tok: Token, scope: str) -> str:
        with Session(engine) as db:
            return issue_ticket(db, token_id=tok.id, scope=scope, ttl_s=self.ttl_s, now=self.clock())

    def redeem(self, engine, plain: str, scope: str) -> Token | None:
        with Session(engine) as db:
            tok = redeem_ticket(db, plain, scope, now=self.clock())
            return None if tok is None else Token(**tok.model_dump())  # detached: outlives the session


def tickets(app) -> Tickets:
    t = getattr(app.state, "tickets", None)
    if t is None:
        t = app.state.tickets = Tickets()
    return t
