"""The stored records (SQLModel tables) and the API's request/response shapes.

Tables never go over the wire: routes answer with the ``*Public`` shapes. JSON columns hold
documents (models, reports, endpoint lines) exactly as they were given.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, StrictInt, ValidationInfo, field_validator
from pydantic import Field as PField
from sqlalchemy import JSON, BigInteger, Column, Index, Integer, UniqueConstraint
from sqlmodel import Field, SQLModel

from .files import MAX_MAGNITUDE, magnitude_problem


def utcnow() -> datetime:
    return datetime.now(UTC)


ROLES = ("viewer", "technician", "job", "admin")
SESSION_STATES = ("planned", "running", "paused", "interrupted", "completed", "failed", "aborted")
ACTIVE = ("planned", "running")  # a session drives its cell (a cell runs one at a time)
TERMINAL = ("completed", "failed", "aborted")  # nothing resumes it

# Ids and the columns that refer to them are 64-bit on every database (the docs promise 1 to
# 2**63 - 1; PostgreSQL's INTEGER stopped at 2**31 - 1 and answered 500 beyond it, schema v8).
# SQLite's INTEGER is already 64-bit, and only an INTEGER PRIMARY KEY is its autoincrementing rowid.
ID_TYPE = BigInteger().with_variant(Integer, "sqlite")


# --------------------------------------------------------------------------- a session's records
#
# What a session was asked and planned, what its controller's kinematics did when it ran, and what
# a verify session found: typed records, each written by one method of RunSession and read through
# its type; JSON only here, at the store's edge (``to_json``/``from_json``, lossless both ways).
# The public ``plan_info`` of a session (contracts) is the three together (:func:`public_plan_info`).


def _tuple_or_none(values: Any) -> tuple | None:
    return None if values is None else tuple(values)


@dataclass(frozen=True)
class ImportedFile:
    """The file an imported session's measurements came from (``plan_info.imported``)."""

    name: str
    rows: int


@dataclass(frozen=True)
class InstrumentSigma:
    """The per-axis standard uncertainty ``sigma_m`` (m) a session plans, predicts and weighs
    with, and ``source``: the registry's label of the instrument that declares it, or why the
    library's default stands in (service.devices.instrument_sigma). Stored with the session's
    plan (:attr:`SessionPlan.instrument_sigma`) so that its figures stay those of its time when
    the cell's devices change."""

    sigma_m: float
    source: str

    def as_info(self) -> dict[str, Any]:
        return {"sigma_m": self.sigma_m, "source": self.source}

    @classmethod
    def from_info(cls, info: Any) -> InstrumentSigma | None:
        """The record :meth:`as_info` stored; None when there is none (a session planned before
        the figure was stored, an imported one)."""
        if not isinstance(info, dict) or not isinstance(info.get("sigma_m"), int | float) or not info["sigma_m"] > 0:
            return None
        return cls(float(info["sigma_m"]), str(info.get("source") or "stored with the session"))


@dataclass(frozen=True)
class SessionPlan:
    """What a session was asked (joints, repeats, payloads), what it was planned from and what its
    planner said (``planner``: the planner's predictions, JSON-ready as it gave them; ``method``
    and ``limits_checked`` typed, as the result page and the certificate read them). Stored in
    ``session.plan_info``."""

    joints: tuple[int, ...] | None = None  # circle / joint sessions: the joints swept (1-based)
    repeats: int | None = None  # verify sessions: visits of each configuration (None: once)
    payloads: tuple[tuple[float, ...], ...] | None = None  # [kg, x, y, z] SI, the plan split between them
    nominal_version: int | None = None  # the cell's nominal model version it was planned for
    swept_joint: tuple[int, ...] | None = None  # per configuration, the joint a circle sweeps (0: none)
    dry_run: bool = False  # planned and checked, nothing moved
    from_dry_run: int | None = None  # the dry run whose plan it runs
    imported: ImportedFile | None = None  # measurements imported from a file, not measured
    method: str | None = None  # how the planner chose the configurations
    limits_checked: bool = False  # every configuration checked against the joint limits and region
    instrument_sigma: InstrumentSigma | None = None  # the instrument's noise it was planned with
    planner: dict[str, Any] = field(default_factory=dict)  # the planner's other figures (predictions, spans)

    _TYPED = (
        "instrument_sigma",
        "joints",
        "repeats",
        "payloads",
        "nominal_version",
        "swept_joint",
        "dry_run",
        "from_dry_run",
        "imported",
        "method",
        "limits_checked",
    )

    @property
    def visits(self) -> int:
        """How often each configuration is visited (1 unless ``repeats`` says more)."""
        return int(self.repeats or 1)

    def planned(self, planner_info: dict[str, Any], *, swept_joint: list[int], nominal_version: int) -> SessionPlan:
        """This request with what the planner said (``planner_info``, service.plans.Plan.info)."""
        planned = SessionPlan.from_json({**self.to_json(), **planner_info})
        return replace(planned, swept_joint=tuple(swept_joint), nominal_version=nominal_version)

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = dict(self.planner)
        if self.method is not None:
            doc["method"] = self.method
        if self.limits_checked:
            doc["limits_checked"] = True
        for name in ("joints", "swept_joint"):
            if getattr(self, name) is not None:
                doc[name] = list(getattr(self, name))
        if self.payloads is not None:
            doc["payloads"] = [list(p) for p in self.payloads]
        for name in ("repeats", "nominal_version", "from_dry_run"):
            if getattr(self, name) is not None:
                doc[name] = getattr(self, name)
        if self.dry_run:
            doc["dry_run"] = True
        if self.imported is not None:
            doc["imported"] = {"name": self.imported.name, "rows": self.imported.rows}
        if self.instrument_sigma is not None:
            doc["instrument_sigma"] = self.instrument_sigma.as_info()
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any] | None) -> SessionPlan:
        doc = doc or {}
        imported = doc.get("imported")
        payloads = doc.get("payloads")
        return cls(
            joints=_tuple_or_none(doc.get("joints")),
            repeats=doc.get("repeats"),
            payloads=None if payloads is None else tuple(tuple(p) for p in payloads),
            nominal_version=doc.get("nominal_version"),
            swept_joint=_tuple_or_none(doc.get("swept_joint")),
            dry_run=bool(doc.get("dry_run")),
            from_dry_run=doc.get("from_dry_run"),
            imported=None if imported is None else ImportedFile(str(imported["name"]), int(imported["rows"])),
            method=doc.get("method"),
            limits_checked=bool(doc.get("limits_checked")),
            instrument_sigma=InstrumentSigma.from_info(doc.get("instrument_sigma")),
            planner={k: v for k, v in doc.items() if k not in cls._TYPED},
        )


@dataclass(frozen=True)
class ControllerEvent:
    """What a session did with its UR controller's own kinematics (service.controller): the
    stored version it used or made, whether they changed, a warning for the operator, and the
    figures of the read or check (``figures``: ``moved_mm``, ``tcp_registers_mm``,
    ``tolerance_mm``, ``from_registers``, ``registers_rms_um``, as measured). Stored in
    ``session.controller_event``; the public ``plan_info.controller_model``."""

    version: int | None
    changed: bool | None
    warning: str | None
    figures: dict[str, float | bool | None] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"version": self.version, "changed": self.changed, "warning": self.warning, **self.figures}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> ControllerEvent:
        figures = {k: v for k, v in doc.items() if k not in ("version", "changed", "warning")}
        return cls(doc.get("version"), doc.get("changed"), doc.get("warning"), figures)


@dataclass(frozen=True)
class VerifyResult:
    """A verify session's result (service.kinds.verify): the position errors of the calibration
    it checked (``calibration_id``, None: the nominal model) on its fresh configurations,
    statistics in the model's length unit ``unit``, with the optional parts when they apply.
    Stored in ``session.verify``; the public ``plan_info.verify``."""

    calibration_id: int | None
    n: int | None
    rms: float | None
    max: float | None
    p95: float | None
    mean: float | None
    unit: str | None
    residual_correction: dict[str, Any] | None = None  # the correction's family, rows outside its region
    registered: dict[str, float] | None = None  # rms, max with the base placed where it fits best
    outside_calibrated_region: int | None = None  # configurations outside the calibration's data
    iso9283: dict[str, Any] | None = None  # a repeated session's ISO 9283 figures
    candidate: dict[str, Any] | None = None  # the candidate calibration it judged, and the verdict
    extra: dict[str, Any] = field(default_factory=dict)  # any other figure a stored result carries

    _CORE = ("calibration_id", "n", "rms", "max", "p95", "mean", "unit")
    _OPTIONAL = ("residual_correction", "registered", "outside_calibrated_region", "iso9283", "candidate")

    def to_json(self) -> dict[str, Any]:
        doc = {k: getattr(self, k) for k in self._CORE}
        doc.update({k: getattr(self, k) for k in self._OPTIONAL if getattr(self, k) is not None})
        return {**doc, **self.extra}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> VerifyResult:
        known = cls._CORE + cls._OPTIONAL
        return cls(
            **{k: doc.get(k) for k in known},
            extra={k: v for k, v in doc.items() if k not in known},
        )


def public_plan_info(
    plan: SessionPlan, controller: ControllerEvent | None, verify: VerifyResult | None
) -> dict[str, Any] | None:
    """A session's ``plan_info`` as the API shows it (contracts): its plan (without the swept
    joint of each configuration, internal), ``controller_model`` and ``verify`` when it has them;
    None when there is nothing to say."""
    doc = {k: v for k, v in plan.to_json().items() if k != "swept_joint"}
    if controller is not None:
        doc["controller_model"] = controller.to_json()
    if verify is not None:
        doc["verify"] = verify.to_json()
    return doc or None


class Cell(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    name: str = Field(index=True, unique=True)
    site: str = Field(default="default", index=True)
    model: dict = Field(sa_column=Column(JSON, nullable=False))  # nominal recal.model/1
    devices: dict = Field(sa_column=Column(JSON, nullable=False))  # endpoint line shape
    allowed_region: list | None = Field(default=None, sa_column=Column(JSON))  # [[lo, hi], ...] model units
    drift_threshold: float | None = None  # model length unit; nightly recalibrates beyond it
    created_at: datetime = Field(default_factory=utcnow)
    # counts the nominal models this cell has had (PATCH model; the old ones are in the audit log)
    model_version: int = Field(default=1, sa_column_kwargs={"server_default": "1"})


class RunSession(SQLModel, table=True):
    __tablename__ = "session"
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    cell_id: int = Field(foreign_key="cell.id", sa_type=ID_TYPE, index=True)
    kind: str
    state: str = Field(default="planned", index=True)
    planned: int = 0
    device: str = "tracker"
    target: str | None = None
    dry_run: bool = False
    plan: list | None = Field(default=None, sa_column=Column(JSON))  # joint configurations, SI
    plan_info: dict | None = Field(default=None, sa_column=Column(JSON))  # SessionPlan.to_json()
    reason: str | None = None  # why it paused, failed or was interrupted
    calibration_id: int | None = Field(default=None, sa_type=ID_TYPE)
    created_by: str = ""
    created_at: datetime = Field(default_factory=utcnow)
    updated_at: datetime = Field(default_factory=utcnow)
    lease_owner: str | None = None
    lease_expires: datetime | None = None
    requested: str | None = None  # "pause" / "abort" asked of the process running it (fleet: workers poll it)
    # What the devices were doing at the last committed pose, stop or fault (schema v3):
    # {"robot": {"state", "detail"}, "tracker" | "cmm" | "encoder": {"state", "detail"}, "at": ISO time}
    device_state: dict | None = Field(default=None, sa_column=Column(JSON))
    # Beam breaks the session repaired itself by pointing the tracker at the reflector (schema v4)
    beam_recoveries: int = Field(default=0, sa_column_kwargs={"server_default": "0"})
    # What the session did with its UR controller's kinematics (ControllerEvent.to_json()) and a
    # verify session's result (VerifyResult.to_json()), each in its own column (schema v10; they
    # were keys of plan_info before)
    controller_event: dict | None = Field(default=None, sa_column=Column(JSON))
    verify: dict | None = Field(default=None, sa_column=Column(JSON))

    def session_plan(self) -> SessionPlan:
        """What the session was asked and planned (an empty plan before it was asked anything)."""
        return SessionPlan.from_json(self.plan_info)

    def record_plan(self, plan: SessionPlan) -> None:
        doc = plan.to_json()
        self.plan_info = doc or None

    def controller(self) -> ControllerEvent | None:
        """What the session did with its controller's kinematics (None: nothing, not a UR cell)."""
        return None if not self.controller_event else ControllerEvent.from_json(self.controller_event)

    def record_controller(self, event: ControllerEvent) -> None:
        self.controller_event = event.to_json()

    def verify_result(self) -> VerifyResult | None:
        """A completed verify session's result (None: none yet, or not a verify session)."""
        return None if not self.verify else VerifyResult.from_json(self.verify)

    def record_verify(self, result: VerifyResult) -> None:
        self.verify = result.to_json()

    def public_plan_info(self) -> dict[str, Any] | None:
        """``plan_info`` as the API shows it (:func:`public_plan_info`)."""
        return public_plan_info(self.session_plan(), self.controller(), self.verify_result())


class Measurement(SQLModel, table=True):
    __table_args__ = (UniqueConstraint("session_id", "seq", "target", name="uq_measurement_seq_target"),)
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    session_id: int = Field(foreign_key="session.id", sa_type=ID_TYPE, index=True)
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
    # Which calibration is a cell's current one, read from the index alone (schema v9): the JSON
    # columns come first in a row, and a query that read activated_at from each row of a cell with
    # a thousand calibrations read all their reports (0.4 s).
    __table_args__ = (
        Index("ix_calibration_current", "cell_id", "kind", "nominal_version", "retired_at", "activated_at"),
    )
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    cell_id: int = Field(foreign_key="cell.id", sa_type=ID_TYPE, index=True)
    session_id: int | None = Field(default=None, foreign_key="session.id", sa_type=ID_TYPE)
    kind: str = "pose"
    model: dict = Field(sa_column=Column(JSON, nullable=False))
    report: dict = Field(sa_column=Column(JSON, nullable=False))
    # the parameters' covariance is the model's identification.covariance (SI), stored once (schema v11)
    rms: float | None = None  # hold-out / residual RMS, model length unit
    created_at: datetime = Field(default_factory=utcnow)
    nominal_version: int | None = None  # the cell's model_version this was identified from (schema v3)
    # Predicted accuracy over the workspace (the 95 % radius statistics /result shows), stored when the
    # calibration is made so that drift over hundreds of calibrations reads no reports (schema v3).
    predicted: dict | None = Field(default=None, sa_column=Column(JSON))
    # Calibrations are activated, not overwritten (schema v9): the cell's current calibration is
    # the one activated last that is not retired (a new one waits as a candidate until a verify
    # session passes it or someone activates it; a cell's first one is activated at once).
    activated_at: datetime | None = None
    activated_by: str | None = None
    retired_at: datetime | None = None
    retired_by: str | None = None


class ControllerModel(SQLModel, table=True):
    """A UR controller's own kinematics (its factory calibration), as read from the controller
    (``service.controller``); one row per version, the newest is the cell's (schema v4)."""

    __tablename__ = "controller_model"
    __table_args__ = (UniqueConstraint("cell_id", "version", name="uq_controller_model_version"),)
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    cell_id: int = Field(foreign_key="cell.id", sa_type=ID_TYPE, index=True)
    version: int = 1
    model: dict = Field(sa_column=Column(JSON, nullable=False))  # recal.model/1 with its `controller` block
    session_id: int | None = Field(default=None, sa_type=ID_TYPE)  # the session that read it (None: uploaded)
    moved_m: float | None = None  # how far it moved from the previous version (m, worst flange position)
    created_at: datetime = Field(default_factory=utcnow)


class Compensation(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    calibration_id: int = Field(foreign_key="calibration.id", sa_type=ID_TYPE, index=True)
    name: str = ""
    mode: str = "joints"
    output: str = ""
    # the compensated file is ``output.encode(encoding)``: "utf-8", or "iso-8859-1" for a program
    # that was not UTF-8 (a character per byte: its bytes kept, schema version 7)
    encoding: str = "utf-8"
    report: dict | None = Field(default=None, sa_column=Column(JSON))
    created_by: str = ""
    created_at: datetime = Field(default_factory=utcnow)


class TaskFile(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    cell_id: int = Field(foreign_key="cell.id", sa_type=ID_TYPE, index=True)
    name: str
    content: str
    mode: str = "joints"
    # the file is ``content.encode(encoding)`` (as Compensation.encoding; schema version 7)
    encoding: str = "utf-8"
    # a KRL .src's other files, compensated with it: [{"name", "content", "encoding"}] (its .dat,
    # and a $config.dat for the TOOL_DATA and BASE_DATA it selects); None for a single file
    files: list | None = Field(default=None, sa_column=Column(JSON))
    created_at: datetime = Field(default_factory=utcnow)


class Token(SQLModel, table=True):
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    name: str = Field(index=True)
    role: str
    hash: str = Field(index=True, unique=True)  # sha256 of the token; the token itself is never stored
    revoked: bool = False
    created_at: datetime = Field(default_factory=utcnow)


class EventTicket(SQLModel, table=True):
    """A short-lived, single-use ticket for one connection to a session's event stream (what a
    browser's ``EventSource`` puts in the URL instead of a token), kept in the database so that
    any API process of a fleet accepts it (docs/fleet.md). Only its hash is stored; it is deleted
    when used (store.redeem_ticket)."""

    __tablename__ = "event_ticket"
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
    hash: str = Field(index=True, unique=True)  # sha256 of the ticket; the ticket itself is never stored
    token_id: int = Field(foreign_key="token.id", sa_type=ID_TYPE)  # whose rights the stream has
    scope: str  # what it opens: "events:<session id>"
    expires_at: datetime = Field(index=True)


class AuditEntry(SQLModel, table=True):
    __tablename__ = "audit"
    id: int | None = Field(default=None, primary_key=True, sa_type=ID_TYPE)
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


MAX_ID = 2**63 - 1  # ids are 64-bit integers in every database we use


# What a session request may ask of each kind: its kind's (service/kinds/, each SessionKind's
# max_count, carries_payloads and repeats), registered here by service.kinds when it is imported
# (the rows sit below the kinds and do not import them). Nothing here names a kind.
@dataclass(frozen=True)
class KindRules:
    """What the rows, the store and the pages need to know of a session kind (its SessionKind
    says it; service.kinds registers it)."""

    max_count: int  # configurations (or points per swept joint) a session of the kind can use
    carries_payloads: bool = False  # the plan may be split between payloads
    repeats: bool = False  # the configurations may be visited more than once (ISO 9283)
    stores: str = "calibration"  # what a completed session leaves: "calibration" or "verification"
    calibration_kind: str | None = None  # Calibration.kind of what it stores ("cpa" for circle sessions)
    current_model: bool = False  # its calibration is the one the cell's robot is known by
    importable: bool = False  # external measurements may be imported as a session of this kind
    predicts_accuracy: bool = False  # its plan shows the accuracy identification is predicted to reach
    # the live page's residuals so far: (db, run, cell, rows, L) -> dict, or None (none shown)
    live_residuals: Callable[..., dict | None] | None = None


def identified_calibration_kinds() -> list[str]:
    """The ``Calibration.kind`` of the calibrations a cell's robot is known by (a pose session's)."""
    return [r.calibration_kind for r in KIND_RULES.values() if r.current_model and r.calibration_kind]


def kinds_that(predicate: Callable[[KindRules], bool]) -> list[str]:
    """The names of the registered kinds whose rules satisfy ``predicate``, in the table's order."""
    return [name for name, rules in KIND_RULES.items() if predicate(rules)]


KIND_RULES: dict[str, KindRules] = {}
MAX_COUNT: dict[str, int] = {}  # kind -> KindRules.max_count (filled with KIND_RULES)


def register_kind_rules(name: str, rules: KindRules) -> None:
    KIND_RULES[name] = rules
    MAX_COUNT[name] = rules.max_count


MAX_REPEATS = 30  # ISO 9283 measures repeatability over 30 cycles


def _trimmed(value: str) -> str:
    if not value.strip() or value != value.strip():
        raise ValueError("expected a name that is not blank and has no leading or trailing blanks")
    return value


Name = Annotated[str, PField(min_length=1, max_length=200), AfterValidator(_trimmed)]


def _finite(value: Any, path: str) -> None:
    """Raise ``ValueError`` naming the first number the model cannot use (NaN, infinite, beyond
    ``files.MAX_MAGNITUDE``) or the first text with a NUL character inside a JSON document
    (neither database stores NUL in text: PostgreSQL refused it with a 500)."""
    if isinstance(value, float) and magnitude_problem(value):
        raise ValueError(f"{path}: {magnitude_problem(value)}")
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > MAX_MAGNITUDE:
        raise ValueError(f"{path}: expected a number from {-MAX_MAGNITUDE:g} to {MAX_MAGNITUDE:g}, got {value}")
    if isinstance(value, str) and "\x00" in value:
        raise ValueError(f"{path}: expected text without NUL characters")
    if isinstance(value, dict):
        for k, v in value.items():
            if "\x00" in str(k):
                raise ValueError(f"{path}: expected field names without NUL characters")
            _finite(v, f"{path}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _finite(v, f"{path}[{i}]")


class _In(BaseModel):
    """A request body: unknown fields, NaN and infinities are refused (JSON has none, and the
    store could not hold them)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _documents_are_finite(cls, value: Any, info: ValidationInfo) -> Any:
        if isinstance(value, (dict, list, str, float, int)):
            _finite(value, info.field_name or "body")
        return value


DEVICES_DOC = (
    "the cell's devices: the simulated cell's endpoint line (contracts §7) or the same shape for real "
    "equipment; its JSON Schema is GET /api/v1/schemas/devices (checked by the route, stored as sent)"
)


class CellCreate(_In):
    name: Name
    model: dict[str, Any]
    devices: dict[str, Any] = PField(default_factory=dict, description=DEVICES_DOC)
    site: Name = "default"
    allowed_region: list[list[float]] | None = None  # per joint [lower, upper], model units (checked by the route)
    drift_threshold: float | None = PField(default=None, gt=0)


def _omitted_or_value(schema: dict[str, Any]) -> None:
    """A field that may be left out but is never null: its schema without the ``null`` default."""
    schema.pop("default", None)


class CellUpdate(_In):
    """Fields to change; a field left out stays as it is. ``model`` replaces the nominal model
    (refused while a session drives the cell; the old one is kept in the audit log)."""

    # Omitted or a value, never null (the OpenAPI document says so: no "null" in their types and
    # no default, which once let a client generated from it send nulls the route refused). The
    # None default is what "left out" reads as (cells.py reads exclude_unset), never a value.
    name: Name = PField(None, json_schema_extra=_omitted_or_value)  # type: ignore[assignment]
    model: dict[str, Any] = PField(None, json_schema_extra=_omitted_or_value)  # type: ignore[arg-type]
    devices: dict[str, Any] = PField(
        None,  # type: ignore[arg-type]
        description=DEVICES_DOC,
        json_schema_extra=_omitted_or_value,
    )
    site: Name = PField(None, json_schema_extra=_omitted_or_value)  # type: ignore[assignment]
    allowed_region: list[list[float]] | None = None  # null: no region beyond the model's joint limits
    drift_threshold: float | None = PField(default=None, gt=0)  # null: no threshold

    @field_validator("name", "model", "devices", "site", mode="before")
    @classmethod
    def _not_null(cls, value: Any) -> Any:
        if value is None:
            raise ValueError("may not be null (leave the field out to keep it)")
        return value


class CellPublic(BaseModel):
    id: int
    name: str
    site: str
    model: dict[str, Any]
    model_version: int = 1
    devices: dict[str, Any]
    allowed_region: list[list[float]] | None
    drift_threshold: float | None
    created_at: datetime
    last_calibration_id: int | None = None


def _one_of(names: list[str]) -> str:
    """Pydantic's words for a choice: 'a', 'b' or 'c'."""
    quoted = [f"'{n}'" for n in names]
    return quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"


class SessionCreate(_In):
    # one of the kinds of service/kinds/ (their names are the schema's enum, read when it is made)
    kind: str = PField(json_schema_extra=lambda s: s.update(enum=list(KIND_RULES)))
    # true and "10" are not counts; the kind's own cap is checked below
    count: StrictInt = PField(default=30, ge=1, json_schema_extra=lambda s: s.update(maximum=max(MAX_COUNT.values())))
    device: Literal["tracker", "cmm"] = "tracker"
    target: str | None = None
    dry_run: bool = False
    joints: list[int] | None = PField(default=None, min_length=1)  # circle / joint sessions: which joints (1-based)
    repeats: StrictInt = PField(default=1, ge=1, le=MAX_REPEATS)  # verify: visits of each configuration (ISO 9283)
    # pose / verify sessions: payloads [kg] or [kg, x, y, z] (centre of gravity in the tool frame, model length
    # unit), the plan split between them in order (a compliant model separates the arm's weight from the payload's)
    payloads: list[list[float]] | None = PField(default=None, min_length=1, max_length=4)

    @field_validator("kind")
    @classmethod
    def _a_known_kind(cls, kind: str) -> str:
        if kind not in KIND_RULES:
            raise ValueError(f"Input should be {_one_of(list(KIND_RULES))}")
        return kind

    @field_validator("payloads")
    @classmethod
    def _payloads(cls, payloads, info: ValidationInfo):
        if payloads is None:
            return None
        rules = KIND_RULES.get(info.data.get("kind", ""))
        if rules is None or not rules.carries_payloads:
            carrying = " and ".join(k for k, r in KIND_RULES.items() if r.carries_payloads)
            raise ValueError(f"only {carrying} sessions carry payloads (this is a {info.data.get('kind')} session)")
        for p in payloads:
            if len(p) not in (1, 4) or p[0] < 0:
                raise ValueError(f"each payload is [kg] or [kg, x, y, z] with kg >= 0, got {p}")
        return [list(p) + [0.0] * (4 - len(p)) for p in payloads]

    @field_validator("count")
    @classmethod
    def _count_within_what_the_kind_uses(cls, count: int, info: ValidationInfo) -> int:
        kind = info.data.get("kind")
        if count > max(MAX_COUNT.values(), default=count):  # the schema's maximum, as pydantic words it
            raise ValueError(f"Input should be less than or equal to {max(MAX_COUNT.values())}")
        if kind in MAX_COUNT and count > MAX_COUNT[kind]:
            raise ValueError(f"at most {MAX_COUNT[kind]} for a {kind} session, got {count}")
        return count

    @field_validator("repeats")
    @classmethod
    def _repeats_of_verify_sessions(cls, repeats: int, info: ValidationInfo) -> int:
        kind, count = info.data.get("kind"), info.data.get("count")
        rules = KIND_RULES.get(kind or "")
        if repeats != 1 and (rules is None or not rules.repeats):
            repeating = " and ".join(k for k, r in KIND_RULES.items() if r.repeats)
            raise ValueError(f"only {repeating} sessions repeat their configurations (this is a {kind} session)")
        if rules is not None and count is not None and count * repeats > rules.max_count:
            raise ValueError(f"count x repeats is at most {rules.max_count} measurements, got {count} x {repeats}")
        return repeats


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
    device_state: dict[str, Any] | None = None  # the devices at the last committed pose, stop or fault
    beam_recoveries: int = 0  # beam breaks repaired by pointing the tracker at the reflector


class CalibrationPublic(BaseModel):
    id: int
    cell_id: int
    session_id: int | None
    kind: str
    model: dict[str, Any]
    report: dict[str, Any]
    rms: float | None
    created_at: datetime
    nominal_version: int | None = None
    predicted: dict[str, Any] | None = None
    # "current", "candidate" (waits for a verify session or an activation), "superseded" (was
    # current once) or "retired"; "superseded" too for one of an earlier nominal model
    status: str | None = None
    activated_at: datetime | None = None
    activated_by: str | None = None
    retired_at: datetime | None = None
    retired_by: str | None = None


class TokenCreate(_In):
    role: Literal["viewer", "technician", "job", "admin"]
    name: str = PField(default="", max_length=200)
