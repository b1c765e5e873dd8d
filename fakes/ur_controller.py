"""A Universal Robots e-Series controller on the wire, driven by a ``SimCell``.

It listens on the controller's fixed ports of one host address:

- RTDE (Real-Time Data Exchange, protocol version 2) on 30004,
- the dashboard server (text lines) on 29999,
- the script server (URScript programs in) on 30003,

enough that the unchanged ``ur_rtde`` 1.6.5 ``RTDEReceiveInterface`` and
``RTDEControlInterface`` (``moveJ``, ``stopJ``, ``stopScript``, ``disconnect``) work against it.
The ports are fixed because ``ur_rtde`` has no port argument; run several controllers on
different loopback addresses (``127.0.0.2``, ``127.0.0.3``, ...).

What it simulates:

- ``actual_q`` / ``target_q`` are ``cell.joints()`` (rad); ``actual_TCP_pose`` is what a real
  controller reports: its own forward kinematics of those joints, through its factory
  calibration (``cell.controller_fk``, robot base frame, ``[x, y, z, rx, ry, rz]``: m and a
  rotation vector in rad), not where the tool truly is (``cell.T_world_tool()``);
- the control script that ``ur_rtde`` uploads: when a program arrives on the script port the
  controller starts "playing" it and emulates its register handshake (``input_int_register_0``
  is the command, ``output_int_register_0`` is 1 = ready, 2 = done; ``output_int_register_2`` is
  the script's encoded async-operation status: bit 15 running, bits 16-22 a write counter,
  bits 24-30 an operation id). ``MOVEJ`` starts ``cell.start_move``; ``MOVEJ_IK`` and
  ``MOVEL`` (a pose target) first turn the pose into joints through the factory calibration,
  nearest the current joints (``cell.controller_ik``; the end point is exact, the path is
  joint-interpolated); a blocking move reports done when the simulated motion is over;
  ``GET_FORWARD_KINEMATICS_*`` and ``GET_INVERSE_KINEMATICS_*`` (``getForwardKinematics``,
  ``getInverseKinematics``) answer through the factory calibration in output double registers
  0-5 (no solution: the script stops, as ``get_inverse_kin`` raising does); ``STOPJ`` stops the
  robot; ``STOP_SCRIPT`` ends the program; ``SET_PAYLOAD`` (``setPayload``) tells the cell the
  mounted payload, under which a truth with joint compliance sags (``payload``/``payload_cog``
  outputs report it);
- a user's program (anything else sent to the script port, e.g. a compensated task): its
  ``movej``/``movel``/``movep`` to literal targets, variables holding one and
  ``get_inverse_kin(pose, qnear)`` run one after the other (``fakes.urscript_program``), pose
  targets through the factory calibration as on a real controller; the program plays
  (``runtime_state``, ``robot_status_bits``, dashboard ``running``) until its last move ends;
- safety and power, as on a UR: ``safety_status_bits`` / ``safety_mode`` reflect
  ``cell.protective_stop`` and ``cell.emergency_stop``, ``robot_mode`` the arm's power
  (``POWER_OFF`` 3, ``IDLE`` 5: powered with the brakes on, ``RUNNING`` 7). A safety stop halts
  the program, and no program starts unless the robot is ``RUNNING``. The dashboard command
  ``unlock protective stop`` clears a protective stop. Nothing on the wire clears an emergency
  stop: a person releases the button; the arm is then powered off, and ``power on`` and
  ``brake release`` (or ``brake release`` alone) make it ``RUNNING`` again. The simulated
  button is the dashboard's ``sim emergency stop press`` / ``sim emergency stop release``
  (simulator only: no UR controller knows these commands).

Faults (``cell.faults``), counted per command the control script receives (counter
``"ur.command"``; the kinematics queries count too: a Recal session on a UR cell starts with 24
``getForwardKinematics``, docs/devices/ur.md): ``drop_connection_at`` loses that command and closes every open connection
of the controller (new connections are accepted again at once); ``garble_at`` /
``garble_rate`` lose that command and send, on every RTDE stream, one package whose header
claims a size smaller than the header itself (a controller or gateway gone wrong: TCP itself
delivers bytes intact or not at all; ``ur_rtde`` aborts its process on such a package);
``delay_s`` delays every dashboard reply and the completion of every command (with
``delay_at``: only the completion of those commands); ``protective_stop_at_move`` and
``emergency_stop_at_move`` are applied by the cell itself.

Not simulated: the primary/secondary interfaces (30001/30002), the real-time state stream out
of 30003, script commands other than those above (the others report "done" and do nothing),
anything in a user's program but its moves and ``set_tcp``, deceleration (``stopJ`` stops at
once), Cartesian (straight-line) paths.

Run alone (tests, debugging)::

    python -m fakes.ur_controller --truth TRUE.json --host 127.0.0.2

prints one JSON line ``{"ready": true, "rtde": "127.0.0.2"}`` and serves until SIGINT/SIGTERM.
"""

from __future__ import annotations

import re
import socket
import struct
import sys
import threading
import time

import numpy as np

from fakes.urscript_program import ProgramError, is_control_script, parse_program
from fakes.world import SimCell, matrix_to_ur_pose, ur_pose_to_matrix

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

# RTDE package types (UR "Real-Time Data Exchange (RTDE) guide", protocol version 2).
_HEADER = struct.Struct(">HB")  # total package size incl. header, package type
RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
RTDE_GET_URCONTROL_VERSION = ord("v")
RTDE_TEXT_MESSAGE = ord("M")
RTDE_DATA_PACKAGE = ord("U")
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
RTDE_CONTROL_PACKAGE_START = ord("S")
RTDE_CONTROL_PACKAGE_PAUSE = ord("P")

# struct codes of the RTDE data types
_TYPE_FORMAT = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}


_V6 = "VECTOR6D"

# UR's RTDE variables by name -> type (the numbered registers are added by _variable_types).
# ``ur_rtde`` decodes data packages with its own copy of this table, whatever the server
# answered, so every type here must be exactly UR's.
_NAMED_VARIABLE_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": _V6,
    "target_qd": _V6,
    "target_qdd": _V6,
    "target_current": _V6,
    "target_moment": _V6,
    "actual_q": _V6,
    "actual_qd": _V6,
    "actual_qdd": _V6,
    "actual_current": _V6,
    "actual_moment": _V6,
    "joint_control_output": _V6,
    "actual_TCP_pose": _V6,
    "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6,
    "target_TCP_pose": _V6,
    "target_TCP_speed": _V6,
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": _V6,
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": _V6,
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "ft_raw_wrench": _V6,
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": _V6,
    "script_control_line": "UINT32",
    "external_force_torque": _V6,
    # inputs written by clients
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
}


def _variable_types() -> dict[str, str]:
    """UR's name -> type table: :data:`_NAMED_VARIABLE_TYPES`, then the numbered registers
    (48 integer and 48 double registers each way, bit registers 64-127 each way)."""
    types = dict(_NAMED_VARIABLE_TYPES)
    for i in range(48):
        for side in ("input", "output"):
            types[f"{side}_int_register_{i}"] = "INT32"
            types[f"{side}_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        for side in ("input", "output"):
            types[f"{side}_bit_register_{i}"] = "BOOL"
    return types


RTDE_TYPES = _variable_types()

# Values of the controller's enumerations that the fake reports.
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
JOINT_MODE_RUNNING = 253
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP, SAFETY_MODE_ROBOT_EMERGENCY_STOP = 1, 3, 7
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
# safety_status_bits
SAFETY_BIT_NORMAL = 1 << 0
SAFETY_BIT_PROTECTIVE_STOPPED = 1 << 2
SAFETY_BIT_ROBOT_EMERGENCY_STOPPED = 1 << 6
SAFETY_BIT_EMERGENCY_STOPPED = 1 << 7
SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 1 << 10
# robot_status_bits
ROBOT_STATUS_POWER_ON = 1 << 0
ROBOT_STATUS_PROGRAM_RUNNING = 1 << 1

# ur_rtde's control-script commands (RTDE::RobotCommand::Type) that the fake executes.
CMD_NO_CMD, CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_STOPJ, CMD_STOP_SCRIPT = 0, 1, 2, 3, 34, 255
CMD_GET_INVERSE_KINEMATICS_ARGS, CMD_GET_INVERSE_KINEMATICS_DEFAULT = 30, 46
CMD_GET_FORWARD_KINEMATICS_DEFAULT, CMD_GET_FORWARD_KINEMATICS_ARGS = 43, 44
CMD_SET_PAYLOAD = 17  # ur_rtde's setPayload: mass and centre of gravity (flange) in input_double_register_0..3
# "Real-time" commands that the script executes without reporting done.
_CONTINUOUS_COMMANDS = {6, 9, 10, 11, 12, 24, 25, 26, 27, 38, 58}
SCRIPT_READY, SCRIPT_DONE, SCRIPT_BUSY = 1, 2, 0
# A package header whose size field (1) is smaller than the header (3 bytes): malformed.
MALFORMED_PACKAGE = struct.pack(">HB", 1, RTDE_DATA_PACKAGE)


class UrControllerFake:
    """A UR controller (RTDE, dashboard, script server) whose robot is ``cell``'s robot.

    ``port`` is the RTDE port (the other two are fixed as well). ``version`` is what the
    controller reports (major, minor, bugfix, build); 5.x makes ``ur_rtde`` use 500 Hz.
    ``max_frequency_hz`` caps the RTDE output rate whatever a client asks for.
    """

    def __init__(
        self,
        cell: SimCell,
        host: str = "127.0.0.1",
        port: int = RTDE_PORT,
        *,
        dashboard_port: int = DASHBOARD_PORT,
        script_port: int = SCRIPT_PORT,
        version: tuple[int, int, int, int] = (5, 11, 1, 108318),
        max_frequency_hz: float = 500.0,
    ):
        if cell.truth.n_joints != 6:
            raise ValueError(f"a UR controller drives 6 joints; the truth model has {cell.truth.n_joints}")
        self.cell = cell
        self.host = host
        self.port = port
        self.dashboard_port = dashboard_port
        self.script_port = script_port
        self.version = version
        self.max_frequency_hz = max_frequency_hz
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._listeners: list[socket.socket] = []
        self._clients: set[socket.socket] = set()
        self._threads: list[threading.Thread] = []
        self._t0 = time.monotonic()
        # The controller's register file and the emulated control script.
        self._registers: dict[str, float | int] = {
            name: (0.0 if t == "DOUBLE" else 0) for name, t in RTDE_TYPES.items() if "_register_" in name
        }
        self._script_running = False
        self._user_program = False  # the program playing is a user's, not ur_rtde's control script
        self._program_id = 0  # counts programs started, so a replaced one's thread stops
        self.last_program_error: str | None = None
        self._executing: int | None = None  # command being executed, None when idle
        self._command_done_at = 0.0  # monotonic time from which a command may report done
        self._blocking_move = False
        self._async_move = False
        self._async_writes = 0  # the script's async_wr_count
        self._async_op_id = 0  # the script's async_op_id
        self._malformed = 0  # how many malformed packages every RTDE stream must send
        self._last_q = cell.joints()
        self._last_q_time = time.monotonic()
        self._qd = np.zeros(6)
        self._payload_cog_flange = [0.0, 0.0, 0.0]  # set_payload's centre of gravity (flange frame, m)

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Bind the three ports and serve them from background threads."""
        try:
            for port, handler in (
                (self.port, self._serve_rtde),
                (self.dashboard_port, self._serve_dashboard),
                (self.script_port, self._serve_script),
            ):
                listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self._listeners.append(listener)
                listener.bind((self.host, port))
                listener.listen(8)
                self._spawn(self._accept_loop, listener, handler)
        except OSError:
            self.stop()
            raise

    def stop(self) -> None:
        """Close every socket and let the threads end. Idempotent."""
        self._stopping.set()
        for listener in self._listeners:
            try:
                listener.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked in accept()
            except OSError:
                pass
            _close_quietly(listener)
        self._listeners.clear()
        self._drop_clients()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(timeout=1.0)
        self._threads.clear()

    def endpoint(self) -> dict:
        return {"rtde": self.host}

    def _spawn(self, target, *args) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept_loop(self, listener: socket.socket, handler) -> None:
        while not self._stopping.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._clients.add(conn)
            threading.Thread(target=self._run_client, args=(handler, conn), daemon=True).start()

    def _run_client(self, handler, conn: socket.socket) -> None:
        try:
            handler(conn)
        except OSError:
            pass  # the client went away, or a fault dropped the connection
        finally:
            with self._lock:
                self._clients.discard(conn)
            _close_quietly(conn)

    def _drop_clients(self) -> None:
        """Close every open client connection abruptly (a network fault, or stop())."""
        with self._lock:
            clients = list(self._clients)
            self._clients.clear()
        for conn in clients:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            _close_quietly(conn)

    # ----------------------------------------------------------------- the control script

    def _tick(self) -> None:
        """Advance the emulated control script one step. Caller holds ``self._lock``."""
        cell = self.cell
        if not self._script_running:
            return
        if cell.protective_stop or cell.emergency_stop or not cell.running:
            self._halt_script()  # a safety stop (or power off) halts the running program
            return
        if self._user_program:
            return  # a user's program runs in its own thread, not the register handshake
        regs = self._registers
        if self._async_move and not cell.is_moving():
            self._async_move = False
            self._write_async_progress(-1)
        cmd = int(regs["input_int_register_0"])
        if cmd == CMD_NO_CMD:
            self._executing = None
            regs["output_int_register_0"] = SCRIPT_READY
            return
        if cmd in _CONTINUOUS_COMMANDS:
            regs["output_int_register_0"] = SCRIPT_READY
            return
        if self._executing is None:
            self._begin(cmd)
            if not self._script_running:
                return
        if self._command_finished():
            regs["output_int_register_0"] = SCRIPT_DONE

    def _begin(self, cmd: int) -> None:
        cell = self.cell
        regs = self._registers
        self._executing = cmd
        self._blocking_move = False
        regs["output_int_register_0"] = SCRIPT_BUSY
        n = cell.count("ur.command")
        faults = cell.faults
        self._command_done_at = time.monotonic() + faults.reply_delay_s(n)
        dropped = n in faults.drop_connection_at
        garbled = not dropped and (n in faults.garble_at or cell.chance(faults.garble_rate))
        if dropped or garbled:
            # The network fails as the command arrives: it is lost, and every connection
            # drops, or every RTDE stream sends a malformed package.
            regs["input_int_register_0"] = CMD_NO_CMD
            regs["output_int_register_0"] = SCRIPT_READY
            self._executing = None
            if dropped:
                threading.Thread(target=self._drop_clients, daemon=True).start()
            else:
                self._malformed += 1
            return
        if cmd == CMD_MOVEJ:
            self._start_move(np.array(self._doubles(0, 6)))
        elif cmd in (CMD_MOVEJ_IK, CMD_MOVEL):
            # A Cartesian target: the controller turns it into joints with its own
            # (factory-calibrated) kinematics, nearest the joints it is at.
            q = cell.controller_ik(ur_pose_to_matrix(self._doubles(0, 6)), cell.joints())
            if q is None:
                self._halt_script()  # URScript: "Inverse kinematics failed", the program stops
                return
            self._start_move(q)
        elif cmd == CMD_GET_FORWARD_KINEMATICS_DEFAULT:
            self._write_doubles(matrix_to_ur_pose(cell.controller_fk()[0]))
        elif cmd == CMD_GET_FORWARD_KINEMATICS_ARGS:
            q = np.array(self._doubles(0, 6))
            T = cell.controller_fk(q[None, :], np.array(self._doubles(6, 12)))[0]
            self._write_doubles(matrix_to_ur_pose(T))
        elif cmd in (CMD_GET_INVERSE_KINEMATICS_ARGS, CMD_GET_INVERSE_KINEMATICS_DEFAULT):
            q_near = np.array(self._doubles(6, 12)) if cmd == CMD_GET_INVERSE_KINEMATICS_ARGS else cell.joints()
            q = cell.controller_ik(ur_pose_to_matrix(self._doubles(0, 6)), q_near)
            if q is None:
                self._halt_script()  # get_inverse_kin raises a runtime error: the script stops
                return
            self._write_doubles(list(q))
        elif cmd == CMD_STOPJ:
            cell.stop()
            if self._async_move:
                self._async_move = False
                self._write_async_progress(-1)
        elif cmd == CMD_STOP_SCRIPT:
            self._halt_script()
        elif cmd == CMD_SET_PAYLOAD:
            mass = float(regs["input_double_register_0"])
            cog = [float(regs[f"input_double_register_{i}"]) for i in (1, 2, 3)]
            if not any(cog):  # the control script keeps the current centre of gravity then
                cog = list(self._payload_cog_flange)
            self._payload_cog_flange = cog
            cell.set_payload(mass, cog)

    def _doubles(self, start: int, stop: int) -> list[float]:
        """``input_double_register_start`` .. ``stop - 1``."""
        return [float(self._registers[f"input_double_register_{i}"]) for i in range(start, stop)]

    def _write_doubles(self, values) -> None:
        """The script's ``pose_to_output_float_registers(0, ...)`` / ``q_to_output_...``."""
        for i, v in enumerate(values):
            self._registers[f"output_double_register_{i}"] = float(v)

    def _start_move(self, q: np.ndarray) -> None:
        """Start the move of MOVEJ / MOVEJ_IK / MOVEL: speed and acceleration in input double
        registers 6 and 7, asynchronous when input int register 1 is 1."""
        regs = self._registers
        speed = float(regs["input_double_register_6"])
        accel = float(regs["input_double_register_7"])
        asynchronous = int(regs["input_int_register_1"]) == 1
        try:
            self.cell.start_move(q, speed, accel)
        except RuntimeError:  # stopped by safety: the program halts
            self._halt_script()
            return
        if asynchronous:
            self._async_move = True
            self._write_async_progress(0)
        else:
            self._blocking_move = True

    def _write_async_progress(self, value: int) -> None:
        """Encode the async status register as the control script does: ``value`` >= 0 is
        the progress of a running operation (0 starts a new one), -1 means finished."""
        self._async_writes = (self._async_writes + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_writes * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._registers["output_int_register_2"] = reg

    def _command_finished(self) -> bool:
        if time.monotonic() < self._command_done_at:
            return False
        return not (self._blocking_move and self.cell.is_moving())

    def _start_script(self) -> None:
        """A program arrived on the script port: play it (unless a safety stop forbids, or
        the arm is not running)."""
        with self._lock:
            cell = self.cell
            if cell.protective_stop or cell.emergency_stop or not cell.running:
                return
            self._script_running = True
            self.cell.program_running = True
            self._executing = None
            self._async_move = False
            self._registers["output_int_register_0"] = SCRIPT_READY
            self._write_async_progress(-1)

    def _halt_script(self) -> None:
        self._script_running = False
        self._user_program = False
        self.cell.program_running = False
        self._executing = None
        self._async_move = False

    # ----------------------------------------------------------------- robot state

    def _values(self, names: list[str]) -> list:
        """The current values of the named RTDE outputs, flattened, ready to pack."""
        with self._lock:
            self._tick()
            now = time.monotonic()
            q = self.cell.joints()
            if now - self._last_q_time > 1e-3:
                self._qd = (q - self._last_q) / (now - self._last_q_time)
                self._last_q, self._last_q_time = q, now
            state = self._state(now, q)
            regs = self._registers
            flat: list = []
            for name in names:
                if name in state:
                    value = state[name]
                elif name in regs:
                    value = regs[name]
                elif name in ("actual_TCP_pose", "target_TCP_pose"):
                    value = self._tcp_pose()
                else:
                    value = _zero(RTDE_TYPES[name])
                if isinstance(value, (list, tuple, np.ndarray)):
                    flat.extend(value)
                else:
                    flat.append(value)
            return flat

    def _state(self, now: float, q: np.ndarray) -> dict:
        cell = self.cell
        safety_bits, safety_mode = SAFETY_BIT_NORMAL, SAFETY_MODE_NORMAL
        if cell.protective_stop:
            safety_bits = SAFETY_BIT_PROTECTIVE_STOPPED | SAFETY_BIT_STOPPED_DUE_TO_SAFETY
            safety_mode = SAFETY_MODE_PROTECTIVE_STOP
        if cell.emergency_stop:
            safety_bits = (
                SAFETY_BIT_EMERGENCY_STOPPED | SAFETY_BIT_ROBOT_EMERGENCY_STOPPED | SAFETY_BIT_STOPPED_DUE_TO_SAFETY
            )
            safety_mode = SAFETY_MODE_ROBOT_EMERGENCY_STOP
        status_bits = ROBOT_STATUS_POWER_ON if cell.powered else 0
        if self._script_running:
            status_bits |= ROBOT_STATUS_PROGRAM_RUNNING
        qd = list(self._qd) if cell.is_moving() else [0.0] * 6
        return {
            "timestamp": now - self._t0,
            "actual_q": list(q),
            "target_q": list(q),
            "actual_qd": qd,
            "target_qd": qd,
            "robot_mode": _robot_mode(cell),
            "joint_mode": [JOINT_MODE_RUNNING] * 6,
            "safety_mode": safety_mode,
            "safety_status": safety_mode,
            "safety_status_bits": safety_bits,
            "robot_status_bits": status_bits,
            "runtime_state": RUNTIME_PLAYING if self._script_running else RUNTIME_STOPPED,
            "speed_scaling": 1.0,
            "target_speed_fraction": 1.0,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0,
            "joint_temperatures": [30.0] * 6,
            "actual_joint_voltage": [48.0] * 6,
            "actual_tool_accelerometer": [0.0, 0.0, 9.81],
            "payload": float(cell.payload[0]),
            "payload_cog": list(self._payload_cog_flange),
        }

    def _tcp_pose(self) -> list[float]:
        """``actual_TCP_pose``: the controller's forward kinematics of the joints it reads (its
        factory calibration), not where the tool truly is."""
        return matrix_to_ur_pose(self.cell.controller_fk()[0])

    # ----------------------------------------------------------------- RTDE server

    def _serve_rtde(self, conn: socket.socket) -> None:
        """One RTDE client: recipe setup, start/pause, input data packages."""
        send_lock = threading.Lock()
        output = {"names": [], "fmt": None, "recipe_id": 0, "frequency_hz": 125.0}
        inputs: dict[int, tuple[list[str], struct.Struct]] = {}
        streaming = threading.Event()

        def send(kind: int, payload: bytes = b"") -> None:
            with send_lock:
                conn.sendall(_HEADER.pack(_HEADER.size + len(payload), kind) + payload)

        for kind, payload in _read_packages(conn):
            if kind == RTDE_REQUEST_PROTOCOL_VERSION:
                (version,) = struct.unpack(">H", payload[:2])
                send(kind, bytes([1 if version in (1, 2) else 0]))
            elif kind == RTDE_GET_URCONTROL_VERSION:
                send(kind, struct.pack(">IIII", *self.version))
            elif kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
                (frequency_hz,) = struct.unpack(">d", payload[:8])
                names = _csv(payload[8:])
                types = [RTDE_TYPES.get(n, "NOT_FOUND") for n in names]
                ok = "NOT_FOUND" not in types and not any(n.startswith("input_") for n in names)
                if ok:
                    output.update(
                        names=names,
                        fmt=struct.Struct(">B" + "".join(_TYPE_FORMAT[t] for t in types)),
                        recipe_id=1,
                        frequency_hz=min(max(frequency_hz, 1.0), self.max_frequency_hz),
                    )
                send(kind, bytes([1 if ok else 0]) + ",".join(types).encode())
            elif kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
                names = _csv(payload)
                types = [RTDE_TYPES.get(n, "NOT_FOUND") if not n.startswith("output_") else "NOT_FOUND" for n in names]
                recipe_id = 0
                if "NOT_FOUND" not in types:
                    recipe_id = len(inputs) + 1  # ur_rtde assumes ids 1, 2, ... per connection
                    fmt = struct.Struct(">" + "".join(_TYPE_FORMAT[t] for t in types))
                    inputs[recipe_id] = (names, fmt)
                send(kind, bytes([recipe_id]) + ",".join(types).encode())
            elif kind == RTDE_CONTROL_PACKAGE_START:
                ok = output["fmt"] is not None
                send(kind, bytes([1 if ok else 0]))
                if ok and not streaming.is_set():
                    streaming.set()
                    threading.Thread(target=self._stream, args=(conn, send, output, streaming), daemon=True).start()
            elif kind == RTDE_CONTROL_PACKAGE_PAUSE:
                streaming.clear()
                send(kind, b"\x01")
            elif kind == RTDE_DATA_PACKAGE:
                self._apply_inputs(payload, inputs)
            elif kind == RTDE_TEXT_MESSAGE:
                pass  # clients may log to the controller; nothing to answer
        streaming.clear()

    def _apply_inputs(self, payload: bytes, inputs: dict) -> None:
        recipe_id = payload[0]
        if recipe_id not in inputs:
            return  # the real controller ignores packages for unknown recipes
        names, fmt = inputs[recipe_id]
        values = fmt.unpack(payload[1 : 1 + fmt.size])
        with self._lock:
            k = 0
            for name in names:
                width = _width(RTDE_TYPES[name])
                self._registers[name] = values[k] if width == 1 else list(values[k : k + width])
                k += width
            self._tick()

    def _stream(self, conn, send, output: dict, streaming: threading.Event) -> None:
        """Send one data package per period until paused or disconnected."""
        period_s = 1.0 / output["frequency_hz"]
        next_t = time.monotonic()
        malformed_sent = self._malformed
        while streaming.is_set() and not self._stopping.is_set():
            values = self._values(output["names"])
            try:
                if malformed_sent < self._malformed:
                    malformed_sent += 1
                    conn.sendall(MALFORMED_PACKAGE)
                send(RTDE_DATA_PACKAGE, output["fmt"].pack(output["recipe_id"], *values))
            except OSError:
                return
            next_t += period_s
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()

    # ----------------------------------------------------------------- dashboard server

    def _serve_dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        reader = conn.makefile("rb")
        for raw in reader:
            command = raw.decode("ascii", "replace").strip()
            delay_s = self.cell.faults.reply_delay_s(None)
            if delay_s:
                time.sleep(delay_s)
            reply = self._dashboard_reply(command)
            conn.sendall((reply + "\n").encode())
            if command == "quit":
                return

    def _dashboard_reply(self, command: str) -> str:
        cell = self.cell
        major, minor, bugfix, build = self.version
        lower = command.lower()
        with self._lock:
            running = self._script_running
            if lower == "polyscopeversion":
                return f"URSoftware {major}.{minor}.{bugfix}.{build} (Mar 22 2022)"
            if lower == "version":
                return f"Version: {major}.{minor}.{bugfix}.{build}"
            if lower == "get serial number":
                return "20185500000"
            if lower == "get robot model":  # e-Series answer without the "e", e.g. "UR5"
                published = cell.factory.published if cell.factory is not None else "ur5e"
                return published.upper().rstrip("E")
            if lower == "is in remote control":
                return "true"
            if lower == "running":
                return f"Program running: {str(running).lower()}"
            if lower == "programstate":
                return "PLAYING <unnamed>" if running else "STOPPED <unnamed>"
            if lower == "robotmode":
                return f"Robotmode: {_ROBOT_MODE_NAMES[_robot_mode(cell)]}"
            if lower in ("safetystatus", "safetymode"):
                word = "Safetystatus" if lower == "safetystatus" else "Safetymode"
                if cell.emergency_stop:
                    return f"{word}: ROBOT_EMERGENCY_STOP"
                return f"{word}: PROTECTIVE_STOP" if cell.protective_stop else f"{word}: NORMAL"
            if lower == "stop":
                self._halt_script()
                return "Stopped"
            if lower == "pause":
                return "Pausing program"
            if lower == "play":
                return "Failed to execute: play"
            if lower == "unlock protective stop":
                if not cell.unlock_protective_stop():
                    return "Cannot unlock protective stop: the robot is not in a protective stop"
                return "Protective stop releasing"
            if lower == "close safety popup":
                return "closing safety popup"
            if lower == "close popup":
                return "closing popup"
            if lower == "power on":
                if not cell.power_on():
                    return "Failed to execute: power on (emergency stop)"
                return "Powering on"
            if lower == "power off":
                cell.power_off()
                self._halt_script()
                return "Powering off"
            if lower == "brake release":
                if not cell.release_brakes():
                    return "Failed to execute: brake release (emergency stop)"
                return "Brake releasing"
            if lower == "sim emergency stop press":
                cell.press_emergency_stop()
                return "Emergency stop pressed (simulator)"
            if lower == "sim emergency stop release":
                cell.release_emergency_stop()
                return "Emergency stop released (simulator)"
            if lower == "quit":
                return "Disconnected"
        return f"could not understand: '{command}'"

    # ----------------------------------------------------------------- script server

    def _serve_script(self, conn: socket.socket) -> None:
        """URScript text in. A complete ``def name(): ... end`` program starts playing.

        The real controller also streams its legacy real-time state out of this port;
        ``ur_rtde`` never reads it, so the fake sends nothing."""
        buffer = b""
        while True:
            data = conn.recv(65536)
            if not data:
                return
            buffer += data
            if _PROGRAM_START.search(buffer) and _PROGRAM_END.search(buffer):
                text, buffer = buffer.decode("utf-8", "replace"), b""
                if is_control_script(text):
                    self._start_script()
                else:
                    self._start_program(text)

    # ----------------------------------------------------------------- a user's program

    def _start_program(self, text: str) -> None:
        """A program other than ``ur_rtde``'s control script arrived: run its moves
        (``fakes.urscript_program``) in a thread of its own, replacing whatever program runs.
        One the fake cannot evaluate does not start (``last_program_error`` says why, as a
        real controller's pop-up would)."""
        try:
            steps = parse_program(text)
        except ProgramError as exc:
            self.last_program_error = str(exc)
            return
        with self._lock:
            cell = self.cell
            if cell.protective_stop or cell.emergency_stop or not cell.running:
                return
            self._halt_script()
            self._program_id += 1
            self._script_running = self._user_program = True
            cell.program_running = True
            self.last_program_error = None
            thread = threading.Thread(target=self._run_program, args=(self._program_id, steps), daemon=True)
        thread.start()

    def _run_program(self, program_id: int, steps: list) -> None:
        """Each move in turn: a pose target through the controller's own inverse kinematics
        (its factory calibration; ``get_inverse_kin``'s ``qnear``, else nearest the joints the
        robot is at, for the active TCP), then the simulated motion to its end."""
        cell = self.cell
        tcp = None
        for step in steps:
            with self._lock:
                if program_id != self._program_id or not self._script_running:
                    return  # stopped (dashboard, safety) or replaced
                if step.kind == "set_tcp":
                    tcp = np.array(step.pose)
                    continue
                if step.pose is not None:
                    q_near = cell.joints() if step.qnear is None else np.array(step.qnear)
                    q = cell.controller_ik(ur_pose_to_matrix(step.pose), q_near, tcp)
                    if q is None:
                        self.last_program_error = f"line {step.line}: inverse kinematics failed (no solution)"
                        self._halt_script()
                        return
                else:
                    q = np.array(step.joints)
                try:
                    cell.start_move(q, max(step.speed, 1e-3), max(step.accel, 1e-3))
                except RuntimeError:  # stopped by safety: the program halts
                    self._halt_script()
                    return
            while cell.is_moving():  # the move's simulated duration (instant at time scale 0)
                if self._stopping.is_set() or program_id != self._program_id:
                    return
                time.sleep(0.001)
        with self._lock:
            if program_id == self._program_id and self._script_running:
                self._halt_script()


_ROBOT_MODE_NAMES = {
    ROBOT_MODE_POWER_OFF: "POWER_OFF",
    ROBOT_MODE_IDLE: "IDLE",
    ROBOT_MODE_RUNNING: "RUNNING",
}


def _robot_mode(cell: SimCell) -> int:
    """UR's robot mode for the arm's power and brakes."""
    if not cell.powered:
        return ROBOT_MODE_POWER_OFF
    return ROBOT_MODE_RUNNING if cell.brakes_released else ROBOT_MODE_IDLE


_PROGRAM_START = re.compile(rb"^def \w+\(\):", re.M)
_PROGRAM_END = re.compile(rb"\nend\s*$")


def _read_packages(conn: socket.socket):
    """Yield ``(type, payload)`` RTDE packages framed by their size field."""
    buffer = b""
    while True:
        while len(buffer) >= _HEADER.size:
            size, kind = _HEADER.unpack_from(buffer)
            if size < _HEADER.size:
                return  # garbage: a real controller drops such a client
            if len(buffer) < size:
                break
            payload, buffer = buffer[_HEADER.size : size], buffer[size:]
            yield kind, payload
        data = conn.recv(65536)
        if not data:
            return
        buffer += data


def _csv(payload: bytes) -> list[str]:
    """Variable names of a setup request; ur_rtde ends the list with a trailing comma."""
    return [name for name in payload.decode("ascii", "replace").split(",") if name]


def _width(rtde_type: str) -> int:
    code = _TYPE_FORMAT[rtde_type]
    return int(code[0]) if code[0].isdigit() else 1


def _zero(rtde_type: str):
    width = _width(rtde_type)
    value = 0.0 if rtde_type.startswith(("DOUBLE", "VECTOR3D", "VECTOR6D")) else 0
    if rtde_type == "BOOL":
        value = False
    return [value] * width if width > 1 else value


def _close_quietly(sock: socket.socket) -> None:
    try:
        sock.close()
    except OSError:
        pass


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, and its keyword arguments from the command line.
CELL_FAKE = {"key": "ur", "order": 10, "cls": UrControllerFake}


def main(argv: list[str] | None = None) -> int:
    """``python -m fakes.ur_controller --truth TRUE.json [--host H]``: serve one controller."""
    from fakes.cell import main as cell_main

    args = list(sys.argv[1:] if argv is None else argv)
    return cell_main([*args, "--only", CELL_FAKE["key"]])


if __name__ == "__main__":
    sys.exit(main())
