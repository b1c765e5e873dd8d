"""Simulated CANopen reference encoders and resolver readers behind a socketcand gateway.

The device side of the CAN wire (contracts §7, ``"can"``, ``"encoders"``, ``"resolvers"``):

- a TCP server speaking the socketcand protocol in raw mode (``< hi >``, ``< open vcan0 >``,
  ``< rawmode >``, ``< send ID LEN B0 .. >`` in, ``< frame ID SECS.USECS DATA >`` out), so that
  python-can's ``socketcand`` interface reaches it from any process;
- behind it an internal python-can ``virtual`` bus with one ``canopen`` ``LocalNode`` per device
  (SDO server, NMT slave with heartbeat, EMCY producer); the gateway forwards every frame both
  ways between the TCP clients and that bus, and between the clients (like socketcand on a real
  interface).

Encoder nodes (``fakes/eds/cia406_encoder.eds``, CiA 406 multi-turn, 2^17 steps per revolution,
4096 revolutions) report in 0x6004 the true rotation of their joint, ``cell.joint_angle(j)``
(the truth model's joint variable, which includes the gear-eccentricity harmonic of book
eq. 2.4 when the truth model's joint has ``harmonic``), plus a fixed mount zero offset,
quantised to the resolution, with ``cell.noise.encoder_counts`` of noise, wrapped into the
total measuring range. A preset written to 0x6003 shifts the position like a real encoder.

Resolver reader nodes (``fakes/eds/resolver_reader.eds``) report the 16-bit electrical angle
``pole_pairs * (joint angle + mount offset)`` in 0x6004 (0..65535 per electrical turn), with
noise in LSB, and fault bits in 0x2000 (bit 0 LOS, bit 1 DOS, bit 2 LOT, bit 3 parity).

TPDO1 (COB-ID 0x180 + node id, mapping from 0x1A00) is produced on SYNC (transmission type
1..240: every n-th SYNC) or by the event timer (types 254/255, 0x1800 sub 5 in ms), only in
NMT OPERATIONAL; the mapping written by a client over SDO is honoured.

Faults (read live from ``cell.faults``; counted per position request, i.e. per SDO upload of
0x6004 or SYNC frame, with ``cell.count("canopen.read")``):

- ``drop_connection_at``: the gateway closes the requesting client's TCP connection;
- ``delay_s``: every frame towards the clients is delivered that much later; with
  ``delay_at``, only the reply to those position requests (the SDO answer, or the TPDOs after
  that SYNC), and the frames behind it wait for it, as on a bus;
- ``garble_at`` / ``garble_rate``: the reply is corrupted (SDO command byte inverted; PDO
  truncated to half its length);
- ``sensor_fault_at``: the encoder answers the position request with SDO abort 0x06060000 (and
  no TPDO) after EMCY 0x7320; the resolver reports fault bits (LOS | LOT by default) with EMCY
  0x7300; the next good reading sends the EMCY reset;
- ``silent_nodes``: nothing from these node ids reaches the clients (no SDO answer, PDO,
  heartbeat or EMCY), as if the node were unplugged.

Mount offsets default to :func:`default_mount_offset_rad` (node id based, deterministic).
``python -m fakes.canopen_nodes --help`` runs the gateway alone and prints one JSON ready line.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import signal
import socket
import struct
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import numpy as np
from canopen.sdo import SdoAbortedError

from fakes.world import SimCell

log = logging.getLogger(__name__)

DEFAULT_PORT = 29536
EDS_DIR = Path(__file__).resolve().parent / "eds"
ENCODER_EDS = EDS_DIR / "cia406_encoder.eds"
RESOLVER_EDS = EDS_DIR / "resolver_reader.eds"
READ_COUNTER = "canopen.read"
TAU = 2.0 * math.pi

POSITION_VALUE = 0x6004
RESOLVER_FAULTS = 0x2000
RESOLVER_POLE_PAIRS = 0x2001
RESOLVER_LSB_PER_TURN = 1 << 16

FAULT_LOS = 0x01  # loss of signal
FAULT_DOS = 0x02  # degradation of signal (amplitude mismatch, over-range)
FAULT_LOT = 0x04  # loss of tracking
FAULT_PARITY = 0x08  # configuration parity

EMCY_POSITION_SENSOR = 0x7320
EMCY_SENSOR = 0x7300
ABORT_HARDWARE_ERROR = 0x06060000

_NODE_SERVICES = (0x080, 0x180, 0x280, 0x380, 0x480, 0x580, 0x700)
_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_EVENT_RECHECK_S = 0.05  # the event-timer loop's longest sleep (see CanGatewayFake._event_loop)


def default_mount_offset_rad(node_id: int) -> float:
    """The fixed zero offset (rad) between the joint's kinematic zero and the zero of the device
    with this node id: a deterministic value in [-pi, pi) (golden-ratio spread over node ids)."""
    return round(((node_id * 0.6180339887) % 1.0) * TAU - math.pi, 6)


@dataclass
class _Node:
    """One simulated device: its canopen LocalNode and the simulation state behind it."""

    joint: int
    node_id: int
    kind: str  # "encoder" | "resolver"
    local: canopen.LocalNode
    mount_offset_rad: float
    preset_steps: int = 0
    fault_next: bool = False
    fault_bits: int = 0
    emcy_active: bool = False
    sync_count: int = 0
    next_event_s: float = 0.0


class _Client:
    """One TCP client of the gateway."""

    def __init__(self, sock: socket.socket, address):
        self.sock = sock
        self.address = address
        self.rawmode = False
        self.alive = True
        self._lock = threading.Lock()

    def send(self, text: str) -> None:
        with self._lock:
            if not self.alive:
                return
            try:
                self.sock.sendall(text.encode("ascii"))
            except OSError:
                self._close_locked()

    def close(self) -> None:
        with self._lock:
            self._close_locked()

    def _close_locked(self) -> None:
        if not self.alive:
            return
        self.alive = False
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class CanGatewayFake:
    """A socketcand gateway on ``host:port`` with CANopen encoder and resolver reader nodes.

    ``encoders`` / ``resolvers`` map joint number (1-based) to node id. ``mount_offsets_rad``
    maps node id to the device's zero offset (default :func:`default_mount_offset_rad`).
    """

    def __init__(
        self,
        cell: SimCell,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        encoders: Mapping[int, int] | None = None,
        resolvers: Mapping[int, int] | None = None,
        *,
        channel: str = "vcan0",
        encoder_steps_per_rev: int = 1 << 17,
        encoder_revolutions: int = 4096,
        mount_offsets_rad: Mapping[int, float] | None = None,
        resolver_pole_pairs: int = 1,
        resolver_noise_lsb: float = 1.0,
        resolver_fault_bits: int = FAULT_LOS | FAULT_LOT,
    ):
        self.cell = cell
        self.host = host
        self.port = port
        self.channel = channel
        self.encoders = dict({1: 17, 2: 18} if encoders is None else encoders)
        self.resolvers = dict({1: 33} if resolvers is None else resolvers)
        self.encoder_steps_per_rev = int(encoder_steps_per_rev)
        self.encoder_total_steps = int(encoder_steps_per_rev) * int(encoder_revolutions)
        self.encoder_revolutions = int(encoder_revolutions)
        self.resolver_pole_pairs = int(resolver_pole_pairs)
        self.resolver_noise_lsb = float(resolver_noise_lsb)
        self.resolver_fault_bits = int(resolver_fault_bits)
        self._offsets = dict(mount_offsets_rad or {})
        self._check_layout()
        if self.encoder_total_steps > 0xFFFFFFFF:
            raise ValueError("encoder_steps_per_rev * encoder_revolutions must fit in 32 bits")
        self._nodes: dict[int, _Node] = {}
        self._clients: list[_Client] = []
        self._clients_lock = threading.Lock()
        self._garble_cob_ids: set[int] = set()  # the next frame with this COB-ID is garbled
        self._delay_cob_ids: set[int] = set()  # ... is late (with ``delay_at``)
        self._marks_lock = threading.Lock()
        self._stop = threading.Event()
        self._events_changed = threading.Event()  # wakes the event-timer loop
        self._threads: list[threading.Thread] = []
        self._server: socket.socket | None = None
        self._dev_net: canopen.Network | None = None
        self._bridge: can.BusABC | None = None
        self._started = False

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the nodes and the gateway; returns once the TCP port accepts connections."""
        if self._started:
            return
        self._started = True
        self._stop.clear()
        vchannel = f"recal-canopen-{id(self):x}"
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.1
        net.NOTIFIER_SHUTDOWN_TIMEOUT = 1.0
        net.connect(interface="virtual", channel=vchannel, receive_own_messages=False)
        self._dev_net = net
        for joint, node_id in self.encoders.items():
            self._add_node(joint, node_id, "encoder")
        for joint, node_id in self.resolvers.items():
            self._add_node(joint, node_id, "resolver")
        net.subscribe(0x080, self._on_sync)
        net.subscribe(0x000, self._on_nmt)
        self._bridge = can.Bus(interface="virtual", channel=vchannel, receive_own_messages=False)
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((self.host, self.port))
        server.listen(8)
        server.settimeout(0.1)
        self._server = server
        self.port = server.getsockname()[1]
        for node in self._nodes.values():
            self._boot(node, reset_application=True)
        for target, name in ((self._accept_loop, "accept"), (self._pump_loop, "pump"), (self._event_loop, "events")):
            t = threading.Thread(target=target, name=f"canopen-gateway-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        """Close the gateway, its clients and the internal bus. Idempotent."""
        if not self._started:
            return
        self._started = False
        self._stop.set()
        self._events_changed.set()
        if self._server is not None:
            self._server.close()
        with self._clients_lock:
            clients, self._clients = self._clients, []
        for c in clients:
            c.close()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        if self._dev_net is not None:
            for node in self._nodes.values():
                node.local.nmt.stop_heartbeat()
            self._dev_net.disconnect()
            self._dev_net = None
        if self._bridge is not None:
            self._bridge.shutdown()
            self._bridge = None
        self._nodes = {}

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()

    def endpoint(self) -> dict:
        """This fake's part of the endpoint line (contracts §7)."""
        return {
            "can": {"interface": "socketcand", "channel": self.channel, "host": self.host, "port": self.port},
            "encoders": {str(j): n for j, n in sorted(self.encoders.items())},
            "resolvers": {str(j): n for j, n in sorted(self.resolvers.items())},
        }

    def mount_offset_rad(self, node_id: int) -> float:
        """The zero offset (rad) of the device with this node id."""
        return float(self._offsets.get(node_id, default_mount_offset_rad(node_id)))

    def reboot_node(self, node_id: int) -> None:
        """Power-cycle one node: defaults restored, boot-up message, PRE-OPERATIONAL."""
        self._boot(self._nodes[node_id], reset_application=True)

    def client_count(self) -> int:
        with self._clients_lock:
            return sum(1 for c in self._clients if c.alive)

    # ------------------------------------------------------------------ nodes

    def _check_layout(self) -> None:
        n_joints = self.cell.truth.n_joints
        seen: set[int] = set()
        for kind, table in (("encoders", self.encoders), ("resolvers", self.resolvers)):
            for joint, node_id in table.items():
                if not 1 <= int(joint) <= n_joints:
                    raise ValueError(f"{kind}: joint {joint} is not a joint of the {n_joints}-joint robot")
                if not 1 <= int(node_id) <= 127:
                    raise ValueError(f"{kind}: node id {node_id} is outside 1..127")
                if node_id in seen:
                    raise ValueError(f"{kind}: node id {node_id} is used twice")
                seen.add(node_id)

    def _add_node(self, joint: int, node_id: int, kind: str) -> None:
        eds = ENCODER_EDS if kind == "encoder" else RESOLVER_EDS
        local = self._dev_net.create_node(node_id, str(eds))
        node = _Node(
            joint=int(joint),
            node_id=int(node_id),
            kind=kind,
            local=local,
            mount_offset_rad=self.mount_offset_rad(node_id),
        )
        local.add_read_callback(functools.partial(self._on_read, node))
        local.add_write_callback(functools.partial(self._on_write, node))
        self._nodes[node.node_id] = node

    def _boot(self, node: _Node, *, reset_application: bool) -> None:
        """Reset (application: every object; communication: 0x1000-0x1FFF), then boot-up
        message and PRE-OPERATIONAL with the heartbeat of 0x1017."""
        store = node.local.data_store
        for index in list(store):
            if reset_application or 0x1000 <= index <= 0x1FFF:
                del store[index]
        if reset_application:
            node.preset_steps = 0
        node.sync_count = 0
        node.fault_bits = 0
        node.emcy_active = False
        self._store_constants(node)
        node.local.nmt.state = "INITIALISING"  # sends the boot-up message
        node.local.nmt.state = "PRE-OPERATIONAL"  # starts the heartbeat producer

    def _store_constants(self, node: _Node) -> None:
        """Device constants that depend on this fake's configuration, not the EDS defaults."""

        def put(index: int, value: int) -> None:
            od = node.local.object_dictionary[index]
            node.local.data_store.setdefault(index, {})[0] = od.encode_raw(value)

        if node.kind == "encoder":
            put(0x6001, self.encoder_steps_per_rev)
            put(0x6002, self.encoder_total_steps)
            put(0x6501, self.encoder_steps_per_rev)
            put(0x6502, min(self.encoder_revolutions, 0xFFFF))
        else:
            put(RESOLVER_POLE_PAIRS, self.resolver_pole_pairs)

    def _silent(self, node_id: int | None) -> bool:
        return node_id is not None and node_id in self.cell.faults.silent_nodes

    def _raw_steps(self, node: _Node) -> float:
        """The device's position now, before quantisation (steps or LSB)."""
        theta = self.cell.joint_angle(node.joint) + node.mount_offset_rad
        if node.kind == "encoder":
            steps = theta / TAU * self.encoder_steps_per_rev + node.preset_steps
            return steps + float(self.cell.normal(self.cell.noise.encoder_counts))
        pole_pairs = _U8.unpack(node.local.get_data(RESOLVER_POLE_PAIRS, 0))[0] or 1
        lsb = pole_pairs * theta / TAU * RESOLVER_LSB_PER_TURN
        return lsb + float(self.cell.normal(self.resolver_noise_lsb))

    def _position(self, node: _Node) -> int:
        """Sample the position value (0x6004); applies a pending sensor fault."""
        fault, node.fault_next = node.fault_next, False
        if node.kind == "encoder":
            if fault:
                self._emcy(node, EMCY_POSITION_SENSOR, b"\x01")
                raise SdoAbortedError(ABORT_HARDWARE_ERROR)
            self._emcy_clear(node)
            return int(round(self._raw_steps(node))) % self.encoder_total_steps
        node.fault_bits = self.resolver_fault_bits if fault else 0
        if fault:
            self._emcy(node, EMCY_SENSOR, bytes([node.fault_bits]))
        else:
            self._emcy_clear(node)
        return int(round(self._raw_steps(node))) % RESOLVER_LSB_PER_TURN

    def _emcy(self, node: _Node, code: int, data: bytes) -> None:
        node.emcy_active = True
        if not self._silent(node.node_id):
            node.local.emcy.send(code, 0x01, data)

    def _emcy_clear(self, node: _Node) -> None:
        if node.emcy_active:
            node.emcy_active = False
            node.local.emcy.reset()

    def _on_read(self, node: _Node, index: int, subindex: int, od) -> int | None:
        """LocalNode read callback: live values; ``None`` falls back to the stored value."""
        if index == POSITION_VALUE:
            return self._position(node)
        if node.kind == "resolver" and index == RESOLVER_FAULTS:
            return node.fault_bits
        if node.kind == "encoder" and index == 0x6503:  # alarms: bit 0 position error
            return 1 if node.emcy_active else 0
        if node.kind == "encoder" and index == 0x6509:  # offset value
            return node.preset_steps % self.encoder_total_steps
        if index == 0x1001:
            return 0x01 if node.emcy_active else 0
        return None

    def _on_write(self, node: _Node, index: int, subindex: int, od, data: bytes) -> None:
        """LocalNode write callback: a preset (0x6003) makes the current position read ``preset``;
        any write may change the TPDO's timer (the event loop looks again)."""
        self._events_changed.set()
        if node.kind == "encoder" and index == 0x6003:
            preset = _U32.unpack(bytes(data))[0]
            theta = self.cell.joint_angle(node.joint) + node.mount_offset_rad
            node.preset_steps = preset - int(round(theta / TAU * self.encoder_steps_per_rev))

    # ------------------------------------------------------------------ PDO production

    def _tpdo1(self, node: _Node) -> tuple[int, bytes] | None:
        """TPDO1's COB-ID and payload from the node's current mapping, or ``None`` (disabled,
        or the sensor failed)."""
        get = node.local.get_data
        cob_id = _U32.unpack(get(0x1800, 1))[0]
        if cob_id & 0x80000000:
            return None
        payload = b""
        try:
            for sub in range(1, _U8.unpack(get(0x1A00, 0))[0] + 1):
                entry = _U32.unpack(get(0x1A00, sub))[0]
                index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
                if index:
                    payload += get(index, subindex)[: bits // 8]
        except SdoAbortedError:
            return None
        return cob_id & 0x7FF, payload[:8]

    def _transmission(self, node: _Node) -> tuple[int, int]:
        """(transmission type, event timer ms) of TPDO1."""
        get = node.local.get_data
        return _U8.unpack(get(0x1800, 2))[0], _U16.unpack(get(0x1800, 5))[0]

    def _send_tpdo(self, node: _Node) -> None:
        frame = self._tpdo1(node)
        if frame is not None:
            self._dev_net.send_message(*frame)

    def _operational(self, node: _Node) -> bool:
        return node.local.nmt.state == "OPERATIONAL"

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        for node in list(self._nodes.values()):
            if not self._operational(node):
                continue
            trans_type, _ = self._transmission(node)
            if trans_type > 240:
                continue
            node.sync_count += 1
            if node.sync_count % max(trans_type, 1) == 0:
                self._send_tpdo(node)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._events_changed.set()  # a node started or stopped: its TPDO events too
        if len(data) < 2 or data[0] not in (129, 130):
            return
        for node in list(self._nodes.values()):
            if data[1] in (0, node.node_id):
                self._boot(node, reset_application=data[0] == 129)

    def _event_loop(self) -> None:
        """Event-driven TPDOs (transmission type 254/255 with an event timer). Sleeps until the
        next node is due, woken early by a write to a node's object dictionary or an NMT
        command (either may start or change a timer). An idle cell costs next to nothing:
        the bench runs fifty of them on two cores."""
        wait_s = 0.0
        while True:
            self._events_changed.wait(wait_s)
            if self._stop.is_set():
                return
            self._events_changed.clear()
            now = time.monotonic()
            # Check again at least this often: NMT start/stop handled inside canopen's LocalNode
            # (not ours to hook) may change which nodes produce.
            due_s = now + _EVENT_RECHECK_S
            for node in list(self._nodes.values()):
                try:
                    if not self._operational(node):
                        continue
                    trans_type, timer_ms = self._transmission(node)
                    if trans_type < 254 or timer_ms == 0:
                        continue
                    if now >= node.next_event_s:
                        node.next_event_s = now + timer_ms / 1000.0
                        self._send_tpdo(node)
                    due_s = min(due_s, node.next_event_s)
                except Exception:  # the bus closed under us while stopping
                    if self._stop.is_set():
                        return
                    log.exception("TPDO event of node %d failed", node.node_id)
            wait_s = max(0.0, due_s - time.monotonic())

    # ------------------------------------------------------------------ the TCP side

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, address = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, address)
            with self._clients_lock:
                self._clients.append(client)
            threading.Thread(target=self._serve, args=(client,), name="canopen-gateway-client", daemon=True).start()

    def _serve(self, client: _Client) -> None:
        client.sock.settimeout(0.2)
        client.send("< hi >")
        buf = b""
        try:
            while client.alive and not self._stop.is_set():
                try:
                    data = client.sock.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                buf += data
                while b">" in buf:
                    raw, buf = buf.split(b">", 1)
                    self._command(client, raw.decode("ascii", "replace").strip().lstrip("<").strip())
        finally:
            client.close()
            with self._clients_lock:
                if client in self._clients:
                    self._clients.remove(client)

    def _command(self, client: _Client, command: str) -> None:
        words = command.split()
        if not words:
            return
        if words[0] == "open":
            if len(words) == 2 and words[1] == self.channel:
                client.send("< ok >")
            else:
                client.send(f"< error could not open bus '{' '.join(words[1:])}' >")
        elif words[0] == "rawmode":
            client.send("< ok >")
            # python-can reads each handshake reply with one recv(): keep frames back until it
            # has read this "< ok >" on its own (its first frame, or 0.1 s, says it has).
            timer = threading.Timer(0.1, setattr, args=(client, "rawmode", True))
            timer.daemon = True
            timer.start()
        elif words[0] == "echo":
            client.send("< echo >")
        elif words[0] == "send":
            client.rawmode = True
            msg = _parse_send(words)
            if msg is None:
                log.warning("ignoring malformed send from %s: %r", client.address, command)
            else:
                self._from_client(client, msg)
        else:
            log.info("ignoring socketcand command %r", command)

    def _from_client(self, client: _Client, msg: can.Message) -> None:
        if not self._admit(client, msg):
            return
        self._bridge.send(msg)
        line = _frame_line(msg.arbitration_id, msg.is_extended_id, time.time(), bytes(msg.data))
        with self._clients_lock:
            others = [c for c in self._clients if c is not client and c.rawmode]
        for other in others:
            other.send(line)

    def _admit(self, client: _Client, msg: can.Message) -> bool:
        """Count position requests and apply the request-counted faults; ``False`` drops it."""
        can_id, data = msg.arbitration_id, bytes(msg.data)
        if can_id == 0x080:
            targets = list(self._nodes.values())
            reply_base = 0x180
        elif 0x601 <= can_id <= 0x67F and len(data) >= 4 and data[0] == 0x40 and data[1:4] == b"\x04\x60\x00":
            node = self._nodes.get(can_id - 0x600)
            targets = [node] if node is not None else []
            reply_base = 0x580
        else:
            return True
        n = self.cell.count(READ_COUNTER)
        faults = self.cell.faults
        if n in faults.drop_connection_at:
            log.info("fault: dropping client %s at request %d", client.address, n)
            client.close()
            return False
        replies = {reply_base + node.node_id for node in targets}
        with self._marks_lock:
            if n in faults.garble_at or self.cell.chance(faults.garble_rate):
                self._garble_cob_ids.update(replies)
            if n in faults.delay_at:
                self._delay_cob_ids.update(replies)
        if n in faults.sensor_fault_at:
            for node in targets:
                node.fault_next = True
        return True

    def _pump_loop(self) -> None:
        """Frames from the internal bus to every client in raw mode (faults applied)."""
        while not self._stop.is_set():
            try:
                msg = self._bridge.recv(0.1)
            except Exception:
                if self._stop.is_set():
                    return
                raise
            if msg is None or self._silent(_source_node(msg.arbitration_id)):
                continue
            faults = self.cell.faults
            with self._marks_lock:
                delayed = not faults.delay_at or _take(self._delay_cob_ids, msg.arbitration_id)
                garbled = _take(self._garble_cob_ids, msg.arbitration_id)
            if delayed and faults.delay_s > 0:
                # Frames stay in order, as on a bus: the ones behind a late frame wait too.
                wait_s = msg.timestamp + faults.delay_s - time.time()
                if wait_s > 0 and self._stop.wait(wait_s):
                    return
            data = _garble(msg.arbitration_id, bytes(msg.data)) if garbled else bytes(msg.data)
            line = _frame_line(msg.arbitration_id, msg.is_extended_id, msg.timestamp, data)
            with self._clients_lock:
                clients = [c for c in self._clients if c.rawmode]
            for c in clients:
                c.send(line)


# ---------------------------------------------------------------------- socketcand text


def _parse_send(words: list[str]) -> can.Message | None:
    """``send <id hex> <len hex> <byte hex> ...`` as a CAN message, or ``None`` if malformed."""
    try:
        cob = words[1]
        length = int(words[2], 16)
        data = bytes(int(b, 16) for b in words[3 : 3 + length])
        if len(data) != length or length > 8:
            return None
        return can.Message(arbitration_id=int(cob, 16), is_extended_id=len(cob) > 3, data=data)
    except (IndexError, ValueError):
        return None


def _frame_line(can_id: int, extended: bool, timestamp: float, data: bytes) -> str:
    cob = f"{can_id:08X}" if extended else f"{can_id:03X}"
    return f"< frame {cob} {timestamp:.6f} {data.hex().upper()} >"


def _source_node(can_id: int) -> int | None:
    """The node id that sent a frame with this COB-ID (EMCY, TPDO, SDO reply, heartbeat)."""
    node_id = can_id & 0x7F
    if can_id <= 0x7FF and (can_id & 0x780) in _NODE_SERVICES and node_id:
        return node_id
    return None


def _take(marks: set[int], can_id: int) -> bool:
    """Whether ``can_id`` is marked; the mark is used up."""
    if can_id in marks:
        marks.discard(can_id)
        return True
    return False


def _garble(can_id: int, data: bytes) -> bytes:
    """Corrupt a reply: an SDO reply gets an inverted command byte, anything else is truncated."""
    if (can_id & 0x780) == 0x580 and data:
        return bytes([data[0] ^ 0xFF]) + data[1:]
    return data[: len(data) // 2]


# ---------------------------------------------------------------------- command line


def _joint_map(text: str) -> dict[int, int]:
    """``"1:17,2:18"`` -> ``{1: 17, 2: 18}``; empty -> ``{}``."""
    out: dict[int, int] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        joint, node_id = item.split(":")
        out[int(joint)] = int(node_id)
    return out


def _truth(args):
    from calibration.model import model_from_dict
    from calibration.robots import nominal

    if args.truth:
        return model_from_dict(json.loads(Path(args.truth).read_text()))
    return nominal(args.robot)


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, and its keyword arguments from the command line.
CELL_FAKE = {"key": "can", "order": 60, "cls": CanGatewayFake}


def main(argv: list[str] | None = None) -> int:
    from fakes.world import Faults

    p = argparse.ArgumentParser(prog="python -m fakes.canopen_nodes", description=__doc__.split("\n")[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="0 picks a free port")
    p.add_argument("--truth", help="recal.model/1 JSON of the true robot (default: --robot nominal)")
    p.add_argument("--robot", default="ur5e", help="nominal model name when --truth is not given")
    p.add_argument("--q", default="", help="initial joint readings, comma separated, rad")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-scale", type=float, default=0.0)
    p.add_argument("--encoders", default="1:17,2:18", help="joint:node,... ('' for none)")
    p.add_argument("--resolvers", default="1:33", help="joint:node,... ('' for none)")
    p.add_argument("--pole-pairs", type=int, default=1)
    p.add_argument("--silent-node", type=int, action="append", default=[])
    p.add_argument("--drop-at", type=int, action="append", default=[])
    p.add_argument("--garble-at", type=int, action="append", default=[])
    p.add_argument("--garble-rate", type=float, default=0.0)
    p.add_argument("--sensor-fault-at", type=int, action="append", default=[])
    p.add_argument("--delay-s", type=float, default=0.0)
    args = p.parse_args(argv)

    truth = _truth(args)
    q_home = np.array([float(v) for v in args.q.split(",")]) if args.q else None
    faults = Faults(
        drop_connection_at=args.drop_at,
        delay_s=args.delay_s,
        garble_rate=args.garble_rate,
        garble_at=args.garble_at,
        silent_nodes=args.silent_node,
        sensor_fault_at=args.sensor_fault_at,
    )
    cell = SimCell(truth, seed=args.seed, time_scale=args.time_scale, faults=faults, q_home=q_home)
    fake = CanGatewayFake(
        cell,
        args.host,
        args.port,
        _joint_map(args.encoders),
        _joint_map(args.resolvers),
        resolver_pole_pairs=args.pole_pairs,
    )
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    fake.start()
    try:
        print(json.dumps({"ready": True, **fake.endpoint()}), flush=True)
        stop.wait()
    finally:
        fake.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
