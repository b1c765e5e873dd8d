"""The API's response shapes beyond the store's (service.models): errors, and what the system
routes answer. Routes name these in ``response_model`` / ``responses`` so that the OpenAPI
document says what each status really carries (issue 12: a fuzzer checks every answer
against it)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from ..models import SessionPublic


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
    id: int
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


class TaskFilePartContent(BaseModel):
    name: str
    content: str
    encoding: str = Field(description="`content.encode(encoding)` is the file's bytes")


class TaskFileContent(TaskFileInfo):
    content: str
    encoding: str = Field(description="`content.encode(encoding)` is the file's bytes: utf-8 or iso-8859-1")
    files: list[TaskFilePartContent] = Field(description="a KRL .src's other files (its .dat)")


class Document(BaseModel):
    """A JSON document whose fields the route's description lists."""

    model_config = {"extra": "allow"}


# --------------------------------------------------------------------------- cells, sessions, results
# Shapes of the page's and the jobs' JSON answers. Nested documents the service computes in one
# place (a calibration's report, the certificate's sections, a plan's preview) are typed as
# objects here and described by the function that builds them; ``Open`` models keep any field
# they do not list (added later by that function) instead of dropping it.

Timestamp = datetime | str  # ISO 8601; some routes format it themselves (with the UTC offset)
Number = float | None


class Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class CalibrationListItem(BaseModel):
    id: int
    kind: str
    session_id: int | None
    rms: Number
    created_at: Timestamp
    nominal_version: int | None = None
    predicted: dict[str, Any] | None = None
    # current, candidate, superseded or retired (GET /calibrations/{id}'s status)
    status: str | None = None


class DriftCalibration(BaseModel):
    id: int
    created_at: Timestamp
    rms: Number
    predicted: dict[str, Any] | None = None
    nominal_version: int | None = None


class DriftParameterPoint(BaseModel):
    calibration_id: int
    value: Number
    std_error: Number = None
    unit: str | None = None
    change: Number = None
    change_sigmas: Number = None


class DriftVerify(BaseModel):
    session_id: int
    at: Timestamp
    calibration_id: int | None = None
    n: int | None = None
    rms: Number = None
    max: Number = None
    p95: Number = None
    unit: str | None = None
    iso9283: dict[str, Any] | None = None


class Drift(BaseModel):
    calibrations: list[DriftCalibration]
    parameters: dict[str, list[DriftParameterPoint]]
    verify: list[DriftVerify]


class TaskCompensation(BaseModel):
    task_id: int
    name: str
    compensation_id: int | None = None
    summary: dict[str, Any] | None = None
    error: str | None = Field(default=None, description="why this task file could not be compensated")


class TasksCompensated(BaseModel):
    calibration_id: int
    tasks: list[TaskCompensation]


class MeasurementOut(BaseModel):
    id: int
    seq: int
    target: str
    joint: int | None = None
    q: list[float]
    x: float
    y: float
    z: float
    qw: Number = None
    qx: Number = None
    qy: Number = None
    qz: Number = None
    sigma: Number = None
    reference: Number = None
    created_at: Timestamp


class ComparedParameter(Open):
    name: str
    unit: str | None = None
    group: str
    from_: Number = Field(default=None, alias="from")
    to: Number = None
    change: Number = None
    sigma: Number = None
    change_sigmas: Number = None
    moved: bool
    status: str


class Comparison(Open):
    """From one calibration to another (``parameters`` null when there is no previous one)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    from_: int | None = Field(default=None, alias="from")
    to: int
    rms_from: Number = None
    rms_to: Number = None
    parameters: list[ComparedParameter] | None = None
    counts: dict[str, int] | None = None


class CalibrationResult(Open):
    """The result page's data (service.results.calibration_result)."""

    id: int
    kind: str
    created_at: Timestamp
    cell: dict[str, Any]
    units: dict[str, str]
    rms: Number = None
    previous_id: int | None = None
    report: dict[str, Any]


class Certificate(Open):
    """The calibration certificate's content (service.certificate.certificate_data)."""

    title: str
    number: str
    issued_at: Timestamp
    calibration: dict[str, Any]
    cell: dict[str, Any]
    units: dict[str, str]


class CompensationReport(BaseModel):
    id: int
    calibration_id: int
    name: str
    mode: str
    created_by: str
    created_at: Timestamp
    report: dict[str, Any]


class CellSummary(Open):
    id: int
    name: str
    site: str
    robot: dict[str, Any]
    devices: list[str] = Field(description="the kinds of device the cell has: rtde, modbus, emscon, tracker, cmm, can")
    devices_error: str | None = Field(
        None, description="why the cell's stored devices document cannot be used (no devices listed then)"
    )
    unit: str | None = None
    drift_threshold: Number = None
    last: dict[str, Any] | None = Field(None, description="the newest pose calibration, current or not")
    current: dict[str, Any] | None = Field(None, description="the cell's current calibration (None: its nominal model)")
    candidate: dict[str, Any] | None = Field(
        None, description="a newer calibration that waits for a verify session to pass it, or an activation"
    )
    trend: list[dict[str, Any]]
    active_session: dict[str, Any] | None = None


class Overview(BaseModel):
    me: Me
    total: int
    cells: list[CellSummary]


class HistoryItem(BaseModel):
    id: int
    kind: str
    session_id: int | None
    status: str | None = None  # current, candidate, superseded or retired
    rms: Number
    created_at: Timestamp


class History(BaseModel):
    total: int
    offset: int
    items: list[HistoryItem]


class DeviceCheck(Open):
    device: str
    address: str | None = None
    ok: bool | None = Field(description="null: not tried (a session drives the cell)")


class DeviceTest(BaseModel):
    cell_id: int
    ok: bool
    results: list[DeviceCheck]


class JsonSchema(BaseModel):
    """A JSON Schema document (draft 2020-12): an object's ``properties``, with ``$defs`` for the
    objects inside it. Keywords beyond the ones named here are kept (``pattern``,
    ``x-expected``: the words of the error when a value does not match, ...)."""

    model_config = ConfigDict(extra="allow")

    title: str
    type: str
    properties: dict[str, Any]
    additionalProperties: bool


class LastDeviceTest(BaseModel):
    cell_id: int
    last: dict[str, Any] | None


class LibraryRobot(Open):
    name: str
    convention: str | None = None
    joints: int
    units: dict[str, str] | None = None
    targets: list[str]
    model_name: str | None = None


class PlanPreview(Open):
    """A session's plan before anything moves (service.results.plan_preview)."""

    session_id: int
    state: str
    kind: str


class LiveSession(Open):
    """A session's residuals so far and its pace (service.results.session_live)."""

    session_id: int
    state: str
    planned: int
    measured: int


class SessionPage(BaseModel):
    total: int
    offset: int
    items: list[SessionPublic]


class SessionKindPublic(BaseModel):
    """One session kind (service/kinds/), as the page offers it: a new kind shows up here alone."""

    name: str = Field(description="the request's `kind`")
    title: str = Field(description="the page's short name for the choice")
    summary: str = Field(description="what a session of this kind does")
    heading: str = Field(description="the title of a session's page")
    default_count: int = Field(description="the page's proposal for `count`")
    max_count: int = Field(description="the largest `count` a session of this kind takes")
    count_help: str = Field(description="what `count` counts for this kind")
    instruments: list[str] = Field(description="roles of the device registry it measures with: tracker, cmm, encoder")
    device_choice: bool = Field(description="the request's `device` chooses the instrument")
    payloads: bool = Field(description="the request may carry `payloads`")
    repeats: bool = Field(description="the request may ask for `repeats`")
    importable: bool = Field(description="external measurements may be imported as a session of this kind")
    stores: str = Field(description="what a completed session leaves: calibration or verification")
