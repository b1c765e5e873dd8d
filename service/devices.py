"""Opening a cell's devices from its ``devices`` document (the fake cell's endpoint line,
contracts §7, or the same shape for real equipment).

This is the one place that names concrete drivers (after python-can's backend table): the
orchestrator only sees the interfaces of ``drivers.base``. Drivers are imported when a cell
needs them, so a missing client library matters only to the cells that use it.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

from calibration.errors import RecalError
from drivers.base import Cmm, JointEncoder, PositionSensor, Robot


class DeviceConfigError(RecalError, ValueError):
    """A cell's ``devices`` document cannot be used: names the field at fault."""


# The tooling balls' radius when the cell does not give one: the common 25 mm ball.
DEFAULT_BALL_RADIUS_M = 0.0125


@dataclass
class CellDevices:
    """The open devices of one cell. Closing closes every one (idempotent). ``cmm_ball_radius_m``:
    the radius of the tooling balls the CMM probes (:func:`cmm_ball_radius_m`)."""

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


def open_robot(devices: dict[str, Any], *, timeout_s: float = 10.0) -> Robot:
    """The cell's robot: UR over RTDE when ``rtde`` is given, else Modbus TCP (``modbus``)."""
    if devices.get("rtde"):
        from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

        return UrRtdeRobot(UrRtdeConfig(host=str(devices["rtde"])))
    if devices.get("modbus"):
        from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

        host, _, port = str(devices["modbus"]).rpartition(":")
        if not host or not port.isdigit():
            raise DeviceConfigError(f"devices.modbus: expected HOST:PORT, got {devices['modbus']!r}")
        return ModbusRobot(ModbusRobotConfig(host=host, port=int(port), timeout_s=timeout_s))
    raise DeviceConfigError("devices: no robot (expected an `rtde` host or a `modbus` HOST:PORT)")


#: Settings of an ``emscon`` entry given as an object (the fields of ``drivers.leica_emscon.EmsconConfig``).
EMSCON_FIELDS = {
    "host": str,
    "port": int,
    "reflector": str,
    "measure_time_s": float,
    "use_adm": bool,
    "environment": str,
    "temperature_c": float,
    "pressure_mbar": float,
    "humidity_pct": float,
    "initialize_timeout_s": float,
}


def has_tracker(devices: dict[str, Any]) -> bool:
    """The cell has a laser tracker: a Leica on emScon (``emscon``) or one on the line protocol
    (``tracker``, directly or through a bridge)."""
    return bool(devices.get("emscon") or devices.get("tracker"))


def emscon_config(value: Any, *, timeout_s: float = 10.0):
    """``devices.emscon``: ``"HOST:PORT"`` (the endpoint line, contracts §7), ``"HOST"`` (port
    700), or an object with ``host`` and any of :data:`EMSCON_FIELDS`. Raises
    ``DeviceConfigError`` naming the field."""
    from drivers.leica_emscon import EmsconConfig

    try:
        if isinstance(value, str):
            return EmsconConfig.from_endpoint(value, timeout_s=timeout_s)
        if not isinstance(value, dict):
            raise DeviceConfigError(f'devices.emscon: expected "HOST:PORT" or an object; got {value!r}')
        kwargs: dict[str, Any] = {"timeout_s": timeout_s}
        for key, v in value.items():
            kind = EMSCON_FIELDS.get(key)
            if kind is None:
                raise DeviceConfigError(
                    f"devices.emscon.{key}: unknown setting; expected one of {', '.join(EMSCON_FIELDS)}"
                )
            ok = isinstance(v, kind) if kind in (str, bool) else isinstance(v, (int, float)) and not isinstance(v, bool)
            if not ok or (kind is int and v != int(v)):
                raise DeviceConfigError(f"devices.emscon.{key}: expected {kind.__name__}; got {v!r}")
            kwargs[key] = kind(v)
        if "host" not in kwargs:
            raise DeviceConfigError("devices.emscon.host: missing; the emScon server's address")
        return EmsconConfig(**kwargs)
    except ValueError as exc:
        if isinstance(exc, DeviceConfigError):
            raise
        raise DeviceConfigError(f"devices.emscon: {exc}") from exc


def open_tracker(devices: dict[str, Any], *, timeout_s: float = 10.0) -> PositionSensor:
    """The cell's laser tracker: a Leica through its emScon server when ``emscon`` is given (the
    simulated cell names both: sessions use emScon), else the line protocol of ``tracker``."""
    if devices.get("emscon"):
        config = emscon_config(devices["emscon"], timeout_s=timeout_s)
        from drivers.leica_emscon import EmsconTracker

        return EmsconTracker(config)
    if not devices.get("tracker"):
        raise DeviceConfigError("devices.tracker: this cell has no laser tracker (expected `emscon` or `tracker`)")
    from drivers.tracker import LineTracker, TrackerConfig

    return LineTracker(TrackerConfig(url=str(devices["tracker"]), timeout_s=timeout_s))


def open_cmm(devices: dict[str, Any], *, timeout_s: float = 10.0) -> Cmm:
    if not devices.get("cmm"):
        raise DeviceConfigError("devices.cmm: this cell has no CMM")
    from drivers.ippdme import IppDmeCmm, IppDmeConfig

    # The session finds the tooling balls where the cell's current model puts them. After a
    # tracker calibration that model cannot know the tool's orientation (one reflector does not
    # show it) nor how the balls are really mounted, so it is a few millimetres off; with the
    # driver's default 3 mm approach the probe then starts inside a ball (I++ 1001 "Illegal
    # touch"). Start 10 mm off the nominal surface and search 15 mm past it, as CMM programs
    # probing a part that is not yet aligned do (each point then takes a little longer).
    return IppDmeCmm(IppDmeConfig(url=str(devices["cmm"]), timeout_s=timeout_s, approach_m=0.010, search_m=0.015))


def cmm_ball_radius_m(devices: dict[str, Any]) -> float:
    """``devices.cmm_ball_radius_m``: the radius of the tool's tooling balls (m) that the CMM
    probes (every ball alike), default :data:`DEFAULT_BALL_RADIUS_M`. Raises
    ``DeviceConfigError`` naming the field unless it is a radius a tooling ball can have."""
    value = (devices or {}).get("cmm_ball_radius_m", DEFAULT_BALL_RADIUS_M)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0005 <= value <= 0.1:
        raise DeviceConfigError(
            f"devices.cmm_ball_radius_m: expected a tooling ball's radius in metres, 0.0005 to 0.1, got {value!r}"
        )
    return float(value)


def encoder_nodes(devices: dict[str, Any]) -> dict[int, tuple[int, str]]:
    """The cell's reference encoders and resolvers: joint (1-based) -> (CANopen node, ``encoder``
    or ``resolver``); where a joint has both, the encoder (the better reference)."""
    if not devices.get("can"):
        return {}
    nodes: dict[int, tuple[int, str]] = {}
    for kind, key in (("resolver", "resolvers"), ("encoder", "encoders")):  # encoders win
        for j, node in (devices.get(key) or {}).items():
            nodes[int(j)] = (int(node), kind)
    return nodes


def open_encoders(
    devices: dict[str, Any], joints: list[int] | None = None, *, timeout_s: float = 5.0
) -> dict[int, JointEncoder]:
    """Reference encoders (preferred) or resolver readers on the given joints (1-based)."""
    if not devices.get("can"):
        raise DeviceConfigError("devices.can: this cell has no CAN bus for reference encoders")
    from drivers.canopen_encoder import CanBusConfig, CanopenEncoder, CanopenEncoderConfig

    bus = CanBusConfig.from_endpoint(devices["can"])
    nodes = encoder_nodes(devices)
    wanted = sorted(nodes) if joints is None else joints
    out: dict[int, JointEncoder] = {}
    try:
        for j in wanted:
            if j not in nodes:
                raise DeviceConfigError(f"devices: no reference encoder or resolver on joint {j}")
            node, kind = nodes[j]
            out[j] = CanopenEncoder(CanopenEncoderConfig(bus=bus, node_id=node, kind=kind, timeout_s=timeout_s))
    except BaseException:
        for e in out.values():
            with contextlib.suppress(Exception):
                e.close()
        raise
    return out


def describe(devices: dict[str, Any]) -> list[str]:
    """The kinds of device a document names (for listings)."""
    return [k for k in ("rtde", "modbus", "emscon", "tracker", "cmm", "can") if devices.get(k)]
