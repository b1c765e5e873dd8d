"""What every ``Robot`` driver does against the simulated cell, written once.

A test class for one driver inherits ``RobotContract`` and provides

- ``connect(self, endpoint: dict) -> Robot``: a driver for the cell whose endpoint line
  (contracts §7) is ``endpoint``;
- ``tolerance_rad``: how close a reading comes to the commanded target;
- ``drop_faults``: ``fakes.cell`` flags under which one or more requests of the first few
  moves lose their connection beyond what the driver repairs by itself.

The cells run in other processes (``tests/drivers/conftest.py``), so every byte goes over a
real socket through the real client library.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time

import numpy as np
import pytest

from drivers.base import Robot
from drivers.errors import DeviceConnectionError, RobotStoppedError

SPEED_RAD_S = 1.0
ACCEL_RAD_S2 = 2.0
HOME = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])
TIME_SCALE = 0.25  # of the timed cell


def move_duration_s(dq_rad: float) -> float:
    """Real duration of a trapezoidal joint move at SPEED_RAD_S, ACCEL_RAD_S2 (the fake's)."""
    if dq_rad <= SPEED_RAD_S**2 / ACCEL_RAD_S2:
        return 2.0 * np.sqrt(dq_rad / ACCEL_RAD_S2)
    return dq_rad / SPEED_RAD_S + SPEED_RAD_S / ACCEL_RAD_S2


def dashboard(host: str, *commands: str) -> list[str]:
    """The replies of the cell's UR dashboard server (port 29999) to ``commands``."""
    with socket.create_connection((host, 29999), timeout=5.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()  # the greeting
        replies = []
        for command in commands:
            sock.sendall(command.encode() + b"\n")
            replies.append(reader.readline().decode().strip())
    return replies


def step_towards_zero(q: np.ndarray, joint: int, dq_rad: float) -> np.ndarray:
    """``q`` with one joint moved by ``dq_rad`` towards 0 (stays inside any +-2 pi limit)."""
    target = q.copy()
    target[joint] -= np.sign(q[joint] or 1.0) * dq_rad
    return target


# How long a test waits for the controller's state packets to show what it just did (a released
# stop, a powered arm): generous, since they come every few milliseconds and the wait ends as
# soon as they do; only a driver that never sees the change waits this long, and fails.
STATE_TIMEOUT_S = 10.0


def wait_for(condition, timeout_s: float, what: str, robot) -> None:
    """Return once ``condition()`` holds; fail naming ``what`` after ``timeout_s``. Between tries
    the robot's joints are read (fresh state from the controller)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"waited {timeout_s:g} s for {what}"
        robot.read_joints()
        time.sleep(0.01)


class RobotContract:
    tolerance_rad: float = 1e-9
    drop_faults: tuple[str, ...] = ()

    def connect(self, endpoint: dict) -> Robot:
        raise NotImplementedError

    def move(self, robot: Robot, q: np.ndarray, **kwargs) -> None:
        robot.move_joints(q, speed_rad_s=SPEED_RAD_S, accel_rad_s2=ACCEL_RAD_S2, **kwargs)

    @pytest.fixture(scope="class")
    @classmethod
    def robot(cls, fake_cell):
        with contextlib.closing(cls().connect(fake_cell.endpoint)) as robot:
            yield robot

    @pytest.fixture(scope="class")
    @classmethod
    def timed_robot(cls, timed_cell):
        with contextlib.closing(cls().connect(timed_cell.endpoint)) as robot:
            yield robot

    # ----------------------------------------------------------------- readings and moves

    def test_read_joints_gives_one_finite_value_per_joint(self, robot):
        q = robot.read_joints()
        assert q.shape == (robot.n_joints,)
        assert np.all(np.isfinite(q))

    def test_move_arrives_at_the_target(self, robot):
        # joint 6 beyond -pi and joint 1 negative: the readings must unwrap correctly
        target = HOME + np.array([-0.5, -0.05, 0.2, 0.0, 0.1, -4.0])
        self.move(robot, target)
        np.testing.assert_allclose(robot.read_joints(), target, atol=self.tolerance_rad)
        state = robot.state()
        assert not state.moving
        assert not state.stopped_by_safety
        assert state.program_running
        np.testing.assert_allclose(state.q, target, atol=self.tolerance_rad)

    def test_each_state_is_a_new_reading(self, robot):
        first, second = robot.state(), robot.state()
        assert second.timestamp_s > first.timestamp_s

    def test_target_outside_the_joint_limits_is_refused_before_moving(self, robot):
        self.move(robot, HOME)
        target = HOME.copy()
        target[2] = 7.0
        with pytest.raises(ValueError, match="joint 3"):
            self.move(robot, target)
        np.testing.assert_allclose(robot.read_joints(), HOME, atol=self.tolerance_rad)

    @pytest.mark.parametrize("speed, accel", [(0.0, 1.0), (-1.0, 1.0), (50.0, 1.0), (1.0, 0.0), (1.0, 500.0)])
    def test_speed_and_acceleration_outside_the_limits_are_refused(self, robot, speed, accel):
        with pytest.raises(ValueError, match=r"speed_rad_s|accel_rad_s2"):
            robot.move_joints(HOME + 0.1, speed_rad_s=speed, accel_rad_s2=accel)

    def test_wrong_number_of_joints_is_refused(self, robot):
        with pytest.raises(ValueError, match="`q`"):
            self.move(robot, np.zeros(robot.n_joints + 1))

    def test_stop_when_idle_is_harmless(self, robot):
        self.move(robot, HOME)
        robot.stop()
        np.testing.assert_allclose(robot.read_joints(), HOME, atol=self.tolerance_rad)
        self.move(robot, HOME + 0.1)
        np.testing.assert_allclose(robot.read_joints(), HOME + 0.1, atol=self.tolerance_rad)

    # ----------------------------------------------------------------- simulated time

    def test_moves_take_the_simulated_time(self, timed_robot):
        q0 = timed_robot.read_joints()
        target = step_towards_zero(q0, 0, 0.5)
        expected_s = move_duration_s(0.5) * TIME_SCALE
        started = time.monotonic()
        self.move(timed_robot, target)
        elapsed_s = time.monotonic() - started
        assert 0.9 * expected_s <= elapsed_s < expected_s + 2.0
        np.testing.assert_allclose(timed_robot.read_joints(), target, atol=self.tolerance_rad)

    def test_state_reports_a_move_in_progress(self, timed_robot):
        target = step_towards_zero(timed_robot.read_joints(), 1, 1.0)  # 0.375 s of wall time
        mover = threading.Thread(target=self.move, args=(timed_robot, target))
        mover.start()
        # Poll until the move shows, or the mover is done: a state read while the joints move
        # away from where they started must say "moving".
        seen_moving = False
        while mover.is_alive() and not seen_moving:
            seen_moving = timed_robot.state().moving
        mover.join(timeout=10.0)
        assert seen_moving, "no state read during the move said it was moving"
        assert not timed_robot.state().moving

    def test_stop_interrupts_a_move(self, timed_robot):
        q0 = timed_robot.read_joints()
        target = step_towards_zero(q0, 0, 2.0)  # 0.625 s of wall time
        errors: list[Exception] = []

        def move() -> None:
            try:
                self.move(timed_robot, target)
            except Exception as exc:  # noqa: BLE001 - kept whatever it is, so that the assertion names a wrong one
                errors.append(exc)

        mover = threading.Thread(target=move)
        mover.start()
        # stop once the move is under way (the joint has left its start), not after a guessed delay
        deadline = time.monotonic() + 5.0
        while abs(timed_robot.read_joints()[0] - q0[0]) < 0.05:
            assert mover.is_alive() and time.monotonic() < deadline, "the move did not start"
        timed_robot.stop()
        mover.join(timeout=10.0)
        assert len(errors) == 1 and isinstance(errors[0], RobotStoppedError), errors
        # the driver knows it was its own stop(), so it need not wait to see whether the move arrives
        assert "stopped by stop()" in str(errors[0]), errors[0]
        stopped = timed_robot.read_joints()
        assert abs(stopped[0] - q0[0]) > 0.05  # it moved ...
        assert abs(stopped[0] - target[0]) > 0.5  # ... and stopped well short of the target
        time.sleep(0.1)
        np.testing.assert_allclose(timed_robot.read_joints(), stopped, atol=self.tolerance_rad)
        assert not timed_robot.state().moving

    # ----------------------------------------------------------------- faults

    def test_protective_stop_raises_robot_stopped(self, fault_cell):
        cell = fault_cell("--fault", "protective_stop_at_move=2")
        with contextlib.closing(self.connect(cell.endpoint)) as robot:
            self.move(robot, HOME)
            with pytest.raises(RobotStoppedError, match="protective stop"):
                self.move(robot, HOME + 0.2)
            state = robot.state()
            assert state.protective_stop and not state.emergency_stop
            assert not state.moving
            reached = robot.read_joints()
            assert 0.0 < abs(reached[0] - HOME[0]) < 0.2 - self.tolerance_rad  # stopped on the way
            started = time.monotonic()
            with pytest.raises(RobotStoppedError, match="protective stop"):
                self.move(robot, HOME)
            assert time.monotonic() - started < 1.0
            robot.stop()  # harmless: it is stopped already
            np.testing.assert_allclose(robot.read_joints(), reached, atol=self.tolerance_rad)

    def test_emergency_stop_raises_robot_stopped_until_released_and_powered_on(self, fault_cell):
        cell = fault_cell("--fault", "emergency_stop_at_move=2")
        with contextlib.closing(self.connect(cell.endpoint)) as robot:
            self.move(robot, HOME)
            with pytest.raises(RobotStoppedError, match="emergency stop"):
                self.move(robot, HOME + 0.2)
            state = robot.state()
            assert state.emergency_stop and not state.protective_stop
            assert not state.moving and not state.program_running
            # As on a UR (docs/devices/ur.md): nothing on the wire releases an emergency stop.
            assert dashboard(cell.host, "unlock protective stop") != ["Protective stop releasing"]
            with pytest.raises(RobotStoppedError, match="emergency stop"):
                self.move(robot, HOME)
            # A person releases the button; the arm stays powered off until it is powered on
            # and its brakes are released.
            dashboard(cell.host, "sim emergency stop release", "close safety popup")
            # the release shows in the controller's next state packets: wait for the driver to
            # see it (once read straight away, under load the last packet still had the stop)
            wait_for(lambda: not robot.state().emergency_stop, STATE_TIMEOUT_S, "the emergency stop to clear", robot)
            with pytest.raises(RobotStoppedError, match="not running"):
                self.move(robot, HOME)
            assert dashboard(cell.host, "power on", "brake release") == ["Powering on", "Brake releasing"]
            # the arm reports RUNNING in the controller's next state packets (a real UR takes
            # seconds to release its brakes): move once the driver has seen it
            deadline = time.monotonic() + STATE_TIMEOUT_S
            while True:
                try:
                    self.move(robot, HOME)
                    break
                except RobotStoppedError as exc:
                    if "not running" not in str(exc) or time.monotonic() > deadline:
                        raise
                    robot.read_joints()  # fresh readings: the next state the controller sends
            np.testing.assert_allclose(robot.read_joints(), HOME, atol=self.tolerance_rad)
            assert not robot.state().stopped_by_safety

    def test_dropped_connection_raises_then_the_driver_reconnects(self, fault_cell):
        cell = fault_cell(*self.drop_faults)
        with contextlib.closing(self.connect(cell.endpoint)) as robot:
            failures = []
            for i in range(6):
                try:
                    self.move(robot, HOME + 0.05 * i)
                except DeviceConnectionError as exc:
                    failures.append(exc)
            assert failures, "the injected connection drop went unnoticed"
            assert all(cell.host in str(exc) for exc in failures)
            self.move(robot, HOME - 0.1)
            np.testing.assert_allclose(robot.read_joints(), HOME - 0.1, atol=self.tolerance_rad)

    def test_vanished_controller_gives_a_connection_error_quickly(self, fault_cell):
        cell = fault_cell()
        robot = self.connect(cell.endpoint)
        try:
            robot.read_joints()
            cell.kill()
            started = time.monotonic()
            with pytest.raises(DeviceConnectionError, match=cell.host.replace(".", r"\.")):
                robot.read_joints()
            assert time.monotonic() - started < 5.0
        finally:
            started = time.monotonic()
            robot.close()
            assert time.monotonic() - started < 10.0

    def test_absent_controller_fails_fast(self, free_host):
        started = time.monotonic()
        with pytest.raises(DeviceConnectionError, match=free_host.replace(".", r"\.")):
            self.connect({"rtde": free_host, "modbus": f"{free_host}:502"})
        assert time.monotonic() - started < 3.0

    def test_close_is_idempotent_and_final(self, fake_cell):
        robot = self.connect(fake_cell.endpoint)
        robot.close()
        robot.close()
        with pytest.raises(DeviceConnectionError, match="closed"):
            robot.read_joints()
