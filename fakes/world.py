"""The simulated world shared by every fake device of one cell.

One ``SimCell`` holds the truth: a robot whose joints move with simple timing and whose real
kinematics is the ``truth`` model, and the faults to inject. The device fakes (UR controller,
Modbus server, tracker, CMM, CANopen encoder nodes) read and drive it; they never share state
any other way. Everything is SI: metres, radians, seconds.

A cell whose robot is a Universal Robots arm also has a *factory calibration*
(:class:`FactoryCalibration`): the controller's own per-robot DH deltas to the published table,
as ``calibration.conf`` keeps them on a real controller. The UR controller fake and the Modbus
server compute everything Cartesian through that model (``SimCell.controller_fk`` /
``controller_ik``), never through the truth: like a real controller, they know only their
factory calibration.

Simulated time: a motion that would take ``t`` seconds on the real robot takes
``t * time_scale`` seconds of wall time (``time_scale = 0``: instant).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from calibration.conventions import poe_to_dh
from calibration.ik import solve_ik, ur_geometry, ur_ik_all
from calibration.kinematics import fk, joint_variables
from calibration.model import KinematicModel
from calibration.robots import nominal
from calibration.simulate import perturbed
from calibration.transforms import homogeneous, matrix_to_rotvec, pose_to_matrix, rotvec_to_matrix
from calibration.transmission import JointTransmission


def ur_pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """A UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) -> (4, 4)."""
    pose = np.asarray(pose, dtype=float).reshape(6)
    return homogeneous(rotvec_to_matrix(pose[3:]), pose[:3])


def matrix_to_ur_pose(T: np.ndarray) -> list[float]:
    """(4, 4) -> a UR pose ``[x, y, z, rx, ry, rz]``."""
    T = np.asarray(T, dtype=float)
    return [*map(float, T[:3, 3]), *map(float, matrix_to_rotvec(T[:3, :3]))]


# Library robots whose published DH table a UR controller starts from.
UR_MODELS = ("ur3e", "ur5e", "ur10e", "ur16e")


@dataclass
class Faults:
    """Faults to inject, set from ``recal fake-cell --fault NAME=VALUE`` or a test.

    Rates are probabilities per request; ``*_at`` lists are 1-based counts at which the fault
    fires once (deterministic, for tests). Each fake counts its own requests (the tracker its
    commands, the CMM its commands, the CAN gateway its position requests, the UR controller
    the commands its control script receives, the Modbus server its requests), so a count
    means "the N-th request to that device"; each fake's docstring says what it counts.
    """

    drop_connection_at: list[int] = field(
        default_factory=list, metadata={"help": "requests whose connection is closed instead of answered"}
    )
    delay_s: float = field(
        default=0.0, metadata={"help": "extra latency (s) before every reply, or only those of delay_at"}
    )
    delay_at: list[int] = field(
        default_factory=list,
        metadata={"help": "requests whose reply alone waits delay_s (tracker, CMM, CAN, UR commands)"},
    )
    garble_rate: float = field(default=0.0, metadata={"help": "probability that a reply is garbled"})
    garble_at: list[int] = field(default_factory=list, metadata={"help": "requests whose reply is garbled"})
    beam_break_rate: float = field(
        default=0.0, metadata={"help": "tracker: probability that a measurement finds the beam broken"}
    )
    beam_break_at: list[int] = field(
        default_factory=list,
        metadata={"help": "tracker: MEAS? (emScon: StartMeasurement) counts that find the beam broken"},
    )
    protective_stop_at_move: list[int] = field(
        default_factory=list, metadata={"help": "robot: moves that stop halfway in a protective stop"}
    )
    emergency_stop_at_move: list[int] = field(
        default_factory=list, metadata={"help": "robot: moves that stop halfway in an emergency stop (arm powered off)"}
    )
    no_touch_at: list[int] = field(default_factory=list, metadata={"help": "CMM: PtMeas counts that touch nothing"})
    silent_nodes: list[int] = field(
        default_factory=list, metadata={"help": "CAN: node ids from which nothing reaches the bus"}
    )
    sensor_fault_at: list[int] = field(
        default_factory=list, metadata={"help": "CAN: position requests answered with a sensor fault (EMCY)"}
    )
    error_status_at: list[int] = field(
        default_factory=list,
        metadata={"help": "emScon tracker: commands answered with an error packet (ES_RS_Unknown)"},
    )

    def reply_delay_s(self, n: int | None) -> float:
        """The delay before the reply to request ``n``: ``delay_s`` for every reply, or, when
        ``delay_at`` is set, only for the requests it lists (``n=None``: an uncounted reply,
        which is then not delayed)."""
        if not self.delay_at:
            return self.delay_s
        return self.delay_s if n in self.delay_at else 0.0


@dataclass(frozen=True)
class FactoryCalibration:
    """A UR controller's factory calibration: its corrections to the published DH table of
    ``published`` (a library robot, ``calibration.robots``), one value per joint, SI (rad, m),
    as in the ``[mounting]`` section of a real controller's ``calibration.conf``.

    The controller's model is ``theta_i + delta_theta_i``, ``a_i + delta_a_i``,
    ``d_i + delta_d_i``, ``alpha_i + delta_alpha_i`` (standard DH), base and flange where the
    chain puts them (the controller's base frame is defined by its own model). The parallel
    joints 2-4 come out "linearised" (``calibration_status`` 2): a twist of a fraction of a
    milliradian between nearly parallel axes moves their common normal metres away, so
    ``delta_d`` of joints 2-4 are metres to kilometres with a sum near zero. The chain
    is exact, only awkward to read.
    """

    published: str
    delta_theta: tuple[float, ...]
    delta_a: tuple[float, ...]
    delta_d: tuple[float, ...]
    delta_alpha: tuple[float, ...]
    calibration_status: int = 2

    FIELDS = ("delta_theta", "delta_a", "delta_d", "delta_alpha")

    def model(self) -> KinematicModel:
        """The controller's kinematic model: the published table plus the deltas."""
        pub = nominal(self.published)
        joints = tuple(
            dataclasses.replace(j, theta=j.theta + dt, a=j.a + da, d=j.d + dd, alpha=j.alpha + dal)
            for j, dt, da, dd, dal in zip(pub.joints, self.delta_theta, self.delta_a, self.delta_d, self.delta_alpha)
        )
        return dataclasses.replace(pub, name=f"{self.published}-controller", joints=joints)

    def to_dict(self) -> dict:
        """The ``ur_factory_calibration`` block of a truth file (SI)."""
        return {
            "published": self.published,
            "calibration_status": self.calibration_status,
            **{f: list(getattr(self, f)) for f in self.FIELDS},
        }

    @classmethod
    def from_dict(cls, doc, where: str = "ur_factory_calibration") -> FactoryCalibration:
        """Read the block written by :meth:`to_dict`; ``ValueError`` names the field at fault."""
        if not isinstance(doc, dict):
            raise ValueError(f"{where}: expected an object with published, {', '.join(cls.FIELDS)}")
        published = str(doc.get("published", "")).lower()
        if published not in UR_MODELS:
            raise ValueError(f"{where}.published: expected one of {', '.join(UR_MODELS)}, got {doc.get('published')!r}")
        values = {}
        for f in cls.FIELDS:
            v = doc.get(f)
            if (
                not isinstance(v, list)
                or len(v) != 6
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in v)
            ):
                raise ValueError(f"{where}.{f}: expected a list of 6 numbers (SI: rad or m), got {v!r}")
            values[f] = tuple(float(x) for x in v)
        status = doc.get("calibration_status", 2)
        if status not in (0, 1, 2):
            raise ValueError(f"{where}.calibration_status: expected 0, 1 or 2, got {status!r}")
        return cls(published=published, calibration_status=int(status), **values)


def draw_factory_calibration(
    published: str,
    seed: int = 0,
    *,
    length_m: float = 0.3e-3,
    angle_rad: float = 0.3e-3,
    offset_rad: float = 0.5e-3,
) -> FactoryCalibration:
    """A factory calibration of the size real UR robots have: every joint axis of the
    published robot tilted (``angle_rad``) and shifted (``length_m``), every joint offset by
    ``offset_rad`` (standard deviations), written as a UR controller writes it: plain DH deltas
    (no Hayati form), so that joints 2-4 come out in the linearised form. The controller's base
    frame is its own first axis (where ``poe_to_dh`` puts frame 0), and its flange the last DH
    frame: what the perturbation moves beyond those is the robot's mounting, not the controller's."""
    pub = nominal(published)
    physical = perturbed(
        pub, np.random.default_rng(seed), length_m=length_m, angle_rad=angle_rad, offset_rad=offset_rad
    )
    # parallel_tol_rad=0: never Hayati's beta, as on the controller.
    dh = poe_to_dh(physical, reference=pub, parallel_tol_rad=0.0)
    return FactoryCalibration(
        published=published,
        delta_theta=tuple(float(j.theta - p.theta) for j, p in zip(dh.joints, pub.joints)),
        delta_a=tuple(float(j.a - p.a) for j, p in zip(dh.joints, pub.joints)),
        delta_d=tuple(float(j.d - p.d) for j, p in zip(dh.joints, pub.joints)),
        delta_alpha=tuple(float(j.alpha - p.alpha) for j, p in zip(dh.joints, pub.joints)),
    )


def published_ur_for(truth: KinematicModel) -> str | None:
    """The library UR whose published table the true robot is closest to, or ``None`` when it
    is no UR arm (6 revolute joints, every relative flange displacement within 5 cm). The
    comparison uses ``T(q_a)^-1 T(q_b)``, which the base frame (where the robot stands in the
    world) does not change, so a truth of any convention and base placement is recognised."""
    if truth.n_joints != 6 or any(not j.revolute for j in truth.joints):
        return None
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (16, 6))

    def relative(model: KinematicModel) -> np.ndarray:
        T = fk(dataclasses.replace(model, tool=np.zeros(6)), q)
        return np.einsum("nji,nj->ni", T[:-1, :3, :3], T[1:, :3, 3] - T[:-1, :3, 3])

    p = relative(truth)
    best, best_err = None, 0.05
    for name in UR_MODELS:
        err = float(np.max(np.linalg.norm(relative(nominal(name)) - p, axis=1)))
        if err < best_err:
            best, best_err = name, err
    return best


@dataclass(frozen=True)
class Noise:
    """Standard deviations of the simulated instruments (SI)."""

    tracker_m: float = 20e-6  # per axis (the line-protocol tracker)
    # The emScon tracker's maximum permissible error of a point, MPE = const + per_m * range:
    # Leica's published Uxyz for the AT960/AT930 (fakes/leica_tracker.py).
    tracker_mpe_const_m: float = 15e-6
    tracker_mpe_per_m: float = 6e-6
    cmm_m: float = 2e-6  # per probed point, along the surface normal
    encoder_counts: float = 0.5
    robot_repeatability_rad: float = 0.0  # joint noise on arrival (robot repeatability)


class SimCell:
    """A robot cell: the true robot, its motion, and the noise and faults of its devices.

    Thread-safe: every fake may call it from its own thread.
    """

    def __init__(
        self,
        truth: KinematicModel,
        *,
        seed: int = 0,
        time_scale: float = 0.0,
        noise: Noise | None = None,
        faults: Faults | None = None,
        q_home: np.ndarray | None = None,
        tracker_range_m: float = 30.0,
        cmm_volume_m: tuple[np.ndarray, np.ndarray] | None = None,
        balls_tool: dict[str, np.ndarray] | None = None,
        ball_radius_m: float = 0.0125,
        factory: FactoryCalibration | None = None,
        transmission: JointTransmission | None = None,
    ):
        self.truth = truth
        # joint transmission errors (calibration.simulate.harmonic_drive_errors): each joint truly
        # stands at its reading plus δq(reading), which no device of the cell reports
        self.transmission = transmission
        # The controller's own kinematics (robot base frame, flange): the factory calibration's
        # model; without one (not a UR cell) the controller computes with the truth, in the
        # world frame, as this simulator always did.
        self.factory = factory
        self.controller = factory.model() if factory is not None else truth
        self._published = nominal(factory.published) if factory is not None else None
        self.time_scale = float(time_scale)
        self.noise = noise or Noise()
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(seed)
        self.tracker_range_m = tracker_range_m
        self.cmm_volume_m = cmm_volume_m
        self.ball_radius_m = ball_radius_m
        # Tooling balls sit at the truth model's targets whose names start with "ball";
        # the reflector is every other target.
        self.balls_tool = (
            balls_tool
            if balls_tool is not None
            else {name: p for name, p in truth.targets.items() if name.startswith("ball")}
        )
        self._lock = threading.RLock()
        n = truth.n_joints
        self._q_start = np.zeros(n) if q_home is None else np.asarray(q_home, float).copy()
        self._q_goal = self._q_start.copy()
        self._t_start = 0.0
        self._t_end = 0.0
        self.protective_stop = False
        self.emergency_stop = False  # the emergency stop button is pressed
        self.powered = True  # the arm is powered on ...
        self.brakes_released = True  # ... and its brakes are released: it can move
        self.program_running = False
        self.move_count = 0
        self.counters: dict[str, int] = {}
        self.reflector: str | None = next((name for name in truth.targets if not name.startswith("ball")), None)
        # The payload the controller was told it carries (kg, centre of gravity in the tool
        # frame, m): a truth with joint compliance under gravity sags under it.
        self.payload = np.zeros(4)

    # ----------------------------------------------------------------- bookkeeping

    def count(self, key: str) -> int:
        """Increment and return the 1-based request counter ``key`` (for deterministic faults)."""
        with self._lock:
            self.counters[key] = self.counters.get(key, 0) + 1
            return self.counters[key]

    def chance(self, rate: float) -> bool:
        with self._lock:
            return rate > 0 and self.rng.random() < rate

    def normal(self, sigma: float, size=None) -> np.ndarray:
        with self._lock:
            return self.rng.normal(0.0, sigma, size)

    # ----------------------------------------------------------------- robot motion

    def joints(self) -> np.ndarray:
        """The controller's joint readings now, ``(n,)``."""
        with self._lock:
            return self._q_at(time.monotonic())

    def is_moving(self) -> bool:
        with self._lock:
            return time.monotonic() < self._t_end and not np.allclose(self._q_start, self._q_goal)

    def _q_at(self, now: float) -> np.ndarray:
        if now >= self._t_end or self._t_end <= self._t_start:
            return self._q_goal.copy()
        s = (now - self._t_start) / (self._t_end - self._t_start)
        return self._q_start + s * (self._q_goal - self._q_start)

    def motion_duration_s(self, q_from: np.ndarray, q_to: np.ndarray, speed: float, accel: float) -> float:
        """Time a trapezoidal joint move takes on the real robot (the slowest joint)."""
        dq = float(np.max(np.abs(np.asarray(q_to) - np.asarray(q_from)), initial=0.0))
        speed = max(float(speed), 1e-6)
        accel = max(float(accel), 1e-6)
        if dq <= speed * speed / accel:  # triangular profile
            return 2.0 * np.sqrt(dq / accel)
        return dq / speed + speed / accel

    def start_move(self, q_goal: np.ndarray, speed: float, accel: float) -> float:
        """Start a joint move; returns its wall-clock duration. Raises ``RuntimeError`` if the
        robot is stopped by safety or not running (powered off, brakes on). A protective or
        emergency stop injected for this move stops the robot halfway."""
        q_goal = np.asarray(q_goal, dtype=float).reshape(-1)
        if q_goal.shape != (self.truth.n_joints,):
            raise ValueError(f"joint target must have {self.truth.n_joints} values, got {q_goal.shape}")
        with self._lock:
            if self.protective_stop or self.emergency_stop:
                raise RuntimeError("robot is stopped by safety")
            if not self.running:
                raise RuntimeError("robot is not powered on with its brakes released")
            self.move_count += 1
            now = time.monotonic()
            q_now = self._q_at(now)
            duration = self.motion_duration_s(q_now, q_goal, speed, accel) * self.time_scale
            if self.noise.robot_repeatability_rad > 0:
                q_goal = q_goal + self.rng.normal(0, self.noise.robot_repeatability_rad, q_goal.shape)
            if self.move_count in self.faults.protective_stop_at_move:
                q_goal = q_now + 0.5 * (q_goal - q_now)
                self.protective_stop = True
            if self.move_count in self.faults.emergency_stop_at_move:
                q_goal = q_now + 0.5 * (q_goal - q_now)
                self.emergency_stop = True
                self.powered = self.brakes_released = False  # a category 1 stop
            self._q_start, self._q_goal = q_now, q_goal
            self._t_start, self._t_end = now, now + duration
            return duration

    def stop(self) -> None:
        """Stop where the robot is now."""
        with self._lock:
            q = self._q_at(time.monotonic())
            self._q_start = self._q_goal = q
            self._t_end = self._t_start = time.monotonic()

    # ----------------------------------------------------------------- safety and power
    # As on a Universal Robots arm: an emergency stop (a category 1 stop) halts the robot and
    # then powers the arm off. Only a person releases the button; after that the arm must be
    # powered on and its brakes released before it moves again. A protective stop leaves the
    # arm powered; it is unlocked remotely.

    @property
    def running(self) -> bool:
        """Powered on with the brakes released (UR robot mode RUNNING)."""
        return self.powered and self.brakes_released

    def power_off(self) -> None:
        """Stop now and power the arm off (the brakes engage)."""
        with self._lock:
            self.stop()
            self.powered = self.brakes_released = False

    def press_emergency_stop(self) -> None:
        """The emergency stop button is pressed: stop now and power the arm off."""
        with self._lock:
            self.power_off()
            self.emergency_stop = True

    def release_emergency_stop(self) -> None:
        """The button is released (by a person); the arm stays powered off."""
        with self._lock:
            self.emergency_stop = False

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop; ``False`` if there is none."""
        with self._lock:
            was_stopped, self.protective_stop = self.protective_stop, False
            return was_stopped

    def power_on(self) -> bool:
        """Power the arm on (brakes stay on); ``False`` while the emergency stop is pressed."""
        with self._lock:
            if self.emergency_stop:
                return False
            self.powered = True
            return True

    def release_brakes(self) -> bool:
        """Release the brakes, powering the arm on first if needed; ``False`` while the
        emergency stop is pressed."""
        with self._lock:
            if not self.power_on():
                return False
            self.brakes_released = True
            return True

    # ----------------------------------------------------------------- the controller's kinematics

    def controller_fk(self, q: np.ndarray | None = None, tcp_offset: np.ndarray | None = None) -> np.ndarray:
        """``get_forward_kin(q, tcp)``: the TCP pose (N, 4, 4) the controller computes for
        readings ``q`` (N, 6) (default: the joints now, N = 1) and TCP offset ``tcp_offset``
        (6,) (flange frame, UR pose: metres and a rotation vector; default none), through its
        factory calibration, never the truth."""
        q = self.joints()[None, :] if q is None else np.asarray(q, dtype=float).reshape(-1, self.truth.n_joints)
        T = fk(self.controller, q)
        if tcp_offset is not None:
            T = T @ ur_pose_to_matrix(tcp_offset)
        return T

    def controller_ik(
        self, T_base_tcp: np.ndarray, q_near: np.ndarray | None = None, tcp_offset: np.ndarray | None = None
    ) -> np.ndarray | None:
        """``get_inverse_kin(x, qnear)``: the readings (6,) that put the TCP at ``T_base_tcp``
        (4, 4) through the controller's model, on the branch nearest ``q_near`` (default: the
        joints now), or ``None`` when the pose is out of reach. As a calibrated controller
        does: the published table's closed form picks the branch, Newton on the calibrated
        model finishes (to 1e-10 m and rad)."""
        q_near = self.joints() if q_near is None else np.asarray(q_near, dtype=float).reshape(-1)
        T = np.asarray(T_base_tcp, dtype=float)
        if tcp_offset is not None:
            T = T @ np.linalg.inv(ur_pose_to_matrix(tcp_offset))
        closed = self._published if self._published is not None else self.controller
        if ur_geometry(closed) is not None:
            qs, oks, _ = ur_ik_all(closed, T[None], q_near[None])
            if not np.any(oks):
                return None
            dist = np.sum((qs[0] - q_near) ** 2, axis=1) + np.where(oks[0], 0.0, 1e6)
            q0 = qs[0, int(np.argmin(dist))]
        else:
            q0 = q_near
        r = solve_ik(self.controller, T[None], q0[None], position_tol_m=1e-10, rotation_tol_rad=1e-10)
        return r.q[0] if bool(r.converged[0]) else None

    # ----------------------------------------------------------------- truth

    def set_payload(self, mass_kg: float, cog_flange_m) -> None:
        """The payload mounted now: ``mass_kg`` and its centre of gravity relative to the tool
        flange (as UR's ``set_payload`` takes it), kept in the tool frame."""
        F = pose_to_matrix(self.truth.tool)
        cog_tool = F[:3, :3].T @ (np.asarray(cog_flange_m, float) - F[:3, 3])
        with self._lock:
            self.payload = np.array([float(mass_kg), *cog_tool])

    def T_world_tool(self) -> np.ndarray:
        """The true tool pose now, (4, 4): a compliant truth sags under the payload."""
        return fk(self.truth, self._true_readings(), self.payload)[0]

    def _true_readings(self) -> np.ndarray:
        """(1, n): the readings the truth's kinematics sees, transmission errors included."""
        q = self.joints()[None, :]
        return q if self.transmission is None else q + self.transmission.joint_errors(q)

    def point_world(self, p_tool: np.ndarray) -> np.ndarray:
        """Where a point fixed in the tool frame truly is now, (3,)."""
        T = self.T_world_tool()
        return T[:3, :3] @ np.asarray(p_tool, float) + T[:3, 3]

    def target_world(self, name: str | None = None) -> np.ndarray:
        """The true position of a named target (default: the reflector, else the tool origin)."""
        name = name if name is not None else self.reflector
        p_tool = np.zeros(3) if name is None else self.truth.targets[name]
        return self.point_world(p_tool)

    def joint_angle(self, joint: int) -> float:
        """The true rotation of joint ``joint`` (1-based) from its kinematic zero, rad: what a
        reference encoder on the joint sees (book eq. 2.4: gain, offset and gear eccentricity
        relative to the controller's reading)."""
        v = joint_variables(self.truth, self._true_readings())[0]
        return float(v[joint - 1])
