"""Health, tokens, the caller's identity and the audit log."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from sqlmodel import select

from ...models import AuditEntry, Token, TokenCreate
from ...store import audit, create_token
from ..deps import Admin, CurrentToken, DbSession, token_cache

router = APIRouter(tags=["system"])


@router.get("/health")
def health() -> dict:
    return {"status": "ok"}


@router.get("/me")
def me(tok: CurrentToken) -> dict:
    return {"name": tok.name, "role": tok.role}


@router.post("/tokens", status_code=201)
def create(body: TokenCreate, db: DbSession, tok: Admin) -> dict:
    new, plain = create_token(db, role=body.role, name=body.name)
    audit(db, actor=tok.name, action="create token", subject=f"token {new.id}", detail={"role": new.role, "name": new.name})
    return {"id": new.id, "name": new.name, "role": new.role, "token": plain}


@router.get("/tokens")
def list_tokens(db: DbSession, tok: Admin) -> list[dict]:
    return [{"id": t.id, "name": t.name, "role": t.role, "revoked": t.revoked, "created_at": t.created_at}
            for t in db.exec(select(Token).order_by(Token.id)).all()]


@router.delete("/tokens/{token_id}")
def revoke(token_id: int, request: Request, db: DbSession, tok: Admin) -> dict:
    t = db.get(Token, token_id)
    if t is None:
        raise HTTPException(404, f"no token {token_id}")
    t.revoked = True
    db.add(t)
    db.commit()
    token_cache(request.app).forget(token_id)
    audit(db, actor=tok.name, action="revoke token", subject=f"token {token_id}")
    return {"id": token_id, "revoked": True}


@router.get("/audit")
def audit_log(db: DbSession, tok: Admin, limit: int = 200) -> list[dict]:
    rows = db.exec(select(AuditEntry).order_by(AuditEntry.id.desc()).limit(max(1, min(limit, 5000)))).all()
    return [{"at": a.at, "actor": a.actor, "action": a.action, "subject": a.subject, "detail": a.detail} for a in rows]
