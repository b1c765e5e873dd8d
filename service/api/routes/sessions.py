"""Sessions: start, read, pause, resume, abort; their measurements and progress events."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import StreamingResponse
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ...kinds import describe_kinds
from ...models import SessionPublic, Token
from ...records import stored_rows
from ...sessions import (
    TERMINAL,
    abort_session,
    get_run,
    pause_session,
    read_public_session,
    resume_session,
)
from ..deps import PERMISSIONS, DbSession, Reader, SessionOperator, SessionRunnerDep, current_token, quick_read, tickets
from ..schemas import EventTicket, MeasurementOut, SessionKindPublic

router = APIRouter(tags=["sessions"])


def _read_public(engine, session_id: int) -> SessionPublic:
    with Session(engine) as db:
        return read_public_session(db, session_id)


@router.get("/kinds", response_model=list[SessionKindPublic])
def session_kinds(tok: Reader) -> list[dict]:
    """The kinds of session (service/kinds/), in the table's order: the page offers these."""
    return describe_kinds()


@router.get("/sessions/{session_id}", response_model=SessionPublic)
async def read_session(session_id: int, request: Request, tok: Reader):
    return await quick_read(request, _read_public, session_id)  # polled by pages and jobs: see quick_read


@router.post("/sessions/{session_id}/resume", response_model=SessionPublic)
def resume(session_id: int, db: DbSession, tok: SessionOperator, runner: SessionRunnerDep):
    """Continue a paused or interrupted session with the first configuration not yet measured."""
    return resume_session(db, get_run(db, session_id), tok, runner)


@router.post("/sessions/{session_id}/pause", response_model=SessionPublic)
def pause(session_id: int, db: DbSession, tok: SessionOperator, runner: SessionRunnerDep):
    """Pause a running session at its next step."""
    return pause_session(db, get_run(db, session_id), tok, runner)


@router.post("/sessions/{session_id}/abort", response_model=SessionPublic)
def abort(session_id: int, response: Response, db: DbSession, tok: SessionOperator, runner: SessionRunnerDep):
    """Stop the robot now and end the session (answered with the state it ends in)."""
    t0 = time.perf_counter()
    ended, stop_s = abort_session(db, get_run(db, session_id), tok, runner)
    # When, after the request reached this route, the robot was told to stop and the session's
    # end was read back (bench/heavy.py).
    response.headers["Server-Timing"] = (
        f"robot-stop;dur={(stop_s - t0) * 1e3:.1f}, session-end;dur={(time.perf_counter() - t0) * 1e3:.1f}"
    )
    return ended


@router.get("/sessions/{session_id}/measurements", response_model=list[MeasurementOut])
def measurements(session_id: int, db: DbSession, tok: Reader) -> list[dict]:
    run = get_run(db, session_id)
    return [r.model_dump(exclude={"session_id"}) for r in stored_rows(db, run)]


@router.post("/sessions/{session_id}/events/ticket", status_code=201, response_model=EventTicket)
async def events_ticket(session_id: int, request: Request, tok: Reader):
    """A ticket for one connection to the session's event stream, good for 30 seconds: what a
    browser's ``EventSource`` (which cannot send an Authorization header) puts in the stream's
    URL instead of the token (``GET .../events?ticket=...``)."""
    await quick_read(request, _read_public, session_id)  # 404 for a session that does not exist
    store = tickets(request.app)
    plain = await run_in_threadpool(store.issue, request.app.state.engine, tok, f"events:{session_id}")
    return EventTicket(ticket=plain, expires_in_s=store.ttl_s)


async def stream_reader(
    session_id: int, request: Request, ticket: Annotated[str | None, Query(max_length=200)] = None
) -> Token:
    """The event stream's caller: a ticket (single use, this session's), else the bearer token."""
    if ticket is not None:
        tok = await run_in_threadpool(
            tickets(request.app).redeem, request.app.state.engine, ticket, f"events:{session_id}"
        )
        if tok is None:
            raise HTTPException(
                401, "unknown, used or expired ticket: ask for a new one (POST /api/v1/sessions/{id}/events/ticket)"
            )
        return tok
    tok = await current_token(request)
    if tok.role not in PERMISSIONS["read"]:
        raise HTTPException(403, f"role {tok.role!r} may not do this")
    return tok


@router.get(
    "/sessions/{session_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "Server-sent events (`event: progress`), each one's data the session",
            "content": {
                "text/event-stream": {
                    "schema": {  # each event (OpenAPI 3.1: `schema`)
                        "type": "object",
                        "required": ["event", "data"],
                        "properties": {
                            "event": {"const": "progress"},
                            "data": {
                                "type": "string",
                                "contentMediaType": "application/json",
                                "contentSchema": {"$ref": "#/components/schemas/SessionPublic"},
                            },
                        },
                    }
                }
            },
        }
    },
)
async def events(session_id: int, request: Request, tok: Annotated[Token, Depends(stream_reader)]):
    """Progress as server-sent events: an ``event: progress`` with the session's state,
    planned and measured counts and reason whenever one changes; ends when the session is
    completed, failed or aborted. Authenticated by the Authorization header or by a ticket
    (``?ticket=``, from ``POST .../events/ticket``); never by a token in the URL."""
    engine = request.app.state.engine
    with Session(engine) as db:
        get_run(db, session_id)

    async def stream():
        last = None
        idle = 0.0
        while True:
            if await request.is_disconnected():
                return
            with Session(engine) as db:
                snap = read_public_session(db, session_id).model_dump(mode="json")
            key = (snap["state"], snap["measured"], snap["reason"], json.dumps(snap.get("device_state")))
            if key != last:
                last = key
                idle = 0.0
                yield f"event: progress\ndata: {json.dumps(snap)}\n\n"
                if snap["state"] in TERMINAL:
                    return
            else:
                idle += 0.25
                if idle >= 15.0:
                    idle = 0.0
                    yield ": keep-alive\n\n"
            await asyncio.sleep(0.25)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )
