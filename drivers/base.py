"""The device interfaces: one small interface per kind of device.

A driver implements exactly one of these over a real client library and takes one typed,
frozen config object (no ``**kwargs``, no ambient configuration). Every device is a context
manager; ``close()`` is idempotent.

Must / might (after python-can's ``BusABC``):

- every device **must** implement ``close()`` and set ``name`` (a human-readable address);
- a ``Robot`` **must** implement ``read_joints``, ``move_joints``, ``stop`` and ``state``; it
  **might** take the mounted payload (``takes_payload``: ``set_payload``) and tell its own
  kinematics (``kinematics_source``: ``"forward_kinematics"``, it answers ``forward_kinematics``
  for any readings; ``"tcp_pose"``, it reports ``read_tcp_pose`` where it stands, its readings
  resolved to ``joint_resolution_rad``): what it declares is what it does, nobody asks ``hasattr``;
- a ``PositionSensor`` **must** implement ``measure`` and ``status``; a
  ``SteerablePositionSensor`` (a tracker that can be pointed) also ``find_reflector``;
- a ``Cmm`` **must** implement ``probe``; ``measure_ball`` and ``measure_pose`` are built on it
  here and **might** be overridden by a CMM that measures spheres itself;
- an instrument (``PositionSensor``, ``Cmm``) **must** declare ``sigma_m``: the per-axis standard
  uncertainty of one measured position (m), from its typed config, the vendor's figure (named in
  a comment) by default: sessions plan and weigh with it (``service.device_registry``);
- a ``JointEncoder`` **must** implement ``read`` and ``status``.

Units are SI: metres, radians, seconds. Arrays carry the frame in their name
(``p_world`` is a point in the instrument's frame).

A measurement is never stale: each new value carries a ``sequence`` number that increases
with every fresh reading from the device; a driver that cannot get a fresh value raises
instead of returning the previous one.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from calibration.geometry import fit_sphere, pose_from_points


class Device(abc.ABC):
    """Common lifecycle: context manager, idempotent ``close``."""

    name: str = "device"

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection. Calling it twice is harmless."""

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


# --------------------------------------------------------------------------- robots


@dataclass(frozen=True, slots=True)
class RobotState:
    """What the controller reports about itself.

    ``q`` are the joint readings as the controller reports them (rad, or m for prismatic
    joints), shape ``(n,)``.
    """

    q: np.ndarray
    moving: bool
    protective_stop: bool
    emergency_stop: bool
    program_running: bool
    timestamp_s: float

    @property
    def stopped_by_safety(self) -> bool:
        return self.protective_stop or self.emergency_stop


# What a controller tells of its own kinematics (its factory calibration, not a published table).
KinematicsSource = Literal["forward_kinematics", "tcp_pose"]


class Robot(Device):
    """A robot controller that reports joint readings and moves to joint targets.

    What it **might** do beyond that, declared (the module docstring): ``takes_payload``,
    ``kinematics_source`` (None: it tells nothing of its kinematics) and ``joint_resolution_rad``
    (the step of its joint readings; 0: floating point)."""

    n_joints: int
    takes_payload: bool = False
    kinematics_source: KinematicsSource | None = None
    joint_resolution_rad: float = 0.0

    @abc.abstractmethod
    def read_joints(self) -> np.ndarray:
        """Fresh joint readings, shape ``(n,)``, rad (m for prismatic joints)."""

    @abc.abstractmethod
    def move_joints(self, q: np.ndarray, *, speed_rad_s: float, accel_rad_s2: float, timeout_s: float = 60.0) -> None:
        """Move to joint target ``q`` ``(n,)`` and return once it is reached.

        Raises ``RobotStoppedError`` if a protective or emergency stop or :meth:`stop` (from
        another thread: at once, saying "stopped by stop()") interrupts the move,
        ``DeviceTimeoutError`` if it does not finish within ``timeout_s``.
        """

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now (decelerating). Safe to call when nothing moves."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """The controller's current state."""

    def set_payload(self, mass_kg: float, cog_m) -> None:
        """Tell the controller the payload now mounted: ``mass_kg`` and its centre of gravity
        ``cog_m`` (3,) relative to the tool flange (UR's ``set_payload``), so that it (and a
        calibration with joint compliance) accounts for the arm's sag under it. Controllers
        without such an interface (``takes_payload`` False) raise ``NotImplementedError``: set the
        payload on the pendant."""
        raise NotImplementedError(f"{type(self).__name__}: this controller has no payload interface")

    def forward_kinematics(self, q: np.ndarray, tcp_offset: np.ndarray | None = None) -> np.ndarray:
        """(``kinematics_source == "forward_kinematics"``) The controller's own forward kinematics,
        ``T_base_tcp`` (N, 4, 4) for readings ``q`` (N, n); ``tcp_offset`` a pose from the flange
        (default none). Nothing moves."""
        raise NotImplementedError(f"{type(self).__name__}: this controller answers no forward kinematics")

    def read_tcp_pose(self) -> np.ndarray:
        """(``kinematics_source == "tcp_pose"``) The TCP pose the controller computes where it
        stands, ``T_base_tcp`` (4, 4)."""
        raise NotImplementedError(f"{type(self).__name__}: this controller reports no TCP pose")


# --------------------------------------------------------------------------- position sensors


@dataclass(frozen=True, slots=True)
class PointMeasurement:
    """One measured point: the reflector (target) position in the instrument frame.

    ``p_world`` (3,) m; ``sigma`` (3,) m standard uncertainty per axis; ``sequence`` increases
    with every fresh measurement.
    """

    p_world: np.ndarray
    sigma: np.ndarray
    sequence: int
    timestamp_s: float = field(default_factory=time.time)
    status: str = "ok"


class PositionSensor(Device):
    """A laser tracker (or anything that measures one point at a time)."""

    @property
    @abc.abstractmethod
    def sigma_m(self) -> float:
        """The per-axis standard uncertainty of one measured point (m), as its config declares."""

    @abc.abstractmethod
    def measure(self) -> PointMeasurement:
        """Take one fresh measurement. Raises ``MeasurementError`` if it cannot be taken."""

    @abc.abstractmethod
    def status(self) -> str:
        """``"ready"``, ``"beam_broken"`` or ``"not_initialised"``."""


class SteerablePositionSensor(PositionSensor):
    """A laser tracker that can be pointed at where the reflector should be and search for it
    there (after a beam break, a tracker has lost the reflector until it is found again)."""

    @abc.abstractmethod
    def find_reflector(self, p_world: np.ndarray) -> None:
        """Point at ``p_world`` (3,) m, instrument frame, and search for the reflector there.
        Raises ``MeasurementError`` when it is not found."""


# --------------------------------------------------------------------------- CMMs


@dataclass(frozen=True, slots=True)
class BallMeasurement:
    """A tooling-ball centre from probed points: ``centre_world`` (3,) m, fitted ``radius_m``,
    RMS distance of the probed points from the fitted sphere, and the points themselves."""

    centre_world: np.ndarray
    radius_m: float
    residual_rms_m: float
    points_world: np.ndarray


@dataclass(frozen=True, slots=True)
class PoseMeasurement:
    """A full tool pose from three or more tooling balls (book §3.3.4, eq. 6.12-6.15).

    ``T_world_tool`` (4, 4); ``residual_rms_m`` how far the measured ball centres lie from the
    fitted rigid transform of their tool-frame positions.
    """

    T_world_tool: np.ndarray
    balls: tuple[BallMeasurement, ...]
    residual_rms_m: float


class Cmm(Device):
    """A coordinate measuring machine with a touch-trigger probe."""

    @property
    @abc.abstractmethod
    def sigma_m(self) -> float:
        """The per-axis standard uncertainty of a measured tool position (m), as its config declares."""

    @abc.abstractmethod
    def probe(self, p_world: np.ndarray, approach_world: np.ndarray) -> np.ndarray:
        """Probe the surface near each nominal point.

        ``p_world`` (k, 3) nominal surface points; ``approach_world`` (k, 3) unit directions the
        probe travels in. Returns the touched points ``(k, 3)`` (probe-radius compensated along
        the approach direction). Raises ``MeasurementError`` on no touch.
        """

    def measure_ball(self, centre_world: np.ndarray, radius_m: float, *, n_points: int = 5) -> BallMeasurement:
        """Probe a tooling ball near its nominal centre and fit its centre.

        Points are spread over the upper hemisphere (seen from +z of the world frame); at least
        four are needed for a sphere of unknown radius (book §6.2: four touches a ball).
        The centre is fitted with the ball's calibrated radius ``radius_m``: on a cap of the
        sphere a free radius correlates with the centre's height (about four times the probing
        noise in z with the 45-degree ring). The free-radius fit gives the reported
        ``radius_m`` and ``residual_rms_m``, a check on the ball and the probe.
        """
        if n_points < 4:
            raise ValueError(f"n_points must be at least 4 to fit a sphere, got {n_points}")
        centre_world = np.asarray(centre_world, dtype=float).reshape(3)
        dirs = _hemisphere_directions(n_points)
        nominal = centre_world + radius_m * dirs
        touched = self.probe(nominal, -dirs)
        centre_free, radius, rms = fit_sphere(touched)
        centre, _, _ = fit_sphere(touched, radius=radius_m, centre_hint=centre_free)
        return BallMeasurement(centre, float(radius), float(rms), touched)

    def measure_pose(
        self,
        balls_tool: np.ndarray,
        T_world_tool_nominal: np.ndarray,
        radius_m: float,
        *,
        n_points: int = 5,
    ) -> PoseMeasurement:
        """Measure three or more tooling balls and fit the tool pose.

        ``balls_tool`` (k, 3) ball centres in the tool frame, k >= 3; ``T_world_tool_nominal``
        (4, 4) where the tool is expected, used only to find the balls.
        """
        balls_tool = np.asarray(balls_tool, dtype=float)
        if balls_tool.ndim != 2 or balls_tool.shape[0] < 3 or balls_tool.shape[1] != 3:
            raise ValueError(f"`balls_tool` must have shape (k, 3) with k >= 3; got {balls_tool.shape}")
        T = np.asarray(T_world_tool_nominal, dtype=float)
        expected = balls_tool @ T[:3, :3].T + T[:3, 3]
        balls = tuple(self.measure_ball(c, radius_m, n_points=n_points) for c in expected)
        centres = np.array([b.centre_world for b in balls])
        T_fit, rms = pose_from_points(balls_tool, centres)
        return PoseMeasurement(T_fit, balls, float(rms))


def _hemisphere_directions(n: int) -> np.ndarray:
    """``n`` unit vectors: one at the pole (+z) and the rest on a ring at 45 degrees."""
    ring = n - 1
    phi = 2 * np.pi * np.arange(ring) / ring
    tilt = np.pi / 4
    ring_dirs = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.full(ring, np.cos(tilt))], axis=1)
    return np.vstack([[0.0, 0.0, 1.0], ring_dirs])


# --------------------------------------------------------------------------- joint encoders


@dataclass(frozen=True, slots=True)
class EncoderReading:
    """A reference encoder's or resolver's reading of one joint.

    ``angle_rad`` the position in radians (counts scaled by the device's resolution),
    ``counts`` the raw value, ``sequence`` increases with every fresh reading.
    """

    angle_rad: float
    counts: int
    sequence: int
    timestamp_s: float = field(default_factory=time.time)
    status: str = "ok"


class JointEncoder(Device):
    """A reference encoder or resolver reader on one joint.

    ``status()`` belongs to the interface (like ``PositionSensor.status``) because a reading
    cannot say why there is none: a fault makes ``read()`` raise, so a reading's ``status``
    is always ``"ok"``. ``status()`` says, without taking a reading, whether readings can be
    taken and if not why (for a connection test, or before a sweep).
    """

    @abc.abstractmethod
    def read(self) -> EncoderReading:
        """One fresh reading. Raises ``DeviceTimeoutError`` when none arrives in time."""

    @abc.abstractmethod
    def status(self) -> str:
        """``"operational"`` when the device is ready to be read, otherwise its state or what
        is wrong, in a few words (for example ``"no heartbeat"``, ``"fault: EMCY 0x7320
        (position sensor)"``, ``"disconnected"``). Never raises and never waits for the device."""
