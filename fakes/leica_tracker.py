"""A simulated Leica laser tracker behind an emScon server (TPI binary packets over TCP).

It speaks the subset of the emScon TPI that Recal's driver uses, with the packet layouts of
Leica's ``ES_C_API_Def.h`` (as the ``cesapi`` package carries them; this module packs them
itself: fakes and drivers meet only at the wire), so the independent ``cesapi`` client works
against it. Every command gets its reply (``BasicCommandRT``: command and status); a command
outside the subset is answered as the real server does, with its reply and the status
``ES_RS_NotImplemented``. ``StartMeasurement`` is answered with its reply and then one
``SingleMeasResultT`` (``SingleMeasResult2T``, with covariances, when ``extended_result``).
The state of the instrument (initialised, units, environment, reflector, where the beam points,
whether it holds the reflector) is shared by every connection.

The tracker frame is the world frame of the simulated cell. The reflector is the cell's
reflector target (``cell.target_world()``).

Geometry of the beam (checked whenever a command needs the beam):

- the reflector faces along ``reflector_axis_tool`` (tool frame, for example ``(0, 0, 1)``: out
  of the flange) and accepts the beam within ``acceptance_deg`` of that axis (a 1.5" red-ring
  reflector: +-30 deg, Leica's figure); ``None`` leaves this out;
- the arm must not block the line of sight. The arm is approximated as capsules of radius
  ``arm_radius_m`` around the segments joining the origins of the truth model's elementary
  motions (the link lengths and offsets of a DH/MDH model, the joint frames of a PoE model) from
  the base to the flange; the last ``reflector_clearance_m`` of the sight line before the
  reflector is not checked (the reflector sits on the flange). A coarse approximation: no
  link shapes, no tooling, no other obstacles; ``arm_radius_m=0`` leaves this out;
- the reflector farther than ``cell.tracker_range_m`` is out of range.

Both geometric checks are off unless asked for (``recal fake-cell --reflector-axis 0,0,1
--arm-radius 0.045``): Recal's session planning does not know where the tracker stands, so with
a realistic reflector most planned configurations of the simulated cell would face away (with
the test cell's UR5e and +z of the flange at 30 degrees, 29 of 30 planned poses did). Real cells
aim the reflector at the tracker with a nest or use several reflectors.

Losing and finding the reflector. The tracker holds the reflector (follows it as the robot
moves) until the beam breaks: geometry, or an injected break. It then keeps its beam where it
lost the reflector and does not search by itself (auto-lock is off, as Recal leaves it); it
holds the reflector again when a client points it near the reflector (``GoPosition`` then
``FindReflector``, which searches within ``search_radius_m`` of the pointed direction at the given
distance) or when the reflector is brought back into the beam (within ``capture_m`` of it) after
having left it. While it does not hold the reflector, ``StartMeasurement`` fails with
``ES_RS_MeasurementStatusNotReady``; the loss and the re-lock are announced to every client
with a status change (``ES_SSC_MeasStatus_NotReady`` / ``_Ready``).

Noise. Each coordinate gets Gaussian noise whose standard deviation is half the instrument's
maximum permissible error divided by sqrt(3): ``MPE(r) = noise.tracker_mpe_const_m +
noise.tracker_mpe_per_m * r`` (r the distance to the reflector). The defaults, 15 um + 6 um/m,
are Leica's published MPE of the 3D point (Uxyz) for the AT960 and AT930 (ASME B89.4.19,
ISO 10360-10), whose typical values are half the MPE. The result's deviations ``dStd1..3``
report that sigma; the noise is isotropic (a real tracker's radial error is smaller than its
transverse one).

Faults (``cell.faults``), counted per command with ``cell.count("emscon.request")``:
``drop_connection_at`` (the connection is closed instead of answering), ``delay_s`` /
``delay_at`` (latency before the answer), ``garble_at`` / ``garble_rate`` (a malformed packet:
the reply's size field is wrong), ``error_status_at`` (the command is answered with an error
packet, ``ErrorResponseT`` with ``ES_RS_Unknown``); per ``StartMeasurement`` with
``cell.count("emscon.meas")``: ``beam_break_at`` / ``beam_break_rate`` (the beam is interrupted
during the measurement: the tracker loses the reflector as above).

Run it alone: ``python -m fakes.leica_tracker --robot ur5e --reflector 0,0,0.05`` prints one
JSON ready line (contracts §7 keys) and serves until interrupted.
"""

from __future__ import annotations

import logging
import struct
import threading
import time

import numpy as np

from calibration.kinematics import program, walk
from fakes._lineserver import Client, DropConnection, LineServer
from fakes.world import SimCell

log = logging.getLogger(__name__)

# Codes (ES_C_API_Def.h): data types, commands, result statuses, status changes.
DT_COMMAND, DT_ERROR, DT_RESULT, DT_STATUS_CHANGE, DT_RESULT2 = 0, 1, 2, 8, 9
(C_GET_SYSTEM_STATUS, C_GET_TRACKER_STATUS, C_SET_UNITS, C_GET_UNITS, C_INITIALIZE) = (1, 2, 5, 6, 7)
C_SET_ENV, C_GET_ENV, C_SET_MODE, C_GET_MODE, C_SET_STATIONARY, C_GET_STATIONARY = 20, 21, 24, 25, 28, 29
C_SET_COORDINATE_SYSTEM, C_GET_COORDINATE_SYSTEM = 26, 27
C_SET_REFLECTOR, C_GET_REFLECTOR, C_GET_REFLECTORS, C_START_MEASUREMENT = 40, 41, 42, 49
C_GO_BIRD_BATH, C_GO_POSITION, C_FIND_REFLECTOR, C_GET_MEAS_STATUS_INFO = 54, 55, 63, 122
RS_OK, RS_NOT_IMPLEMENTED, RS_WRONG_PARAMETER1, RS_UNKNOWN, RS_NOT_INITIALIZED = 0, 2, 4, 36, 39
RS_MEAS_NOT_READY, RS_NO_STATIONARY_RESULT = 10004, 10009
SSC_MEAS_NOT_READY, SSC_MEAS_READY = 25, 27

# Layouts: what follows the command (BasicCommandCT: size, type, command) and what follows
# the reply (BasicCommandRT: size, type, command, status); little-endian, packed.
COMMANDS = {
    C_GET_SYSTEM_STATUS: "",
    C_GET_TRACKER_STATUS: "",
    C_SET_UNITS: "5I",
    C_GET_UNITS: "",
    C_INITIALIZE: "",
    C_SET_ENV: "3d",
    C_GET_ENV: "",
    C_SET_MODE: "I",
    C_GET_MODE: "",
    C_SET_STATIONARY: "2i",
    C_GET_STATIONARY: "",
    C_SET_REFLECTOR: "i",
    C_GET_REFLECTOR: "",
    C_GET_REFLECTORS: "",
    C_START_MEASUREMENT: "",
    C_GO_BIRD_BATH: "",
    C_GO_POSITION: "3di",
    C_FIND_REFLECTOR: "d",
    C_GET_MEAS_STATUS_INFO: "",
    C_SET_COORDINATE_SYSTEM: "I",
    C_GET_COORDINATE_SYSTEM: "",
}
REPLIES = {
    C_GET_SYSTEM_STATUS: "4I3iIii",
    C_GET_TRACKER_STATUS: "I",
    C_GET_UNITS: "5I",
    C_GET_ENV: "3d",
    C_GET_MODE: "I",
    C_GET_STATIONARY: "2i",
    C_GET_REFLECTOR: "i",
    C_GET_REFLECTORS: "iiId64s",
    C_GET_MEAS_STATUS_INFO: "Ii",
    C_GET_COORDINATE_SYSTEM: "I",
}
HEADER = struct.Struct("<iI")
RESULT = struct.Struct("<iIIIi17d")  # ReturnDataT, measMode, bIsTryMode, 17 doubles
RESULT2 = struct.Struct("<iIIIi23d")  # ... 23 doubles (with covariances)
STATUS_CHANGE = struct.Struct("<iII")
ERROR = struct.Struct("<iIII")

# ES_LengthUnit -> metres
LENGTH_UNITS_M = {0: 1.0, 1: 1e-3, 2: 1e-6, 3: 0.3048, 4: 0.9144, 5: 0.0254}
# (internal id, name, ES_TargetType, surface offset mm): Leica's red-ring reflectors and a
# break-resistant one
REFLECTORS = ((0, "RRR 1.5in", 5, 19.05), (1, "RRR 0.5in", 6, 6.35), (2, "BRR 1.5in", 7, 19.05))
SERVER_VERSION = (3, 8, 400)
SERIAL = 750123
MSI_TRACKER_FOUND, MSI_ADM_FOUND, MSI_REFLECTOR_FOUND, MSI_INITIALIZED = 1, 4, 2048, 65536


def pack_reply(command: int, status: int, *data) -> bytes:
    s = struct.Struct("<iIII" + (REPLIES.get(command, "") if data else ""))
    return s.pack(s.size, DT_COMMAND, command, status, *data)


# --------------------------------------------------------------------------- geometry


def arm_segments(cell: SimCell) -> np.ndarray:
    """The arm's links as segments ``(k, 2, 3)`` (m, world): consecutive distinct origins of
    the truth model's elementary motions, base to flange, at the robot's current joints."""
    ops = program(cell.truth)
    w = walk(cell.truth, cell.joints()[None, :], record={op.key for op in ops if op.key})
    points = []
    for op in ops:
        if op.key in w.axes:
            points.append(w.axes[op.key][1][0])
        elif op.key in w.frames:
            points.append(w.frames[op.key][1][0])
    points.append(w.p[0])
    pts = [points[0]]
    for p in points[1:]:
        if np.linalg.norm(p - pts[-1]) > 1e-6:
            pts.append(p)
    pts = np.array(pts)
    return np.stack([pts[:-1], pts[1:]], axis=1)


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Shortest distance between segments a0-a1 and b0-b1 (clamped closest points)."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    aa, ee, f = d1 @ d1, d2 @ d2, d2 @ r
    if aa < 1e-15 and ee < 1e-15:
        return float(np.linalg.norm(r))
    if aa < 1e-15:
        s, t = 0.0, np.clip(f / ee, 0.0, 1.0)
    else:
        c = d1 @ r
        if ee < 1e-15:
            s, t = np.clip(-c / aa, 0.0, 1.0), 0.0
        else:
            b = d1 @ d2
            denom = aa * ee - b * b
            s = np.clip((b * f - c * ee) / denom, 0.0, 1.0) if denom > 1e-15 else 0.0
            t = (b * s + f) / ee
            if t < 0.0:
                s, t = np.clip(-c / aa, 0.0, 1.0), 0.0
            elif t > 1.0:
                s, t = np.clip((b - c) / aa, 0.0, 1.0), 1.0
    return float(np.linalg.norm(a0 + s * d1 - (b0 + t * d2)))


# --------------------------------------------------------------------------- the fake


class LeicaTrackerFake(LineServer):
    """The emScon server of a simulated cell's tracker (see the module docstring)."""

    device_name = "emscon"

    def __init__(
        self,
        cell: SimCell,
        host: str = "127.0.0.1",
        port: int = 700,
        *,
        reflector_axis_tool: np.ndarray | None = None,
        acceptance_deg: float = 30.0,
        arm_radius_m: float = 0.0,
        reflector_clearance_m: float = 0.08,
        search_radius_m: float = 0.1,
        capture_m: float = 0.002,
        initialised: bool = False,
        initialize_time_s: float = 1.0,
        extended_result: bool = False,
        weather_station: bool = True,
    ):
        super().__init__(host, port)
        self.cell = cell
        self.reflector_axis_tool = None if reflector_axis_tool is None else np.asarray(reflector_axis_tool, float)
        self.acceptance_deg = acceptance_deg
        self.arm_radius_m = arm_radius_m
        self.reflector_clearance_m = reflector_clearance_m
        self.search_radius_m = search_radius_m
        self.capture_m = capture_m
        self.initialize_time_s = initialize_time_s
        self.extended_result = extended_result
        self.weather_station = weather_station
        self._state_lock = threading.RLock()  # one command at a time changes the instrument
        # the instrument's state, shared by every connection
        self.initialised = initialised
        self.units = (1, 1, 0, 0, 0)  # mm, degree, Celsius, mbar, %RH
        self.environment = (20.0, 1013.25, 50.0)
        self.meas_mode = 0
        self.coordinate_system = 0  # ES_CS_RHR (the fake reports x, y, z whatever is set)
        self.stationary = (1000, 0)
        self.reflector_id = 0
        self.locked = True  # the tracker holds the reflector
        self.beam_world: np.ndarray | None = None  # where the beam points when it holds nothing
        self.left_beam = False  # the reflector has left the beam since it was lost
        self.breaks = 0  # beam breaks so far (geometry or injected)

    def endpoint(self) -> dict:
        return {"emscon": f"{self.host}:{self.port}"}

    def start(self) -> None:
        """Listen on the given port; emScon's port 700 needs root, so when it cannot be bound
        the server takes an ephemeral port (the endpoint line says which)."""
        try:
            super().start()
        except PermissionError:
            if self.port == 0:
                raise
            log.warning("emscon fake: cannot bind port %d; taking an ephemeral port", self.port)
            self.port = 0
            super().start()

    # ----------------------------------------------------------------- transport

    def _client_loop(self, client: Client) -> None:
        """Packets instead of lines: read a header, then the rest of the packet."""
        buffer = bytearray()
        client.sock.settimeout(0.2)
        try:
            while not self._stopping.is_set() and not client.closed:
                try:
                    chunk = client.sock.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                buffer += chunk
                while len(buffer) >= 12:
                    size, kind = HEADER.unpack_from(buffer)
                    if size < 12 or size > 4096:  # a client that lost the framing: hang up, as a server must
                        raise DropConnection
                    if len(buffer) < size:
                        break
                    packet = bytes(buffer[:size])
                    del buffer[:size]
                    self.handle_packet(client, kind, packet)
        except DropConnection:
            log.info("emscon fake: dropping the connection")
        except Exception:  # a fake must not die silently in a thread
            log.exception("emscon fake: client handler failed")
        finally:
            client.close()
            with self._lock:
                self._clients.discard(client)

    def handle_line(self, client: Client, line: str) -> None:  # pragma: no cover - packets, not lines
        raise NotImplementedError

    def broadcast_status(self, change: int) -> None:
        data = STATUS_CHANGE.pack(STATUS_CHANGE.size, DT_STATUS_CHANGE, change)
        for c in self.clients():
            c.send_raw(data)

    # ----------------------------------------------------------------- protocol

    def handle_packet(self, client: Client, kind: int, packet: bytes) -> None:
        n = self.cell.count("emscon.request")
        faults = self.cell.faults
        if n in faults.drop_connection_at:
            raise DropConnection
        command = struct.unpack_from("<I", packet, 8)[0] if kind == DT_COMMAND and len(packet) >= 12 else -1
        if n in faults.error_status_at:
            answer = [ERROR.pack(ERROR.size, DT_ERROR, command, RS_UNKNOWN)]
        else:
            answer = self._answer(kind, command, packet)
        delay_s = faults.reply_delay_s(n)
        if delay_s > 0:
            time.sleep(delay_s)
        if n in faults.garble_at or self.cell.chance(faults.garble_rate):
            bad = bytearray(answer[0])
            struct.pack_into("<i", bad, 0, len(bad) + 7)  # a size that is not this packet's
            answer[0] = bytes(bad)
        for data in answer:
            client.send_raw(data)

    def _answer(self, kind: int, command: int, packet: bytes) -> list[bytes]:
        """The packets that answer one command packet."""
        if kind != DT_COMMAND or command not in COMMANDS:
            return [pack_reply(command if command >= 0 else 0, RS_NOT_IMPLEMENTED)]
        fmt = struct.Struct("<iII" + COMMANDS[command])
        if len(packet) != fmt.size:
            return [pack_reply(command, RS_WRONG_PARAMETER1)]
        params = fmt.unpack(packet)[3:]
        with self._state_lock:
            return self._command(command, params)

    def _command(self, c: int, params: tuple) -> list[bytes]:
        ok = lambda *data: [pack_reply(c, RS_OK, *data)]  # noqa: E731
        if c == C_GET_SYSTEM_STATUS:
            return ok(
                RS_OK, 5 if self.initialised else 4, 3, 2, *SERVER_VERSION, 2 if self.weather_station else 0, 0, SERIAL
            )
        if c == C_GET_TRACKER_STATUS:
            return ok(2 if self.initialised else 0)
        if c == C_INITIALIZE:
            self._sleep(self.initialize_time_s)
            self.initialised = True
            return ok()
        if c == C_SET_UNITS:
            if params[0] not in LENGTH_UNITS_M:
                return [pack_reply(c, RS_WRONG_PARAMETER1)]
            self.units = tuple(params)
            return ok()
        if c == C_GET_UNITS:
            return ok(*self.units)
        if c == C_SET_COORDINATE_SYSTEM:
            self.coordinate_system = params[0]
            return ok()
        if c == C_GET_COORDINATE_SYSTEM:
            return ok(self.coordinate_system)
        if c == C_SET_ENV:
            self.environment = tuple(params)
            return ok()
        if c == C_GET_ENV:
            return ok(*self.environment)
        if c == C_SET_MODE:
            if params[0] != 0:  # stationary only
                return [pack_reply(c, RS_WRONG_PARAMETER1)]
            self.meas_mode = params[0]
            return ok()
        if c == C_GET_MODE:
            return ok(self.meas_mode)
        if c == C_SET_STATIONARY:
            if not 1 <= params[0] <= 100_000:
                return [pack_reply(c, RS_WRONG_PARAMETER1)]
            self.stationary = tuple(params)
            return ok()
        if c == C_GET_STATIONARY:
            return ok(*self.stationary)
        if c == C_SET_REFLECTOR:
            if params[0] not in [r[0] for r in REFLECTORS]:
                return [pack_reply(c, RS_WRONG_PARAMETER1)]
            self.reflector_id = params[0]
            return ok()
        if c == C_GET_REFLECTOR:
            return ok(self.reflector_id)
        if c == C_GET_REFLECTORS:
            return [
                pack_reply(c, RS_OK, len(REFLECTORS), rid, ttype, offset, name.encode("utf-16-le"))
                for rid, name, ttype, offset in REFLECTORS
            ]
        if c == C_GET_MEAS_STATUS_INFO:
            self._check_beam()
            info = MSI_TRACKER_FOUND | MSI_ADM_FOUND | (MSI_INITIALIZED if self.initialised else 0)
            if self.initialised and self.locked:
                info |= MSI_REFLECTOR_FOUND
            return ok(RS_OK, info)
        if not self.initialised:
            return [pack_reply(c, RS_NOT_INITIALIZED)]
        if c == C_START_MEASUREMENT:
            return self._measure()
        if c == C_GO_POSITION:
            return self._go_position(np.array(params[:3]) * self._length_m())
        if c == C_GO_BIRD_BATH:
            return self._go_position(np.zeros(3) + np.array([0.1, 0.0, 0.0]))
        if c == C_FIND_REFLECTOR:
            return self._find_reflector(params[0] * self._length_m())
        return [pack_reply(c, RS_NOT_IMPLEMENTED)]  # pragma: no cover - COMMANDS lists what is handled

    def _length_m(self) -> float:
        return LENGTH_UNITS_M[self.units[0]]

    def _sleep(self, simulated_s: float) -> None:
        if self.cell.time_scale > 0 and simulated_s > 0:
            time.sleep(simulated_s * self.cell.time_scale)

    # ----------------------------------------------------------------- the beam

    def visible(self) -> str | None:
        """Why the tracker cannot see the reflector now (``None``: it can)."""
        p = self.cell.target_world()
        r = float(np.linalg.norm(p))
        if r > self.cell.tracker_range_m:
            return "out of range"
        if self.reflector_axis_tool is not None:
            T = self.cell.T_world_tool()
            axis = T[:3, :3] @ self.reflector_axis_tool
            to_tracker = -p / max(r, 1e-12)
            cos_angle = float(axis @ to_tracker) / float(np.linalg.norm(axis))
            if cos_angle < np.cos(np.deg2rad(self.acceptance_deg)):
                return "the reflector faces away"
        if self.arm_radius_m > 0 and r > self.reflector_clearance_m:
            end = p * (1.0 - self.reflector_clearance_m / r)
            for a, b in arm_segments(self.cell):
                if segment_distance(np.zeros(3), end, a, b) < self.arm_radius_m:
                    return "the arm blocks the line of sight"
        return None

    def _lose(self, why: str) -> None:
        self.locked = False
        self.beam_world = self.cell.target_world()
        self.left_beam = False
        self.breaks += 1
        log.info("emscon fake: beam broken (%s)", why)
        self.broadcast_status(SSC_MEAS_NOT_READY)

    def _lock_on(self) -> None:
        self.locked = True
        self.beam_world = None
        self.broadcast_status(SSC_MEAS_READY)

    def _off_beam_m(self, p: np.ndarray) -> float:
        """How far ``p`` is from the line of the beam."""
        u = self.beam_world / max(float(np.linalg.norm(self.beam_world)), 1e-12)
        return float(np.linalg.norm(p - (p @ u) * u))

    def _check_beam(self) -> None:
        """Bring the beam up to date with the world: lost when the reflector cannot be seen;
        found again when the reflector came back into the beam."""
        why = self.visible()
        if self.locked:
            if why is not None:
                self._lose(why)
            return
        if self.beam_world is None:
            return
        near = self._off_beam_m(self.cell.target_world()) <= self.capture_m
        if not near:
            self.left_beam = True
        elif self.left_beam and why is None:
            self._lock_on()

    def _go_position(self, p_world: np.ndarray) -> list[bytes]:
        self._check_beam()
        if self.locked:
            self.locked = False
            self.broadcast_status(SSC_MEAS_NOT_READY)
        self.beam_world = p_world if np.linalg.norm(p_world) > 1e-9 else np.array([1.0, 0.0, 0.0])
        self.left_beam = True  # the beam moved: the reflector in it now is a reflector found
        self._sleep(0.5)
        self._check_beam()
        return [pack_reply(C_GO_POSITION, RS_OK)]

    def _find_reflector(self, distance_m: float) -> list[bytes]:
        self._check_beam()
        if not self.locked:
            p = self.cell.target_world()
            u = self.beam_world / max(float(np.linalg.norm(self.beam_world)), 1e-12)
            searched = u * distance_m
            self._sleep(2.0)
            if self.visible() is None and np.linalg.norm(p - searched) <= self.search_radius_m:
                self._lock_on()
            else:
                return [pack_reply(C_FIND_REFLECTOR, RS_MEAS_NOT_READY)]
        return [pack_reply(C_FIND_REFLECTOR, RS_OK)]

    def _measure(self) -> list[bytes]:
        k = self.cell.count("emscon.meas")
        faults = self.cell.faults
        self._sleep(self.stationary[0] / 1000.0)
        self._check_beam()
        if self.locked and (k in faults.beam_break_at or self.cell.chance(faults.beam_break_rate)):
            self._lose("injected")
        if not self.locked:
            return [pack_reply(C_START_MEASUREMENT, RS_MEAS_NOT_READY)]
        if self.cell.is_moving():
            return [pack_reply(C_START_MEASUREMENT, RS_NO_STATIONARY_RESULT)]
        p = self.cell.target_world()
        r = float(np.linalg.norm(p))
        mpe = self.cell.noise.tracker_mpe_const_m + self.cell.noise.tracker_mpe_per_m * r
        sigma = 0.5 * mpe / np.sqrt(3.0)
        p_meas = (p + self.cell.normal(sigma, 3)) / self._length_m()
        s = sigma / self._length_m()
        total = float(np.sqrt(3.0) * s)
        env = self.environment
        head = [pack_reply(C_START_MEASUREMENT, RS_OK)]
        if self.extended_result:
            doubles = [*p_meas, s, s, s, total, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, s, s, s, total, 0.0, 0.0, 0.0, *env]
            return head + [RESULT2.pack(RESULT2.size, DT_RESULT2, RS_OK, self.meas_mode, 0, *doubles)]
        doubles = [*p_meas, s, s, s, total, 0.0, 0.0, 0.0, s, s, s, total, *env]
        return head + [RESULT.pack(RESULT.size, DT_RESULT, RS_OK, self.meas_mode, 0, *doubles)]


def _xyz(text: str) -> list[float]:
    """``--reflector-axis X,Y,Z``."""
    import argparse

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z; got {text!r}")
    return values


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, its keyword arguments from the command line, and its own
# command-line options.
CELL_FAKE = {
    "key": "emscon",
    "order": 40,
    "cls": LeicaTrackerFake,
    "kwargs": lambda args: {
        "port": args.emscon_port,
        "reflector_axis_tool": args.reflector_axis,
        "arm_radius_m": args.arm_radius,
    },
    "options": [
        (
            "--emscon-port",
            {"type": int, "default": 700, "help": "emScon TPI port (default 700; a free port if that cannot be bound)"},
        ),
        (
            "--reflector-axis",
            {
                "type": _xyz,
                "default": None,
                "metavar": "X,Y,Z",
                "help": "emScon tracker: the reflector faces along this tool-frame axis (default: no acceptance check)",
            },
        ),
        (
            "--arm-radius",
            {
                "type": float,
                "default": 0.0,
                "metavar": "M",
                "help": "emScon tracker: the arm's links block the beam within this radius (default 0: not checked)",
            },
        ),
    ],
}


def main(argv: list[str] | None = None) -> int:
    from fakes._standalone import run_fake

    return run_fake(
        LeicaTrackerFake,
        default_port=700,
        argv=argv,
        description="Run a simulated Leica tracker's emScon server.",
    )


if __name__ == "__main__":
    raise SystemExit(main())
