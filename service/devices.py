"""Opening a cell's devices from its typed configuration (:class:`DevicesConfig`, parsed from
the ``devices`` document by :func:`service.device_config.parse_devices`).

This is the one place that names concrete drivers (after python-can's backend table): the
orchestrator only sees the interfaces of ``drivers.base``. Drivers are imported when a cell
needs them, so a missing client library matters only to the cells that use it.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

from drivers.base import Cmm, JointEncoder, PositionSensor, Robot

from .device_config import (
    DEFAULT_BALL_RADIUS_M,
    DeviceConfigError,
    DevicesConfig,
    EmsconSettings,
    parse_devices,
    stored_devices,
)

__all__ = [
    "DEFAULT_BALL_RADIUS_M",
    "CellDevices",
    "DeviceConfigError",
    "DevicesConfig",
    "describe",
    "emscon_config",
    "encoder_nodes",
    "open_cmm",
    "open_encoders",
    "open_line_tracker",
    "open_robot",
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


def open_robot(config: DevicesConfig, *, timeout_s: float = 10.0) -> Robot:
    """The cell's robot: UR over RTDE when ``rtde`` is given, else Modbus TCP (``modbus``).
    ``timeout_s`` bounds each request (RTDE: each probe of the controller and each call; its
    connection, which uploads ``ur_rtde``'s control script, gets at least the driver's 15 s)."""
    if config.rtde:
        from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

        connect_s = max(UrRtdeConfig.__dataclass_fields__["connect_timeout_s"].default, timeout_s)
        return UrRtdeRobot(
            UrRtdeConfig(
                host=config.rtde, probe_timeout_s=timeout_s, command_timeout_s=timeout_s, connect_timeout_s=connect_s
            )
        )
    if config.modbus:
        from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

        host, _, port = config.modbus.rpartition(":")
        return ModbusRobot(ModbusRobotConfig(host=host.strip("[]"), port=int(port), timeout_s=timeout_s))
    raise DeviceConfigError("devices", "no robot (expected an `rtde` host or a `modbus` HOST:PORT)")


def emscon_config(settings: EmsconSettings, *, timeout_s: float = 10.0):
    """The driver's configuration of ``devices.emscon`` (:attr:`DevicesConfig.emscon_settings`).
    What the driver still refuses is named as the entry's fault."""
    from drivers.leica_emscon import EmsconConfig

    try:
        return EmsconConfig(**settings.driver_kwargs(), timeout_s=timeout_s)
    except ValueError as exc:
        raise DeviceConfigError("devices.emscon", str(exc)) from exc


def open_tracker(config: DevicesConfig, *, timeout_s: float = 10.0) -> PositionSensor:
    """The cell's laser tracker: a Leica through its emScon server when ``emscon`` is given (the
    simulated cell names both: sessions use emScon), else the line protocol of ``tracker``."""
    if config.emscon is not None:
        settings = emscon_config(config.emscon_settings, timeout_s=timeout_s)
        from drivers.leica_emscon import EmsconTracker

        return EmsconTracker(settings)
    return open_line_tracker(config, timeout_s=timeout_s)


def open_line_tracker(config: DevicesConfig, *, timeout_s: float = 10.0) -> PositionSensor:
    """The laser tracker on the line protocol (``tracker``: directly or through a bridge)."""
    if not config.tracker:
        raise DeviceConfigError("devices.tracker", "this cell has no laser tracker (expected `emscon` or `tracker`)")
    from drivers.tracker import LineTracker, TrackerConfig

    return LineTracker(TrackerConfig(url=config.tracker, timeout_s=timeout_s))


def open_cmm(config: DevicesConfig, *, timeout_s: float = 10.0) -> Cmm:
    if not config.cmm:
        raise DeviceConfigError("devices.cmm", "this cell has no CMM")
    from drivers.ippdme import IppDmeCmm, IppDmeConfig

    # The session finds the tooling balls where the cell's current model puts them. After a
    # tracker calibration that model cannot know the tool's orientation (one reflector does not
    # show it) nor how the balls are really mounted, so it is a few millimetres off; with the
    # driver's default 3 mm approach the probe then starts inside a ball (I++ 1001 "Illegal
    # touch"). Start 10 mm off the nominal surface and search 15 mm past it, as CMM programs
    # probing a part that is not yet aligned do (each point then takes a little longer).
    return IppDmeCmm(IppDmeConfig(url=config.cmm, timeout_s=timeout_s, approach_m=0.010, search_m=0.015))


def can_bus_config(config: DevicesConfig):
    """The driver's configuration of ``devices.can``."""
    if config.can is None:
        raise DeviceConfigError("devices.can", "this cell has no CAN bus for reference encoders")
    from drivers.canopen_encoder import CanBusConfig

    try:
        return CanBusConfig(**config.can.driver_kwargs())
    except ValueError as exc:
        raise DeviceConfigError("devices.can", str(exc)) from exc


def can_node_configs(config: DevicesConfig, *, timeout_s: float = 0.5) -> list[tuple[int, Any]]:
    """``(joint, CanopenEncoderConfig)`` of every reference encoder and resolver reader, by joint
    then encoder first (a joint may have both)."""
    from drivers.canopen_encoder import CanopenEncoderConfig

    bus = can_bus_config(config)
    out = []
    for key, kind in (("encoders", "encoder"), ("resolvers", "resolver")):
        for joint, node in getattr(config, key).items():
            out.append((int(joint), CanopenEncoderConfig(bus=bus, node_id=node, kind=kind, timeout_s=timeout_s)))
    return sorted(out, key=lambda jc: (jc[0], jc[1].kind))


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
    from drivers.canopen_encoder import CanopenEncoder

    nodes = {}
    for j, node in reversed(can_node_configs(config, timeout_s=timeout_s)):  # the encoder wins
        nodes[j] = node
    wanted = sorted(nodes) if joints is None else joints
    out: dict[int, JointEncoder] = {}
    try:
        for j in wanted:
            if j not in nodes:
                raise DeviceConfigError("devices", f"no reference encoder or resolver on joint {j}")
            out[j] = CanopenEncoder(nodes[j])
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
