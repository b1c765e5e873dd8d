"""The stored records (SQLModel tables) and the API's request/response shapes.

Tables never go over the wire: routes answer with the ``*Public`` shapes. JSON columns hold
documents (models, reports, endpoint lines) exactly as they were given.
"""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field as PField
from sqlalchemy import JSON, Column, UniqueConstraint
from sqlmodel import Field, SQLModel


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


ROLES = ("viewer", "technician", "job", "admin")
SESSION_KINDS = ("pose", "circle", "joint", "verify")
SESSION_STATES = ("planned", "running", "paused", "interrupted", "completed", "failed", "aborted")


class Cell(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True)
    name: str = Field(index=True, unique=True)
    site: str = Field(default="default", index=True)
    model: dict = Field(sa_column=Column(JSON, nullable=False))  # nominal recal.model/1
    devices: dict = Field(sa_column=Column(JSON, nullable=False))  # endpoint line shape
    allowed_region: list | None = Field(default=None, sa_column=Column(JSON))  # [[lo, hi], ...] model units
    drift_threshold: float | None = None  # model length unit; nightly recalibrates beyond it
    created_at: datetime = Field(default_factory=utcnow)


class RunSession(SQLModel, table=True):
    __tablename__ = "session"
    id: int | None = Field(default=None, primary_key=True)
    cell_id: int = Field(foreign_key="cell.id", index=True)
    kind: str
    state: str = Field(default="planned", index=True)
    planned: int = 0
    device: str = "tracker"
    target: str | None = None
    dry_run: bool = False
    plan: list | None = Field(default=None, sa_column=Column(JSON))  # joint configurations, SI
    plan_info: dict | None = Field(default=None, sa_column=Column(JSON))
    reason: str | None = None  # why it paused, failed or was interrupted
    calibration_id: int | None = None
    created_by: str = ""
    created_at: datetime = Field(default_factory=utcnow)
    updated_at: datetime = Field(default_factory=utcnow)
    lease_owner: str | None = None
    lease_expires: datetime | None = None
    requested: str | None = None  # "pause" / "abort" asked of the process running it (fleet: workers poll it)


class Measurement(SQLModel, table=True):
    __table_args__ = (UniqueConstraint("session_id", "seq", "target", name="uq_measurement_seq_target"),)
    id: int | None = Field(default=None, primary_key=True)
    session_id: int = Field(foreign_key="session.id", index=True)
    seq: int  # index in the session's plan
    target: str = ""  # "" is the tool origin
    joint: int | None = None  # circle sessions: the swept joint (1-based)
    q: list = Field(sa_column=Column(JSON, nullable=False))  # readings, SI
    x: float
    y: float
    z: float
    qw: float | None = None
    qx: float | None = None
    qy: float | None = None
    qz: float | None = None
    sigma: float | None = None  # m
    reference: float | None = None  # joint sessions: reference encoder angle, rad
    created_at: datetime = Field(default_factory=utcnow)


class Calibration(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True)
    cell_id: int = Field(foreign_key="cell.id", index=True)
    session_id: int | None = Field(default=None, foreign_key="session.id")
    kind: str = "pose"
    model: dict = Field(sa_column=Column(JSON, nullable=False))
    report: dict = Field(sa_column=Column(JSON, nullable=False))
    covariance: dict | None = Field(default=None, sa_column=Column(JSON))  # {"names": [...], "matrix": [[...]]} SI
    rms: float | None = None  # hold-out / residual RMS, model length unit
    created_at: datetime = Field(default_factory=utcnow)


class Compensation(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True)
    calibration_id: int = Field(foreign_key="calibration.id", index=True)
    name: str = ""
    mode: str = "joints"
    output: str = ""
    report: dict | None = Field(default=None, sa_column=Column(JSON))
    created_by: str = ""
    created_at: datetime = Field(default_factory=utcnow)


class TaskFile(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True)
    cell_id: int = Field(foreign_key="cell.id", index=True)
    name: str
    content: str
    mode: str = "joints"
    created_at: datetime = Field(default_factory=utcnow)


class Token(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True)
    name: str = Field(index=True)
    role: str
    hash: str = Field(index=True, unique=True)  # sha256 of the token; the token itself is never stored
    revoked: bool = False
    created_at: datetime = Field(default_factory=utcnow)


class AuditEntry(SQLModel, table=True):
    __tablename__ = "audit"
    id: int | None = Field(default=None, primary_key=True)
    at: datetime = Field(default_factory=utcnow)
    actor: str
    action: str
    subject: str
    detail: dict | None = Field(default=None, sa_column=Column(JSON))


class SchemaVersion(SQLModel, table=True):
    __tablename__ = "schema_version"
    id: int = Field(default=1, primary_key=True)
    version: int


# --------------------------------------------------------------------------- API shapes


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CellCreate(_In):
    name: str = PField(min_length=1, max_length=200)
    model: dict[str, Any]
    devices: dict[str, Any] = PField(default_factory=dict)
    site: str = "default"
    allowed_region: list[list[float]] | None = None
    drift_threshold: float | None = PField(default=None, gt=0)


class CellUpdate(_In):
    name: str | None = PField(default=None, min_length=1, max_length=200)
    devices: dict[str, Any] | None = None
    site: str | None = None
    allowed_region: list[list[float]] | None = None
    drift_threshold: float | None = PField(default=None, gt=0)


class CellPublic(BaseModel):
    id: int
    name: str
    site: str
    model: dict[str, Any]
    devices: dict[str, Any]
    allowed_region: list[list[float]] | None
    drift_threshold: float | None
    created_at: datetime
    last_calibration_id: int | None = None


class SessionCreate(_In):
    kind: Literal["pose", "circle", "joint", "verify"]
    count: int = PField(default=30, ge=1, le=100000)
    device: Literal["tracker", "cmm"] = "tracker"
    target: str | None = None
    dry_run: bool = False
    joints: list[int] | None = None  # circle / joint sessions: which joints (1-based); default all


class SessionPublic(BaseModel):
    id: int
    cell_id: int
    kind: str
    state: str
    planned: int
    measured: int
    device: str
    target: str | None
    dry_run: bool
    reason: str | None
    calibration_id: int | None
    created_by: str
    created_at: datetime
    updated_at: datetime
    plan_info: dict[str, Any] | None = None


class CalibrationPublic(BaseModel):
    id: int
    cell_id: int
    session_id: int | None
    kind: str
    model: dict[str, Any]
    report: dict[str, Any]
    rms: float | None
    created_at: datetime


class TokenCreate(_In):
    role: Literal["viewer", "technician", "job", "admin"]
    name: str = PField(default="", max_length=200)
