"""The process that hosts the ``ur_rtde`` client objects for ``drivers.ur_rtde``.

Run as a script (``python ur_rtde_worker.py``) by ``UrRtdeRobot``; it imports nothing of ours.
``ur_rtde`` 1.6.5 is kept out of the calling process because

- its constructors block on sockets while holding the GIL (a silent controller freezes every
  thread of the process, timeouts included);
- after a lost connection its control interface reconnects in an endless loop from its
  receive thread (``should_reconnect`` is never reset) and can crash the process;
- it writes diagnostics straight to file descriptors 1 and 2.

Protocol: frames of a 4-byte big-endian length and a pickle, requests on stdin, replies on
the original stdout. A request is ``(op, args)``; a reply is ``("ok", result, lost)`` or
``("error", kind, message, lost)`` where ``kind`` is ``"connection"``, ``"timeout"``,
``"value"`` or ``"runtime"`` and ``lost`` is the first line ``ur_rtde`` printed about a lost
connection since the worker started (else ``None``): the caller must then discard this worker.
Everything ``ur_rtde`` prints is captured (and dropped, except the first line about a lost
connection).
"""

from __future__ import annotations

import os
import pickle
import struct
import sys
import threading
import time

_FRAME = struct.Struct(">I")
_LOSS_MARKERS = (
    "Could not receive data",
    "Robot closed the connection",
    "Reconnecting",
    "Lost connection",
    "boost system Exception",
    "Robot is disconnected",
)


class _Capture:
    """Everything written to fds 1 and 2 goes through a pipe read by a thread, which keeps
    the first line that reports a lost connection."""

    def __init__(self) -> None:
        self.lost: str | None = None
        read_fd, write_fd = os.pipe()
        os.dup2(write_fd, 1)
        os.dup2(write_fd, 2)
        os.close(write_fd)
        threading.Thread(target=self._read, args=(read_fd,), daemon=True).start()

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", errors="replace") as stream:
            for line in stream:
                line = line.strip()
                if self.lost is None and any(m in line for m in _LOSS_MARKERS):
                    self.lost = line


class _Session:
    """The receive and control interfaces of one controller, and the operations on them."""

    def __init__(self):
        self.receive = None
        self.control = None

    def connect(self, host: str, frequency_hz: float, variables: list[str]) -> dict:
        import rtde_control
        import rtde_receive

        self.receive = rtde_receive.RTDEReceiveInterface(host, frequency_hz, variables)
        self.control = rtde_control.RTDEControlInterface(host)
        return self.snapshot()

    def snapshot(self) -> dict:
        """The receive interface's latest state, and the control script's async status."""
        r, c = self.receive, self.control
        status = c.getAsyncOperationProgressEx()
        robot_status_bits = r.getRobotStatus()
        return {
            "timestamp_s": r.getTimestamp(),
            "q": list(r.getActualQ()),
            "qd": list(r.getActualQd()),
            "safety_status_bits": r.getSafetyStatusBits(),
            "safety_mode": r.getSafetyMode(),
            "robot_mode": r.getRobotMode(),
            "robot_status_bits": robot_status_bits,
            "runtime_state": r.getRuntimeState(),
            "program_running": bool(robot_status_bits & 2),  # bit 1: program running
            "async_status": status.value(),
            "async_running": status.isAsyncOperationRunning(),
            "connected": r.isConnected() and c.isConnected(),
        }

    def fresh_snapshot(self, timeout_s: float) -> dict:
        """A snapshot from a data package that arrived after this call began."""
        t0 = self.receive.getTimestamp()
        deadline = time.monotonic() + timeout_s
        while self.receive.getTimestamp() <= t0:
            if not self.receive.isConnected():
                raise ConnectionError("the RTDE receive connection is closed")
            if time.monotonic() > deadline:
                raise TimeoutError(f"no new RTDE data package within {timeout_s:g} s")
            time.sleep(0.0005)
        return self.snapshot()

    def move(self, q: list[float], speed: float, accel: float) -> tuple[bool, int]:
        """Start an asynchronous moveJ; returns (accepted, async status before the move)."""
        before = self.control.getAsyncOperationProgressEx().value()
        return bool(self.control.moveJ(q, speed, accel, True)), before

    def forward_kinematics(self, qs: list[list[float]], tcp_offset: list[float]) -> list[list[float]]:
        """``getForwardKinematics(q, tcp_offset)`` for each q (the controller's own kinematics)."""
        poses = []
        for q in qs:
            pose = list(self.control.getForwardKinematics(q, tcp_offset))
            if len(pose) != 6:  # ur_rtde returns [] when its script did not answer
                raise RuntimeError("getForwardKinematics got no answer (is the control script running?)")
            poses.append(pose)
        return poses

    def stop(self, accel: float) -> None:
        self.control.stopJ(accel, False)

    def set_payload(self, mass: float, cog: list[float]) -> bool:
        return bool(self.control.setPayload(mass, cog))

    def close(self) -> None:
        """End the control script. The worker then exits, which closes every connection
        (``disconnect()`` would do the same and then sleep 0.5 s per interface)."""
        if self.control is not None and self.control.isConnected():
            self.control.stopScript()


def _error_kind(exc: BaseException) -> str:
    if isinstance(exc, ConnectionError):
        return "connection"
    if isinstance(exc, TimeoutError):
        return "timeout"
    if isinstance(exc, (ValueError, TypeError)):
        return "value"
    return "runtime"


def _read_exact(stream, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = stream.read(n - len(data))
        if not chunk:
            raise EOFError
        data += chunk
    return data


def main() -> int:
    requests = sys.stdin.buffer
    replies = os.fdopen(os.dup(1), "wb")
    capture = _Capture()
    session = _Session()
    while True:
        try:
            (size,) = _FRAME.unpack(_read_exact(requests, _FRAME.size))
            op, args = pickle.loads(_read_exact(requests, size))
        except EOFError:
            return 0  # the driver went away
        try:
            result = getattr(session, op)(*args)
            reply: tuple = ("ok", result, capture.lost)
        except Exception as exc:  # noqa: BLE001 - every failure goes back to the driver, never kills the worker
            message = str(exc) or type(exc).__name__
            reply = ("error", _error_kind(exc), message, capture.lost)
        data = pickle.dumps(reply)
        replies.write(_FRAME.pack(len(data)) + data)
        replies.flush()
        if op == "close":
            os._exit(0)  # skip ur_rtde's destructors: they disconnect again, with sleeps


if __name__ == "__main__":
    sys.exit(main())
