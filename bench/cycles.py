"""Benchmark of move-and-measure cycles (issue "Device drivers", target: with time scale 0,
100 move-and-measure cycles through RTDE and the tracker in under 10 s).

One simulated cell (``recal fake-cell``, time scale 0: a move takes no simulated time, so what
is measured is the software on both sides of the wires) on its own loopback address. Two
set-ups run the same 100 joint targets, side by side in this one run:

- ``recal drivers``: ``UrRtdeRobot.move_joints`` (``ur_rtde`` in the driver's supervised worker
  process, the arrival check on a fresh RTDE package) then ``LineTracker.measure`` (``MEAS?``
  through ``serial_for_url``), as a pose session does;
- ``bare libraries`` (the baseline): ``ur_rtde``'s ``RTDEControlInterface.moveJ`` (blocking)
  in this process, then ``RTDEReceiveInterface.getActualQ`` polled until it shows the arrival,
  and ``MEAS?`` written and read on a raw ``serial_for_url`` port: the least any client of
  these wires can do (no safety checks, no timeouts, no isolation from ``ur_rtde``).

Each set-up also reports its connect time (``ur_rtde`` uploads its control script), the
per-cycle median and 95th percentile, and checks that every cycle arrived (joints within
1e-4 rad of the target) and measured a point.

Run: ``python bench/cycles.py`` (about 15 s); ``--cycles N``, ``--host 127.0.4.1``.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration import robots
from calibration.simulate import perturbed
from service.files import save_model
from service.processes import start_fake_cell


def joint_targets(n: int, seed: int = 3) -> np.ndarray:
    """``n`` configurations of a UR10e well inside its limits (rad)."""
    rng = np.random.default_rng(seed)
    lo = np.deg2rad([-170, -150, -150, -170, -150, -170])
    hi = np.deg2rad([170, -30, 150, 170, 150, 170])
    return rng.uniform(lo, hi, size=(n, 6))


def run_drivers(endpoint: dict, targets: np.ndarray) -> dict:
    from drivers.tracker import LineTracker, TrackerConfig
    from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

    t0 = time.perf_counter()
    robot = UrRtdeRobot(UrRtdeConfig(host=endpoint["rtde"]))
    tracker = LineTracker(TrackerConfig(url=endpoint["tracker"]))
    connect_s = time.perf_counter() - t0
    cycles, worst = [], 0.0
    try:
        for q in targets:
            c0 = time.perf_counter()
            robot.move_joints(q, speed_rad_s=1.0, accel_rad_s2=1.4)
            m = tracker.measure()
            cycles.append(time.perf_counter() - c0)
            worst = max(worst, float(np.max(np.abs(robot.read_joints() - q))))
            assert np.all(np.isfinite(m.p_world))
    finally:
        tracker.close()
        robot.close()
    return {"connect_s": connect_s, "cycles_s": cycles, "worst_arrival_rad": worst}


def run_bare(endpoint: dict, targets: np.ndarray) -> dict:
    import rtde_control
    import rtde_receive
    import serial

    t0 = time.perf_counter()
    receive = rtde_receive.RTDEReceiveInterface(endpoint["rtde"])
    control = rtde_control.RTDEControlInterface(endpoint["rtde"])
    port = serial.serial_for_url(endpoint["tracker"], timeout=2.0)
    connect_s = time.perf_counter() - t0
    cycles, worst = [], 0.0
    try:
        for q in targets:
            c0 = time.perf_counter()
            if not control.moveJ(list(q), 1.0, 1.4, False):
                raise RuntimeError("moveJ refused")
            # moveJ returns when the controller says the move is done; the receive stream
            # shows the arrival a few packages later: measure only once it does.
            deadline = time.perf_counter() + 1.0
            while (err := float(np.max(np.abs(np.array(receive.getActualQ()) - q)))) > 1e-4:
                if time.perf_counter() > deadline:
                    break
                time.sleep(0.001)
            port.write(b"MEAS?\r\n")
            reply = port.readline().decode()
            cycles.append(time.perf_counter() - c0)
            assert reply.count(",") == 5, reply
            worst = max(worst, err)
    finally:
        port.close()
        control.stopScript()
        control.disconnect()
        receive.disconnect()
    return {"connect_s": connect_s, "cycles_s": cycles, "worst_arrival_rad": worst}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=100)
    ap.add_argument("--host", default="127.0.4.1", help="loopback address of the simulated cell")
    args = ap.parse_args(argv)

    targets = joint_targets(args.cycles)
    with tempfile.TemporaryDirectory(prefix="recal-bench-cycles-") as tmp:
        nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
        save_model(Path(tmp) / "truth.json", perturbed(nominal, np.random.default_rng(1), tool_length_m=0.0))
        cell = start_fake_cell(Path(tmp) / "truth.json", args.host, time_scale=0.0, log_path=Path(tmp) / "cell.log")
        try:
            results = {
                "recal drivers": run_drivers(cell.ready, targets),
                "bare libraries": run_bare(cell.ready, targets),
            }
        finally:
            cell.stop()

    print(f"# {args.cycles} move-and-measure cycles, RTDE + tracker, time scale 0")
    print(
        f"# {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"{platform.system()} {platform.release()}"
    )
    print(
        "| client | connect (s) | 100 cycles (s) | per cycle median (ms) | per cycle p95 (ms) | worst arrival (rad) |".replace(
            "100", str(args.cycles)
        )
    )
    print("|---|---|---|---|---|---|")
    for name, r in results.items():
        c = sorted(r["cycles_s"])
        p95 = c[min(len(c) - 1, int(round(0.95 * (len(c) - 1))))]
        print(
            f"| {name} | {r['connect_s']:.2f} | {sum(c):.3f} | {statistics.median(c) * 1e3:.2f} | "
            f"{p95 * 1e3:.2f} | {r['worst_arrival_rad']:.1e} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
