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

import numpy as np

from .devices import (
    DeviceConfigError,
    DevicesConfig,
    can_node_configs,
    emscon_config,
    open_cmm,
    open_line_tracker,
    open_robot,
    stored_devices,
)


def _fmt(v: float, digits: int = 4) -> str:
    return f"{v:.{digits}f}"


def _robot(robot_only: DevicesConfig, timeout_s: float) -> dict:
    robot = open_robot(robot_only, timeout_s=timeout_s)
    try:
        st = robot.state()
        q = np.rad2deg(np.asarray(st.q, dtype=float))
        flags = []
        if st.emergency_stop:
            flags.append("EMERGENCY STOP")
        if st.protective_stop:
            flags.append("protective stop")
        flags.append("moving" if st.moving else "standing still")
        flags.append("program running" if st.program_running else "no program running")
        return {
            "ok": not st.stopped_by_safety,
            "name": robot.name,
            "answer": f"joints [{', '.join(_fmt(v, 2) for v in q)}] deg; {', '.join(flags)}",
            "details": {
                "q_deg": [float(v) for v in q],
                "moving": bool(st.moving),
                "protective_stop": bool(st.protective_stop),
                "emergency_stop": bool(st.emergency_stop),
                "program_running": bool(st.program_running),
            },
        }
    finally:
        robot.close()


def _emscon(config: DevicesConfig, timeout_s: float) -> dict:
    from drivers.leica_emscon import EmsconTracker

    tr = EmsconTracker(emscon_config(config.emscon_settings, timeout_s=timeout_s))
    try:
        ident, refl, env = tr.identity, tr.reflector, tr.environment
        idn = f"Leica, emScon {ident.server_version}, tracker {ident.serial}"
        status = tr.status()
        details: dict[str, Any] = {
            "identity": idn,
            "status": status,
            "reflector": refl.name,
            "environment": {"temperature_c": env[0], "pressure_mbar": env[1], "humidity_pct": env[2]},
        }
        answer = (
            f"{idn}; reflector {refl.name}; {env[0]:.1f} °C, {env[1]:.1f} mbar, {env[2]:.0f} %RH "
            f"({tr.config.environment}); {status.replace('_', ' ')}"
        )
        ok = status == "ready"
        if ok:
            m = tr.measure()
            p, s = m.p_world * 1e3, m.sigma * 1e3
            details.update({"position_mm": [float(v) for v in p], "sigma_mm": [float(v) for v in s]})
            answer += f"; reflector at ({', '.join(_fmt(v, 3) for v in p)}) mm ± {_fmt(float(np.max(s)), 4)} mm"
        return {"ok": ok, "name": tr.name, "answer": answer, "details": details}
    finally:
        tr.close()


def _tracker(config: DevicesConfig, timeout_s: float) -> dict:
    tr = open_line_tracker(config, timeout_s=timeout_s)
    try:
        ident = getattr(tr, "identity", None)
        idn = ", ".join([ident.maker, ident.model, ident.serial, ident.firmware]) if ident else "?"
        status = tr.status()
        details: dict[str, Any] = {"identity": idn, "status": status}
        answer = f"*IDN? {idn}; STAT? {status.upper()}"
        ok = status == "ready"
        if ok:
            m = tr.measure()
            p, s = m.p_world * 1e3, m.sigma * 1e3
            details.update({"position_mm": [float(v) for v in p], "sigma_mm": [float(v) for v in s]})
            answer += f"; MEAS? reflector at ({', '.join(_fmt(v, 3) for v in p)}) mm ± {_fmt(float(np.max(s)), 4)} mm"
        return {"ok": ok, "name": tr.name, "answer": answer, "details": details}
    finally:
        tr.close()


def _cmm(config: DevicesConfig, timeout_s: float) -> dict:
    cmm = open_cmm(config, timeout_s=timeout_s)
    try:
        version = getattr(cmm, "dme_version", None)
        pos = cmm.position() * 1e3 if hasattr(cmm, "position") else None
        err = cmm.error_status() if hasattr(cmm, "error_status") else False
        answer = f"I++ DME session started (server {version or '?'})"
        if pos is not None:
            answer += f"; probe at ({', '.join(_fmt(v, 3) for v in pos)}) mm"
        answer += "; error state" if err else "; no error"
        return {
            "ok": not err,
            "name": cmm.name,
            "answer": answer,
            "details": {
                "dme_version": version,
                "probe_mm": None if pos is None else [float(v) for v in pos],
                "error": bool(err),
            },
        }
    finally:
        cmm.close()


def _checks(config: DevicesConfig) -> list[tuple[str, str, Callable[[float], Any]]]:
    """(device label, address, check) for the robot and each instrument the configuration names
    (the reference encoders and resolvers are tested node by node: :func:`_test_can_nodes`)."""
    checks = []
    # each robot's check is bound to its own configuration (functools.partial, not a closure over
    # a variable the next branch reassigns: the RTDE row once tested the Modbus robot, issue 22)
    if config.rtde:
        rtde_only = DevicesConfig(rtde=config.rtde)
        checks.append(("robot (UR RTDE)", config.address("rtde"), functools.partial(_robot, rtde_only)))
    if config.modbus:
        modbus_only = DevicesConfig(modbus=config.modbus)
        checks.append(("robot (Modbus TCP)", config.address("modbus"), functools.partial(_robot, modbus_only)))
    if config.emscon is not None:
        checks.append(("laser tracker", config.address("emscon"), lambda t: _emscon(config, t)))
    if config.tracker:
        label = "laser tracker (line protocol)" if config.emscon is not None else "laser tracker"
        checks.append((label, config.address("tracker"), lambda t: _tracker(config, t)))
    if config.cmm:
        checks.append(("CMM (I++ DME)", config.address("cmm"), lambda t: _cmm(config, t)))
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
                "error": "the cell's devices document names no device (expected rtde, modbus, emscon, tracker, cmm or can)",
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
    has_other = any(getattr(config, k) is not None for k in ("rtde", "modbus", "emscon", "tracker", "cmm"))
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
    from drivers.canopen_encoder import CanopenEncoder

    label = f"{'reference encoder' if config.kind == 'encoder' else 'resolver'}, joint {joint}"
    t0 = time.monotonic()
    base = {"device": label, "address": f"CANopen node {config.node_id} on {config.bus.describe()}"}
    try:
        enc = CanopenEncoder(config)
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
