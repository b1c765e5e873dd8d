"""A Universal Robots controller's Modbus TCP server, with Recal's motion program running.

The register map is the wire contract written out in ``docs/devices/ur.md`` (holding
registers, 0-based protocol addresses; input registers read the same values, as on UR):

UR's own registers (read only here)::

    258        robot mode (3 power off, 5 idle: brakes on, 7 running)
    260..262   power on, protective stop ("isSecurityStopped"), emergency stop (0/1)
    270..275   joint angles, mrad, wrapped into [0, 2 pi): 0..6283
    320..325   joint revolution counters, int16 (two's complement; -1 for angles in [-2 pi, 0))
    400..405   TCP x, y, z in 0.1 mm and rx, ry, rz in mrad (int16), base frame

Recal's motion handshake in the general-purpose registers 128..255 (what
``drivers/urscript/modbus_motion.script`` does on a real controller)::

    128  command (1 MOVEJ, 2 STOP)          written by the client, together with
    129  sequence number 1..65535            a new sequence number starts the command
    130..141  target joints, int32 urad (high word first), 6 x 2 registers
    142  speed, mrad/s (uint16)              143  acceleration, mrad/s^2 (uint16)
    150  acknowledged sequence number        151  state: 0 idle, 1 busy, 2 done, 3 error
    152  error: 0 none, 1 unknown command, 2 bad speed/acceleration, 3 refused by the robot
    153  heartbeat, +1 per controller cycle (500 Hz) while the program runs
    160..171  joint readings, int32 urad (high word first), refreshed every cycle

Simulation: joints from ``cell.joints()``, TCP pose (400..405) from the controller's own
forward kinematics (``cell.controller_fk``: the factory calibration, robot base frame, not the
truth), motion by
``cell.start_move``; "done" when the simulated motion is over. A safety stop (for example
``cell.faults.protective_stop_at_move`` or ``emergency_stop_at_move``) halts the motion
program: no acknowledgements, the heartbeat freezes, 261/262 report the stop (an emergency
stop also powers the arm off: 258, 260). The program counts as running again as soon as the
cell's safety stop is cleared and the arm runs (powered on, brakes released; on a real
controller it must also be started again).

Faults (``cell.faults``), counted per request with ``cell.count("modbus.request")``:
``drop_connection_at`` closes the connection instead of answering, ``garble_at`` /
``garble_rate`` answers with a corrupted frame (right header, unknown function code and
junk data), ``delay_s`` delays every answer (none when ``delay_at`` is set: the server does
not count requests before it answers them).

Port 502 needs root; if it cannot be bound the server takes an ephemeral port and
``endpoint()`` reports the port it has.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time

import numpy as np
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from calibration.transforms import matrix_to_rotvec
from fakes.world import SimCell

N_JOINTS = 6
# UR's own registers
ROBOT_MODE, POWER_ON, PROTECTIVE_STOP, EMERGENCY_STOP = 258, 260, 261, 262
JOINT_ANGLE, JOINT_TURNS, TCP_POSE = 270, 320, 400
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
# Recal's handshake
COMMAND, SEQUENCE, TARGET, SPEED, ACCEL = 128, 129, 130, 142, 143
ACK, STATE, ERROR, HEARTBEAT = 150, 151, 152, 153
JOINT_URAD = 160
CMD_MOVEJ, CMD_STOP = 1, 2
STATE_IDLE, STATE_BUSY, STATE_DONE, STATE_ERROR = 0, 1, 2, 3
ERROR_NONE, ERROR_UNKNOWN_COMMAND, ERROR_BAD_PARAMETER, ERROR_REFUSED = 0, 1, 2, 3

_REGISTER_COUNT = 1024
_READ_ONLY_FROM = 256  # UR's state registers


def _u16(value: int) -> int:
    return int(value) & 0xFFFF


def _s16(value: int) -> int:
    value = int(value) & 0xFFFF
    return value - 0x10000 if value >= 0x8000 else value


def _int32_words(value: int) -> list[int]:
    """A signed 32-bit integer as two registers, high word first."""
    value = int(value) & 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def _int32(high: int, low: int) -> int:
    value = (high << 16) | low
    return value - 0x100000000 if value >= 0x80000000 else value


def ur_joint_registers(q: np.ndarray) -> tuple[list[int], list[int]]:
    """UR's encoding: angle mod 2 pi in mrad (uint16) and revolution counts (int16)."""
    angles, turns = [], []
    for angle in np.asarray(q, dtype=float):
        turn = math.floor(angle / (2 * math.pi))
        angles.append(_u16(round((angle - turn * 2 * math.pi) * 1000.0)))  # 0..6283
        turns.append(_u16(turn))
    return angles, turns


class ModbusRobotFake:
    """The Modbus TCP side of a simulated UR controller (see the module docstring)."""

    def __init__(self, cell: SimCell, host: str = "127.0.0.1", port: int = 502):
        if cell.truth.n_joints != N_JOINTS:
            raise ValueError(f"the UR Modbus map has {N_JOINTS} joints; the truth model has {cell.truth.n_joints}")
        self.cell = cell
        self.host = host
        self.port = port
        self._requested_port = port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server = None
        self._lock = threading.Lock()
        self._last_sequence = 0
        self._state = STATE_IDLE
        self._heartbeat = 0
        self._t0 = time.monotonic()

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Serve from a thread of its own; returns once the port accepts connections."""
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        future = asyncio.run_coroutine_threadsafe(self._listen(), self._loop)
        try:
            future.result(timeout=10.0)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Close the server and its connections. Idempotent."""
        loop, self._loop = self._loop, None
        if loop is None:
            return
        if self._server is not None:
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), loop).result(timeout=5.0)
            except Exception:  # noqa: BLE001 - stopping is best effort; the loop is stopped next
                pass
            self._server = None
        loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        loop.close()

    def endpoint(self) -> dict:
        return {"modbus": f"{self.host}:{self.port}"}

    async def _listen(self) -> None:
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # faults are expected here
        device = SimDevice(
            id=0,  # answers every device id, as UR's server does
            simdata=[
                SimData(0, count=_READ_ONLY_FROM, values=0, datatype=DataType.REGISTERS),
                SimData(
                    _READ_ONLY_FROM,
                    count=_REGISTER_COUNT - _READ_ONLY_FROM,
                    values=0,
                    datatype=DataType.REGISTERS,
                    readonly=True,
                ),
            ],
            action=self._action,
        )
        for port in (self._requested_port, 0) if self._requested_port else (0,):
            server = _FaultyServer(self, device, address=(self.host, port))
            try:
                await server.serve_forever(background=True)
            except RuntimeError:  # could not listen (port 502 needs root)
                continue
            self._server = server
            self.port = server.transport.sockets[0].getsockname()[1]
            return
        raise OSError(f"cannot listen on {self.host}:{self._requested_port} nor on a free port")

    # ----------------------------------------------------------------- registers

    async def _action(self, function_code, start_address, address, count, registers, values):
        """Called by pymodbus before every register access (``values`` is None for reads)."""
        delay_s = self.cell.faults.reply_delay_s(None)
        if delay_s:
            await asyncio.sleep(delay_s)
        with self._lock:
            if values:
                offset = address - start_address
                registers[offset : offset + len(values)] = values
                if address <= SEQUENCE < address + len(values):
                    self._on_command(registers, start_address)
            self._refresh(registers, start_address)
        return None

    def _program_running(self) -> bool:
        cell = self.cell
        return cell.running and not (cell.protective_stop or cell.emergency_stop)

    def _on_command(self, registers: list[int], base: int) -> None:
        """The motion program sees a new sequence number: acknowledge and execute."""

        def reg(address: int) -> int:
            return registers[address - base]

        sequence = reg(SEQUENCE)
        if sequence == self._last_sequence or not self._program_running():
            return
        self._last_sequence = sequence
        registers[ACK - base] = sequence
        command, error = reg(COMMAND), ERROR_NONE
        if command == CMD_MOVEJ:
            q = [_int32(reg(TARGET + 2 * i), reg(TARGET + 2 * i + 1)) * 1e-6 for i in range(6)]
            speed, accel = reg(SPEED) * 1e-3, reg(ACCEL) * 1e-3
            if speed <= 0 or accel <= 0:
                error = ERROR_BAD_PARAMETER
            else:
                try:
                    self.cell.start_move(np.array(q), speed, accel)
                    self._state = STATE_BUSY
                except (RuntimeError, ValueError):
                    error = ERROR_REFUSED
        elif command == CMD_STOP:
            self.cell.stop()
            self._state = STATE_DONE
        else:
            error = ERROR_UNKNOWN_COMMAND
        if error:
            self._state = STATE_ERROR
        registers[ERROR - base] = error

    def _refresh(self, registers: list[int], base: int) -> None:
        """Write the controller's current state into the registers."""
        cell = self.cell
        q = cell.joints()
        running = self._program_running()
        if running:
            self._heartbeat = int((time.monotonic() - self._t0) * 500.0) & 0xFFFF
            if self._state == STATE_BUSY and not cell.is_moving():
                self._state = STATE_DONE

        def put(address: int, words: list[int]) -> None:
            registers[address - base : address - base + len(words)] = words

        angles, turns = ur_joint_registers(q)
        put(JOINT_ANGLE, angles)
        put(JOINT_TURNS, turns)
        if cell.running:
            put(ROBOT_MODE, [ROBOT_MODE_RUNNING])
        else:
            put(ROBOT_MODE, [ROBOT_MODE_IDLE if cell.powered else ROBOT_MODE_POWER_OFF])
        put(POWER_ON, [int(cell.powered), int(cell.protective_stop), int(cell.emergency_stop)])
        # UR's TCP registers hold the controller's own forward kinematics of these joints
        # (its factory calibration, robot base frame), as actual_TCP_pose does.
        T = cell.controller_fk(q[None, :])[0]
        rotvec = matrix_to_rotvec(T[:3, :3])
        position = [_u16(round(v * 1e4)) for v in T[:3, 3]]  # 0.1 mm
        put(TCP_POSE, position + [_u16(round(v * 1e3)) for v in rotvec])  # mrad
        put(STATE, [self._state])
        put(HEARTBEAT, [self._heartbeat])
        if running:
            put(JOINT_URAD, [w for angle in q for w in _int32_words(round(angle * 1e6))])

    # ----------------------------------------------------------------- faults

    def reply_fault(self) -> str | None:
        """``"drop"``, ``"garble"`` or None for the reply about to be sent."""
        faults = self.cell.faults
        n = self.cell.count("modbus.request")
        if n in faults.drop_connection_at:
            return "drop"
        if n in faults.garble_at or self.cell.chance(faults.garble_rate):
            return "garble"
        return None


class _Handler(ServerRequestHandler):
    """pymodbus' per-connection handler, with a chance to drop or garble each reply."""

    def server_send(self, pdu, addr):
        fault = self.server.fake.reply_fault() if pdu else None
        if fault == "drop":
            self.close()
        elif fault == "garble":
            # A frame with the right MBAP header (transaction, protocol 0, length, unit) and a
            # PDU with an unknown function code and junk: framed right, meaningless inside.
            junk = bytes([0x63, 0xDE, 0xAD, 0xBE])
            header = pdu.transaction_id.to_bytes(2, "big") + b"\x00\x00"
            header += (len(junk) + 1).to_bytes(2, "big") + bytes([pdu.dev_id & 0xFF])
            self.low_level_send(header + junk)
        else:
            super().server_send(pdu, addr)


class _FaultyServer(ModbusTcpServer):
    def __init__(self, fake: ModbusRobotFake, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.fake = fake

    def callback_new_connection(self):
        return _Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, its keyword arguments from the command line, and its own
# command-line options.
CELL_FAKE = {
    "key": "modbus",
    "order": 20,
    "cls": ModbusRobotFake,
    "kwargs": lambda args: {"port": args.modbus_port},
    "options": [
        (
            "--modbus-port",
            {"type": int, "default": 502, "help": "Modbus TCP port (default 502; a free port if that cannot be bound)"},
        ),
    ],
}


def main(argv: list[str] | None = None) -> int:
    """``python -m fakes.modbus_server --truth TRUE.json [--host H] [--modbus-port P]``."""
    import sys

    from fakes.cell import main as cell_main

    args = list(sys.argv[1:] if argv is None else argv)
    return cell_main([*args, "--only", CELL_FAKE["key"]])


if __name__ == "__main__":
    raise SystemExit(main())
