"""Reference joint encoders and resolver readers on CANopen (CiA 406), over python-can.

One ``CanopenEncoder`` reads one node: a CiA 406 absolute encoder (``kind="encoder"``) or a
resolver-to-digital reader that exposes the same position objects (``kind="resolver"``).

Objects used (CiA 406; resolver extras are this project's reference device,
``drivers/eds/resolver_reader.eds``):

- 0x1000 device type (an encoder must report profile 406 in its low 16 bits);
- 0x6000 operating parameters, bit 2 "scaling": with scaling the position is in measuring units
  (0x6001 per revolution, 0x6002 total range), without it in physical steps (0x6501 per
  revolution, 0x6501 * 0x6502 total);
- 0x6004 position value (U32): read by SDO expedited upload, or received in TPDO1;
- resolver only: 0x2000 fault bits (bit 0 LOS, bit 1 DOS, bit 2 LOT, bit 3 parity), 0x2001 pole
  pairs.

Counts become radians as "angle within the turn plus turns": ``(counts mod cpr) / cpr * 2 pi``
plus ``2 pi * (counts div cpr)``; a multi-turn range is centred on zero (``signed_range``) so
that a joint a little below the encoder's zero reads a small negative angle. A resolver's angle
is electrical; it is divided by the pole pairs, so it is known modulo ``2 pi / pole_pairs``.

Freshness: an SDO reading is the answer to this request (answers to earlier, abandoned requests
are recognised by their object index and skipped). In PDO mode the driver configures TPDO1 over
SDO (mapping 0x6004 [+ 0x2000], COB-ID 0x180 + node id; transmission type 1, one TPDO per SYNC,
or 254 with an event timer) and a reading is the first TPDO1 that arrives after the request (the
SYNC it sends, or the moment of the call in event mode). After a timed-out or bad request the
next read first completes an SDO round trip to the same node (a barrier: the node's frames
arrive in order, so every late answer to the old request has then been seen and discarded).

NMT: the driver starts the node (NMT start, and PRE-OPERATIONAL around the PDO configuration),
follows its heartbeat (a boot-up message means the node restarted with defaults: the next read
sets it up again) and its EMCY messages (an active EMCY makes reads fail with
``DeviceFaultError``).

Errors: SDO abort codes become ``ProtocolError`` (the request does not fit the device: object
missing, access, type) or ``DeviceFaultError`` (hardware error, device state, no data), with the
abort code as ``code`` (``"0x06060000"``); no answer in ``timeout_s`` is ``DeviceTimeoutError``;
a lost bus or gateway is ``DeviceConnectionError`` (a read on a link that dropped reconnects
once and retries: reading is idempotent). For socketcand the TCP port is probed with a timeout
first, because python-can's client retries for 10 s before it gives up.
"""

from __future__ import annotations

import contextlib
import math
import queue
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

# python-can and canopen are dependencies of the package (pyproject.toml): imported plainly
import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.base import EncoderReading, JointEncoder
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceFaultError,
    DeviceTimeoutError,
    DeviceUnavailableError,
    MeasurementError,
    ProtocolError,
)

EDS_DIR = Path(__file__).resolve().parent / "eds"
DEFAULT_EDS = {"encoder": EDS_DIR / "cia406_encoder.eds", "resolver": EDS_DIR / "resolver_reader.eds"}

DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
OPERATING_PARAMETERS = 0x6000
UNITS_PER_REV = 0x6001
TOTAL_RANGE = 0x6002
POSITION_VALUE = 0x6004
SINGLETURN_RESOLUTION = 0x6501
REVOLUTIONS = 0x6502
RESOLVER_FAULTS = 0x2000
RESOLVER_POLE_PAIRS = 0x2001
SCALING_BIT = 0x0004
PROFILE_406 = 406

RESOLVER_FAULT_NAMES = {
    0x01: "LOS loss of signal",
    0x02: "DOS degradation of signal",
    0x04: "LOT loss of tracking",
    0x08: "configuration parity",
}
NMT_STATES = {0: "boot-up", 4: "stopped", 5: "operational", 127: "pre-operational"}

# Abort codes that mean "the device cannot deliver now" rather than "this request does not fit
# the device" (CiA 301 table of SDO abort codes).
_FAULT_ABORTS = {0x06060000, 0x060A0023, 0x08000000, 0x08000020, 0x08000021, 0x08000022, 0x08000024}
_MISSING_ABORTS = {0x06020000, 0x06090011}
_U32 = struct.Struct("<I")
_SDO_REQUEST = struct.Struct("<BHBI")
_SDO_HEADER = struct.Struct("<BHB")


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True, slots=True)
class CanBusConfig:
    """Where the CAN bus is: the keyword arguments of python-can's ``can.Bus`` (contracts §7).

    ``interface`` is a python-can interface name (``"socketcand"``, ``"socketcan"``,
    ``"pcan"``, ``"kvaser"``, ``"slcan"``, ...). ``host``/``port`` are for ``socketcand`` only;
    ``bitrate`` (bit/s) for adapters whose bitrate python-can sets (not socketcan, which takes
    it from ``ip link``). ``connect_timeout_s`` bounds the TCP probe of a socketcand server;
    ``tcp_tune`` sets python-can's low-latency TCP options for socketcand (TCP_NODELAY and
    TCP_QUICKACK; without them a request may wait ~40 ms for a delayed ACK).
    """

    interface: str = "socketcand"
    channel: str = "vcan0"
    host: str | None = None
    port: int | None = None
    bitrate: int | None = None
    connect_timeout_s: float = 2.0
    tcp_tune: bool = True

    def __post_init__(self):
        if self.interface == "socketcand" and (not self.host or not self.port):
            raise ValueError("a socketcand bus needs `host` and `port`")
        if self.connect_timeout_s <= 0:
            raise ValueError(f"`connect_timeout_s` must be positive, got {self.connect_timeout_s}")

    @classmethod
    def from_endpoint(cls, can_endpoint: Mapping[str, Any]) -> CanBusConfig:
        """From the ``"can"`` object of the endpoint line (contracts §7)."""
        known = {"interface", "channel", "host", "port", "bitrate", "tcp_tune"}
        unknown = set(can_endpoint) - known
        if unknown:
            raise ValueError(f"unknown keys in the `can` endpoint: {', '.join(sorted(unknown))}")
        kw = dict(can_endpoint)
        if kw.get("port") is not None:
            kw["port"] = int(kw["port"])
        return cls(**kw)

    def bus_kwargs(self) -> dict[str, Any]:
        """The keyword arguments for ``can.Bus``."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "socketcand":
            kw.update(host=self.host, port=self.port, tcp_tune=self.tcp_tune)
        if self.bitrate is not None:
            kw["bitrate"] = self.bitrate
        return kw

    def describe(self) -> str:
        if self.interface == "socketcand":
            return f"socketcand {self.channel}@{self.host}:{self.port}"
        return f"{self.interface} {self.channel}"


@dataclass(frozen=True, slots=True)
class CanopenEncoderConfig:
    """One reference encoder or resolver reader node.

    ``use_pdo``: read TPDO1 instead of SDO; ``pdo_trigger`` ``"sync"`` (the driver sends a SYNC
    per reading; TPDO transmission type 1) or ``"event"`` (the node sends every
    ``event_timer_ms``; type 254: a reading takes the second TPDO that arrives after it is asked
    for, since the first may have been on its way already, sampled before the robot stopped).
    ``configure_pdo=False`` leaves the node's own TPDO1
    configuration alone (it is read back over SDO). ``timeout_s`` bounds every request.
    ``eds_path`` is the device's EDS (default: the reference EDS of ``kind`` in
    ``drivers/eds/``). ``signed_range``: centre a multi-turn range on zero.
    """

    bus: CanBusConfig
    node_id: int
    kind: Literal["encoder", "resolver"] = "encoder"
    use_pdo: bool = False
    pdo_trigger: Literal["sync", "event"] = "sync"
    event_timer_ms: int = 10
    configure_pdo: bool = True
    timeout_s: float = 0.5
    eds_path: str | None = None
    start_node: bool = True
    signed_range: bool = True
    heartbeat_timeout_s: float = 1.0
    reconnect: bool = True

    def __post_init__(self):
        if not 1 <= self.node_id <= 127:
            raise ValueError(f"`node_id` must be in 1..127, got {self.node_id}")
        if self.kind not in ("encoder", "resolver"):
            raise ValueError(f"`kind` must be 'encoder' or 'resolver', got {self.kind!r}")
        if self.pdo_trigger not in ("sync", "event"):
            raise ValueError(f"`pdo_trigger` must be 'sync' or 'event', got {self.pdo_trigger!r}")
        if self.timeout_s <= 0:
            raise ValueError(f"`timeout_s` must be positive, got {self.timeout_s}")
        if not 1 <= self.event_timer_ms <= 0xFFFF:
            raise ValueError(f"`event_timer_ms` must be in 1..65535, got {self.event_timer_ms}")

    @property
    def eds(self) -> Path:
        return Path(self.eds_path) if self.eds_path else DEFAULT_EDS[self.kind]


def configs_from_endpoint(
    endpoint: Mapping[str, Any], *, use_pdo: bool = False, timeout_s: float = 0.5
) -> dict[tuple[str, int], CanopenEncoderConfig]:
    """One config per device of an endpoint line (contracts §7), keyed ``(kind, joint)``:
    ``("encoder", 1)``, ``("resolver", 1)``, ..."""
    bus = CanBusConfig.from_endpoint(endpoint["can"])
    out: dict[tuple[str, int], CanopenEncoderConfig] = {}
    kinds: tuple[tuple[str, Literal["encoder", "resolver"]], ...] = (("encoders", "encoder"), ("resolvers", "resolver"))
    for key, kind in kinds:
        for joint, node_id in (endpoint.get(key) or {}).items():
            out[(kind, int(joint))] = CanopenEncoderConfig(
                bus=bus, node_id=int(node_id), kind=kind, use_pdo=use_pdo, timeout_s=timeout_s
            )
    return out


def counts_to_angle(
    counts: int, counts_per_rev: int, total_range: int, *, signed: bool = True, pole_pairs: int = 1
) -> float:
    """A position value in radians: angle within the turn plus whole turns.

    ``counts`` in ``[0, total_range)``; with ``signed`` and more than one turn in the range, the
    upper half of the range is read as negative (``counts - total_range``). A single-turn device
    gives ``[0, 2 pi)``. The result is divided by ``pole_pairs`` (a resolver's electrical angle).
    """
    if signed and total_range > counts_per_rev and counts >= total_range // 2:
        counts -= total_range
    turns, within = divmod(counts, counts_per_rev)
    return (2.0 * math.pi * (turns + within / counts_per_rev)) / pole_pairs


# --------------------------------------------------------------------------- bus plumbing


class _WatchedBus(can.BusABC):
    """Wraps the python-can bus so that a lost link is reported once and then stays quiet.

    python-can's socketcand client treats a TCP connection closed by the server as "no message"
    and spins on it; here that becomes one ``CanOperationError`` (canopen's notifier records it,
    ``Network.check()`` raises it on the next send), after which receiving just idles.
    """

    def __init__(self, inner, tcp_socket: socket.socket | None, on_error):
        self._inner = inner
        self._tcp = tcp_socket
        self._on_error = on_error
        self.error: Exception | None = None
        self.channel_info = inner.channel_info
        super().__init__(channel=getattr(inner, "channel", ""))

    def _recv_internal(self, timeout):
        if self.error is not None:
            time.sleep(0.1 if timeout is None else min(timeout, 0.1))
            return None, False
        try:
            msg, filtered = self._inner._recv_internal(timeout)
        except Exception as exc:  # noqa: BLE001 - any backend's receive failing means the link is gone
            self._fail(can.CanOperationError(f"receiving failed: {exc}"))
        if msg is None and self._peer_closed():
            self._fail(can.CanOperationError("the socketcand server closed the connection"))
        return msg, filtered

    def _fail(self, exc: Exception):
        self.error = exc
        self._on_error(exc)
        raise exc

    def _peer_closed(self) -> bool:
        if self._tcp is None:
            return False
        try:
            readable, _, _ = select.select([self._tcp], [], [], 0)
            return bool(readable) and self._tcp.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False
        except (OSError, ValueError):
            return True

    def send(self, msg, timeout=None) -> None:
        self._inner.send(msg, timeout)

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()


class _ErrorSink(can.Listener):
    """Tells canopen's notifier that receive errors are handled (recorded by the driver), so
    the notifier thread does not die with a traceback."""

    def on_message_received(self, msg) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        pass

    def stop(self) -> None:
        pass


# --------------------------------------------------------------------------- the driver


@dataclass
class _PdoInbox:
    """TPDO1 receptions, counted, for "a new PDO arrived after the request"."""

    cond: threading.Condition = field(default_factory=threading.Condition)
    count: int = 0
    data: bytes = b""


class CanopenEncoder(JointEncoder):
    """A CiA 406 encoder or a resolver reader on one joint, over CANopen.

    Connects in the constructor (probe, bus, NMT start, scaling objects, PDO configuration) and
    raises our exceptions if that fails. ``read()`` returns fresh readings; ``status()`` tells
    the node's NMT/EMCY state. ``counts_per_rev``, ``total_range`` and ``pole_pairs`` hold what
    the device reported.
    """

    def __init__(self, config: CanopenEncoderConfig):
        self.config = config
        self.name = f"canopen {config.kind} node {config.node_id} on {config.bus.describe()}"
        if not config.eds.is_file():
            raise ValueError(f"{self.name}: EDS file {config.eds} does not exist")
        self._od = canopen.import_od(str(config.eds), config.node_id)
        self._lock = threading.RLock()
        self._network: canopen.Network | None = None
        self._node: canopen.RemoteNode | None = None
        self._link_error: Exception | None = None
        self._sdo_answers: queue.Queue[bytes] = queue.Queue()
        self._pdo = _PdoInbox()
        self._pdo_layout: dict[int, tuple[int, int]] = {}
        self._pdo_cob_id = 0
        self._heartbeat_state: int | None = None
        self._heartbeat_at: float | None = None
        self._needs_setup = False
        self._needs_barrier = False
        self._sequence = 0
        self._closed = False
        self.reconnects = 0
        self.counts_per_rev = 0
        self.total_range = 0
        self.pole_pairs = 1
        self._connect()

    # ------------------------------------------------------------------ public

    def read(self) -> EncoderReading:
        """One fresh reading of the node's position value.

        Raises ``DeviceTimeoutError`` (no answer in ``timeout_s``), ``MeasurementError``
        (resolver fault bits), ``DeviceFaultError`` (EMCY, abort for a device fault),
        ``ProtocolError`` (garbled answer, abort for a bad request) or ``DeviceConnectionError``.
        """
        with self._lock:
            if self._closed:
                raise DeviceConnectionError("the driver is closed", device=self.name)
            had_link = self._network is not None
            try:
                if self._network is None:
                    self._connect()
                return self._read_once()
            except DeviceConnectionError:
                self._disconnect()
                if not (had_link and self.config.reconnect):
                    raise
            # The link dropped under an established connection; a read changes nothing on the
            # device, so reconnect once and read again.
            self.reconnects += 1
            self._connect()
            try:
                return self._read_once()
            except DeviceConnectionError:
                self._disconnect()
                raise

    def status(self) -> str:
        """``"operational"``, ``"pre-operational"``, ``"stopped"``, ``"boot-up"``, ``"no
        heartbeat"``, ``"fault: EMCY 0x...."`` or ``"disconnected"``, from the node's heartbeat
        and EMCY messages (see ``JointEncoder.status``); does not wait for a read in progress."""
        node, heartbeat_at = self._node, self._heartbeat_at
        if node is None or self._link_down():
            return "disconnected"
        active = list(node.emcy.active)
        if active:
            return "fault: " + _emcy_text(active)
        if heartbeat_at is None or time.monotonic() - heartbeat_at > self.config.heartbeat_timeout_s:
            return "no heartbeat"
        state = self._heartbeat_state
        return "no heartbeat" if state is None else NMT_STATES.get(state, f"NMT state {state}")

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._disconnect()

    # ------------------------------------------------------------------ connection

    @property
    def _live_node(self) -> canopen.RemoteNode:
        """The node while connected (every caller runs after :meth:`_connect`)."""
        if self._node is None:
            raise DeviceConnectionError("not connected to the CANopen node", device=self.name)
        return self._node

    @property
    def _live_network(self) -> canopen.Network:
        if self._network is None:
            raise DeviceConnectionError("not connected to the CAN bus", device=self.name)
        return self._network

    def _connect(self) -> None:
        bus = self._open_bus()
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.1
        network.NOTIFIER_SHUTDOWN_TIMEOUT = 1.0
        network.listeners.append(_ErrorSink())  # type: ignore[arg-type]  # a can.Listener is what the notifier calls
        self._link_error = None
        self._network = network
        try:
            network.connect()
            node = network.add_node(self.config.node_id, self._od)
            node.sdo.RESPONSE_TIMEOUT = self.config.timeout_s
            node.sdo.MAX_RETRIES = 1
            node.nmt.add_heartbeat_callback(self._on_heartbeat)
            network.subscribe(0x580 + self.config.node_id, self._on_sdo_answer)
            self._node = node
            self._heartbeat_state = self._heartbeat_at = None
            self._setup()
        except BaseException:
            self._disconnect()
            raise

    def _open_bus(self):
        cfg = self.config.bus
        if cfg.interface == "socketcand":
            self._probe_socketcand()
        try:
            inner = can.Bus(ignore_config=True, **cfg.bus_kwargs())
        except can.CanInterfaceNotImplementedError as exc:
            raise DeviceUnavailableError(f"python-can cannot open this interface: {exc}", device=self.name) from exc
        except (can.CanError, OSError, ValueError) as exc:
            raise DeviceConnectionError(f"cannot open the CAN bus: {exc}", device=self.name) from exc
        tcp = getattr(inner, "_SocketCanDaemonBus__socket", None) if cfg.interface == "socketcand" else None
        return _WatchedBus(inner, tcp, self._on_link_error)

    def _probe_socketcand(self) -> None:
        """Fail fast and cleanly: python-can's socketcand client retries connecting for 10 s,
        waits for the handshake without a timeout and leaks its socket when it fails."""
        cfg = self.config.bus
        where = f"socketcand server {cfg.host}:{cfg.port}"
        try:
            with socket.create_connection((cfg.host, cfg.port), timeout=cfg.connect_timeout_s) as probe:
                greeting = probe.recv(64)
                if not greeting.startswith(b"< hi >"):
                    raise ProtocolError(f"{where} greeted with {greeting[:32]!r}, expected '< hi >'", device=self.name)
                probe.sendall(f"< open {cfg.channel} >".encode("ascii"))
                answer = probe.recv(128)
        except TimeoutError as exc:
            raise DeviceConnectionError(
                f"{where} did not answer within {cfg.connect_timeout_s:g} s", device=self.name
            ) from exc
        except OSError as exc:
            raise DeviceConnectionError(f"cannot connect to {where}: {exc}", device=self.name) from exc
        if not answer.startswith(b"< ok >"):
            text = answer.decode("ascii", "replace").strip() or "the connection closed"
            raise DeviceConnectionError(f"{where} cannot open channel {cfg.channel!r}: {text}", device=self.name)

    def _disconnect(self) -> None:
        network, self._network, self._node = self._network, None, None
        if network is None:
            return
        if network.notifier is not None:
            network.notifier.exception = None  # already recorded in _link_error; not worth a log line
        with contextlib.suppress(Exception):
            network.disconnect()

    def _on_link_error(self, exc: Exception) -> None:
        self._link_error = exc
        self._sdo_answers.put(b"")  # wakes a waiting SDO request
        with self._pdo.cond:
            self._pdo.cond.notify_all()

    def _link_down(self) -> bool:
        return self._link_error is not None

    def _on_heartbeat(self, state: int) -> None:
        self._heartbeat_state = state
        self._heartbeat_at = time.monotonic()
        if state == 0:  # boot-up: the node restarted with its defaults
            self._needs_setup = True

    def _on_sdo_answer(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._sdo_answers.put(bytes(data))

    # ------------------------------------------------------------------ setup

    def _setup(self) -> None:
        """Check the device, read its scaling, configure TPDO1 and start the node."""
        node = self._live_node
        with self._errors("reading the device configuration"):
            if self.config.kind == "encoder":
                device_type = self._sdo_int(DEVICE_TYPE)
                if device_type & 0xFFFF != PROFILE_406:
                    raise ProtocolError(f"device type 0x{device_type:08X} is not a CiA 406 encoder", device=self.name)
            self._read_scaling()
            if self.config.kind == "resolver":
                self.pole_pairs = self._sdo_int(RESOLVER_POLE_PAIRS) or 1
        if self.config.use_pdo:
            with self._errors("configuring TPDO1"):
                self._setup_pdo()
        if self.config.start_node:
            with self._errors("starting the node (NMT)"):
                node.nmt.state = "OPERATIONAL"
        self._needs_setup = False
        self._needs_barrier = False

    def _read_scaling(self) -> None:
        operating = self._sdo_int_optional(OPERATING_PARAMETERS)
        if operating is None or operating & SCALING_BIT:
            cpr, total = self._sdo_int(UNITS_PER_REV), self._sdo_int(TOTAL_RANGE)
        else:
            cpr = self._sdo_int(SINGLETURN_RESOLUTION)
            revolutions = self._sdo_int_optional(REVOLUTIONS)
            total = cpr * revolutions if revolutions else self._sdo_int(TOTAL_RANGE)
        if cpr <= 0 or total < cpr:
            raise ProtocolError(
                f"inconsistent scaling: {cpr} units per revolution, total range {total}", device=self.name
            )
        self.counts_per_rev, self.total_range = cpr, total

    def _setup_pdo(self) -> None:
        node = self._live_node
        tpdo = node.tpdo
        if self.config.configure_pdo:
            node.nmt.state = "PRE-OPERATIONAL"
            tpdo.read(from_od=True)
            t = tpdo[1]
            t.clear()
            t.add_variable(POSITION_VALUE)
            if self.config.kind == "resolver":
                t.add_variable(RESOLVER_FAULTS)
            t.cob_id = 0x180 + self.config.node_id
            t.enabled = True
            if self.config.pdo_trigger == "sync":
                t.trans_type, t.event_timer = 1, 0
            else:
                t.trans_type, t.event_timer = 254, self.config.event_timer_ms
            t.save()
        else:
            tpdo.read(from_od=False)
        t = tpdo[1]
        self._pdo_layout = {var.index: (var.offset // 8, var.length // 8) for var in t}
        if POSITION_VALUE not in self._pdo_layout or not t.enabled:
            raise ProtocolError("TPDO1 does not carry the position value 0x6004", device=self.name)
        self._pdo_cob_id = t.cob_id
        if self._on_tpdo not in t.callbacks:
            t.add_callback(self._on_tpdo)

    def _on_tpdo(self, pdo_map) -> None:
        with self._pdo.cond:
            self._pdo.count += 1
            self._pdo.data = bytes(pdo_map.data)
            self._pdo.cond.notify_all()

    def _sdo_int(self, index: int) -> int:
        """An unsigned object of up to 4 bytes (configuration reads)."""
        value = self._sdo_int_optional(index, optional=False)
        assert value is not None  # not optional: a missing object raised
        return value

    def _sdo_int_optional(self, index: int, *, optional: bool = True) -> int | None:
        """As :meth:`_sdo_int`; ``optional``: ``None`` if the device does not have the object."""
        try:
            data = self._upload(index)
        except SdoAbortedError as exc:
            if optional and exc.code in _MISSING_ABORTS:
                return None
            raise
        return int.from_bytes(data, "little")

    # ------------------------------------------------------------------ reading

    def _read_once(self) -> EncoderReading:
        if self._link_down():
            raise DeviceConnectionError(f"CAN link lost: {self._link_error}", device=self.name)
        if self._needs_setup:
            self._setup()
        elif self.config.start_node and self._heartbeat_state not in (None, 5):
            with self._errors("starting the node (NMT)"):
                self._live_node.nmt.state = "OPERATIONAL"
        try:
            if self._needs_barrier:
                with self._errors("re-synchronising after a failed request"):
                    self._upload(ERROR_REGISTER)
                self._needs_barrier = False
            if self.config.use_pdo:
                counts, faults = self._read_pdo()
            else:
                counts, faults = self._read_sdo()
        except (DeviceTimeoutError, ProtocolError, DeviceFaultError):
            self._needs_barrier = True  # a late answer to this request may still come
            raise
        timestamp = time.time()
        self._check_faults(faults)
        self._sequence += 1
        angle = counts_to_angle(
            counts, self.counts_per_rev, self.total_range, signed=self.config.signed_range, pole_pairs=self.pole_pairs
        )
        return EncoderReading(angle_rad=angle, counts=counts, sequence=self._sequence, timestamp_s=timestamp)

    def _read_sdo(self) -> tuple[int, int]:
        with self._errors("reading the position value 0x6004"):
            data = self._upload(POSITION_VALUE)
            faults = self._upload(RESOLVER_FAULTS) if self.config.kind == "resolver" else b"\x00"
        if len(data) != 4 or len(faults) != 1:
            raise ProtocolError(
                f"position answer of {len(data)} bytes / fault bits of {len(faults)} bytes, expected 4 / 1",
                device=self.name,
            )
        return _U32.unpack(data)[0], faults[0]

    def _upload(self, index: int, subindex: int = 0) -> bytes:
        """SDO expedited upload, skipping answers that belong to earlier requests."""
        while not self._sdo_answers.empty():  # answers to abandoned requests
            self._sdo_answers.get_nowait()
        self._live_network.send_message(0x600 + self.config.node_id, _SDO_REQUEST.pack(0x40, index, subindex, 0))
        deadline = time.monotonic() + self.config.timeout_s
        while True:
            try:
                answer = self._sdo_answers.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise SdoCommunicationError("No SDO response received") from None
            if not answer and self._link_down():
                raise DeviceConnectionError(f"CAN link lost: {self._link_error}", device=self.name)
            if len(answer) < 8:
                raise ProtocolError(f"SDO answer of {len(answer)} bytes, expected 8", device=self.name)
            command, r_index, r_subindex = _SDO_HEADER.unpack_from(answer)
            if (r_index, r_subindex) != (index, subindex):
                continue  # the late answer to an earlier request
            if command == 0x80:
                raise SdoAbortedError(_U32.unpack_from(answer, 4)[0])
            if command & 0xE0 != 0x40 or not command & 0x02:
                raise ProtocolError(
                    f"unexpected SDO answer 0x{command:02X} to the upload of 0x{index:04X}", device=self.name
                )
            size = 4 - ((command >> 2) & 0x3) if command & 0x01 else 4
            return answer[4 : 4 + size]

    def _read_pdo(self) -> tuple[int, int]:
        inbox = self._pdo
        with inbox.cond:
            start = inbox.count
        if self.config.pdo_trigger == "sync":
            with self._errors("sending SYNC"):
                self._live_network.sync.transmit()
        # SYNC: the node samples when it sees our SYNC, so the first TPDO after it is fresh.
        # Event timer: the first TPDO after the call may have been sampled before it and been
        # on its way (gateway, TCP); the second was sampled at least one timer period later.
        wanted = start + (1 if self.config.pdo_trigger == "sync" else 2)
        with inbox.cond:
            arrived = inbox.cond.wait_for(lambda: inbox.count >= wanted or self._link_down(), self.config.timeout_s)
            data = inbox.data
        if self._link_down():
            raise DeviceConnectionError(f"CAN link lost: {self._link_error}", device=self.name)
        if not arrived or inbox.count < wanted:
            active = list(self._live_node.emcy.active)
            trigger = "after SYNC" if self.config.pdo_trigger == "sync" else "(event timer)"
            message = f"no TPDO1 (COB-ID 0x{self._pdo_cob_id:03X}) within {self.config.timeout_s:g} s {trigger}"
            if active:
                raise DeviceFaultError(
                    f"{message}; the node reports {_emcy_text(active)}",
                    device=self.name,
                    code=f"0x{active[-1].code:04X}",
                )
            raise DeviceTimeoutError(message, device=self.name)
        return self._pdo_value(data, POSITION_VALUE, 4), self._pdo_value(data, RESOLVER_FAULTS, 1, default=0)

    def _pdo_value(self, data: bytes, index: int, size: int, *, default: int | None = None) -> int:
        if index not in self._pdo_layout:
            if default is None:  # the layout was checked when TPDO1 was configured
                raise ProtocolError(f"TPDO1 does not map 0x{index:04X}", device=self.name)
            return default
        offset, length = self._pdo_layout[index]
        if length != size or len(data) < offset + length:
            raise ProtocolError(
                f"TPDO1 of {len(data)} bytes does not hold 0x{index:04X} ({size} bytes at byte {offset})",
                device=self.name,
            )
        return int.from_bytes(data[offset : offset + length], "little")

    def _check_faults(self, fault_bits: int) -> None:
        if fault_bits:
            names = [text for bit, text in RESOLVER_FAULT_NAMES.items() if fault_bits & bit] or ["unknown fault"]
            raise MeasurementError(f"resolver reports {', '.join(names)}", device=self.name, code=f"0x{fault_bits:02X}")
        active = list(self._live_node.emcy.active)
        if active:
            raise DeviceFaultError(
                f"the node reports {_emcy_text(active)}", device=self.name, code=f"0x{active[-1].code:04X}"
            )

    # ------------------------------------------------------------------ errors

    @contextlib.contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        """Turn canopen / python-can / socket exceptions raised ``what``-ing into ours."""
        try:
            yield
        except DeviceError:
            raise
        except SdoAbortedError as exc:
            code = exc.code
            text = SdoAbortedError.CODES.get(code, "unknown abort code")
            active = list(self._node.emcy.active) if self._node is not None else []
            emcy = f"; the node reports {_emcy_text(active)}" if active else ""
            cls = DeviceFaultError if code in _FAULT_ABORTS else ProtocolError
            raise cls(f"SDO abort {what}: {text}{emcy}", device=self.name, code=f"0x{code:08X}") from exc
        except SdoCommunicationError as exc:
            if self._link_down():
                raise DeviceConnectionError(f"CAN link lost {what}: {self._link_error}", device=self.name) from exc
            if "No SDO response" in str(exc):
                raise DeviceTimeoutError(
                    f"no SDO answer {what} within {self.config.timeout_s:g} s", device=self.name
                ) from exc
            raise ProtocolError(f"unexpected SDO answer {what}: {exc}", device=self.name) from exc
        except (can.CanError, OSError) as exc:
            raise DeviceConnectionError(f"CAN link lost {what}: {exc}", device=self.name) from exc


# EMCY codes an encoder or resolver reader typically sends (CiA 301 / CiA 406); canopen's own
# table only knows the code groups.
EMCY_TEXT = {
    0x5000: "device hardware",
    0x6000: "device software",
    0x7300: "sensor",
    0x7320: "position sensor",
    0x8110: "CAN overrun",
    0x8120: "CAN error passive",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
}


def _emcy_text(active) -> str:
    return ", ".join(f"EMCY 0x{e.code:04X} ({EMCY_TEXT.get(e.code) or e.get_desc() or 'unknown'})" for e in active)
