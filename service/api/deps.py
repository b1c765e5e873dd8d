"""Dependencies of the routes: the database session, the caller's token and role checks."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from sqlmodel import Session

from ..models import Token
from ..store import find_token


def get_db(request: Request) -> Iterator[Session]:
    with Session(request.app.state.engine) as db:
        yield db


DbSession = Annotated[Session, Depends(get_db)]


def get_orchestrator(request: Request):
    return request.app.state.orchestrator


Orchestrator = Annotated[object, Depends(get_orchestrator)]


def _bearer(request: Request) -> str | None:
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    # EventSource (server-sent events in a browser) cannot set headers: allow ?token= on GETs.
    if request.method == "GET":
        return request.query_params.get("token")
    return None


def current_token(request: Request, db: DbSession) -> Token:
    plain = _bearer(request)
    if not plain:
        raise HTTPException(401, "missing token: send `Authorization: Bearer <token>`",
                            headers={"WWW-Authenticate": "Bearer"})
    tok = find_token(db, plain)
    if tok is None:
        raise HTTPException(401, "unknown or revoked token", headers={"WWW-Authenticate": "Bearer"})
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

    def check(tok: CurrentToken) -> Token:
        if tok.role not in roles:
            raise HTTPException(403, f"role {tok.role!r} may not do this (needs one of: {', '.join(sorted(roles))})")
        return tok

    return Depends(check)


Reader = Annotated[Token, require("read")]
Runner = Annotated[Token, require("run")]
Compensator = Annotated[Token, require("compensate")]
CellEditor = Annotated[Token, require("cells")]
Admin = Annotated[Token, require("admin")]
