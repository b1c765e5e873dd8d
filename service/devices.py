"""Opening a cell's devices from its typed configuration (:class:`DevicesConfig`, parsed from
the ``devices`` document by :func:`service.device_config.parse_devices`).

Which driver opens which key is the registry's (:data:`service.device_registry.DEVICES`); the
session loop only sees the interfaces of ``drivers.base``. The CAN bus's nodes are opened here,
joint by joint, each by the registry's ``open_can_node``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

from calibration.identification import INSTRUMENT_SIGMA_M
from drivers.base import Cmm, JointEncoder, PositionSensor, Robot

from .device_config import (
    DEFAULT_BALL_RADIUS_M,
    DeviceConfigError,
    DevicesConfig,
    parse_devices,
    stored_devices,
)
from .device_registry import DEVICES, ROLE_NAMES, can_bus_config, can_node_configs, emscon_config, open_can_node
from .models import InstrumentSigma

__all__ = [
    "DEFAULT_BALL_RADIUS_M",
    "CellDevices",
    "DeviceConfigError",
    "DevicesConfig",
    "InstrumentSigma",
    "can_bus_config",
    "can_node_configs",
    "describe",
    "emscon_config",
    "encoder_nodes",
    "instrument_sigma",
    "open_can_node",
    "open_cmm",
    "open_encoders",
    "open_robot",
    "open_role",
    "open_tracker",
    "parse_devices",
    "stored_devices",
]


@dataclass
class CellDevices:
    """The open devices of one cell. Closing closes every one (idempotent). ``cmm_ball_radius_m``:
    the radius of the tooling balls the CMM probes (``DevicesConfig.cmm_ball_radius_m``)."""

    robot: Robot | None = None
    tracker: PositionSensor | None = None
    cmm: Cmm | None = None
    encoders: dict[int, JointEncoder] = field(default_factory=dict)
    cmm_ball_radius_m: float = DEFAULT_BALL_RADIUS_M

    def close(self) -> None:
        for dev in [self.robot, self.tracker, self.cmm, *self.encoders.values()]:
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def instrument_sigma(doc: Any, role: str) -> InstrumentSigma:
    """What the cell's measuring device of ``role`` (``tracker``, ``cmm``) declares it measures
    to (its driver's typed config, through the registry: :meth:`DevicesConfig.instrument_sigma`).
    Where the cell names none of that role, or its document cannot be read, the library's
    documented default (``calibration.identification.INSTRUMENT_SIGMA_M``, a laser tracker's)
    stands in, and ``source`` says so."""
    try:
        config = stored_devices(doc)
        found = config.instrument_sigma(role)
    except DeviceConfigError:
        found = None
    if found is not None:
        entry = found[1]
        if getattr(config, f"{entry.key}_sigma_um", None) is not None:
            return InstrumentSigma(found[0], f"the cell's devices document: {entry.key}_sigma_um ({entry.label})")
        return InstrumentSigma(found[0], f"the driver's default: {entry.label}")
    what = ROLE_NAMES.get(role, role)
    return InstrumentSigma(INSTRUMENT_SIGMA_M, f"the library's default: the cell declares no {what} figure")


def open_role(config: DevicesConfig, role: str, *, timeout_s: float = 10.0) -> Any:
    """The cell's device of ``role`` (the registry's first of that role the configuration
    names: ``rtde`` before ``modbus``, ``emscon`` before ``tracker``), open."""
    for entry in config.present(role):
        if entry.open is not None:
            return entry.open(config, timeout_s)
    keys = [e.key for e in DEVICES if e.role == role]
    raise DeviceConfigError(
        "devices" if role == "robot" else f"devices.{keys[-1]}",
        f"this cell has no {ROLE_NAMES[role]} (expected {' or '.join(f'`{k}`' for k in keys)})",
    )


def open_robot(config: DevicesConfig, *, timeout_s: float = 10.0) -> Robot:
    """The cell's robot: UR over RTDE when ``rtde`` is given, else Modbus TCP (``modbus``).
    ``timeout_s`` bounds each request."""
    return open_role(config, "robot", timeout_s=timeout_s)


def open_tracker(config: DevicesConfig, *, timeout_s: float = 10.0) -> PositionSensor:
    """The cell's laser tracker: a Leica through its emScon server when ``emscon`` is given (the
    simulated cell names both: sessions use emScon), else the line protocol of ``tracker``."""
    return open_role(config, "tracker", timeout_s=timeout_s)


def open_cmm(config: DevicesConfig, *, timeout_s: float = 10.0) -> Cmm:
    return open_role(config, "cmm", timeout_s=timeout_s)


def encoder_nodes(config: DevicesConfig) -> dict[int, tuple[int, str]]:
    """The cell's reference encoders and resolvers: joint (1-based) -> (CANopen node, ``encoder``
    or ``resolver``); where a joint has both, the encoder (the better reference). None without
    the CAN bus they are on."""
    if config.can is None:
        return {}
    nodes: dict[int, tuple[int, str]] = {}
    for kind, key in (("resolver", "resolvers"), ("encoder", "encoders")):  # encoders win
        for j, node in getattr(config, key).items():
            nodes[int(j)] = (node, kind)
    return nodes


def open_encoders(
    config: DevicesConfig, joints: list[int] | None = None, *, timeout_s: float = 5.0
) -> dict[int, JointEncoder]:
    """Reference encoders (preferred) or resolver readers on the given joints (1-based)."""
    nodes = {}
    for j, node in reversed(can_node_configs(config, timeout_s=timeout_s)):  # the encoder wins
        nodes[j] = node
    wanted = sorted(nodes) if joints is None else joints
    out: dict[int, JointEncoder] = {}
    try:
        for j in wanted:
            if j not in nodes:
                raise DeviceConfigError("devices", f"no reference encoder or resolver on joint {j}")
            out[j] = open_can_node(nodes[j])
    except BaseException:
        for e in out.values():
            with contextlib.suppress(Exception):
                e.close()
        raise
    return out


def describe(doc: Any) -> tuple[list[str], str | None]:
    """The kinds of device a cell's stored document names (for listings), and what is wrong
    with the document when it cannot be read (no kinds then)."""
    try:
        return stored_devices(doc).kinds(), None
    except DeviceConfigError as exc:
        return [], str(exc)
