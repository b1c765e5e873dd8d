"""The device registry: one table (:data:`DEVICES`) from a key of a cell's ``devices`` document
to everything the service does with that device — the configuration field (its JSON Schema
fragment, served at ``GET /api/v1/schemas/devices`` for the page's form), its role in a session,
its driver and how it is opened, its fake in ``recal fake-cell``, its connection test, and how
the page names and enters it.

Adding an instrument (docs/architecture.md, "Adding an instrument"): its driver (``drivers/``),
its fake (``fakes/``, with a ``CELL_FAKE`` line that ``recal fake-cell`` finds), its tests, its
docs page, and in this file a field of :class:`DevicesConfig` with one :class:`DeviceEntry`.
Nothing else names a device's key: the opening (``devices.py``), the connection test
(``devicetest.py``), the listings and the page go through this table.

Drivers are imported when a device is opened, so a missing client library matters only to the
cells that use it (after python-can's backend table). This module may import drivers and fakes;
they never import it (tests/test_architecture.py).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from pydantic import ConfigDict, Field, ValidationInfo, model_validator

# the drivers' own defaults, stated in the schema's words (the registry is the one place that names drivers)
from drivers.ippdme import CMM_SIGMA_M
from drivers.leica_emscon import AT960_SIGMA_M
from drivers.tracker import LINE_TRACKER_SIGMA_M

from .device_fields import (
    DEFAULT_BALL_RADIUS_M,
    HOST_PATTERN,
    HOST_PORT_PATTERN,
    CanBus,
    CmmUrl,
    DeviceConfigError,
    Emscon,
    EmsconSettings,
    JointNumber,
    NodeId,
    SerialUrl,
    _Strict,
    _text,
)

# What a device is to a session: the robot, or one of the measuring devices a session kind names
# (SessionKind.instrument: ``tracker``, ``cmm``, ``encoder``).
ROLES = ("robot", "tracker", "cmm", "encoder")
ROLE_NAMES = {"robot": "robot", "tracker": "laser tracker", "cmm": "CMM", "encoder": "CAN bus for reference encoders"}


@dataclass(frozen=True)
class DeviceEntry:
    """One row of the registry: the device of configuration key ``key``.

    - ``role``: what sessions use it as (:data:`ROLES`); of several devices of one role the
      first in the table is the one a session opens (``rtde`` before ``modbus``);
    - ``label``: how the page and the connection test name it; ``short_label``: the connection
      test's name when it is the first of its role the cell has;
    - ``driver`` / ``fake``: ``module:Class`` of its driver and of its simulation;
    - ``open(config, timeout_s)``: the open driver (None: opened by its session kind);
    - ``test(config, timeout_s)``: the connection test's row (None: tested elsewhere);
    - ``robot_type(config, timeout_s)``: for a robot, what its controller says it is (UR's
      dashboard: ``UR5``), asked without opening the driver (None: it cannot be asked);
    - ``sigma_m(config)``: for an instrument, the per-axis standard uncertainty (m) its driver's
      typed config declares for this configuration (the vendor's figure unless stated), what a
      session plans and weighs with (None: no position instrument);
    - ``page``: the page's kind of field for it (``text``: one text field with the schema's
      pattern; ``text-or-settings``: a text field keeping an object written elsewhere; ``can``:
      the bus's fields and the joints' nodes).
    """

    key: str
    role: str
    label: str
    driver: str
    fake: str | None
    open: Callable[[DevicesConfig, float], Any] | None = None
    test: Callable[[DevicesConfig, float], dict] | None = None
    robot_type: Callable[[DevicesConfig, float], str] | None = None
    sigma_m: Callable[[DevicesConfig], float] | None = None
    short_label: str | None = None
    page: str = "text"

    def driver_class(self) -> type:
        """The driver's class (imported now: a driver module imports its client library only
        when it connects), for what it declares it can do (drivers/base.py: must and might)."""
        module, _, name = self.driver.partition(":")
        return getattr(importlib.import_module(module), name)

    def describe(self) -> dict[str, Any]:
        """The entry as the page reads it (``x-devices`` of the served schema)."""
        return {"key": self.key, "role": self.role, "label": self.label, "page": self.page}


def _fmt(v: float, digits: int = 4) -> str:
    return f"{v:.{digits}f}"


# --------------------------------------------------------------------------- robots


def open_rtde(config: DevicesConfig, timeout_s: float) -> Any:
    """UR over RTDE. ``timeout_s`` bounds each request (each probe of the controller and each
    call); its connection, which uploads ``ur_rtde``'s control script, gets at least the driver's
    15 s."""
    from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

    connect_s = max(UrRtdeConfig.__dataclass_fields__["connect_timeout_s"].default, timeout_s)
    return UrRtdeRobot(
        UrRtdeConfig(
            host=config.rtde, probe_timeout_s=timeout_s, command_timeout_s=timeout_s, connect_timeout_s=connect_s
        )
    )


def rtde_robot_type(config: DevicesConfig, timeout_s: float) -> str:
    """The dashboard's ``get robot model`` (``UR5``): asked on the dashboard port, so that the
    control script is not uploaded (connecting RTDE would stop a program that runs)."""
    from drivers.ur_rtde import dashboard_query

    return dashboard_query(config.rtde, "get robot model", timeout_s)


def open_modbus(config: DevicesConfig, timeout_s: float) -> Any:
    from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

    host, _, port = config.modbus.rpartition(":")
    return ModbusRobot(ModbusRobotConfig(host=host.strip("[]"), port=int(port), timeout_s=timeout_s))


def test_robot(opener: Callable[[DevicesConfig, float], Any], config: DevicesConfig, timeout_s: float) -> dict:
    """A robot's state: joint readings, safety stops, program running (nothing moves)."""
    robot = opener(config, timeout_s)
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


# --------------------------------------------------------------------------- laser trackers


def own_sigma(config: DevicesConfig, key: str) -> dict[str, float]:
    """The instrument's own figure the cell's devices document states (``<key>_sigma_um``), as
    its driver config's ``sigma_m`` keyword; empty when the document states none (the driver's
    default, the vendor's figure, then stands)."""
    sigma_um = getattr(config, f"{key}_sigma_um", None)
    return {} if sigma_um is None else {"sigma_m": float(sigma_um) * 1e-6}


def emscon_config(settings: EmsconSettings, *, timeout_s: float = 10.0, sigma: dict[str, float] | None = None) -> Any:
    """The driver's configuration of ``devices.emscon`` (:attr:`DevicesConfig.emscon_settings`),
    with the document's own figure (``sigma``: :func:`own_sigma`) if it states one. What the
    driver still refuses is named as the entry's fault."""
    from drivers.leica_emscon import EmsconConfig

    try:
        return EmsconConfig(**settings.driver_kwargs(), timeout_s=timeout_s, **(sigma or {}))
    except ValueError as exc:
        raise DeviceConfigError("devices.emscon", str(exc)) from exc


def open_emscon(config: DevicesConfig, timeout_s: float) -> Any:
    settings = emscon_config(config.emscon_settings, timeout_s=timeout_s, sigma=own_sigma(config, "emscon"))
    from drivers.leica_emscon import EmsconTracker

    return EmsconTracker(settings)


def emscon_sigma_m(config: DevicesConfig) -> float:
    return emscon_config(config.emscon_settings, sigma=own_sigma(config, "emscon")).sigma_m


def line_tracker_config(config: DevicesConfig, timeout_s: float = 2.0) -> Any:
    from drivers.tracker import TrackerConfig

    return TrackerConfig(url=config.tracker, timeout_s=timeout_s, **own_sigma(config, "tracker"))


def open_line_tracker(config: DevicesConfig, timeout_s: float) -> Any:
    from drivers.tracker import LineTracker

    return LineTracker(line_tracker_config(config, timeout_s))


def _measure_once(tr: Any, details: dict) -> str:
    m = tr.measure()
    p, s = m.p_world * 1e3, m.sigma * 1e3
    details.update({"position_mm": [float(v) for v in p], "sigma_mm": [float(v) for v in s]})
    return f"reflector at ({', '.join(_fmt(v, 3) for v in p)}) mm ± {_fmt(float(np.max(s)), 4)} mm"


def test_emscon(config: DevicesConfig, timeout_s: float) -> dict:
    """Its set-up (server version, serial, reflector, environment), its measurement status and,
    when ready, one measurement (the tracker is not moved)."""
    tr = open_emscon(config, timeout_s)
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
            answer += "; " + _measure_once(tr, details)
        return {"ok": ok, "name": tr.name, "answer": answer, "details": details}
    finally:
        tr.close()


def test_line_tracker(config: DevicesConfig, timeout_s: float) -> dict:
    """``*IDN?``, ``STAT?`` and, when ready, one measurement."""
    tr = open_line_tracker(config, timeout_s)
    try:
        ident = getattr(tr, "identity", None)
        idn = ", ".join([ident.maker, ident.model, ident.serial, ident.firmware]) if ident else "?"
        status = tr.status()
        details: dict[str, Any] = {"identity": idn, "status": status}
        answer = f"*IDN? {idn}; STAT? {status.upper()}"
        ok = status == "ready"
        if ok:
            answer += "; MEAS? " + _measure_once(tr, details)
        return {"ok": ok, "name": tr.name, "answer": answer, "details": details}
    finally:
        tr.close()


# --------------------------------------------------------------------------- CMM


def ippdme_config(config: DevicesConfig, timeout_s: float = 5.0) -> Any:
    from drivers.ippdme import IppDmeConfig

    # The session finds the tooling balls where the cell's current model puts them. After a
    # tracker calibration that model cannot know the tool's orientation (one reflector does not
    # show it) nor how the balls are really mounted, so it is a few millimetres off; with the
    # driver's default 3 mm approach the probe then starts inside a ball (I++ 1001 "Illegal
    # touch"). Start 10 mm off the nominal surface and search 15 mm past it, as CMM programs
    # probing a part that is not yet aligned do (each point then takes a little longer).
    return IppDmeConfig(
        url=config.cmm, timeout_s=timeout_s, approach_m=0.010, search_m=0.015, **own_sigma(config, "cmm")
    )


def open_ippdme(config: DevicesConfig, timeout_s: float) -> Any:
    from drivers.ippdme import IppDmeCmm

    return IppDmeCmm(ippdme_config(config, timeout_s))


def test_ippdme(config: DevicesConfig, timeout_s: float) -> dict:
    """The I++ DME session, server version, probe position and error state."""
    cmm = open_ippdme(config, timeout_s)
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


# --------------------------------------------------------------------------- the CAN bus's nodes
# opened joint by joint (service.devices.open_encoders) and tested node by node (service.devicetest)


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


def open_can_node(node_config: Any) -> Any:
    """One reference encoder or resolver reader on the CAN bus, open (a ``JointEncoder``)."""
    from drivers.canopen_encoder import CanopenEncoder

    return CanopenEncoder(node_config)


# --------------------------------------------------------------------------- the table

DEVICES: tuple[DeviceEntry, ...] = (
    DeviceEntry(
        key="rtde",
        role="robot",
        label="robot (UR RTDE)",
        driver="drivers.ur_rtde:UrRtdeRobot",
        fake="fakes.ur_controller:UrControllerFake",
        open=open_rtde,
        test=functools.partial(test_robot, open_rtde),
        robot_type=rtde_robot_type,
    ),
    DeviceEntry(
        key="modbus",
        role="robot",
        label="robot (Modbus TCP)",
        driver="drivers.modbus_robot:ModbusRobot",
        fake="fakes.modbus_server:ModbusRobotFake",
        open=open_modbus,
        test=functools.partial(test_robot, open_modbus),
    ),
    DeviceEntry(
        key="emscon",
        role="tracker",
        label="laser tracker (Leica emScon)",
        short_label="laser tracker",
        driver="drivers.leica_emscon:EmsconTracker",
        fake="fakes.leica_tracker:LeicaTrackerFake",
        open=open_emscon,
        test=test_emscon,
        sigma_m=emscon_sigma_m,
        page="text-or-settings",
    ),
    DeviceEntry(
        key="tracker",
        role="tracker",
        label="laser tracker (line protocol)",
        short_label="laser tracker",
        driver="drivers.tracker:LineTracker",
        fake="fakes.tracker:TrackerFake",
        open=open_line_tracker,
        test=test_line_tracker,
        sigma_m=lambda config: line_tracker_config(config).sigma_m,
    ),
    DeviceEntry(
        key="cmm",
        role="cmm",
        label="CMM (I++ DME)",
        driver="drivers.ippdme:IppDmeCmm",
        fake="fakes.cmm:IppCmmFake",
        open=open_ippdme,
        test=test_ippdme,
        sigma_m=lambda config: ippdme_config(config).sigma_m,
    ),
    # the CAN bus's nodes are opened joint by joint (devices.open_encoders) and tested node by
    # node (devicetest._test_can_nodes): its entry opens and tests nothing itself
    DeviceEntry(
        key="can",
        role="encoder",
        label="CAN bus",
        driver="drivers.canopen_encoder:CanopenEncoder",
        fake="fakes.canopen_nodes:CanGatewayFake",
        page="can",
    ),
)

DEVICE_BY_KEY: dict[str, DeviceEntry] = {e.key: e for e in DEVICES}


# An instrument's own per-axis noise figure (its certificate's), µm: optional, in a sane range
# (0.1 µm is beyond any tracker or CMM; 1000 µm is a millimetre, no measuring instrument).
_SigmaUm = Annotated[float, Field(ge=0.1, le=1000, allow_inf_nan=False)] | None
_SIGMA_DESC = (
    "the instrument's own per-axis standard uncertainty (its certificate's figure), µm, 0.1 to 1000; "
    "sessions plan and weigh with it; absent: its driver's default, the vendor's figure"
)


class DevicesConfig(_Strict):
    """A cell's devices: the robot controller (``rtde`` or ``modbus``), the instruments
    (``emscon``, ``tracker``, ``cmm``), the CAN bus and the reference encoders and resolvers on
    it, and the CMM's tooling ball radius. Every device may be absent."""

    model_config = ConfigDict(title="Cell devices")

    ready: bool | None = Field(
        None, description="the endpoint line's marker (recal fake-cell); accepted so that the line pastes as it is"
    )
    rtde: (
        _text(
            HOST_PATTERN,
            "the controller's host name or IP address, e.g. 192.168.1.10 (no port: RTDE uses 30004)",
            examples=["192.168.1.10"],
        )
        | None
    ) = Field(None, title="UR controller (RTDE) host", description="Universal Robots: RTDE on 30004")
    modbus: _text(HOST_PORT_PATTERN, "HOST:PORT, e.g. 192.168.1.10:502", examples=["192.168.1.10:502"]) | None = Field(
        None, title="Modbus TCP host:port", description="a robot read over Modbus TCP (UR register map)"
    )
    emscon: Emscon | None = Field(
        None,
        title="Leica laser tracker (emScon)",
        description="HOST:PORT of the tracker's emScon server (port 700), or an object with its settings; "
        "tracker sessions use it when it is given",
    )
    tracker: SerialUrl | None = Field(
        None,
        title="Laser tracker (line protocol)",
        description="socket://HOST:PORT, or the serial port it is plugged into (a bridge for FARO and API trackers)",
    )
    cmm: CmmUrl | None = Field(None, title="CMM (I++ DME)", description="socket://HOST:PORT of the I++ DME server")
    can: CanBus | None = Field(None, title="CAN bus", description="where the reference encoders and resolvers are")
    encoders: dict[JointNumber, NodeId] = Field(
        default_factory=dict,
        title="Reference encoders",
        description="joint number -> CANopen node id of the reference encoder on that joint",
    )
    resolvers: dict[JointNumber, NodeId] = Field(
        default_factory=dict,
        title="Resolvers",
        description="joint number -> CANopen node id of the resolver reader on that joint",
    )
    cmm_ball_radius_m: Annotated[float, Field(ge=0.0005, le=0.1)] = Field(
        DEFAULT_BALL_RADIUS_M,
        title="CMM tooling ball radius (m)",
        description="radius of the tool's tooling balls the CMM probes, every ball alike, m (0.0005 to 0.1)",
        # the page shows and takes it in mm, as every length on the page (it converts)
        json_schema_extra={"x-page-unit": "mm"},
    )

    emscon_sigma_um: _SigmaUm = Field(
        None,
        title="emScon tracker's own noise (µm)",
        description=_SIGMA_DESC + f" (the driver's default: the AT960's {AT960_SIGMA_M * 1e6:g} µm)",
        json_schema_extra={"x-page-unit": "µm", "x-instrument": "emscon"},
    )
    tracker_sigma_um: _SigmaUm = Field(
        None,
        title="Line-protocol tracker's own noise (µm)",
        description=_SIGMA_DESC + f" (the driver's default: {LINE_TRACKER_SIGMA_M * 1e6:g} µm)",
        json_schema_extra={"x-page-unit": "µm", "x-instrument": "tracker"},
    )
    cmm_sigma_um: _SigmaUm = Field(
        None,
        title="CMM's own noise (µm)",
        description=_SIGMA_DESC + f" (the driver's default: {CMM_SIGMA_M * 1e6:g} µm)",
        json_schema_extra={"x-page-unit": "µm", "x-instrument": "cmm"},
    )

    @model_validator(mode="after")
    def _one_bus_for_the_nodes(self, info: ValidationInfo) -> DevicesConfig:
        # Checked for a document being registered or edited; a stored one is read as it is (these
        # were not checked before): opening the encoders refuses it then.
        if not (info.context or {}).get("registering"):
            return self
        if (self.encoders or self.resolvers) and self.can is None:
            raise ValueError("[can] missing; the reference encoders and resolvers need the CAN bus they are on")
        seen: dict[int, str] = {}
        for key in ("encoders", "resolvers"):
            for joint, node in getattr(self, key).items():
                if node in seen:
                    raise ValueError(f"[{key}.{joint}] node {node} is already {seen[node]}")
                seen[node] = f"{key}.{joint}"
        return self

    # ----------------------------------------------------------------- what a cell has
    # All from the registry (DEVICES): a device's key, its role and its order are its entry's.

    def present(self, role: str | None = None) -> list[DeviceEntry]:
        """The registry's entries this configuration names (of ``role``), in the table's order."""
        return [e for e in DEVICES if getattr(self, e.key) is not None and role in (None, e.role)]

    @property
    def has_robot(self) -> bool:
        return bool(self.present("robot"))

    @property
    def robot_takes_payload(self) -> bool:
        """The cell's robot (the first of the role, as sessions open it) takes the mounted payload,
        as its driver declares (``Robot.takes_payload``)."""
        robots = self.present("robot")
        return bool(robots) and bool(robots[0].driver_class().takes_payload)

    @property
    def has_tracker(self) -> bool:
        """A laser tracker: a Leica on emScon (``emscon``) or one on the line protocol (``tracker``)."""
        return bool(self.present("tracker"))

    def has(self, device: str) -> bool:
        """The cell has the session's measuring ``device`` (a role of the registry: ``tracker``
        (either kind), ``cmm``, or ``encoder``: a CAN bus with reference encoders or resolvers)."""
        if device not in ROLES or device == "robot":
            raise ValueError(f"unknown measuring device {device!r}")
        if device == "encoder":
            return bool(self.present("encoder")) and bool(self.encoders or self.resolvers)
        return bool(self.present(device))

    @property
    def emscon_settings(self) -> EmsconSettings | None:
        """``emscon`` in one form, whichever was written ("HOST", "HOST:PORT" or the object)."""
        if self.emscon is None or isinstance(self.emscon, EmsconSettings):
            return self.emscon
        return EmsconSettings.from_address(self.emscon)

    def instrument_sigma(self, device: str) -> tuple[float, DeviceEntry] | None:
        """What the session's measuring ``device`` (a role) is declared to measure to: the
        per-axis standard uncertainty (m) of the first device of that role the cell names (the
        one sessions open), from its driver's typed config, with its entry; None when the cell
        has no such device or it declares none (a CAN bus's encoders measure no position)."""
        for entry in self.present(device):
            if entry.sigma_m is not None:
                return float(entry.sigma_m(self)), entry
        return None

    def kinds(self) -> list[str]:
        """The kinds of device the document names, in the registry's order (for listings)."""
        return [e.key for e in self.present()]

    def address(self, key: str) -> str:
        """How a person finds the device of entry ``key`` (``rtde``, ``emscon``, ``can``, ...);
        empty when the cell has none."""
        value = getattr(self, key, None) if key in type(self).model_fields else None
        if value is None or isinstance(value, dict | bool | float):
            return ""
        return value.address() if hasattr(value, "address") else str(value)

    def instrument_address(self, device: str) -> str:
        """The address of a session's measuring ``device`` (its role): the first device of that
        role the cell names, as sessions open it (``tracker``: the Leica on emScon when there
        is one)."""
        present = self.present(device)
        return self.address(present[0].key if present else device)

    def document(self) -> dict[str, Any]:
        """The document this configuration reads from (the endpoint line's shape, defaults left
        out): ``parse_devices(c.document()) == c``."""
        return self.model_dump(mode="json", exclude_defaults=True, exclude_none=True)
