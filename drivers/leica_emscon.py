"""Leica laser trackers through the emScon server's TPI (binary packets over TCP, port 700).

The emScon server (on the tracker controller of an AT9xx or AT4xx, or on a PC for older
trackers) answers the Tracker Programming Interface: packed little-endian C structures whose
layouts Leica publishes in ``ES_C_API_Def.h``. This module is its own codec of the subset
Recal needs, written with ``struct`` from the layouts in the MIT-licensed ``cesapi`` package
(``CESAPI/packet.py``, generated from that header). ``cesapi`` itself is only a test peer
(tests/drivers/test_leica_emscon.py decodes every packet this driver writes with it): it reads
its socket in 0.2 s steps and is unmaintained since 2018.

Every packet starts with ``PacketHeaderT`` (``int32 lPacketSize`` of the whole packet, ``uint32
type``). A command is ``BasicCommandCT`` (the header, ``uint32 command``) and its parameters;
its reply is ``BasicCommandRT`` (the header, ``command``, ``uint32 status``) and the reply's
data. A stationary measurement answers ``StartMeasurement`` with its reply and one result
packet (``SingleMeasResultT``, or ``SingleMeasResult2T`` with covariances). Status changes
(``SystemStatusChangeT``) arrive unasked; errors may come as ``ErrorResponseT``.

Connecting (every connect, reconnects included, runs the whole set-up):
``GetSystemStatus`` and ``GetTrackerStatus``; ``Initialize`` when the tracker processor is not
initialised; ``SetUnits`` (millimetre, degree, Celsius, mbar, %RH); ``GetCoordinateSystemType``
(it must be the right-handed cartesian one: Recal reads x, y, z and never changes it); the environment: set from the
config (``SetEnvironmentParams``) or read from the tracker's meteo station
(``GetEnvironmentParams``); ``GetReflectors`` and ``SetReflector`` by the configured name;
``SetMeasurementMode`` stationary and ``SetStationaryModeParams`` (averaging time).

``measure()`` sends ``StartMeasurement`` and returns only the result that follows its own
successful reply: a result or reply that arrives at any other moment is unsolicited and never
returned (it is logged and dropped; within a command it is a ``ProtocolError``). Errors (all from
:mod:`drivers.errors`, naming the tracker and carrying the emScon status code):

- reflector not locked, no stationary result, not ready to measure, ADM warming up
  -> ``MeasurementError`` (the beam is broken or the reflector moved: point the tracker at the
  reflector with :meth:`EmsconTracker.find_reflector`, then measure again);
- ``ES_RS_NotImplemented`` and the wrong-parameter codes -> ``ProtocolError`` (we sent something
  this server does not take);
- ``ES_RS_TrackerNotInitialized`` and every other status -> ``DeviceFaultError``; the link is
  dropped so that the next command reconnects and initialises;
- a packet of a wrong size or unknown type, a reply to another command -> ``ProtocolError``,
  the link is dropped and the next command reconnects with the full set-up; a size field larger
  than the packet is caught by ``PACKET_BODY_S`` (the rest of a packet that does not follow its
  header promptly), not by the command's deadline, which for ``Initialize`` is minutes;
- no (complete) reply within the deadline -> ``DeviceTimeoutError``, the link is dropped;
- a dropped connection -> one reconnect with the full set-up and one resend; if that fails
  too, ``DeviceConnectionError``.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.base import PointMeasurement, SteerablePositionSensor
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
    translate_errors,
)

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- codes (ES_C_API_Def.h)

# ES_DataType
DT_COMMAND, DT_ERROR, DT_SINGLE_MEAS_RESULT, DT_SYSTEM_STATUS_CHANGE, DT_SINGLE_MEAS_RESULT2 = 0, 1, 2, 8, 9
# ES_Command
C_GET_SYSTEM_STATUS = 1
C_GET_TRACKER_STATUS = 2
C_SET_UNITS = 5
C_INITIALIZE = 7
C_SET_ENVIRONMENT_PARAMS = 20
C_GET_ENVIRONMENT_PARAMS = 21
C_SET_MEASUREMENT_MODE = 24
C_GET_COORDINATE_SYSTEM_TYPE = 27
C_SET_STATIONARY_MODE_PARAMS = 28
C_SET_REFLECTOR = 40
C_GET_REFLECTORS = 42
C_START_MEASUREMENT = 49
C_GO_POSITION = 55
C_FIND_REFLECTOR = 63
C_GET_MEASUREMENT_STATUS_INFO = 122
# ES_ResultStatus
RS_ALL_OK = 0
RS_NOT_IMPLEMENTED = 2
RS_TRACKER_NOT_INITIALIZED = 39
RS_MEASUREMENT_STATUS_NOT_READY = 10004
RS_ADM_STARTUP_BUSY = 10005
RS_NO_STATIONARY_RESULT = 10009
RS_SENSOR_NOT_STABLE = 10013
RS_SYSTEM_NOT_READY_FOR_MEASUREMENT = 10014
#: statuses meaning "this measurement cannot be taken now" (beam, reflector, warm-up)
MEASUREMENT_STATUSES = frozenset(
    {
        RS_MEASUREMENT_STATUS_NOT_READY,
        RS_ADM_STARTUP_BUSY,
        RS_NO_STATIONARY_RESULT,
        RS_SENSOR_NOT_STABLE,
        RS_SYSTEM_NOT_READY_FOR_MEASUREMENT,
    }
)
#: statuses meaning "the server does not take what we sent": not implemented, wrong parameter 1..16,
#: parameter out of range (NOK)
PROTOCOL_STATUSES = frozenset({RS_NOT_IMPLEMENTED, *range(3, 11), *range(12, 23, 2), *range(47, 56)})
# ES_SystemStatusChange
SSC_MEAS_STATUS_NOT_READY, SSC_MEAS_STATUS_READY = 25, 27
SSC_TP_CONNECTION_CLOSING, SSC_SERVER_CLOSING = 997, 998
# ES_TrackerProcessorStatus, ES_TrackerStatus, ES_WeatherMonitorStatus, ES_MeasurementStatusInfo bits
TPS_INITIALIZED = 5
TS_NOT_READY, TS_BUSY, TS_READY = 0, 1, 2
WMS_NOT_CONNECTED = 0
MSI_REFLECTOR_FOUND, MSI_INITIALIZED = 2048, 65536
# units: ES_LU_Millimeter, ES_AU_Degree, ES_TU_Celsius, ES_PU_Mbar, ES_HU_RH
UNITS_MM_DEG_C_MBAR_RH = (1, 1, 0, 0, 0)
MM_M = 1e-3
MM_STATIONARY = 0  # ES_MM_Stationary
CS_RHR = 0  # ES_CS_RHR: cartesian, right-handed (dVal1..3 are x, y, z)

# --------------------------------------------------------------------------- layouts
# Little-endian, no padding (the header packs with 4-byte alignment and every field is 4 or 8
# bytes). Each entry is the format of what follows BasicCommandCT (commands) or BasicCommandRT
# (replies); the packet's size is fixed by it.

HEADER = struct.Struct("<iI")  # PacketHeaderT: lPacketSize, type
COMMAND = struct.Struct("<iII")  # BasicCommandCT: header, command
REPLY = struct.Struct("<iIII")  # BasicCommandRT: header, command, status

COMMAND_PARAMS = {
    C_GET_SYSTEM_STATUS: "",
    C_GET_TRACKER_STATUS: "",
    C_INITIALIZE: "",
    C_GET_ENVIRONMENT_PARAMS: "",
    C_GET_REFLECTORS: "",
    C_START_MEASUREMENT: "",
    C_GET_MEASUREMENT_STATUS_INFO: "",
    C_GET_COORDINATE_SYSTEM_TYPE: "",
    C_SET_UNITS: "5I",  # SystemUnitsDataT: length, angle, temperature, pressure, humidity unit
    C_SET_ENVIRONMENT_PARAMS: "3d",  # EnvironmentDataT: temperature, pressure, humidity
    C_SET_MEASUREMENT_MODE: "I",  # ES_MeasMode
    C_SET_STATIONARY_MODE_PARAMS: "2i",  # StationaryModeDataT: lMeasTime (ms), bUseADM
    C_SET_REFLECTOR: "i",  # iInternalReflectorId
    C_GO_POSITION: "3di",  # dVal1..3 (current units), bUseADM
    C_FIND_REFLECTOR: "d",  # dAproxDistance (current length unit)
}
REPLY_DATA = {
    # lastResultStatus, trackerProcessorStatus, laserStatus, admStatus, ESVersionNumberT (3 x int32),
    # weatherMonitorStatus, lFlagsValue, lTrackerSerialNumber
    C_GET_SYSTEM_STATUS: "4I3iIii",
    C_GET_TRACKER_STATUS: "I",  # ES_TrackerStatus
    C_GET_COORDINATE_SYSTEM_TYPE: "I",  # ES_CoordinateSystemType
    C_GET_ENVIRONMENT_PARAMS: "3d",
    C_GET_REFLECTORS: "iiId64s",  # iTotalReflectors, iInternalReflectorId, targetType, dSurfaceOffset, name (32 UTF-16 units)
    C_GET_MEASUREMENT_STATUS_INFO: "Ii",  # lastResultStatus, lMeasurementStatusInfo
}
# After ReturnDataT (header, status): measMode, bIsTryMode, then doubles.
#   SingleMeasResultT: dVal1-3, dStd1-3, dStdTotal, dPointingError1-3, dAprioriStd1-3,
#   dAprioriStdTotal, dTemperature, dPressure, dHumidity
#   SingleMeasResult2T: dVal1-3, dStd1-3, dStdTotal, dCovar12, 13, 23, dPointingErrorH, V, D,
#   dAprioriStd1-3, dAprioriStdTotal, dAprioriCovar12, 13, 23, dTemperature, dPressure, dHumidity
RESULT = {DT_SINGLE_MEAS_RESULT: struct.Struct("<iIIIi17d"), DT_SINGLE_MEAS_RESULT2: struct.Struct("<iIIIi23d")}
APRIORI_STD_AT = {DT_SINGLE_MEAS_RESULT: 11, DT_SINGLE_MEAS_RESULT2: 14}  # index of dAprioriStd1 among the doubles
STATUS_CHANGE = struct.Struct("<iII")  # SystemStatusChangeT: header, systemStatusChange
ERROR = struct.Struct("<iIII")  # ErrorResponseT: header, command, status
_FIXED_SIZES = {
    DT_SYSTEM_STATUS_CHANGE: STATUS_CHANGE.size,
    DT_ERROR: ERROR.size,
    **{t: s.size for t, s in RESULT.items()},
}
MAX_PACKET = 4096
# The server writes each packet whole, so once a header has arrived the rest of that packet is
# on the wire: on a LAN it follows within milliseconds. A header announcing more bytes than
# follow is a wrong size field, and waiting for the command's deadline instead would hold a
# session for initialize_timeout_s (120 s) on a garbled reply to Initialize (issue 22).
PACKET_BODY_S = 1.0


def command_struct(command: int) -> struct.Struct:
    return struct.Struct("<iII" + COMMAND_PARAMS[command])


def reply_struct(command: int) -> struct.Struct:
    return struct.Struct("<iIII" + REPLY_DATA.get(command, ""))


def pack_command(command: int, *params) -> bytes:
    """One command packet: BasicCommandCT and its parameters, ``lPacketSize`` filled in."""
    s = command_struct(command)
    return s.pack(s.size, DT_COMMAND, command, *params)


# --------------------------------------------------------------------------- config

# A Leica AT960's (and AT930's) maximum permissible error of a point, Uxyz = ±(15 um + 6 um/m)
# (Leica Absolute Tracker AT960 product brochure, ISO 10360-10), at 4 m (39 um) taken as two
# standard uncertainties: 20 um per axis. Conservative within a cell (Leica: typical errors are
# half the MPE); the emScon server states each measurement's own uncertainty, stored with it.
AT960_SIGMA_M = 20e-6


@dataclass(frozen=True, slots=True)
class EmsconConfig:
    """How to reach and set up a Leica tracker's emScon server.

    ``host``/``port``: the emScon server (the tracker controller's address; port 700);
    ``timeout_s``: deadline of each reply (a measurement gets ``measure_time_s`` more);
    ``initialize_timeout_s``: deadline of ``Initialize`` (it moves the head and takes tens of
    seconds); ``reflector``: the name of the reflector as the server lists it (``GetReflectors``);
    ``measure_time_s``: stationary averaging time; ``use_adm``: measure the distance with the
    absolute distance meter alone; ``environment``: ``"meteo"`` uses the tracker's weather
    station, ``"config"`` sets ``temperature_c``, ``pressure_mbar`` and ``humidity_pct``;
    ``reconnect``: reconnect once (full set-up) and resend when the link drops; ``sigma_m``: the
    tracker's per-axis standard uncertainty of a point (m), what sessions plan and weigh with
    (:data:`AT960_SIGMA_M` unless stated).
    """

    host: str
    port: int = 700
    timeout_s: float = 5.0
    initialize_timeout_s: float = 120.0
    reflector: str = "RRR 1.5in"
    measure_time_s: float = 0.5
    use_adm: bool = False
    environment: Literal["meteo", "config"] = "meteo"
    temperature_c: float = 20.0
    pressure_mbar: float = 1013.25
    humidity_pct: float = 50.0
    reconnect: bool = True
    sigma_m: float = AT960_SIGMA_M

    def __post_init__(self):
        if not self.host:
            raise ValueError("host must be the emScon server's address")
        if not 0 < int(self.port) < 65536:
            raise ValueError(f"port must be 1..65535; got {self.port}")
        for name in ("timeout_s", "initialize_timeout_s", "sigma_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")
        if not 0 < self.measure_time_s <= 60:
            raise ValueError(f"measure_time_s must be in (0, 60] s; got {self.measure_time_s}")
        if self.environment not in ("meteo", "config"):
            raise ValueError(f"environment must be 'meteo' or 'config'; got {self.environment!r}")
        if not self.reflector:
            raise ValueError("reflector must name a reflector the server lists")

    @classmethod
    def from_endpoint(cls, endpoint: str, **kwargs) -> EmsconConfig:
        """``"HOST:PORT"`` (the endpoint line's ``emscon``, contracts §7) or ``"HOST"``."""
        host, sep, port = str(endpoint).rpartition(":")
        if not sep:
            return cls(host=str(endpoint), **kwargs)
        if not host or not port.isdigit():
            raise ValueError(f"expected HOST:PORT, got {endpoint!r}")
        return cls(host=host, port=int(port), **kwargs)


@dataclass(frozen=True, slots=True)
class EmsconIdentity:
    """What ``GetSystemStatus`` says: the emScon server version and the tracker's serial number."""

    server_version: str
    serial: int
    weather_monitor: int  # ES_WeatherMonitorStatus: 0 none connected


@dataclass(frozen=True, slots=True)
class Reflector:
    id: int
    name: str
    target_type: int
    surface_offset_mm: float


# --------------------------------------------------------------------------- driver


class EmsconTracker(SteerablePositionSensor):
    """A Leica tracker through its emScon server. Connects (and sets up) on construction."""

    def __init__(self, config: EmsconConfig):
        self.config = config
        self.name = f"emScon tracker {config.host}:{config.port}"
        self._sock: socket.socket | None = None
        self._buffer = bytearray()
        self._sequence = 0
        self._closed = False
        self.beam_lost = False  # as the server last said: a status change, a status reply or an error
        self.identity: EmsconIdentity | None = None
        self.reflector: Reflector | None = None
        self.environment: tuple[float, float, float] | None = None  # degC, mbar, %RH in use
        self._connect()

    # ----------------------------------------------------------------- PositionSensor

    @property
    def sigma_m(self) -> float:
        """The per-axis standard uncertainty its configuration declares (m)."""
        return self.config.sigma_m

    def measure(self) -> PointMeasurement:
        """One fresh stationary measurement of the reflector (m, tracker frame) with its per-axis
        standard deviations (m). Raises ``MeasurementError`` when the tracker cannot measure
        now, and the other errors of the module docstring."""
        result = self._command(C_START_MEASUREMENT, extra_s=self.config.measure_time_s)
        kind, values = result
        if values[2] != RS_ALL_OK:  # the result's own status (ReturnDataT)
            raise self._error(C_START_MEASUREMENT, values[2])
        doubles = values[5:]
        p_mm = np.array(doubles[0:3])
        std_mm = np.array(doubles[3:6])
        if not np.all(std_mm > 0):  # firmware that leaves the measured deviations empty: the a-priori ones
            k = APRIORI_STD_AT[kind]
            std_mm = np.array(doubles[k : k + 3])
        if not (np.all(np.isfinite(p_mm)) and np.all(np.isfinite(std_mm)) and np.all(std_mm >= 0)):
            self._drop_link()
            raise ProtocolError(
                f"measurement result with non-finite values or negative deviations: "
                f"{p_mm.tolist()} ± {std_mm.tolist()} mm",
                device=self.name,
            )
        self._sequence += 1
        self.beam_lost = False
        return PointMeasurement(
            p_world=p_mm * MM_M, sigma=std_mm * MM_M, sequence=self._sequence, timestamp_s=time.time()
        )

    def status(self) -> str:
        """``"ready"``, ``"beam_broken"`` (no reflector locked) or ``"not_initialised"``, from
        ``GetMeasurementStatusInfo``."""
        reply = self._command(C_GET_MEASUREMENT_STATUS_INFO)
        info = reply[5]
        if not info & MSI_INITIALIZED:
            return "not_initialised"
        self.beam_lost = not info & MSI_REFLECTOR_FOUND
        return "beam_broken" if self.beam_lost else "ready"

    def find_reflector(self, p_world: np.ndarray) -> None:
        """Point the tracker at where the reflector should be (``p_world`` (3,) m, tracker frame)
        and search for it there: ``GoPosition`` then ``FindReflector`` with the distance to it.
        The only motion of the tracker Recal ever commands. Raises ``MeasurementError`` when the
        reflector is not found there."""
        p_mm = np.asarray(p_world, dtype=float).reshape(3) / MM_M
        if not np.all(np.isfinite(p_mm)):
            raise ValueError(f"p_world must be three finite numbers; got {p_world!r}")
        self._command(C_GO_POSITION, *p_mm.tolist(), int(self.config.use_adm), extra_s=self.config.timeout_s)
        self._command(C_FIND_REFLECTOR, float(np.linalg.norm(p_mm)), extra_s=self.config.timeout_s)
        self.beam_lost = False

    def close(self) -> None:
        self._closed = True
        self._drop_link()

    # ----------------------------------------------------------------- connection

    def _connect(self) -> None:
        """Open the socket and run the whole set-up (module docstring)."""
        self._drop_link()
        try:
            with translate_errors(self.name, timeout_s=self.config.timeout_s):
                sock = socket.create_connection((self.config.host, self.config.port), timeout=self.config.timeout_s)
        except DeviceError as exc:
            raise DeviceConnectionError(f"cannot connect: {exc}", device=self.name) from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        try:
            self._set_up()
        except BaseException:
            self._drop_link()
            raise

    def _set_up(self) -> None:
        cfg = self.config
        status = self._exchange(C_GET_SYSTEM_STATUS)
        _, _, _, _, _last, processor, _laser, _adm, major, minor, build, weather, _flags, serial = status
        self.identity = EmsconIdentity(f"{major}.{minor}.{build}", serial, weather)
        tracker_status = self._exchange(C_GET_TRACKER_STATUS)[4]
        if processor != TPS_INITIALIZED or tracker_status == TS_NOT_READY:
            log.info(
                "%s: initialising the tracker (processor status %d, tracker status %d)",
                self.name,
                processor,
                tracker_status,
            )
            self._exchange(C_INITIALIZE, timeout_s=cfg.initialize_timeout_s)
        self._exchange(C_SET_UNITS, *UNITS_MM_DEG_C_MBAR_RH)
        system = self._exchange(C_GET_COORDINATE_SYSTEM_TYPE)[4]
        if system != CS_RHR:  # spherical or left-handed: dVal1..3 would not be x, y, z; Recal does not change it
            raise DeviceFaultError(
                f"the tracker's coordinate system type is {system}; Recal needs the right-handed "
                f"cartesian one (ES_CS_RHR, 0): set it in the tracker software",
                device=self.name,
            )
        if cfg.environment == "config":
            self._exchange(C_SET_ENVIRONMENT_PARAMS, cfg.temperature_c, cfg.pressure_mbar, cfg.humidity_pct)
            self.environment = (cfg.temperature_c, cfg.pressure_mbar, cfg.humidity_pct)
        else:
            if weather == WMS_NOT_CONNECTED:
                raise DeviceFaultError(
                    "environment 'meteo' but the tracker reports no weather station connected; "
                    "connect it or set environment 'config' with the room's values",
                    device=self.name,
                )
            self.environment = tuple(self._exchange(C_GET_ENVIRONMENT_PARAMS)[4:7])
        reflectors = self._reflectors()
        wanted = next((r for r in reflectors if r.name == cfg.reflector), None)
        if wanted is None:
            names = ", ".join(repr(r.name) for r in reflectors) or "none"
            raise DeviceFaultError(f"no reflector named {cfg.reflector!r}; the server lists {names}", device=self.name)
        self._exchange(C_SET_REFLECTOR, wanted.id)
        self.reflector = wanted
        self._exchange(C_SET_MEASUREMENT_MODE, MM_STATIONARY)
        self._exchange(C_SET_STATIONARY_MODE_PARAMS, round(cfg.measure_time_s * 1000), int(cfg.use_adm))
        log.info(
            "%s: emScon %s, tracker %d, reflector %r, environment %s",
            self.name,
            self.identity.server_version,
            serial,
            wanted.name,
            self.environment,
        )

    def _reflectors(self) -> list[Reflector]:
        """``GetReflectors``: the server answers one reply per reflector it knows."""
        replies = self._exchange(C_GET_REFLECTORS, all_replies=True)
        out = []
        for r in replies:
            name = r[8].decode("utf-16-le", errors="replace").split("\x00", 1)[0].strip()
            out.append(Reflector(r[5], name, r[6], r[7]))
        return out

    def _drop_link(self) -> None:
        """Forget the connection; the next command reconnects with the full set-up."""
        sock, self._sock = self._sock, None
        self._buffer.clear()
        if sock is not None:
            try:
                sock.close()
            except OSError:
                pass

    def _command(self, command: int, *params, extra_s: float = 0.0):
        """Send ``command`` and return its answer, reconnecting once if the link dropped."""
        if self._closed:
            raise DeviceConnectionError("the driver is closed", device=self.name)
        attempts = 2 if self.config.reconnect else 1
        for attempt in range(attempts):
            try:
                if self._sock is None:
                    self._connect()
                return self._exchange(command, *params, timeout_s=self.config.timeout_s + extra_s)
            except DeviceConnectionError as exc:
                self._drop_link()
                if attempt + 1 < attempts:
                    log.warning("%s: %s; reconnecting (full set-up) and resending command %d", self.name, exc, command)
                    continue
                detail = " after one reconnect" if attempts > 1 else ""
                raise DeviceConnectionError(f"command {command} failed{detail}: {exc}", device=self.name) from exc
        raise AssertionError("unreachable")  # pragma: no cover

    # ----------------------------------------------------------------- one exchange

    def _exchange(self, command: int, *params, timeout_s: float | None = None, all_replies: bool = False):
        """Send one command and wait for its answer: the reply's unpacked fields; for
        ``StartMeasurement`` ``(result type, result fields)``; with ``all_replies`` the list of
        every reply (``GetReflectors``). Errors become exceptions (module docstring)."""
        self._discard_unsolicited(command)
        sock = self._sock
        if sock is None:
            raise DeviceConnectionError("not connected", device=self.name)
        limit = self.config.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + limit
        with translate_errors(self.name, timeout_s=limit):
            sock.sendall(pack_command(command, *params))
        replies: list[tuple] = []
        result = None
        try:
            while True:
                kind, data = self._read_packet(deadline, command, limit)
                if kind == DT_SYSTEM_STATUS_CHANGE:
                    self._status_change(data)
                    continue
                if kind == DT_ERROR:
                    _, _, cmd, status = ERROR.unpack(data)
                    if cmd != command:
                        raise self._protocol(f"error packet for command {cmd} while waiting for command {command}")
                    raise self._error(command, status)
                if kind in RESULT:
                    if command != C_START_MEASUREMENT or result is not None:
                        raise self._protocol(f"unsolicited measurement result while waiting for command {command}")
                    result = (kind, RESULT[kind].unpack(data))
                else:  # DT_COMMAND: a reply
                    _, _, cmd, status = REPLY.unpack_from(data)
                    if cmd != command:
                        raise self._protocol(f"reply to command {cmd} while waiting for command {command}")
                    if status != RS_ALL_OK:
                        raise self._error(command, status)
                    expected = reply_struct(command)
                    if len(data) != expected.size:
                        raise self._protocol(
                            f"reply to command {command} of {len(data)} bytes; expected {expected.size}"
                        )
                    replies.append(expected.unpack(data))
                    if all_replies and replies[0][4] > len(replies):
                        continue  # GetReflectors: iTotalReflectors replies
                if command == C_START_MEASUREMENT:
                    if replies and result is not None:  # both, in either order
                        return result
                    continue
                return replies if all_replies else replies[0]
        except (DeviceTimeoutError, ProtocolError):
            self._drop_link()  # a late or partial answer must never be read as the next one
            raise
        except DeviceFaultError as exc:
            if exc.code == RS_TRACKER_NOT_INITIALIZED:
                self._drop_link()  # the next command reconnects and initialises
            raise

    def _read_packet(self, deadline: float, command: int, limit: float) -> tuple[int, bytes]:
        """The next whole packet ``(type, bytes)``; checks its size against its type."""
        header = self._read_exact(HEADER.size, deadline, command, limit)
        size, kind = HEADER.unpack(header)
        if kind == DT_COMMAND:
            ok = REPLY.size <= size <= MAX_PACKET
        elif kind in _FIXED_SIZES:
            ok = size == _FIXED_SIZES[kind]
        else:
            raise self._protocol(f"packet of unknown type {kind} ({size} bytes) while waiting for command {command}")
        if not ok:
            raise self._protocol(f"packet of type {kind} with a wrong size {size} while waiting for command {command}")
        body_deadline = min(deadline, time.monotonic() + PACKET_BODY_S)
        try:
            body = self._read_exact(size - HEADER.size, body_deadline, command, limit)
        except DeviceTimeoutError:
            if body_deadline >= deadline:
                raise  # the command's own deadline ran out: a late answer, not a bad size
            arrived = len(self._buffer)
            raise self._protocol(
                f"packet of type {kind} announced {size} bytes but {HEADER.size + arrived} arrived "
                f"(a wrong size field) while waiting for command {command}"
            ) from None
        return kind, header + body

    def _read_exact(self, n: int, deadline: float, command: int, limit: float) -> bytes:
        sock = self._sock
        if sock is None:
            raise DeviceConnectionError("not connected to the emScon server", device=self.name)
        with translate_errors(self.name, timeout_s=limit):
            while len(self._buffer) < n:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    partial = f" ({len(self._buffer)} bytes of a packet)" if self._buffer else ""
                    raise DeviceTimeoutError(
                        f"no answer to command {command} within {limit:g} s{partial}", device=self.name
                    )
                ready, _, _ = select.select([sock], [], [], remaining)
                if not ready:
                    continue
                chunk = sock.recv(65536)
                if not chunk:
                    raise DeviceConnectionError("the emScon server closed the connection", device=self.name)
                self._buffer += chunk
        data = bytes(self._buffer[:n])
        del self._buffer[:n]
        return data

    def _discard_unsolicited(self, command: int) -> None:
        """Before a command: read what arrived unasked. Status changes are taken note of;
        anything else (a result or a reply nobody waits for) is dropped, never returned."""
        sock = self._sock
        if sock is None:
            return
        with translate_errors(self.name, timeout_s=self.config.timeout_s):
            while select.select([sock], [], [], 0)[0]:
                chunk = sock.recv(65536)
                if not chunk:
                    raise DeviceConnectionError("the emScon server closed the connection", device=self.name)
                self._buffer += chunk
        while len(self._buffer) >= HEADER.size:
            size, kind = HEADER.unpack_from(self._buffer)
            if size < HEADER.size or size > MAX_PACKET:
                raise self._protocol(f"unsolicited packet with a wrong size {size} before command {command}")
            if len(self._buffer) < size:
                return  # the rest is on its way; the exchange reads it
            data = bytes(self._buffer[:size])
            del self._buffer[:size]
            if kind == DT_SYSTEM_STATUS_CHANGE and size == STATUS_CHANGE.size:
                self._status_change(data)
            else:
                log.warning(
                    "%s: dropped an unsolicited packet of type %d (%d bytes) before command %d",
                    self.name,
                    kind,
                    size,
                    command,
                )

    def _status_change(self, data: bytes) -> None:
        change = STATUS_CHANGE.unpack(data)[2]
        if change == SSC_MEAS_STATUS_NOT_READY:
            self.beam_lost = True
        elif change == SSC_MEAS_STATUS_READY:
            self.beam_lost = False
        elif change in (SSC_TP_CONNECTION_CLOSING, SSC_SERVER_CLOSING):
            raise DeviceConnectionError("the emScon server is closing the connection", device=self.name)
        log.debug("%s: status change %d", self.name, change)

    def _protocol(self, message: str) -> ProtocolError:
        self._drop_link()
        return ProtocolError(message, device=self.name)

    def _error(self, command: int, status: int) -> DeviceError:
        """The exception for an emScon status other than ``ES_RS_AllOK`` (module docstring)."""
        if status in MEASUREMENT_STATUSES:
            self.beam_lost = status == RS_MEASUREMENT_STATUS_NOT_READY
            what = {
                RS_MEASUREMENT_STATUS_NOT_READY: "no reflector locked (beam broken)",
                RS_ADM_STARTUP_BUSY: "the distance meter is warming up",
                RS_NO_STATIONARY_RESULT: "no stationary result (reflector moving)",
                RS_SENSOR_NOT_STABLE: "the tracker is not stable",
                RS_SYSTEM_NOT_READY_FOR_MEASUREMENT: "the tracker is not ready to measure",
            }[status]
            return MeasurementError(f"command {command}: cannot measure: {what}", device=self.name, code=status)
        if status in PROTOCOL_STATUSES:
            return ProtocolError(
                f"command {command} rejected by the server (not implemented or a wrong parameter)",
                device=self.name,
                code=status,
            )
        if status == RS_TRACKER_NOT_INITIALIZED:
            return DeviceFaultError(f"command {command}: the tracker is not initialised", device=self.name, code=status)
        return DeviceFaultError(f"command {command}: the server reports status {status}", device=self.name, code=status)
