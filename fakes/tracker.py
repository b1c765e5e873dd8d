"""A simulated laser tracker speaking the line protocol of contracts §8 on TCP.

``MEAS?`` answers the true position of the reflector on the simulated robot
(``cell.target_world()``, the truth model's reflector target at the robot's current joint
state) plus Gaussian noise ``cell.noise.tracker_m`` per axis, in the current ``UNIT:LEN``,
followed by the per-axis standard uncertainty. The tracker frame is the world frame.

Replies (CR LF terminated, one per command; commands are case-insensitive)::

    *IDN?            RECAL,SIM-LT,SN0001,1.0
    UNIT:LEN MM|M|IN OK                      (bad unit: ERR 11,bad argument)
    UNIT:LEN?        MM
    MEAS?            x,y,z,sx,sy,sz          or ERR 20,beam broken / ERR 21,reflector moving
    STAT?            READY | BEAM_BROKEN
    other            ERR 10,unknown command

When a measurement cannot be taken:

- reflector farther than ``cell.tracker_range_m`` from the tracker: ``ERR 20,beam broken``
  and ``STAT?`` says ``BEAM_BROKEN`` while it stays out of range;
- a beam break (``cell.faults.beam_break_at``, counted per ``MEAS?`` with
  ``cell.count("tracker.meas")``, or ``cell.faults.beam_break_rate``): ``ERR 20,beam broken``;
  ``STAT?`` says ``BEAM_BROKEN`` until the next ``MEAS?`` re-acquires the reflector;
- the robot is moving: ``ERR 21,reflector moving``. A real tracker in stationary mode waits
  for the reflector to settle and rejects an unstable reading; the fake refuses rather than
  return a point that belongs to no robot configuration. The beam stays locked (``READY``).

Injected link faults (``cell.faults``, counted per command with ``cell.count("tracker.request")``):
``delay_s`` before every reply (or only those of ``delay_at``), ``garble_at`` /
``garble_rate`` (the reply is corrupted with non-printable bytes), ``drop_connection_at``
(the connection is closed instead of replying).

A stationary measurement takes ``measure_time_s`` of simulated time (wall time
``measure_time_s * cell.time_scale``). The length unit is a setting of the instrument, shared
by all connections; it starts as ``MM``.

Run it alone: ``python -m fakes.tracker --robot ur5e --reflector 0,0,0.05`` prints one JSON
ready line (contracts §7 keys) and serves until interrupted.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from fakes._lineserver import Client, DropConnection, LineServer, garble
from fakes.world import SimCell

UNITS_M = {"MM": 1e-3, "M": 1.0, "IN": 0.0254}
_DECIMALS = {"MM": 6, "M": 9, "IN": 8}  # 1 nm resolution or better


class TrackerFake(LineServer):
    """The tracker of a simulated cell (see the module docstring)."""

    device_name = "tracker"

    def __init__(
        self,
        cell: SimCell,
        host: str = "127.0.0.1",
        port: int = 10001,
        *,
        identity: str = "RECAL,SIM-LT,SN0001,1.0",
        measure_time_s: float = 0.2,
    ):
        super().__init__(host, port)
        self.cell = cell
        self.identity = identity
        self.measure_time_s = measure_time_s
        self.unit = "MM"
        self.beam_broken = False
        self._state_lock = threading.Lock()

    def endpoint(self) -> dict:
        return {"tracker": f"socket://{self.host}:{self.port}"}

    # ----------------------------------------------------------------- protocol

    def handle_line(self, client: Client, line: str) -> None:
        command = line.strip()
        if not command:
            return
        n = self.cell.count("tracker.request")
        faults = self.cell.faults
        if n in faults.drop_connection_at:
            raise DropConnection
        reply = self._reply(command)
        delay_s = faults.reply_delay_s(n)
        if delay_s > 0:
            time.sleep(delay_s)
        if n in faults.garble_at or self.cell.chance(faults.garble_rate):
            reply = garble(reply)
        client.send_line(reply)

    def _reply(self, command: str) -> str:
        upper = command.upper()
        if upper == "*IDN?":
            return self.identity
        if upper == "UNIT:LEN?":
            return self.unit
        if upper.startswith("UNIT:LEN "):
            unit = upper[len("UNIT:LEN ") :].strip()
            if unit not in UNITS_M:
                return "ERR 11,bad argument"
            self.unit = unit
            return "OK"
        if upper == "MEAS?":
            return self._measure()
        if upper == "STAT?":
            with self._state_lock:
                broken = self.beam_broken
            return "BEAM_BROKEN" if broken or not self._in_range() else "READY"
        return "ERR 10,unknown command"

    def _measure(self) -> str:
        k = self.cell.count("tracker.meas")
        faults = self.cell.faults
        if self.cell.time_scale > 0 and self.measure_time_s > 0:
            time.sleep(self.measure_time_s * self.cell.time_scale)
        if k in faults.beam_break_at or self.cell.chance(faults.beam_break_rate) or not self._in_range():
            with self._state_lock:
                self.beam_broken = True
            return "ERR 20,beam broken"
        with self._state_lock:
            self.beam_broken = False
        if self.cell.is_moving():
            return "ERR 21,reflector moving"
        sigma_m = self.cell.noise.tracker_m
        p_m = self.cell.target_world() + self.cell.normal(sigma_m, 3)
        scale = UNITS_M[self.unit]
        decimals = _DECIMALS[self.unit]
        values = [*(p_m / scale), *(np.full(3, sigma_m) / scale)]
        return ",".join(f"{v:.{decimals}f}" for v in values)

    def _in_range(self) -> bool:
        return float(np.linalg.norm(self.cell.target_world())) <= self.cell.tracker_range_m


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, and its keyword arguments from the command line.
CELL_FAKE = {"key": "tracker", "order": 30, "cls": TrackerFake}


def main(argv: list[str] | None = None) -> int:
    from fakes._standalone import run_fake

    return run_fake(TrackerFake, default_port=10001, argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
