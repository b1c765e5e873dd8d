"""A robot over Modbus TCP (pymodbus 3.x): joint readings from the controller's registers and
moves through a register handshake with a program running on the controller.

The default map (``UR_REGISTER_MAP``) is that of a Universal Robots controller's Modbus
server (TCP 502) with ``drivers/urscript/modbus_motion.script`` running on it; addresses are
0-based protocol addresses of holding registers. ``docs/devices/ur.md`` is the reference.

Joint readings: ``joint_angle`` .. +n (UR: 270-275, mrad, unsigned, wrapped into [0, 2 pi))
plus revolution counters ``joint_turns`` .. +n (UR: 320-325, int16), so
``q = turns * 2 pi + angle * joint_angle_scale``. UR's angle registers resolve 1 mrad; with
``joint_urad`` set (``UR_REGISTER_MAP_HIRES``) the readings come instead from the motion
program's int32 microradian copy (160-171), refreshed every controller cycle.

Motion handshake (general-purpose registers, written by this driver unless noted)::

    target .. +2n   target joints, int32 urad, high word first   (UR map: 130-141)
    speed, accel    uint16, mrad/s and mrad/s^2                     (142, 143)
    command, sequence                                               (128, 129)
    status: ack, state, error, heartbeat   written by the program   (150-153)

``read_tcp_pose`` reads UR's TCP-pose registers (400-405: the controller's own forward
kinematics, through its factory calibration, to 0.1 mm and 1 mrad).

1. the driver checks that the robot is not safety-stopped (``protective_stop``,
   ``emergency_stop``: UR 261, 262) and that no move is busy;
2. it writes the target, speed and acceleration, then, in one more request, the command
   (1 MOVEJ, 2 STOP) and a new sequence number (1..65535, never 0);
3. the program sees the new sequence number, copies it to ``ack`` and sets ``state``
   (1 busy; 2 done when ``movej`` returns; 3 error, with ``error`` 1 unknown command,
   2 bad speed/acceleration, 3 refused);
4. the driver polls ``status`` until ``ack`` is its sequence number and ``state`` is done.

Every request is idempotent (a repeated write of the same sequence number starts nothing), so
after a timeout, a garbled reply or a dropped connection the driver reconnects and repeats
the request (``retries`` times) before it raises.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np

from calibration.transforms import homogeneous, rotvec_to_matrix
from drivers.base import KinematicsSource, Robot, RobotState
from drivers.errors import (
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    ProtocolError,
    RobotStoppedError,
)

CMD_MOVEJ, CMD_STOP = 1, 2
STATE_IDLE, STATE_BUSY, STATE_DONE, STATE_ERROR = 0, 1, 2, 3
_ERRORS = {1: "unknown command", 2: "bad speed or acceleration", 3: "the robot refused the move"}
_TWO_PI = 2.0 * math.pi
_MAX_READ = 125  # registers per read request (Modbus limit)


@dataclass(frozen=True, slots=True)
class ModbusRegisterMap:
    """Where a controller keeps what the driver needs: 0-based holding-register addresses
    and the scale of each value (SI unit per count). ``None`` means "not available"."""

    n_joints: int = 6
    joint_angle: int = 270
    joint_angle_scale: float = 1e-3  # rad per count
    joint_angle_signed: bool = False
    joint_turns: int | None = 320  # revolution counters (int16); None: angles are absolute
    joint_urad: int | None = None  # int32 microradians (2 registers per joint), if provided
    protective_stop: int | None = 261
    emergency_stop: int | None = 262
    command: int = 128  # command, then sequence number
    target: int = 130  # int32 per joint, high word first
    target_scale: float = 1e-6  # rad per count
    speed: int = 142
    speed_scale: float = 1e-3  # rad/s per count (uint16)
    accel: int = 143
    accel_scale: float = 1e-3  # rad/s^2 per count (uint16)
    status: int = 150  # ack, state, error, heartbeat
    # UR's TCP pose (the controller's own forward kinematics, robot base frame): x, y, z then
    # rx, ry, rz (rotation vector), int16; None where the controller has no such registers.
    tcp_pose: int | None = 400
    tcp_position_scale: float = 1e-4  # m per count (0.1 mm)
    tcp_rotation_scale: float = 1e-3  # rad per count (mrad)

    def __post_init__(self):
        if self.n_joints < 1:
            raise ValueError(f"n_joints must be positive; got {self.n_joints}")
        for name in ("joint_angle_scale", "target_scale", "speed_scale", "accel_scale"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")


UR_REGISTER_MAP = ModbusRegisterMap()
UR_REGISTER_MAP_HIRES = replace(UR_REGISTER_MAP, joint_urad=160)


def _default_limits() -> tuple[tuple[float, float], ...]:
    return ((-_TWO_PI, _TWO_PI),) * 6


@dataclass(frozen=True, slots=True)
class ModbusRobotConfig:
    """How to reach and drive a robot controller over Modbus TCP.

    ``timeout_s`` bounds every request; ``ack_timeout_s`` how long the controller's program
    may take to acknowledge a command (longer means it is not running); ``heartbeat_timeout_s``
    how long its heartbeat may stand still. ``joint_limits_rad`` has one (lower, upper) pair
    per joint. A move has arrived when the program reports done and every joint reading is
    within ``arrival_tolerance_rad`` of the target (UR's mrad registers: keep it >= 1e-3).
    """

    host: str
    port: int = 502
    device_id: int = 1
    register_map: ModbusRegisterMap = UR_REGISTER_MAP
    timeout_s: float = 1.0
    retries: int = 1
    poll_interval_s: float = 0.005
    ack_timeout_s: float = 1.0
    heartbeat_timeout_s: float = 0.5
    max_speed_rad_s: float = 3.14
    max_accel_rad_s2: float = 40.0
    joint_limits_rad: tuple[tuple[float, float], ...] = field(default_factory=_default_limits)
    arrival_tolerance_rad: float = 2e-3


@dataclass(frozen=True, slots=True)
class _Status:
    ack: int
    state: int
    error: int
    heartbeat: int


class ModbusRobot(Robot):
    """A robot driven through Modbus registers (see the module docstring).

    Thread-safe: ``stop()`` may be called from another thread while ``move_joints`` waits.
    """

    def __init__(self, config: ModbusRobotConfig):
        from pymodbus.client import ModbusTcpClient

        self.config = config
        self.map = config.register_map
        self.n_joints = self.map.n_joints
        if len(config.joint_limits_rad) != self.n_joints:
            raise ValueError(f"joint_limits_rad has {len(config.joint_limits_rad)} pairs for {self.n_joints} joints")
        self.name = f"Modbus robot {config.host}:{config.port}"
        self.reconnects = 0  # how often a request had to reconnect (for diagnostics)
        self._lock = threading.RLock()
        self._closed = False
        self._client = ModbusTcpClient(
            config.host,
            port=config.port,
            timeout=config.timeout_s,
            retries=0,
            reconnect_delay=0,
            reconnect_delay_max=0,
        )
        # last heartbeat seen, and when it last changed (None: it stands still)
        self._heartbeat: tuple[int, float | None] | None = None
        self._stop_sequence = 0
        try:
            self._connect()
            self._sequence = self._read_status().ack
        except BaseException:
            self._client.close()
            raise

    # ----------------------------------------------------------------- Robot

    @property
    def kinematics_source(self) -> KinematicsSource | None:  # type: ignore[override]
        """``tcp_pose`` when the register map has UR's TCP-pose registers."""
        return "tcp_pose" if self.map.tcp_pose is not None else None

    @property
    def joint_resolution_rad(self) -> float:  # type: ignore[override]
        """1 urad from the motion program's registers (``UR_REGISTER_MAP_HIRES``), else the angle
        registers' step (UR: 1 mrad)."""
        return 1e-6 if self.map.joint_urad is not None else self.map.joint_angle_scale

    def read_joints(self) -> np.ndarray:
        """Joint readings (rad), read from the controller by this call."""
        m = self.map
        n = self.n_joints
        if m.joint_urad is not None:
            words = self._read(m.joint_urad, 2 * n)
            return np.array([_int32(words[2 * i], words[2 * i + 1]) for i in range(n)]) * 1e-6
        if m.joint_turns is None:
            return self._angles(self._read(m.joint_angle, n))
        for _ in range(3):  # a joint may cross a revolution between two reads: read again
            turns = self._read(m.joint_turns, n)
            raw = self._read(m.joint_angle, n)
            if self._read(m.joint_turns, n) == turns:
                return self._angles(raw) + _TWO_PI * np.array([_s16(t) for t in turns], dtype=float)
        raise ProtocolError("joint revolution counters keep changing between reads", device=self.name)

    def read_tcp_pose(self) -> np.ndarray:
        """The TCP pose the controller itself computes, ``T_base_tcp`` (4, 4), from its TCP-pose
        registers (UR: 400-405, 0.1 mm and mrad): a UR controller computes it with its factory
        calibration, not the published DH table. ``ValueError`` when the map has none."""
        m = self.map
        if m.tcp_pose is None:
            raise ValueError(f"{self.name}: this register map has no TCP-pose registers")
        words = [_s16(w) for w in self._read(m.tcp_pose, 6)]
        p = np.array(words[:3], dtype=float) * m.tcp_position_scale
        rotvec = np.array(words[3:], dtype=float) * m.tcp_rotation_scale
        return homogeneous(rotvec_to_matrix(rotvec), p)

    def state(self) -> RobotState:
        with self._lock:
            status = self._read_status()
            protective, emergency = self._safety()
            running = self._program_alive(status)
            return RobotState(
                q=self.read_joints(),
                moving=status.state == STATE_BUSY and running and not (protective or emergency),
                protective_stop=protective,
                emergency_stop=emergency,
                program_running=running,
                timestamp_s=time.time(),
            )

    def move_joints(self, q: np.ndarray, *, speed_rad_s: float, accel_rad_s2: float, timeout_s: float = 60.0) -> None:
        """MOVEJ through the handshake; returns once the program reports the move done and
        the joints read within ``arrival_tolerance_rad`` of ``q``."""
        q_target = self._check_move(q, speed_rad_s, accel_rad_s2)
        m = self.map
        with self._lock:
            self._raise_if_stopped()
            status = self._read_status()
            if status.state == STATE_BUSY:
                if not self._program_alive(status):  # halted mid-move (a safety stop, say)
                    raise RobotStoppedError(
                        "the motion program is not running (its heartbeat stands still): power "
                        "the arm on, release its brakes and start the program again",
                        device=self.name,
                    )
                raise DeviceFaultError("a move is still running on the controller; stop() it first", device=self.name)
            counts = [round(v / m.target_scale) for v in q_target]
            words = [w for c in counts for w in _int32_words(c)]
            self._write(m.target, words)
            self._write(m.speed, [round(speed_rad_s / m.speed_scale)])
            self._write(m.accel, [round(accel_rad_s2 / m.accel_scale)])
            sequence = self._send_command(CMD_MOVEJ)
        self._wait_for_move(sequence, q_target, timeout_s)

    def stop(self) -> None:
        """STOP through the handshake and wait for the acknowledgement. Safe when nothing
        moves; a safety-stopped robot is already stopped (the call returns)."""
        with self._lock:
            protective, emergency = self._safety()
            if protective or emergency:
                return
            sequence = self._send_command(CMD_STOP)
            self._stop_sequence = sequence
            deadline = time.monotonic() + self.config.ack_timeout_s
            while self._read_status().ack != sequence:
                if time.monotonic() > deadline:
                    raise RobotStoppedError(
                        "the motion program did not acknowledge STOP: is it running?",
                        device=self.name,
                    )
                time.sleep(self.config.poll_interval_s)

    def reconnect(self) -> None:
        with self._lock:
            self._client.close()
            self._connect()

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._client.close()

    # ----------------------------------------------------------------- handshake

    def _send_command(self, command: int) -> int:
        self._sequence = self._sequence % 0xFFFF + 1
        self._write(self.map.command, [command, self._sequence])
        return self._sequence

    def _wait_for_move(self, sequence: int, q_target: np.ndarray, timeout_s: float) -> None:
        start = time.monotonic()
        acknowledged = False
        while True:
            with self._lock:
                self._raise_if_stopped()
                status = self._read_status()
            if status.ack == sequence:
                acknowledged = True
                if status.state == STATE_DONE:
                    break
                if status.state == STATE_ERROR:
                    raise DeviceFaultError(
                        f"the controller rejected the move: {_ERRORS.get(status.error, 'error')}",
                        device=self.name,
                        code=status.error,
                    )
            elif status.ack == self._stop_sequence:
                raise RobotStoppedError("the move was stopped by stop()", device=self.name)
            elif acknowledged:
                raise RobotStoppedError("another command replaced the move", device=self.name)
            elif time.monotonic() - start > self.config.ack_timeout_s:
                raise RobotStoppedError(
                    f"the motion program did not acknowledge the move within "
                    f"{self.config.ack_timeout_s:g} s: is modbus_motion.script running?",
                    device=self.name,
                )
            if not self._program_alive(status):
                raise RobotStoppedError("the motion program stopped (no heartbeat)", device=self.name)
            if time.monotonic() - start > timeout_s:
                self.stop()
                raise DeviceTimeoutError(
                    f"the move did not finish within {timeout_s:g} s; the robot was stopped",
                    device=self.name,
                )
            time.sleep(self.config.poll_interval_s)
        error = float(np.max(np.abs(self.read_joints() - q_target)))
        if error > self.config.arrival_tolerance_rad:
            raise RobotStoppedError(f"the move ended {error:.3g} rad from its target", device=self.name)

    def _read_status(self) -> _Status:
        return _Status(*self._read(self.map.status, 4))

    def _program_alive(self, status: _Status) -> bool:
        """Whether the program's heartbeat has changed within ``heartbeat_timeout_s``.

        Without a recent change on record, watch it for up to that long. A heartbeat found
        standing still stays "dead" until it changes again."""
        now = time.monotonic()
        timeout_s = self.config.heartbeat_timeout_s
        seen = self._heartbeat
        if seen is not None and seen[0] != status.heartbeat:
            self._heartbeat = (status.heartbeat, now)
            return True
        if seen is not None:
            changed_at = seen[1]
            if changed_at is None:
                return False
            if now - changed_at < timeout_s:
                return True
        deadline = now + timeout_s
        while time.monotonic() < deadline:
            time.sleep(self.config.poll_interval_s)
            heartbeat = self._read_status().heartbeat
            if heartbeat != status.heartbeat:
                self._heartbeat = (heartbeat, time.monotonic())
                return True
        self._heartbeat = (status.heartbeat, None)
        return False

    def _safety(self) -> tuple[bool, bool]:
        m = self.map
        protective = m.protective_stop is not None and self._read(m.protective_stop, 1)[0] != 0
        emergency = m.emergency_stop is not None and self._read(m.emergency_stop, 1)[0] != 0
        return protective, emergency

    def _raise_if_stopped(self) -> None:
        protective, emergency = self._safety()
        if emergency:
            raise RobotStoppedError(
                "the robot is in an emergency stop; once its cause is cleared, release the "
                "emergency stop button, power the arm on, release its brakes and restart the "
                "motion program",
                device=self.name,
            )
        if protective:
            raise RobotStoppedError(
                "the robot is in a protective stop; inspect the cause, unlock it on the teach "
                "pendant and restart the motion program",
                device=self.name,
            )

    def _check_move(self, q, speed_rad_s: float, accel_rad_s2: float) -> np.ndarray:
        n, m = self.n_joints, self.map
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"`q` must be {n} finite joint values (rad); got {q!r}")
        limits = np.asarray(self.config.joint_limits_rad, dtype=float)
        outside = np.flatnonzero((q < limits[:, 0]) | (q > limits[:, 1]))
        if outside.size:
            j = int(outside[0])
            raise ValueError(
                f"joint {j + 1} target {q[j]:.6g} rad is outside its limits "
                f"[{limits[j, 0]:.6g}, {limits[j, 1]:.6g}] rad"
            )
        max_speed = min(self.config.max_speed_rad_s, 0xFFFF * m.speed_scale)
        max_accel = min(self.config.max_accel_rad_s2, 0xFFFF * m.accel_scale)
        if not 0.0 < speed_rad_s <= max_speed:
            raise ValueError(f"speed_rad_s must be in (0, {max_speed:g}]; got {speed_rad_s}")
        if not 0.0 < accel_rad_s2 <= max_accel:
            raise ValueError(f"accel_rad_s2 must be in (0, {max_accel:g}]; got {accel_rad_s2}")
        if np.max(np.abs(q)) / m.target_scale >= 2**31:
            raise ValueError(f"target {q!r} does not fit the int32 target registers")
        return q

    def _angles(self, raw: list[int]) -> np.ndarray:
        m = self.map
        counts = [_s16(v) for v in raw] if m.joint_angle_signed else list(raw)
        q = np.array(counts, dtype=float) * m.joint_angle_scale
        if m.joint_turns is not None and np.any(q >= _TWO_PI + m.joint_angle_scale):
            j = int(np.argmax(q))
            raise ProtocolError(
                f"joint {j + 1} angle register {m.joint_angle + j} holds {raw[j]}, more than one revolution",
                device=self.name,
            )
        return q

    # ----------------------------------------------------------------- transport

    def _connect(self) -> None:
        if self._closed:
            raise DeviceConnectionError("the connection is closed", device=self.name)
        if not self._client.connect():
            raise DeviceConnectionError(
                f"cannot connect to {self.config.host}:{self.config.port} within {self.config.timeout_s:g} s",
                device=self.name,
            )

    def _read(self, address: int, count: int) -> list[int]:
        if not 0 < count <= _MAX_READ:
            raise ValueError(f"cannot read {count} registers in one request")
        response = self._request(
            f"read {count} registers at {address}",
            lambda: self._client.read_holding_registers(address, count=count, device_id=self.config.device_id),
        )
        registers = list(getattr(response, "registers", []))
        if len(registers) != count:
            raise ProtocolError(f"asked for {count} registers at {address}, got {len(registers)}", device=self.name)
        return registers

    def _write(self, address: int, values: list[int]) -> None:
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise ValueError(f"register values must be 0..65535; got {values}")
        self._request(
            f"write {len(values)} registers at {address}",
            lambda: self._client.write_registers(address, values, device_id=self.config.device_id),
        )

    def _request(self, what: str, call):
        """Run one request; reconnect and repeat it on a lost or garbled exchange."""
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        with self._lock:
            for attempt in range(self.config.retries + 1):
                if self._closed:
                    raise DeviceConnectionError("the connection is closed", device=self.name)
                try:
                    if not self._client.connected:
                        self._connect()
                    response = call()
                except ConnectionException as exc:
                    error: Exception = DeviceConnectionError(f"{what}: {exc}", device=self.name)
                except ModbusIOException as exc:
                    if "No response" in str(exc) or "timeout" in str(exc).lower():
                        error = DeviceTimeoutError(
                            f"{what}: no answer within {self.config.timeout_s:g} s",
                            device=self.name,
                        )
                    else:
                        error = ProtocolError(f"{what}: garbled reply ({exc})", device=self.name)
                except DeviceConnectionError as exc:
                    error = exc
                else:
                    if response.isError():
                        code = getattr(response, "exception_code", None)
                        raise ProtocolError(
                            f"{what}: the device answered with Modbus exception",
                            device=self.name,
                            code=code,
                        )
                    return response
                if attempt < self.config.retries:
                    self.reconnects += 1
                    self._client.close()
            raise error


def _s16(value: int) -> int:
    value = int(value) & 0xFFFF
    return value - 0x10000 if value >= 0x8000 else value


def _int32(high: int, low: int) -> int:
    value = ((int(high) & 0xFFFF) << 16) | (int(low) & 0xFFFF)
    return value - 0x100000000 if value >= 0x80000000 else value


def _int32_words(value: int) -> list[int]:
    value = int(value) & 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]
