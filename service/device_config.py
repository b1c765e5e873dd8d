"""A cell's device configuration: one typed, frozen model of its ``devices`` document (the fake
cell's endpoint line, contracts §7, or the same shape for real equipment) and its one parser.

:func:`parse_devices` is the only reader of the document: registration and edits (strict: an
unknown key is refused with "did you mean"), the sessions that open the devices, the connection
test, the overview and the certificate (:func:`stored_devices`). Its JSON Schema
(:func:`devices_json_schema`) is served at ``GET /api/v1/schemas/devices``; the web page builds
and checks its device fields from it, so that the patterns and the words of the errors below are
the page's too.

The model names the devices and their addresses; how long to wait for them is the service's
(``device_timeout_s``, the connection test's limit), given when they are opened (``devices.py``).
"""

from __future__ import annotations

import difflib
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    ValidationInfo,
    model_validator,
)

from calibration.errors import RecalError


class DeviceConfigError(RecalError, ValueError):
    """A cell's ``devices`` document cannot be used: ``field`` names the entry at fault
    (``devices.modbus``, ``devices.emscon.port``), ``message`` says what was expected."""

    def __init__(self, field: str, message: str):
        self.field, self.message = field, message
        super().__init__(f"{field}: {message}")


# --------------------------------------------------------------------------- addresses
# The patterns are ECMAScript- and Python-compatible: the page checks a field with the same
# pattern (from the JSON Schema) as the parser here.

_NAME = r"[A-Za-z0-9](?:[A-Za-z0-9-]*[A-Za-z0-9])?(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]*[A-Za-z0-9])?)*"
_IPV6 = r"\[[0-9A-Fa-f:.]+\]|[0-9A-Fa-f]{0,4}(?::[0-9A-Fa-f]{0,4}){2,7}"
_HOST = f"(?:{_NAME}|{_IPV6})"
_PORT = r"(?:[1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5])"
HOST_PATTERN = f"^{_HOST}$"
HOST_PORT_PATTERN = f"^{_HOST}:{_PORT}$"
HOST_OPTIONAL_PORT_PATTERN = f"^{_HOST}(?::{_PORT})?$"
# pyserial URLs: socket:// and rfc2217:// need HOST:PORT; other schemes (loop://, spy://...),
# device paths (/dev/ttyUSB0, a pty) and Windows COM ports are pyserial's to judge.
SERIAL_URL_PATTERN = (
    f"^(?:(?:socket|rfc2217)://{_HOST}:{_PORT}(?:[/?][^\\s]*)?"
    r"|(?!(?:socket|rfc2217):)[A-Za-z][A-Za-z0-9+.-]*://[^\s]*|/[^\s]+|COM[0-9]+)$"
)


def _text(pattern: str, expected: str, **schema: Any):
    """A string field that must match ``pattern``; refused with "expected ``expected``". The
    pattern and the words go into the JSON Schema (``pattern``, ``x-expected``) for the page."""
    import re

    compiled = re.compile(pattern)

    def check(value: str) -> str:
        if not compiled.match(value):
            raise ValueError(f"expected {expected}, got {value!r}")
        return value

    return Annotated[
        str, AfterValidator(check), Field(json_schema_extra={"pattern": pattern, "x-expected": expected, **schema})
    ]


def _whole(value: Any) -> Any:
    # a whole number written as 700.0 or "700" (JSON writers, HTML forms) is the integer
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str) and value.strip().isdigit():
        return int(value)
    return value


def _whole_float(value: Any) -> Any:
    return int(value) if isinstance(value, float) and value.is_integer() else value


Host = _text(HOST_PATTERN, "a host name or IP address, e.g. 192.168.1.10", examples=["192.168.1.10"])
Port = Annotated[int, Field(ge=1, le=65535), BeforeValidator(_whole_float)]
NodeId = Annotated[int, Field(ge=1, le=127, description="CANopen node id (1-127)"), BeforeValidator(_whole)]
JointNumber = Annotated[str, Field(pattern=r"^[1-9][0-9]?$", description="joint number, 1-based"), BeforeValidator(str)]


class _Strict(BaseModel):
    # JSON types as written (no "700" for 700, no 1 for true), unknown keys refused, immutable.
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, regex_engine="python-re")


class EmsconSettings(_Strict):
    """``devices.emscon`` as an object: the emScon server and how to set the tracker up. Left
    out: the driver's default (``drivers.leica_emscon.EmsconConfig``)."""

    model_config = ConfigDict(title="emScon settings")

    host: Host = Field(description="the emScon server (the tracker controller's address)")
    port: Port | None = Field(None, description="the emScon server's TCP port (default 700)")
    reflector: Annotated[str, Field(min_length=1)] | None = Field(
        None, description="the reflector's name as the server lists it (default RRR 1.5in)"
    )
    measure_time_s: Annotated[float, Field(gt=0, le=60)] | None = Field(
        None, description="stationary averaging time, s (default 0.5)"
    )
    use_adm: bool | None = Field(None, description="measure the distance with the absolute distance meter alone")
    environment: Literal["meteo", "config"] | None = Field(
        None, description='"meteo": the tracker\'s weather station (default); "config": the values below'
    )
    temperature_c: Annotated[float, Field(ge=-40, le=70)] | None = Field(None, description="air temperature, °C")
    pressure_mbar: Annotated[float, Field(ge=500, le=1200)] | None = Field(None, description="air pressure, mbar")
    humidity_pct: Annotated[float, Field(ge=0, le=100)] | None = Field(None, description="relative humidity, %")
    initialize_timeout_s: Annotated[float, Field(gt=0, le=3600)] | None = Field(
        None, description="deadline of Initialize, s (default 120)"
    )

    def driver_kwargs(self) -> dict[str, Any]:
        """The settings given, as keyword arguments of ``EmsconConfig``."""
        return self.model_dump(exclude_none=True)


EmsconAddress = _text(
    HOST_OPTIONAL_PORT_PATTERN,
    "HOST:PORT of the emScon server, e.g. 192.168.0.1:700",
    examples=["192.168.0.1:700"],
    description='"HOST:PORT" of the emScon server (the endpoint line), or "HOST" (port 700)',
)


def _emscon_form(value: Any) -> str | None:
    return "address" if isinstance(value, str) else "settings" if isinstance(value, dict | EmsconSettings) else None


Emscon = Annotated[
    Annotated[EmsconAddress, Tag("address")] | Annotated[EmsconSettings, Tag("settings")],
    Discriminator(
        _emscon_form,
        custom_error_type="emscon_form",
        custom_error_message='expected "HOST:PORT" or an object',
    ),
]


class CanBus(_Strict):
    """``devices.can``: the keyword arguments of python-can's ``can.Bus`` (contracts §7)."""

    model_config = ConfigDict(title="CAN bus")

    interface: Annotated[str, Field(min_length=1)] = Field(
        "socketcand",
        description="python-can interface: socketcand, socketcan, pcan, kvaser, slcan, ...",
        examples=["socketcand", "socketcan", "pcan", "kvaser", "slcan"],
    )
    channel: Annotated[str, Field(min_length=1)] = Field("vcan0", description="e.g. vcan0, can0, PCAN_USBBUS1")
    host: Host | None = Field(None, description="socketcand: the server's address")
    port: Annotated[Port, BeforeValidator(_whole)] | None = Field(None, description="socketcand: the server's port")
    bitrate: Annotated[int, Field(gt=0, le=10_000_000)] | None = Field(
        None, description="bit/s, for adapters whose bitrate python-can sets (not socketcan: ip link sets it)"
    )
    tcp_tune: bool | None = Field(None, description="socketcand: low-latency TCP options (default on)")

    @model_validator(mode="after")
    def _socketcand_needs_its_server(self) -> CanBus:
        if self.interface == "socketcand":
            for name in ("host", "port"):
                if getattr(self, name) is None:
                    raise ValueError(f"[{name}] missing; a socketcand bus needs the server's host and port")
        return self

    def driver_kwargs(self) -> dict[str, Any]:
        """As keyword arguments of ``CanBusConfig``."""
        return self.model_dump(exclude_none=True)


# The tooling balls' radius when the cell does not give one: the common 25 mm ball.
DEFAULT_BALL_RADIUS_M = 0.0125

SerialUrl = _text(
    SERIAL_URL_PATTERN,
    "socket://HOST:PORT or a serial port (/dev/ttyUSB0, COM3)",
    examples=["socket://192.168.1.20:10001"],
)
CmmUrl = _text(SERIAL_URL_PATTERN, "socket://HOST:PORT of the I++ DME server", examples=["socket://192.168.1.30:1294"])


class DevicesConfig(_Strict):
    """A cell's devices: the robot controller (``rtde`` or ``modbus``), the instruments
    (``emscon``, ``tracker``, ``cmm``), the CAN bus and the reference encoders and resolvers on
    it, and the CMM's tooling ball radius. Every device may be absent."""

    model_config = ConfigDict(title="Cell devices")

    ready: bool | None = Field(
        None, description="the endpoint line's marker (recal fake-cell); accepted so that the line pastes as it is"
    )
    rtde: (
        _text(
            HOST_PATTERN,
            "the controller's host name or IP address, e.g. 192.168.1.10 (no port: RTDE uses 30004)",
            examples=["192.168.1.10"],
        )
        | None
    ) = Field(None, title="UR controller (RTDE) host", description="Universal Robots: RTDE on 30004")
    modbus: _text(HOST_PORT_PATTERN, "HOST:PORT, e.g. 192.168.1.10:502", examples=["192.168.1.10:502"]) | None = Field(
        None, title="Modbus TCP host:port", description="a robot read over Modbus TCP (UR register map)"
    )
    emscon: Emscon | None = Field(
        None,
        title="Leica laser tracker (emScon)",
        description="HOST:PORT of the tracker's emScon server (port 700), or an object with its settings; "
        "tracker sessions use it when it is given",
    )
    tracker: SerialUrl | None = Field(
        None,
        title="Laser tracker (line protocol)",
        description="socket://HOST:PORT, or the serial port it is plugged into (a bridge for FARO and API trackers)",
    )
    cmm: CmmUrl | None = Field(None, title="CMM (I++ DME)", description="socket://HOST:PORT of the I++ DME server")
    can: CanBus | None = Field(None, title="CAN bus", description="where the reference encoders and resolvers are")
    encoders: dict[JointNumber, NodeId] = Field(
        default_factory=dict,
        title="Reference encoders",
        description="joint number -> CANopen node id of the reference encoder on that joint",
    )
    resolvers: dict[JointNumber, NodeId] = Field(
        default_factory=dict,
        title="Resolvers",
        description="joint number -> CANopen node id of the resolver reader on that joint",
    )
    cmm_ball_radius_m: Annotated[float, Field(ge=0.0005, le=0.1)] = Field(
        DEFAULT_BALL_RADIUS_M,
        title="CMM tooling ball radius (m)",
        description="radius of the tool's tooling balls the CMM probes, every ball alike, m (0.0005 to 0.1)",
    )

    @model_validator(mode="after")
    def _one_bus_for_the_nodes(self, info: ValidationInfo) -> DevicesConfig:
        # Checked for a document being registered or edited; a stored one is read as it is (these
        # were not checked before): opening the encoders refuses it then.
        if not (info.context or {}).get("registering"):
            return self
        if (self.encoders or self.resolvers) and self.can is None:
            raise ValueError("[can] missing; the reference encoders and resolvers need the CAN bus they are on")
        seen: dict[int, str] = {}
        for key in ("encoders", "resolvers"):
            for joint, node in getattr(self, key).items():
                if node in seen:
                    raise ValueError(f"[{key}.{joint}] node {node} is already {seen[node]}")
                seen[node] = f"{key}.{joint}"
        return self

    # ----------------------------------------------------------------- what a cell has

    @property
    def has_robot(self) -> bool:
        return bool(self.rtde or self.modbus)

    @property
    def has_tracker(self) -> bool:
        """A laser tracker: a Leica on emScon (``emscon``) or one on the line protocol (``tracker``)."""
        return self.emscon is not None or self.tracker is not None

    def has(self, device: str) -> bool:
        """The cell has the session's measuring ``device``: ``tracker`` (either kind), ``cmm``, or
        ``encoder`` (a CAN bus with reference encoders or resolvers)."""
        if device == "tracker":
            return self.has_tracker
        if device == "cmm":
            return self.cmm is not None
        if device == "encoder":
            return self.can is not None and bool(self.encoders or self.resolvers)
        raise ValueError(f"unknown measuring device {device!r}")

    @property
    def emscon_settings(self) -> EmsconSettings | None:
        """``emscon`` in one form, whichever was written ("HOST", "HOST:PORT" or the object)."""
        if self.emscon is None or isinstance(self.emscon, EmsconSettings):
            return self.emscon
        host, sep, port = self.emscon.rpartition(":")
        if not sep or not host or host.endswith(":"):  # "HOST" (port 700), or a bare IPv6 address
            return EmsconSettings(host=self.emscon)
        return EmsconSettings(host=host, port=int(port))

    def kinds(self) -> list[str]:
        """The kinds of device the document names, in a fixed order (for listings)."""
        return [k for k in ("rtde", "modbus", "emscon", "tracker", "cmm", "can") if getattr(self, k) is not None]

    def address(self, key: str) -> str:
        """How a person finds the device of entry ``key`` (``rtde``, ``emscon``, ``can``, ...);
        empty when the cell has none."""
        value = getattr(self, key, None) if key in type(self).model_fields else None
        if value is None or isinstance(value, dict | bool | float):
            return ""
        if isinstance(value, EmsconSettings):
            return value.host if value.port is None else f"{value.host}:{value.port}"
        if isinstance(value, CanBus):
            where = f" {value.host}:{value.port}" if value.host else ""
            return f"{value.interface} {value.channel}{where}"
        return str(value)

    def instrument_address(self, device: str) -> str:
        """The address of a session's measuring ``device`` (``tracker``: the Leica on emScon when
        there is one, as sessions use it; ``cmm``)."""
        return self.address("emscon" if device == "tracker" and self.emscon is not None else device)

    def document(self) -> dict[str, Any]:
        """The document this configuration reads from (the endpoint line's shape, defaults left
        out): ``parse_devices(c.document()) == c``."""
        return self.model_dump(mode="json", exclude_defaults=True, exclude_none=True)


# --------------------------------------------------------------------------- the parser

_TYPES = {
    "string_type": "a string",
    "int_type": "an integer",
    "float_type": "a number",
    "bool_type": "true or false",
    "dict_type": "an object",
    "model_type": "an object",
    "literal_error": None,
}


def parse_devices(doc: Any, *, stored: bool = False) -> DevicesConfig:
    """The cell's devices from its ``devices`` document. Raises :class:`DeviceConfigError`
    naming the field (``devices.modbus: expected HOST:PORT, e.g. 192.168.1.10:502, got 'x'``).

    An absent device may also be written ``null`` or ``""`` (the page's empty fields). A key
    the model does not know is refused, with the nearest known one ("did you mean"), unless
    ``stored``: a cell's stored document, registered before the check, is read with unknown keys
    left out, so that its sessions run as they did.
    """
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise DeviceConfigError("devices", f"expected an object (the endpoint line's shape), got {doc!r}")
    doc = {k: v for k, v in doc.items() if v is not None and v != ""}
    if stored:
        doc = {k: v for k, v in doc.items() if k in DevicesConfig.model_fields}
    try:
        return DevicesConfig.model_validate(doc, context={"registering": not stored})
    except ValidationError as exc:
        raise _error(exc) from None


def stored_devices(doc: Any) -> DevicesConfig:
    """A cell's stored ``devices`` document (``Cell.devices``): :func:`parse_devices` with keys
    from before the check left out."""
    return parse_devices(doc, stored=True)


def _model_of(path: list) -> type[BaseModel] | None:
    """The model whose keys the last element of ``path`` would be one of."""
    model: Any = DevicesConfig
    for part in path:
        field = model.model_fields.get(part) if isinstance(model, type) and issubclass(model, BaseModel) else None
        if field is None:
            return None
        model = {"emscon": EmsconSettings, "can": CanBus}.get(part)
    return model


def _error(exc: ValidationError) -> DeviceConfigError:
    err = exc.errors(include_url=False)[0]
    # without the emscon form's tags, and a dict's key named as its entry
    loc = [str(p) for p in err["loc"] if p not in ("address", "settings", "[key]")]
    kind, value = err["type"], err.get("input")
    message = err["msg"]
    if kind == "extra_forbidden":
        known = list((_model_of(loc[:-1]) or DevicesConfig).model_fields)
        near = difflib.get_close_matches(loc[-1], known, n=1, cutoff=0.6)
        message = (
            "unknown key" + (f"; did you mean {near[0]!r}?" if near else "") + f" (expected one of {', '.join(known)})"
        )
    elif kind == "missing":
        message = "missing"
    elif kind == "value_error":
        message = str(err["ctx"]["error"])
        if message.startswith("["):  # a model rule naming its field: "[host] missing; ..."
            name, _, message = message[1:].partition("] ")
            loc = [*loc, *name.split(".")]
    elif kind == "literal_error":
        message = f"expected {err['ctx']['expected']}, got {value!r}"
    elif kind in _TYPES:
        message = f"expected {_TYPES[kind]}, got {value!r}"
    elif kind in ("greater_than_equal", "less_than_equal", "greater_than", "less_than"):
        message = f"{message.replace('Input should be', 'expected a number')}, got {value!r}"
    elif kind == "emscon_form":
        message = f"{message}, got {value!r}"
    elif kind == "string_too_short":
        message = f"expected a non-empty string, got {value!r}"
    elif kind == "string_pattern_mismatch" and loc[:1] in (["encoders"], ["resolvers"]):
        message = f"expected a joint number (1, 2, ...), got {value!r}"
    return DeviceConfigError(".".join(["devices", *loc]), message)


def devices_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a cell's ``devices`` document, as the page reads it."""
    schema = DevicesConfig.model_json_schema(mode="validation")
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}
