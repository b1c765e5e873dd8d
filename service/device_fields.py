"""The building blocks of a cell's device configuration: the error, the address patterns (the
same for Python and the page's ECMAScript), the field types, and the settings objects of the
devices that take more than an address (``emscon``, ``can``). The configuration itself is the
registry's (:mod:`service.device_registry`); its parser is :mod:`service.device_config`.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
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

    @classmethod
    def from_address(cls, text: str) -> EmsconSettings:
        """The settings of ``emscon`` written as "HOST" (port 700) or "HOST:PORT"."""
        host, sep, port = text.rpartition(":")
        if not sep or not host or host.endswith(":"):  # "HOST", or a bare IPv6 address
            return cls(host=text)
        return cls(host=host, port=int(port))

    def address(self) -> str:
        return self.host if self.port is None else f"{self.host}:{self.port}"


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

    def address(self) -> str:
        where = f" {self.host}:{self.port}" if self.host else ""
        return f"{self.interface} {self.channel}{where}"


# The tooling balls' radius when the cell does not give one: the common 25 mm ball.
DEFAULT_BALL_RADIUS_M = 0.0125

SerialUrl = _text(
    SERIAL_URL_PATTERN,
    "socket://HOST:PORT or a serial port (/dev/ttyUSB0, COM3)",
    examples=["socket://192.168.1.20:10001"],
)
CmmUrl = _text(SERIAL_URL_PATTERN, "socket://HOST:PORT of the I++ DME server", examples=["socket://192.168.1.30:1294"])
