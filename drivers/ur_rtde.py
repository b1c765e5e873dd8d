"""Universal Robots robot over RTDE, through the ``ur_rtde`` library (SDU Robotics).

Network: the robot's controller serves RTDE on TCP 30004, the dashboard on 29999 and the
script interface on 30003; ``ur_rtde`` cannot use other ports. On PolyScope 5.6 and later the
robot must be in Remote Control (teach pendant, top right), or ``ur_rtde`` refuses to connect
from any address other than ``127.0.0.1``. ``ur_rtde`` uploads its own control script: this
driver takes control of the robot while it is connected.

Isolation: the ``ur_rtde`` objects live in a worker process (``drivers/ur_rtde_worker.py``).
Its constructors block while holding the GIL, after a lost connection its control interface
(1.6.5) reconnects in an endless loop and can crash its process, and a malformed RTDE package
(a header whose size is smaller than the header) makes it abort; none of this may happen to
the calling process. (Other malformed data packages, of a wrong type, size or recipe,
``ur_rtde`` drops silently: the driver then waits for the next good one.) Every call to the
worker has a timeout; a worker that reports a lost connection, stops answering or dies is
discarded and the call raises ``DeviceConnectionError``. The next ``read_joints``, ``state``
or ``move_joints`` connects a new worker (reconnecting is safe then: no command is in
flight). A move in progress when the connection drops is not re-sent.

Safety and power: ``move_joints`` raises ``RobotStoppedError`` for a protective or emergency
stop, a safety fault, and an arm that is not running (powered off or brakes on, as after an
emergency stop), each message saying what releases it; the driver itself never does. Connecting
does too (the dashboard's ``safetystatus`` and ``robotmode``, asked before ``ur_rtde`` uploads
its control script, which a stopped controller refuses with only "Failed to start control
script").

Before starting a worker the driver probes the controller with a timeout on each port (the
dashboard greeting, the script port, an RTDE handshake up to the first data package), so an
absent or silent controller gives a quick ``DeviceConnectionError``, never a hang.

``ur_rtde`` has wheels for CPython 3.11/3.12 on x86_64 only; elsewhere constructing
``UrRtdeRobot`` raises ``DeviceUnavailableError``.
"""

from __future__ import annotations

import importlib.util
import math
import os
import pickle
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.transforms import homogeneous, rotvec_to_matrix
from drivers.base import KinematicsSource, Robot, RobotState
from drivers.errors import (
    DeviceConnectionError,
    DeviceFaultError,
    DeviceTimeoutError,
    DeviceUnavailableError,
    ProtocolError,
    RobotStoppedError,
)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
N_JOINTS = 6
_TWO_PI = 2.0 * math.pi

# What the receive interface subscribes to (a short recipe keeps both sides light).
RECEIVE_VARIABLES = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "robot_status_bits",
    "runtime_state",
)
# safety_status_bits
_PROTECTIVE_BITS = (1 << 2) | (1 << 4)  # protective stopped, safeguard stopped
_EMERGENCY_BITS = (1 << 5) | (1 << 6) | (1 << 7)  # system / robot / any emergency stop
# safety_mode values
_PROTECTIVE_MODES = {3, 5, 12, 13}  # protective, safeguard, automatic-mode safeguard, 3PE stop
_EMERGENCY_MODES = {6, 7}
_FAULT_MODES = {8, 9}  # violation, fault
# robot_mode: the arm's power; only RUNNING (powered, brakes released) can move
_ROBOT_MODE_RUNNING = 7
_ROBOT_MODE_NAMES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}

# The tool offset forward_kinematics sends when the caller wants none (m, rotation vector).
FK_PROBE_TCP = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)

_WORKER = Path(__file__).with_name("ur_rtde_worker.py")
_FRAME = struct.Struct(">I")


@dataclass(frozen=True, slots=True)
class UrRtdeConfig:
    """How to reach and drive one UR controller over RTDE.

    ``frequency_hz`` is the RTDE output rate of the receive interface (-1: the controller's
    default, 500 Hz on e-Series, 125 Hz on CB3). Speed and acceleration limits are those of
    ``ur_rtde``'s ``moveJ``; ``joint_limits_rad`` (6 pairs) are checked before every move.
    A move has arrived when the controller reports it finished and every joint is within
    ``arrival_tolerance_rad`` of the target. The joint readings come over the receive
    interface's own connection, which may lag the control interface's that reported the end:
    they get ``arrival_grace_s`` of controller time (RTDE timestamps) to show the arrival before
    the move is called short.
    """

    host: str
    frequency_hz: float = -1.0
    connect_timeout_s: float = 15.0
    probe_timeout_s: float = 2.0
    command_timeout_s: float = 5.0
    poll_interval_s: float = 0.002
    max_speed_rad_s: float = 3.14
    max_accel_rad_s2: float = 40.0
    joint_limits_rad: tuple[tuple[float, float], ...] = ((-_TWO_PI, _TWO_PI),) * N_JOINTS
    arrival_tolerance_rad: float = 1e-4
    arrival_grace_s: float = 0.1
    stop_decel_rad_s2: float = 2.0


class UrRtdeRobot(Robot):
    """A UR robot driven with ``ur_rtde``'s ``moveJ``/``stopJ``; joint readings from RTDE.

    Thread-safe: ``stop()`` may be called from another thread while ``move_joints`` waits.
    """

    takes_payload = True  # setPayload
    kinematics_source: KinematicsSource | None = "forward_kinematics"  # getForwardKinematics: get_forward_kin(q)

    n_joints = N_JOINTS

    def __init__(self, config: UrRtdeConfig):
        if importlib.util.find_spec("rtde_control") is None:
            raise DeviceUnavailableError(
                "the ur_rtde package is not installed (wheels exist only for CPython 3.11/3.12 "
                "on x86_64: pip install ur-rtde==1.6.5)",
                device=f"UR {config.host}",
            )
        self.config = config
        self.name = f"UR {config.host} (RTDE)"
        self._lock = threading.RLock()
        self._worker: _Worker | None = None
        self._closed = False
        self._stops = 0  # stop() calls that returned: a move started before one ends at once
        self._connect()

    # ----------------------------------------------------------------- Robot

    def read_joints(self) -> np.ndarray:
        """Joint readings (rad) from an RTDE data package that arrived during this call."""
        return self._fresh_snapshot()["q"]

    def state(self) -> RobotState:
        snap = self._fresh_snapshot()
        return RobotState(
            q=snap["q"],
            moving=bool((snap["program_running"] and snap["async_running"]) or np.max(np.abs(snap["qd"])) > 1e-4),
            protective_stop=_protective(snap),
            emergency_stop=_emergency(snap),
            program_running=bool(snap["program_running"]),
            timestamp_s=float(snap["timestamp_s"]),
        )

    def move_joints(self, q: np.ndarray, *, speed_rad_s: float, accel_rad_s2: float, timeout_s: float = 60.0) -> None:
        """``moveJ`` to ``q`` (6,) rad and wait until it is reached (see ``Robot``)."""
        q_target = self._check_move(q, speed_rad_s, accel_rad_s2)
        with self._lock:
            stops_before = self._stops
            for _ in range(2):  # the script may end just before the move: then once more
                snap = self._fresh_snapshot()
                self._raise_if_stopped(snap)
                if not snap["program_running"]:
                    # The control script ended (Stop on the pendant, or a safety stop that has
                    # since been released): a fresh connection uploads it again.
                    self._reconnect()
                accepted, status_before = self._call(
                    "move", [float(v) for v in q_target], float(speed_rad_s), float(accel_rad_s2)
                )
                if accepted:
                    break
            else:
                raise DeviceFaultError(
                    "the controller did not accept moveJ (its control script is not ready)",
                    device=self.name,
                )
        self._wait_for_move(q_target, status_before, timeout_s, stops_before)

    def forward_kinematics(self, q: np.ndarray, tcp_offset: np.ndarray | None = None) -> np.ndarray:
        """The controller's own forward kinematics: ``T_base_tcp`` (N, 4, 4) for readings ``q``
        (N, 6) rad, from ``getForwardKinematics(q, tcp_offset)``, which the controller's script
        answers with ``get_forward_kin``, through its factory calibration (not the published
        DH table). ``tcp_offset``: a UR pose (m, rotation vector), default none (the flange).
        Nothing moves."""
        q = np.asarray(q, dtype=float).reshape(-1, N_JOINTS)
        if not np.all(np.isfinite(q)):
            raise ValueError("`q` must be finite joint angles (rad)")
        tcp = np.zeros(6) if tcp_offset is None else np.asarray(tcp_offset, dtype=float).reshape(6)
        # ur_rtde 1.6.5 does not send an all-zero tool offset (it sends q alone), and the control
        # script then reads whatever the last command left in input registers 6-11 (a moveJ's
        # speed and acceleration: metres of "offset"). A known offset is always sent instead,
        # and taken off again.
        sent = tcp if np.any(tcp != 0.0) else np.array(FK_PROBE_TCP)
        poses = self._call(
            "forward_kinematics",
            q.tolist(),
            [float(v) for v in sent],
            timeout_s=self.config.command_timeout_s + 0.1 * len(q),
        )
        T_sent, T_tcp = ur_poses_to_matrices(np.stack([sent, tcp]))
        return ur_poses_to_matrices(np.asarray(poses, dtype=float)) @ np.linalg.inv(T_sent) @ T_tcp

    def stop(self) -> None:
        """``stopJ``: decelerate every joint to zero (at ``stop_decel_rad_s2``). ``stopJ`` is sent
        synchronously: it returns once the joints stand still. A move in progress then raises
        ``RobotStoppedError`` at once (without waiting for its arrival, as it will not come)."""
        with self._lock:
            self._call("stop", float(self.config.stop_decel_rad_s2))
            self._stops += 1

    def set_payload(self, mass_kg: float, cog_m) -> None:
        """``setPayload``: the mounted payload (kg) and its centre of gravity (3,) m from the
        tool flange (the control script's ``set_payload``; an all-zero centre of gravity keeps the
        current one, as the script does)."""
        cog = [float(v) for v in np.asarray(cog_m, dtype=float).reshape(3)]
        if not (np.isfinite(mass_kg) and mass_kg >= 0 and np.all(np.isfinite(cog))):
            raise ValueError(f"payload: expected a mass >= 0 kg and a finite centre of gravity, got {mass_kg}, {cog}")
        with self._lock:
            if not self._call("set_payload", float(mass_kg), cog):
                raise DeviceFaultError("the controller did not accept setPayload", device=self.name)

    def reconnect(self) -> None:
        """Drop the connection and connect again (uploads the control script again)."""
        with self._lock:
            self._reconnect()

    def close(self) -> None:
        """Stop the control script (``stopScript``) and disconnect. Idempotent."""
        with self._lock:
            self._closed = True
            worker, self._worker = self._worker, None
            if worker is not None:
                worker.close(timeout_s=self.config.command_timeout_s)

    # ----------------------------------------------------------------- internals

    def _connect(self) -> None:
        probe_controller(self.config.host, self.config.probe_timeout_s)
        # A safety-stopped (or powered-off) controller refuses ur_rtde's control script, which
        # then reports only "Failed to start control script" after its timeout: ask the
        # dashboard first and say which stop holds the robot and what releases it.
        stop = dashboard_stop(self.config.host, self.config.probe_timeout_s)
        if stop is not None:
            raise stop
        worker = _Worker(self.name)
        try:
            worker.call(
                "connect",
                self.config.host,
                float(self.config.frequency_hz),
                list(RECEIVE_VARIABLES),
                timeout_s=self.config.connect_timeout_s,
            )
        except BaseException:
            worker.kill()
            raise
        self._worker = worker

    def _reconnect(self) -> None:
        if self._worker is not None:
            self._worker.kill()
            self._worker = None
        self._connect()

    def _call(self, op: str, *args, timeout_s: float | None = None):
        """One operation in the worker; (re)connects first if there is no worker."""
        with self._lock:
            if self._closed:
                raise DeviceConnectionError("the robot connection is closed", device=self.name)
            if self._worker is None:
                self._connect()
            worker = self._worker
            assert worker is not None  # _connect() starts one or raises
            try:
                timeout_s = timeout_s or self.config.command_timeout_s
                return worker.call(op, *args, timeout_s=timeout_s)
            except (DeviceConnectionError, DeviceTimeoutError):
                worker.kill()
                self._worker = None
                raise

    def _fresh_snapshot(self) -> dict:
        period_s = 1.0 / self.config.frequency_hz if self.config.frequency_hz > 0 else 0.008
        snap = self._call("fresh_snapshot", max(20 * period_s, 0.2))
        snap["q"] = np.asarray(snap["q"], dtype=float)
        snap["qd"] = np.asarray(snap["qd"], dtype=float)
        return snap

    def _check_move(self, q, speed_rad_s: float, accel_rad_s2: float) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise ValueError(f"`q` must be 6 finite joint angles (rad); got {q!r}")
        limits = np.asarray(self.config.joint_limits_rad, dtype=float)
        outside = np.flatnonzero((q < limits[:, 0]) | (q > limits[:, 1]))
        if outside.size:
            j = int(outside[0])
            raise ValueError(
                f"joint {j + 1} target {q[j]:.6g} rad is outside its limits "
                f"[{limits[j, 0]:.6g}, {limits[j, 1]:.6g}] rad"
            )
        if not 0.0 < speed_rad_s <= self.config.max_speed_rad_s:
            raise ValueError(f"speed_rad_s must be in (0, {self.config.max_speed_rad_s:g}]; got {speed_rad_s}")
        if not 0.0 < accel_rad_s2 <= self.config.max_accel_rad_s2:
            raise ValueError(f"accel_rad_s2 must be in (0, {self.config.max_accel_rad_s2:g}]; got {accel_rad_s2}")
        return q

    def _wait_for_move(self, q_target: np.ndarray, status_before: int, timeout_s: float, stops_before: int) -> None:
        """Poll until the asynchronous move has finished, a safety stop, a ``stop()`` or the timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            snap = self._call("snapshot")
            self._raise_if_stopped(snap)
            if self._stops != stops_before:
                # stop() returned (the joints stand still): the move is over now. Waiting for its
                # end to be reported and for the arrival grace below cost an abort 0.1 s or more.
                error = float(np.max(np.abs(np.asarray(snap["q"], dtype=float) - q_target)))
                if error > self.config.arrival_tolerance_rad:
                    raise RobotStoppedError(
                        f"the move was stopped by stop() {error:.3g} rad from its target", device=self.name
                    )
                return
            if not snap["program_running"]:
                # The receive stream may lag the control stream: look at fresh safety data.
                self._raise_if_stopped(self._fresh_snapshot())
                raise RobotStoppedError("the control script stopped during the move", device=self.name)
            if snap["async_status"] != status_before and not snap["async_running"]:
                break  # a new asynchronous operation has started and finished
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceTimeoutError(
                    f"the move did not finish within {timeout_s:g} s; the robot was stopped",
                    device=self.name,
                )
            time.sleep(self.config.poll_interval_s)
        snap = self._fresh_snapshot()
        self._raise_if_stopped(snap)
        error = float(np.max(np.abs(snap["q"] - q_target)))
        # A package that arrived after the end was reported may still have been sampled before
        # it (the receive connection lagging, e.g. a loaded computer): wait for packages sampled
        # up to arrival_grace_s later, by the controller's clock, before calling the move short.
        settled_by = snap["timestamp_s"] + self.config.arrival_grace_s
        while error > self.config.arrival_tolerance_rad and snap["timestamp_s"] < settled_by:
            snap = self._fresh_snapshot()
            self._raise_if_stopped(snap)
            error = float(np.max(np.abs(snap["q"] - q_target)))
        if error > self.config.arrival_tolerance_rad:
            raise RobotStoppedError(
                f"the move ended {error:.3g} rad from its target (stopped before arriving)",
                device=self.name,
            )

    def _raise_if_stopped(self, snap: dict) -> None:
        if _emergency(snap):
            raise RobotStoppedError(EMERGENCY_STOP_MESSAGE, device=self.name, code=int(snap["safety_mode"]))
        if _protective(snap):
            raise RobotStoppedError(PROTECTIVE_STOP_MESSAGE, device=self.name, code=int(snap["safety_mode"]))
        if int(snap["safety_mode"]) in _FAULT_MODES:
            raise RobotStoppedError(
                "the robot's safety system reports a violation or fault",
                device=self.name,
                code=int(snap["safety_mode"]),
            )
        mode = int(snap["robot_mode"])
        if mode != _ROBOT_MODE_RUNNING:
            raise RobotStoppedError(
                not_running_message(_ROBOT_MODE_NAMES.get(mode, str(mode))), device=self.name, code=mode
            )


# What stops the robot and what releases it, in the technician's words (the driver never does).
EMERGENCY_STOP_MESSAGE = (
    "the robot is in an emergency stop; once its cause is cleared, release the emergency stop "
    "button, then power the arm on and release its brakes (teach pendant, or dashboard 'close "
    "safety popup', 'power on', 'brake release'), then resume"
)
PROTECTIVE_STOP_MESSAGE = (
    "the robot is in a protective stop; inspect the cause, then unlock it on the teach pendant "
    "(or dashboard 'unlock protective stop'), then resume"
)


def not_running_message(mode_name: str) -> str:
    return (
        f"the arm is not running (robot mode {mode_name}): power it on and release its brakes "
        "(teach pendant, or dashboard 'power on', 'brake release'), then resume"
    )


def ur_poses_to_matrices(poses: np.ndarray) -> np.ndarray:
    """UR poses ``[x, y, z, rx, ry, rz]`` (N, 6) (m, rotation vector in rad) -> (N, 4, 4)."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 6)
    return homogeneous(rotvec_to_matrix(poses[:, 3:]), poses[:, :3])


def _protective(snap: dict) -> bool:
    return bool(snap["safety_status_bits"] & _PROTECTIVE_BITS) or (int(snap["safety_mode"]) in _PROTECTIVE_MODES)


def _emergency(snap: dict) -> bool:
    return bool(snap["safety_status_bits"] & _EMERGENCY_BITS) or (int(snap["safety_mode"]) in _EMERGENCY_MODES)


# --------------------------------------------------------------------------- the worker


class _Worker:
    """The worker process and its framed pickle protocol, with a timeout on every call."""

    def __init__(self, device: str):
        self.device = device
        self.process = subprocess.Popen(
            [sys.executable, str(_WORKER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            bufsize=0,
        )
        # both pipes exist (stdin and stdout are PIPE): typed as such, once
        assert self.process.stdin is not None and self.process.stdout is not None
        self.stdin, self.stdout = self.process.stdin, self.process.stdout

    def call(self, op: str, *args, timeout_s: float):
        data = pickle.dumps((op, args))
        try:
            self.stdin.write(_FRAME.pack(len(data)) + data)
            self.stdin.flush()
        except OSError as exc:
            raise DeviceConnectionError(self._ended(op), device=self.device) from exc
        deadline = time.monotonic() + timeout_s
        (size,) = _FRAME.unpack(self._read(_FRAME.size, deadline, op, timeout_s))
        reply = pickle.loads(self._read(size, deadline, op, timeout_s))
        lost = reply[-1]
        if lost is not None:
            raise DeviceConnectionError(f"connection to the controller lost: {lost}", device=self.device)
        if reply[0] == "ok":
            return reply[1]
        _, kind, message, _ = reply
        if kind == "value":
            raise ValueError(f"{self.device}: {message}")
        if kind == "timeout":
            raise DeviceTimeoutError(message, device=self.device)
        if op == "connect" or kind == "connection":
            raise DeviceConnectionError(f"{op}: {message}", device=self.device)
        raise DeviceFaultError(f"{op}: {message}", device=self.device)

    def _read(self, n: int, deadline: float, op: str, timeout_s: float) -> bytes:
        fd = self.stdout.fileno()
        data = b""
        while len(data) < n:
            remaining = deadline - time.monotonic()
            ready, _, _ = select.select([fd], [], [], max(remaining, 0.0))
            if not ready:
                raise DeviceTimeoutError(f"ur_rtde did not complete {op!r} within {timeout_s:g} s", device=self.device)
            chunk = os.read(fd, n - len(data))
            if not chunk:
                raise DeviceConnectionError(self._ended(op), device=self.device)
            data += chunk
        return data

    def _ended(self, op: str) -> str:
        """Why the worker went away during ``op``, for the error message."""
        try:
            code = self.process.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return f"the ur_rtde worker closed its pipes during {op!r}"
        if code == -signal.SIGABRT:
            how = (
                "aborted (ur_rtde aborts its process on what it cannot handle, such as a "
                "malformed RTDE package from the controller)"
            )
        elif code < 0:
            how = f"was killed by signal {-code} ({signal.strsignal(-code)})"
        else:
            how = f"exited with code {code}"
        return f"the ur_rtde worker {how} during {op!r}; the next call starts a new one"

    def close(self, timeout_s: float) -> None:
        try:
            self.call("close", timeout_s=timeout_s)
        except (DeviceConnectionError, DeviceTimeoutError, DeviceFaultError):
            pass  # the controller is gone or broken: nothing left to release
        self.kill()

    def kill(self) -> None:
        """End the worker at once (its connections close with it)."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        for stream in (self.stdin, self.stdout):
            try:
                stream.close()
            except OSError:
                pass


# --------------------------------------------------------------------------- probing


def probe_controller(host: str, timeout_s: float) -> str:
    """Check, with ``timeout_s`` per step, that a UR controller answers on all three ports.

    Returns the PolyScope version string. Raises ``DeviceConnectionError`` (nothing there),
    ``DeviceTimeoutError`` (something there that does not answer), ``ProtocolError`` (not a UR
    controller) or ``DeviceFaultError`` (a PolyScope 5 robot in local control).
    """
    device = f"UR {host}"
    version = _probe_dashboard(host, timeout_s, device)
    with _connect(host, SCRIPT_PORT, timeout_s, device, "script"):
        pass
    _probe_rtde(host, timeout_s, device)
    return version


def dashboard_query(host: str, command: str, timeout_s: float = 2.0) -> str:
    """One dashboard command's answer line (e.g. ``get robot model`` -> ``UR5``)."""
    device = f"UR {host}"
    with _connect(host, DASHBOARD_PORT, timeout_s, device, "dashboard") as sock:
        reader = sock.makefile("rb")
        try:
            reader.readline()  # greeting
            sock.sendall(command.encode() + b"\n")
            line = reader.readline()
        except TimeoutError as exc:
            raise DeviceTimeoutError(
                f"the dashboard did not answer {command!r} within {timeout_s:g} s", device=device
            ) from exc
        except OSError as exc:
            raise DeviceConnectionError(f"dashboard: {exc}", device=device) from exc
    return line.decode("ascii", "replace").strip()


def _connect(host: str, port: int, timeout_s: float, device: str, what: str) -> socket.socket:
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except TimeoutError as exc:
        raise DeviceConnectionError(
            f"no answer from the {what} port {port} within {timeout_s:g} s", device=device
        ) from exc
    except OSError as exc:
        raise DeviceConnectionError(
            f"cannot connect to the {what} port {port}: {exc.strerror or exc}", device=device
        ) from exc
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _probe_dashboard(host: str, timeout_s: float, device: str) -> str:
    with _connect(host, DASHBOARD_PORT, timeout_s, device, "dashboard") as sock:
        reader = sock.makefile("rb")

        def ask(command: str | None) -> str:
            try:
                if command is not None:
                    sock.sendall(command.encode() + b"\n")
                line = reader.readline()
            except TimeoutError as exc:
                raise DeviceTimeoutError(
                    f"the dashboard did not answer {command or 'the connection'!r} within {timeout_s:g} s",
                    device=device,
                ) from exc
            except OSError as exc:
                raise DeviceConnectionError(f"dashboard: {exc}", device=device) from exc
            return line.decode("ascii", "replace").strip()

        greeting = ask(None)
        if "Universal Robots Dashboard Server" not in greeting:
            raise ProtocolError(
                f"port {DASHBOARD_PORT} is not a UR dashboard server (greeting {greeting!r})",
                device=device,
            )
        version = ask("PolyscopeVersion")
        match = re.search(r"(\d+)\.(\d+)\.\d+", version)
        if (
            match
            and int(match.group(1)) >= 5
            and int(match.group(2)) > 5
            and ask("is in remote control").lower() == "false"
        ):
            raise DeviceFaultError(
                "the robot is in Local Control: switch it to Remote Control on the teach "
                "pendant (PolyScope 5.6 and later)",
                device=device,
            )
        return version


def dashboard_stop(host: str, timeout_s: float) -> RobotStoppedError | None:
    """What keeps the robot from moving, asked of the dashboard (``safetystatus``, PolyScope
    3.11 / 5.4 and later, else ``safetymode``; ``robotmode``): a ``RobotStoppedError`` saying
    what releases it, or ``None`` (running, or a controller that does not say)."""
    device = f"UR {host}"
    with _connect(host, DASHBOARD_PORT, timeout_s, device, "dashboard") as sock:
        reader = sock.makefile("rb")

        def ask(command: str | None) -> str:
            try:
                if command is not None:
                    sock.sendall(command.encode() + b"\n")
                return reader.readline().decode("ascii", "replace").strip()
            except OSError as exc:  # timeouts included
                raise DeviceConnectionError(f"dashboard: {exc}", device=device) from exc

        ask(None)  # greeting
        safety = ask("safetystatus")
        if ":" not in safety:  # "could not understand" on older controllers
            safety = ask("safetymode")
        status = safety.partition(":")[2].strip().upper()
        if "EMERGENCY" in status:
            return RobotStoppedError(EMERGENCY_STOP_MESSAGE, device=device)
        if status in (
            "PROTECTIVE_STOP",
            "SAFEGUARD_STOP",
            "AUTOMATIC_MODE_SAFEGUARD_STOP",
            "SYSTEM_THREE_POSITION_ENABLING_STOP",
        ):
            return RobotStoppedError(PROTECTIVE_STOP_MESSAGE, device=device)
        if status in ("VIOLATION", "FAULT"):
            return RobotStoppedError("the robot's safety system reports a violation or fault", device=device)
        mode = ask("robotmode").partition(":")[2].strip().upper()
        if mode and mode != "RUNNING" and mode in _ROBOT_MODE_NAMES.values():
            return RobotStoppedError(not_running_message(mode), device=device)
    return None


def _probe_rtde(host: str, timeout_s: float, device: str) -> None:
    """RTDE handshake up to the first data package: version 2, one-variable recipe, start."""
    header = struct.Struct(">HB")
    with _connect(host, RTDE_PORT, timeout_s, device, "RTDE") as sock:

        def send(kind: str, payload: bytes = b"") -> None:
            sock.sendall(header.pack(header.size + len(payload), ord(kind)) + payload)

        def receive(kind: str) -> bytes:
            while True:
                size, got = header.unpack(_recv_exact(sock, header.size, device, timeout_s))
                if size < header.size:
                    raise ProtocolError(f"RTDE package of size {size}", device=device)
                payload = _recv_exact(sock, size - header.size, device, timeout_s)
                if got == ord(kind):
                    return payload
                if got not in (ord("M"), ord("U")):  # text messages and stray data may come
                    raise ProtocolError(f"RTDE: expected a {kind!r} package, got type {got}", device=device)

        send("V", struct.pack(">H", 2))
        if receive("V")[:1] != b"\x01":
            raise ProtocolError("the controller refused RTDE protocol version 2", device=device)
        send("O", struct.pack(">d", 125.0) + b"timestamp")
        if receive("O")[:1] in (b"", b"\x00"):
            raise ProtocolError("the controller refused an RTDE output recipe", device=device)
        send("S")
        if receive("S")[:1] != b"\x01":
            raise ProtocolError("the controller refused to start RTDE streaming", device=device)
        receive("U")
        send("P")


def _recv_exact(sock: socket.socket, n: int, device: str, timeout_s: float) -> bytes:
    data = b""
    while len(data) < n:
        try:
            chunk = sock.recv(n - len(data))
        except TimeoutError as exc:
            raise DeviceTimeoutError(f"RTDE handshake: no answer within {timeout_s:g} s", device=device) from exc
        except OSError as exc:
            raise DeviceConnectionError(f"RTDE handshake: {exc}", device=device) from exc
        if not chunk:
            raise DeviceConnectionError("RTDE handshake: the controller closed the connection", device=device)
        data += chunk
    return data
