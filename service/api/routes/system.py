"""Health, tokens, the caller's identity and the audit log."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text
from starlette.concurrency import run_in_threadpool

from ... import store
from ...models import TokenCreate
from ...store import audit, create_token
from ..deps import Admin, CurrentToken, DbSession, token_cache
from ..schemas import AuditRow, Health, Me, Ready, ReadyCheck, TokenCreated, TokenInfo, TokenRevoked

router = APIRouter(tags=["system"])


@router.get("/health", response_model=Health)
async def health():
    """The process answers (async: no thread, no database; see ``/ready``)."""
    return {"status": "ok"}


def _database_check(engine) -> ReadyCheck:
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        return ReadyCheck(ok=True, detail=f"{engine.dialect.name}: answers")
    except Exception as exc:  # noqa: BLE001 - not ready is the answer, whatever the cause
        return ReadyCheck(ok=False, detail=f"{engine.dialect.name}: {type(exc).__name__}: {str(exc).splitlines()[0]}")


@router.get("/ready", response_model=Ready, responses={503: {"model": Ready, "description": "not ready"}})
async def ready(request: Request):
    """Whether this process can take work: the database answers a query, and the runner of
    sessions is up (the embedded runner not shut down; a fleet's queue in the database).
    503 with the same body when not. No token: for load balancers and orchestrators."""
    state = request.app.state
    db = await run_in_threadpool(_database_check, state.engine)
    runner_problem = state.runner.not_ready()
    runner = ReadyCheck(ok=runner_problem is None, detail=runner_problem or type(state.runner).__name__ + ": up")
    body = Ready(ready=db.ok and runner.ok, checks={"database": db, "runner": runner})
    return JSONResponse(body.model_dump(), status_code=200 if body.ready else 503)


@router.get("/me", response_model=Me)
def me(tok: CurrentToken):
    return {"name": tok.name, "role": tok.role}


@router.post("/tokens", status_code=201, response_model=TokenCreated)
def create(body: TokenCreate, db: DbSession, tok: Admin):
    new, plain = create_token(db, role=body.role, name=body.name)
    audit(
        db,
        actor=tok.name,
        action="create token",
        subject=f"token {new.id}",
        detail={"role": new.role, "name": new.name},
    )
    return {"id": new.id, "name": new.name, "role": new.role, "token": plain}


@router.get("/tokens", response_model=list[TokenInfo])
def list_tokens(db: DbSession, tok: Admin):
    return [
        {"id": t.id, "name": t.name, "role": t.role, "revoked": t.revoked, "created_at": t.created_at}
        for t in store.list_tokens(db)
    ]


@router.delete("/tokens/{token_id}", response_model=TokenRevoked)
def revoke(token_id: int, request: Request, db: DbSession, tok: Admin):
    if not store.revoke_token(db, token_id):
        raise HTTPException(404, f"no token {token_id}")
    token_cache(request.app).forget(token_id)
    audit(db, actor=tok.name, action="revoke token", subject=f"token {token_id}")
    return {"id": token_id, "revoked": True}


@router.get("/audit", response_model=list[AuditRow])
def audit_log(
    db: DbSession,
    tok: Admin,
    limit: Annotated[int, Query(ge=1, le=5000)] = 200,
    # a cursor, not a reference to an entry (no 404 for an id that names none): hence not *_id
    older_than: Annotated[
        int | None, Query(ge=1, description="the next page: the entries older than this id (the last of a page)")
    ] = None,
):
    """The newest audit entries, newest first, a page of ``limit``; ``older_than`` pages on."""
    rows = store.audit_entries(db, limit, before_id=older_than)
    return [
        {"id": a.id, "at": a.at, "actor": a.actor, "action": a.action, "subject": a.subject, "detail": a.detail}
        for a in rows
    ]


@router.delete("/audit")
def prune_audit(
    db: DbSession,
    tok: Admin,
    before: Annotated[
        str,
        Query(
            description="delete the entries written before this time (ISO 8601, UTC when it names no zone)",
            json_schema_extra={"format": "date-time"},
        ),
    ],
) -> dict:
    """Delete the audit entries older than ``before`` (admin); the pruning is itself audited."""
    try:  # an ISO 8601 time only: a number (pydantic would read 0.5 as seconds since 1970) is refused
        at = datetime.fromisoformat(before)
    except ValueError:
        raise HTTPException(
            422, {"field": "query.before", "message": f"expected an ISO 8601 time, got {before!r}"}
        ) from None
    at = at if at.tzinfo is not None else at.replace(tzinfo=UTC)
    return {"deleted": store.prune_audit(db, before=at, actor=tok.name)}
