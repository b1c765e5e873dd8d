"""Laser tracker over Recal's line protocol (contracts §8).

``LineTracker`` speaks the ASCII line protocol of contracts §8 through pyserial's
``serial_for_url``, so one driver reaches a tracker (or a protocol bridge) on a COM port
(``/dev/ttyUSB0``, ``COM3``), on TCP (``socket://192.168.0.10:10001``) or on a pty::

    *IDN?          -> <maker>,<model>,<serial>,<firmware>
    UNIT:LEN MM    -> OK                (also M, IN)
    UNIT:LEN?      -> MM
    MEAS?          -> <x>,<y>,<z>,<sx>,<sy>,<sz>      (the current length unit)
    STAT?          -> READY | BEAM_BROKEN | NOT_INITIALISED
    anything else  -> ERR <code>,<text>

On connect the driver asks ``*IDN?``, sets ``UNIT:LEN`` to the configured unit and reads it
back, and from then on converts every reply to metres. Errors (all from :mod:`drivers.errors`,
each naming the tracker's address):

- ``ERR 20,...`` (beam broken, reflector out of range) and ``ERR 21,...`` (reflector moving)
  -> ``MeasurementError`` with the code;
- ``ERR 10``/``ERR 11`` (the tracker did not understand the command or its argument)
  -> ``ProtocolError`` with the code; any other ``ERR`` -> ``DeviceFaultError`` with the code;
- a garbled or malformed reply -> ``ProtocolError``;
- no reply in ``timeout_s`` -> ``DeviceTimeoutError``;
- a dropped link -> one reconnect (with the full connect handshake) and one resend of the
  command; if that fails too, ``DeviceConnectionError``.

Never a stale value: every ``measure()`` sends a fresh ``MEAS?`` and returns only the reply to
it. Input that arrived unasked is discarded before each command, and after a timeout or a
garbled reply the link is closed, so a late reply can never be read as the answer to a later
command (the next call reconnects).

Vendor trackers (Leica emScon / LMF, FARO, API)
-----------------------------------------------
Recal only needs the :class:`drivers.base.PositionSensor` interface: ``measure()`` returning a
fresh :class:`~drivers.base.PointMeasurement` (metres, instrument frame, per-axis sigma,
increasing ``sequence``), ``status()`` and ``close()``. There are two ways to plug in a
vendor tracker:

1. *Adapter class.* Write ``drivers/<vendor>_tracker.py`` with a frozen
   ``<Vendor>TrackerConfig`` and a ``<Vendor>Tracker(PositionSensor)`` that talks the vendor's
   interface (emScon's binary TCP protocol on port 700, LMF's .NET SDK, FARO's SDK, API's DLL),
   converts to metres, raises ``MeasurementError`` when the vendor reports no beam / no
   reflector / an unstable reading, and wraps its transport in ``translate_errors``. It must
   never return the vendor's last buffered result as a new measurement: trigger a single
   measurement per ``measure()`` call and check the result's own timestamp or counter. Then
   let the service's device factory build it from the cell's ``devices`` entry.
2. *Protocol bridge.* Run a small program next to the vendor SDK (often a Windows PC) that
   answers the five commands above on a TCP port or serial line; ``LineTracker`` then works
   unchanged with ``socket://<bridge-host>:<port>``.
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass

import numpy as np

from drivers._linelink import LineLink
from drivers.base import PointMeasurement, PositionSensor
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
)

log = logging.getLogger(__name__)

#: Metres per tracker length unit (the arguments of ``UNIT:LEN``).
UNITS_M = {"MM": 1e-3, "M": 1.0, "IN": 0.0254}

# The line protocol is a bridge for FARO and API trackers, whose own figures are a little better
# than Leica's (FARO Vantage: MPE 16 um + 0.8 um/m; API Radian: ±(10 um + 5 um/m)): the per-axis
# standard uncertainty assumed when the configuration states none is the conservative one of the
# emScon driver (drivers.leica_emscon.AT960_SIGMA_M: a Leica AT960's MPE at 4 m, as two standard
# uncertainties). A measurement's own uncertainty (MEAS?) is stored with it; this figure plans.
LINE_TRACKER_SIGMA_M = 20e-6

#: ``ERR`` codes meaning "this measurement cannot be taken now" (contracts §8: 20).
MEASUREMENT_ERR_CODES = frozenset({20, 21})
#: ``ERR`` codes meaning "the tracker did not understand what we sent".
PROTOCOL_ERR_CODES = frozenset({10, 11})

_STATUS = {"READY": "ready", "BEAM_BROKEN": "beam_broken", "NOT_INITIALISED": "not_initialised"}
_ERR = re.compile(r"^ERR (\d+),(.*)$")


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    """How to reach a line-protocol laser tracker.

    ``url``: a pyserial URL (``socket://host:10001``, ``/dev/ttyUSB0``, ``COM3``, a pty path);
    ``timeout_s``: deadline for each reply (a stationary measurement that averages for longer
    needs a longer one); ``units``: the length unit set with ``UNIT:LEN`` on connect (the
    driver converts to metres either way); ``baudrate``: serial ports only;
    ``reconnect``: reconnect once and resend when the link drops; ``sigma_m``: the tracker's
    per-axis standard uncertainty of a point (m), what sessions plan and weigh with
    (:data:`LINE_TRACKER_SIGMA_M` unless stated).
    """

    url: str
    timeout_s: float = 2.0
    units: str = "MM"
    baudrate: int = 115200
    reconnect: bool = True
    sigma_m: float = LINE_TRACKER_SIGMA_M

    def __post_init__(self):
        if self.units.upper() not in UNITS_M:
            raise ValueError(f"units must be one of {', '.join(UNITS_M)}; got {self.units!r}")
        for name in ("timeout_s", "sigma_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")


@dataclass(frozen=True, slots=True)
class TrackerIdentity:
    """The tracker's ``*IDN?`` answer."""

    maker: str
    model: str
    serial: str
    firmware: str


class LineTracker(PositionSensor):
    """A laser tracker speaking the contracts §8 line protocol. Connects on construction."""

    def __init__(self, config: TrackerConfig):
        self.config = config
        self.name = f"tracker {config.url}"
        self._unit = config.units.upper()
        self._link = LineLink(config.url, device=self.name, timeout_s=config.timeout_s, baudrate=config.baudrate)
        self._sequence = 0
        self.identity: TrackerIdentity | None = None
        self._closed = False
        self._connect()

    # ----------------------------------------------------------------- PositionSensor

    @property
    def sigma_m(self) -> float:
        """The per-axis standard uncertainty its configuration declares (m)."""
        return self.config.sigma_m

    def measure(self) -> PointMeasurement:
        """One fresh reflector position (m, tracker frame) with its per-axis sigma (m).

        Raises ``MeasurementError`` when the tracker cannot measure now (beam broken, out of
        range, reflector moving), and the other errors of the module docstring.
        """
        reply = self._command("MEAS?")
        values = self._parse_numbers(reply, 6, "MEAS?", "<x>,<y>,<z>,<sx>,<sy>,<sz>")
        if any(v < 0 for v in values[3:]):
            self._drop_link()
            raise ProtocolError(f"MEAS? reply has a negative uncertainty: {reply!r}", device=self.name)
        scale = UNITS_M[self._unit]
        self._sequence += 1
        return PointMeasurement(
            p_world=np.array(values[:3]) * scale,
            sigma=np.array(values[3:]) * scale,
            sequence=self._sequence,
            timestamp_s=time.time(),
        )

    def status(self) -> str:
        """``"ready"``, ``"beam_broken"`` or ``"not_initialised"``."""
        reply = self._command("STAT?")
        try:
            return _STATUS[reply]
        except KeyError:
            self._drop_link()
            raise ProtocolError(
                f"STAT? replied {reply!r}; expected one of {', '.join(_STATUS)}", device=self.name
            ) from None

    def close(self) -> None:
        self._closed = True
        self._link.close()

    @property
    def unit(self) -> str:
        """The length unit the tracker reports in (``MM``, ``M`` or ``IN``)."""
        return self._unit

    # ----------------------------------------------------------------- connection

    def _connect(self) -> None:
        """Open the link and run the handshake: ``*IDN?``, ``UNIT:LEN <u>``, ``UNIT:LEN?``."""
        self._link.open()
        try:
            self.identity = self._parse_identity(self._exchange("*IDN?"))
            ok = self._exchange(f"UNIT:LEN {self._unit}")
            if ok != "OK":
                raise ProtocolError(f"UNIT:LEN {self._unit} replied {ok!r}; expected 'OK'", device=self.name)
            unit = self._exchange("UNIT:LEN?")
            if unit != self._unit:
                raise ProtocolError(
                    f"tracker reports unit {unit!r} after UNIT:LEN {self._unit}; expected {self._unit!r}",
                    device=self.name,
                )
        except BaseException:
            self._link.close()
            raise
        log.info("%s: connected to %s, unit %s", self.name, self.identity, self._unit)

    def _drop_link(self) -> None:
        """Forget the connection; the next command reconnects."""
        self._link.close()

    def _command(self, command: str) -> str:
        """Send ``command`` and return its reply line, reconnecting once if the link dropped."""
        if self._closed:
            raise DeviceConnectionError("the driver is closed", device=self.name)
        attempts = 2 if self.config.reconnect else 1
        for attempt in range(attempts):
            try:
                if not self._link.is_open:
                    self._connect()
                return self._exchange(command)
            except DeviceConnectionError as exc:
                self._link.close()
                if attempt + 1 < attempts:
                    log.warning("%s: %s; reconnecting once and resending %s", self.name, exc, command)
                    continue
                detail = " after one reconnect" if attempts > 1 else ""
                raise DeviceConnectionError(f"{command} failed{detail}: {exc}", device=self.name) from exc
        raise AssertionError("unreachable")  # pragma: no cover

    def _exchange(self, command: str) -> str:
        """One command, one reply line; ``ERR`` replies become exceptions."""
        stale = self._link.discard_input()
        if stale:
            log.warning("%s: discarded unexpected input before %s: %r", self.name, command, stale)
        self._link.write_line(command)
        try:
            reply = self._link.read_line(expecting=f"reply to {command}")
        except (DeviceTimeoutError, ProtocolError):
            self._drop_link()  # a late or partial reply must not be read as the next answer
            raise
        if reply.startswith("ERR"):
            raise self._error_from_reply(command, reply)
        return reply

    def _error_from_reply(self, command: str, reply: str) -> DeviceError:
        m = _ERR.match(reply)
        if not m:
            self._drop_link()
            return ProtocolError(
                f"{command} replied a malformed error {reply!r}; expected 'ERR <code>,<text>'", device=self.name
            )
        code, text = int(m.group(1)), m.group(2).strip()
        if code in MEASUREMENT_ERR_CODES:
            return MeasurementError(f"{command}: cannot measure: {text}", device=self.name, code=code)
        if code in PROTOCOL_ERR_CODES:
            return ProtocolError(f"{command} rejected by the tracker: {text}", device=self.name, code=code)
        return DeviceFaultError(f"{command}: tracker reports {text}", device=self.name, code=code)

    # ----------------------------------------------------------------- parsing

    def _parse_numbers(self, reply: str, count: int, command: str, shape: str) -> list[float]:
        parts = reply.split(",")
        try:
            if len(parts) != count:
                raise ValueError
            values = [float(p) for p in parts]
            if not all(math.isfinite(v) for v in values):
                raise ValueError
        except ValueError:
            self._drop_link()
            raise ProtocolError(
                f"{command} replied {reply!r}; expected {count} finite numbers {shape}", device=self.name
            ) from None
        return values

    def _parse_identity(self, reply: str) -> TrackerIdentity:
        parts = [p.strip() for p in reply.split(",")]
        if len(parts) != 4 or not parts[0]:
            raise ProtocolError(
                f"*IDN? replied {reply!r}; expected '<maker>,<model>,<serial>,<firmware>'", device=self.name
            )
        return TrackerIdentity(*parts)
