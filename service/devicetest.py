"""``Test connection``: open each device a cell's devices configuration names, ask it something
harmless, and report what it answered (or the error), each within a time limit.

- robot over RTDE or Modbus: its state (joint readings, safety stops, program running);
- laser tracker on the line protocol: ``*IDN?``, ``STAT?`` and, when ready, one measurement;
- Leica tracker on emScon: its set-up (server version, serial, reflector, environment), its
  measurement status and, when ready, one measurement (the tracker is not moved);
- CMM: the I++ DME session, server version, probe position and error state;
- reference encoders / resolvers on CAN: each node's state and one reading.

Nothing moves. Each device runs in its own daemon thread, so a device that does not answer
costs its time limit and no more, and never holds up the others.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from .device_registry import DEVICES
from .devices import DeviceConfigError, DevicesConfig, can_node_configs, open_can_node, stored_devices


def _checks(config: DevicesConfig) -> list[tuple[str, str, Callable[[float], Any]]]:
    """(device label, address, check) for each device of the registry the configuration names
    that has a connection test (the reference encoders and resolvers are tested node by node:
    :func:`_test_can_nodes`). Each check is bound to the configuration and its own entry
    (functools.partial, not a closure over a loop variable: the RTDE row once tested the Modbus
    robot, issue 22)."""
    checks = []
    first_of_role: set[str] = set()
    for entry in config.present():
        label = entry.short_label if entry.short_label and entry.role not in first_of_role else entry.label
        first_of_role.add(entry.role)
        if entry.test is not None:
            checks.append((label, config.address(entry.key), functools.partial(entry.test, config)))
    return checks


def test_devices(config: DevicesConfig, *, timeout_s: float = 8.0, busy: str | None = None) -> list[dict]:
    """Test the robot and each instrument of a cell; one result per device.

    ``busy``: why the devices must not be opened now (a session is driving the cell); each is
    then reported as skipped with that reason."""
    results: list[dict] = []
    checks = _checks(config)
    if not checks:
        return [
            {
                "device": "devices",
                "address": "",
                "ok": False,
                "error": "the cell's devices document names no device (expected "
                + ", ".join(e.key for e in DEVICES[:-1])
                + f" or {DEVICES[-1].key})",
            }
        ]
    if busy:
        return [
            {"device": label, "address": addr, "ok": None, "skipped": True, "answer": f"not opened: {busy}"}
            for label, addr, _ in checks
        ]
    threads = []
    for label, addr, fn in checks:
        box: dict = {}

        def work(fn=fn, box=box):
            t0 = time.monotonic()
            try:
                box["value"] = fn(timeout_s)
            except Exception as exc:  # noqa: BLE001 - every failure is a result to show
                box["error"] = f"{type(exc).__name__}: {exc}"
            box["elapsed_ms"] = round((time.monotonic() - t0) * 1e3, 1)

        th = threading.Thread(target=work, name=f"devtest-{label}", daemon=True)
        th.start()
        threads.append((label, addr, th, box))
    deadline = time.monotonic() + timeout_s + 2.0
    for label, addr, th, box in threads:
        th.join(max(0.0, deadline - time.monotonic()))
        if th.is_alive():
            results.append(
                {"device": label, "address": addr, "ok": False, "error": f"no answer within {timeout_s + 2.0:.0f} s"}
            )
            continue
        if "error" in box:
            results.append(
                {
                    "device": label,
                    "address": addr,
                    "ok": False,
                    "error": box["error"],
                    "elapsed_ms": box.get("elapsed_ms"),
                }
            )
            continue
        value = box.get("value")
        if isinstance(value, list):
            for v in value:
                results.append({"address": addr, **v})
        else:
            results.append({"device": label, "address": addr, "elapsed_ms": box.get("elapsed_ms"), **value})
    return results


# --------------------------------------------------------------------------- the whole cell, CAN nodes included


def test_cell_devices(doc: dict, *, timeout_s: float = 8.0, busy: str | None = None) -> list[dict]:
    """:func:`test_devices` for a cell's whole stored ``devices`` document: the robot and the
    instrument, and alongside them each reference encoder and resolver reader on its own (a
    joint may have both), each within its own time limit. ``busy``: why nothing may be opened
    now (a session drives the cell): every device is then reported as not opened, with that
    reason. A document that cannot be read is one failed result naming the field."""
    try:
        config = stored_devices(doc)
    except DeviceConfigError as exc:
        return [{"device": "devices", "address": "", "ok": False, "error": str(exc)}]
    box: dict = {}
    can_thread = threading.Thread(
        target=lambda: box.update(results=_test_can_nodes(config, timeout_s, busy)), name="devtest-can", daemon=True
    )
    can_thread.start()
    has_other = any(e.test is not None for e in config.present())
    results = test_devices(config, timeout_s=timeout_s, busy=busy) if has_other or not _has_can_nodes(config) else []
    can_thread.join()
    return results + box.get("results", [])


NODE_STATES = {
    "operational": "operational: started and sending readings",
    "pre-operational": "pre-operational: configured but not started (a session starts it)",
    "stopped": "stopped: the node was told to stop (NMT); a session starts it again",
    "no heartbeat": 'no heartbeat: the node answered, but sent no periodic "I am alive" message within '
    "{timeout:g} s, so a node that drops out later goes unnoticed until a reading fails; "
    "set its producer heartbeat time (object 0x1017)",
    "disconnected": "disconnected: the CAN link to the node is down",
}


def _node_state(status: str, timeout_s: float) -> str:
    """What a CANopen node's state (the driver's ``status()``) means, for a technician."""
    if status.startswith("fault"):
        return f"{status}: the node reports an error (EMCY); readings fail until it clears"
    return NODE_STATES.get(status, status).format(timeout=timeout_s)


def _test_can_node(config, joint: int) -> dict:
    """Open one reference encoder or resolver reader, read it once, and wait briefly for its
    heartbeat (nodes send one every 100 ms or so; the first may not have come yet)."""
    label = f"{'reference encoder' if config.kind == 'encoder' else 'resolver'}, joint {joint}"
    t0 = time.monotonic()
    base = {"device": label, "address": f"CANopen node {config.node_id} on {config.bus.describe()}"}
    try:
        enc = open_can_node(config)
    except Exception as exc:  # noqa: BLE001 - every failure is a result to show
        return {
            **base,
            "ok": False,
            "error": f"{type(exc).__name__}: {exc}",
            "elapsed_ms": round((time.monotonic() - t0) * 1e3, 1),
        }
    try:
        reading = enc.read()
        status = enc.status()
        deadline = time.monotonic() + config.heartbeat_timeout_s + 0.2
        while status == "no heartbeat" and time.monotonic() < deadline:
            time.sleep(0.05)
            status = enc.status()
        angle = math.degrees(reading.angle_rad)
        cpr, pairs = int(enc.counts_per_rev), int(enc.pole_pairs)
        details = {
            "joint": joint,
            "kind": config.kind,
            "node_id": config.node_id,
            "angle_deg": angle,
            "counts": int(reading.counts),
            "counts_per_rev": cpr,
            "total_range": int(enc.total_range),
            "resolution_deg": 360.0 / (cpr * pairs) if cpr else None,
            "pole_pairs": pairs,
            "status": status,
            "state": _node_state(status, config.heartbeat_timeout_s),
        }
        answer = f"reads {angle:.4f}°"  # the device's own zero, not the robot's
        if enc.total_range <= cpr:
            answer += f" (within one turn of {360.0 / pairs:g}°)"
        return {
            **base,
            "ok": not status.startswith(("fault", "disconnected")),
            "name": enc.name,
            "answer": f"{answer}; node {status}",
            "details": details,
            "elapsed_ms": round((time.monotonic() - t0) * 1e3, 1),
        }
    except Exception as exc:  # noqa: BLE001 - every failure is a result to show
        return {
            **base,
            "ok": False,
            "name": enc.name,
            "error": f"{type(exc).__name__}: {exc}",
            "elapsed_ms": round((time.monotonic() - t0) * 1e3, 1),
        }
    finally:
        with contextlib.suppress(Exception):
            enc.close()


def _can_node_checks(config: DevicesConfig, timeout_s: float) -> list[tuple]:
    """(config, joint) of every reference encoder and every resolver reader (a joint may have
    both: ``open_encoders`` prefers the encoder, the connection test opens each)."""
    if not _has_can_nodes(config):
        return []
    return [(cfg, joint) for joint, cfg in can_node_configs(config, timeout_s=min(timeout_s, 2.0))]


def _test_can_nodes(config: DevicesConfig, timeout_s: float, busy: str | None) -> list[dict]:
    try:
        checks = _can_node_checks(config, timeout_s)
    except DeviceConfigError as exc:
        return [{"device": "CAN bus", "address": config.address("can"), "ok": False, "error": str(exc)}]
    if busy:
        return [
            {
                "device": f"{'reference encoder' if c.kind == 'encoder' else 'resolver'}, joint {j}",
                "address": f"CANopen node {c.node_id}",
                "ok": None,
                "skipped": True,
                "answer": f"not opened: {busy}",
            }
            for c, j in checks
        ]
    out: list[dict | None] = [None] * len(checks)

    def work(k: int, cfg, joint: int) -> None:
        out[k] = _test_can_node(cfg, joint)

    threads = [
        threading.Thread(target=work, args=(k, cfg, joint), name=f"devtest-can-{k}", daemon=True)
        for k, (cfg, joint) in enumerate(checks)
    ]
    for th in threads:
        th.start()
    deadline = time.monotonic() + timeout_s + 2.0
    for th in threads:
        th.join(max(0.0, deadline - time.monotonic()))
    return [
        r
        if r is not None
        else {
            "device": f"{'reference encoder' if c.kind == 'encoder' else 'resolver'}, joint {j}",
            "address": f"CANopen node {c.node_id}",
            "ok": False,
            "error": f"no answer within {timeout_s + 2.0:.0f} s",
        }
        for r, (c, j) in zip(out, checks)
    ]


def _has_can_nodes(config: DevicesConfig) -> bool:
    return config.has("encoder")
