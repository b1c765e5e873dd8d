"""The API's response shapes beyond the store's (service.models): errors, and what the system
routes answer. Routes name these in ``response_model`` / ``responses`` so that the OpenAPI
document says what each status really carries (issue 12: a fuzzer checks every answer
against it)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class FieldProblem(BaseModel):
    field: str = Field(description="the request field at fault: `body.model.joints[2].a`, `query.limit`, `body`")
    message: str = Field(description="what was expected")


class Problem(BaseModel):
    """Every error: ``detail`` a sentence, or (a request field at fault) the field and message."""

    detail: str | FieldProblem


class ValidationProblem(BaseModel):
    """422: ``detail`` names each field at fault (one sentence, or the field and message);
    ``errors``, when the request's form was checked, lists them one by one."""

    detail: str | FieldProblem
    errors: list[FieldProblem] | None = None


class Health(BaseModel):
    status: str = Field(description="`ok`: the process answers (it reads nothing)")


class ReadyCheck(BaseModel):
    ok: bool
    detail: str


class Ready(BaseModel):
    ready: bool
    checks: dict[str, ReadyCheck]


class Me(BaseModel):
    name: str
    role: str


class TokenCreated(BaseModel):
    id: int
    name: str
    role: str
    token: str = Field(description="the token itself: shown once, stored only as its hash")


class TokenInfo(BaseModel):
    id: int
    name: str
    role: str
    revoked: bool
    created_at: Any


class TokenRevoked(BaseModel):
    id: int
    revoked: bool


class AuditRow(BaseModel):
    at: Any
    actor: str
    action: str
    subject: str
    detail: dict[str, Any] | None = None


class EventTicket(BaseModel):
    ticket: str = Field(description="for one connection to the session's event stream: `?ticket=`")
    expires_in_s: float


class TaskFileInfo(BaseModel):
    id: int
    name: str
    mode: str
    created_at: Any = None


class TaskFileContent(TaskFileInfo):
    content: str


class Document(BaseModel):
    """A JSON document whose fields the route's description lists."""

    model_config = {"extra": "allow"}
