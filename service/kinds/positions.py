"""What the kinds that measure positions share (``pose``, ``verify``, ``circle``): the instrument
is the session's ``device``, a laser tracker (one reflector's position) or a CMM (the tool's
full pose from three tooling balls), and one configuration gives one row."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from calibration.model import KinematicModel
from drivers.base import SteerablePositionSensor
from drivers.errors import DeviceError, MeasurementError

from .. import analysis, records
from ..control import SessionStopped, retry
from ..devices import open_cmm, open_tracker, stored_devices
from ..models import Measurement
from ..problems import Invalid
from .base import SessionKind, Step, cell_devices

log = logging.getLogger("recal.sessions")


def tooling_balls(model: KinematicModel) -> dict[str, np.ndarray]:
    """The model's tooling balls (its targets named ``ball*``), what a CMM probes."""
    return {k: v for k, v in model.targets.items() if k.startswith("ball")}


def reflector_target(model: KinematicModel) -> str | None:
    """The model's reflector when the session names none: its one target that is not a tooling
    ball (what the cell's tracker follows), else the tool origin."""
    names = [k for k in model.targets if not k.startswith("ball")]
    return names[0] if len(names) == 1 else None


class PositionKind(SessionKind):
    """A session measured by the cell's tracker or CMM (``run.device``)."""

    count_help = "number of robot configurations to measure"
    instruments = ("tracker", "cmm")

    def check(self, cell, model, *, device, joints, payloads) -> None:
        devices = cell_devices(cell, field="body.device")  # the CMM's ball radius included
        if device == "cmm":
            if devices.cmm is None:
                raise Invalid("body.device", "this cell has no CMM")
            if len(tooling_balls(model)) < 3:
                raise Invalid(
                    "body.device",
                    "a CMM session needs at least three tooling balls (targets named ball*) in the cell's model",
                )
        elif not devices.has_tracker:
            raise Invalid("body.device", "this cell has no laser tracker")
        if payloads and not devices.robot_takes_payload:
            # only a controller that takes a payload (its driver says: UR's set_payload) can be told what is mounted
            raise Invalid("body.payloads", "a session with payloads needs a controller that takes one (UR, `rtde`)")

    def default_target(self, model, device):
        if device == "cmm":
            return None
        names = [n for n in model.targets if not n.startswith("ball")]
        return names[0] if names else None

    def instrument(self, run) -> str:
        return "cmm" if run.device == "cmm" else "tracker"

    def open_instrument(self, devices, cell, run, settings) -> None:
        config = stored_devices(cell.devices)  # a bad document stops it before anything moves
        if run.device == "cmm":
            devices.cmm_ball_radius_m = config.cmm_ball_radius_m
            devices.cmm = open_cmm(config, timeout_s=settings.device_timeout_s)
        else:
            devices.tracker = open_tracker(config, timeout_s=settings.device_timeout_s)

    def measure_one(self, step: Step, seq, q_read, joint) -> list[Measurement]:
        if step.devices.cmm is not None:
            return [cmm_row(step, seq, q_read, joint)]
        return [tracker_row(step, seq, q_read, joint)]


def cmm_row(step: Step, seq: int, q_read: np.ndarray, joint: int) -> Measurement:
    """The tool's pose at configuration ``seq``: the CMM probes the tooling balls where the
    cell's current model puts them and fits the tool frame to their centres."""
    from calibration.kinematics import fk
    from calibration.transforms import matrix_to_quat

    balls = tooling_balls(step.guide)
    if len(balls) < 3:  # checked when the session started; the model may have changed since
        raise SessionStopped(
            "failed", "a CMM session needs at least three tooling balls (targets named ball*) in the cell's model"
        )
    qv = np.asarray(q_read, dtype=float)
    T_nom = fk(step.guide, qv[None, :])[0]
    names = sorted(balls)
    cmm, radius_m = step.devices.cmm, step.devices.cmm_ball_radius_m
    pose = retry(
        lambda: cmm.measure_pose(np.array([balls[n] for n in names]), T_nom, radius_m),
        "CMM pose",
        step.settings,
        step.control,
        "cmm",
    )
    T = pose.T_world_tool
    qw, qx, qy, qz = matrix_to_quat(T[:3, :3])
    # The row's uncertainty is the probing's (the probed points' scatter about each fitted ball),
    # not how far the centres lie from the drawn layout (pose.residual_rms_m): balls mounted off
    # their drawing leave the same misfit at every pose, and the frame fitted to their drawn
    # positions is then the tool frame times a constant, which identification takes for the tool
    # frame (book eq. 6.12-6.15).
    probing_m = math.sqrt(float(np.mean([b.residual_rms_m**2 for b in pose.balls])))
    return Measurement(
        session_id=step.run.id,
        seq=seq,
        joint=joint or None,
        q=[float(v) for v in qv],
        x=float(T[0, 3]),
        y=float(T[1, 3]),
        z=float(T[2, 3]),
        qw=float(qw),
        qx=float(qx),
        qy=float(qy),
        qz=float(qz),
        sigma=max(probing_m, 5e-6),
    )


def tracker_row(step: Step, seq: int, q_read: np.ndarray, joint: int) -> Measurement:
    """The reflector's position at configuration ``seq``; a tracker that can be pointed gets its
    beam back itself (:func:`measure_recovering_the_beam`)."""
    tracker = step.devices.tracker
    if isinstance(tracker, SteerablePositionSensor):
        m = measure_recovering_the_beam(step, tracker, seq, q_read)
    else:
        m = retry(tracker.measure, "tracker measurement", step.settings, step.control, "tracker")
    return Measurement(
        session_id=step.run.id,
        seq=seq,
        target=step.run.target or "",
        joint=joint or None,
        q=[float(v) for v in q_read],
        x=float(m.p_world[0]),
        y=float(m.p_world[1]),
        z=float(m.p_world[2]),
        sigma=float(np.max(m.sigma)),
    )


def measure_recovering_the_beam(step: Step, tracker: SteerablePositionSensor, seq: int, q_read):
    """A tracker measurement at configuration ``seq``: as :func:`service.control.retry`
    (``device_retries`` more attempts), except that when the tracker says it lost the reflector
    it is first pointed at where the reflector is (:func:`where_the_reflector_is`) and searches
    there. A reflector not found there pauses the session at once with the reason; a measurement
    that succeeds after a search counts as a recovery (``run.beam_recoveries``, committed with
    the row)."""
    run, settings, control = step.run, step.settings, step.control
    what = f"tracker measurement at configuration {seq + 1}"
    attempts = settings.device_retries + 1
    recovered, last = False, None
    for attempt in range(attempts):
        if control.abort.is_set():
            raise SessionStopped("aborted", "aborted on request")
        try:
            m = tracker.measure()
            if recovered:
                run.beam_recoveries = (run.beam_recoveries or 0) + 1
                log.info("session %s: %s: beam recovered", run.id, what)
            return m
        except DeviceError as exc:
            last = exc
            log.warning("%s failed (attempt %d): %s", what, attempt + 1, exc)
        if attempt + 1 == attempts:
            break
        if isinstance(last, MeasurementError) and _status(tracker) == "beam_broken":
            if control.abort.is_set():  # pointing moves the tracker: not after an abort
                raise SessionStopped("aborted", "aborted on request")
            p = where_the_reflector_is(step, q_read)
            try:
                tracker.find_reflector(p)
                recovered = True
                continue
            except MeasurementError as exc:
                where = ", ".join(f"{v * 1e3:.1f}" for v in p)
                raise SessionStopped(
                    "paused",
                    f"{what}: the beam broke and the tracker did not find the reflector "
                    f"where the model puts it ({where}) mm: {exc}",
                    device="tracker",
                    cause=exc,
                ) from exc
            except DeviceError as exc:
                last = exc
        time.sleep(settings.retry_backoff_s * (attempt + 1))
    raise SessionStopped("paused", f"{what} failed after {attempts} attempts: {last}", device="tracker", cause=last)


def _status(tracker) -> str | None:
    try:
        return tracker.status()
    except DeviceError:
        return None


def where_the_reflector_is(step: Step, q_read) -> np.ndarray:
    """Where the reflector is now, (3,) m, tracker frame: the current model (``step.guide``) at
    the joint readings, placed where it fits this session's measurements so far. From four of
    them on, its base and the reflector's mounting are fitted as the identification registers
    them; with one to three, a shift and a turn about the vertical (the tracker stands levelled,
    the robot on the floor); with none, the model as it is (right once the cell is calibrated)."""
    from calibration.kinematics import target_positions
    from calibration.registration import kabsch_levelled

    run, guide = step.run, step.guide
    q = np.asarray(q_read, dtype=float)[None, :]
    try:
        data, rows = analysis.session_measurements(step.db, run)
    except analysis.AnalysisError:  # nothing measured yet
        rows = []
    if len(rows) >= 4:  # the rows' own target: the fitted common offset carries the reflector's mounting
        return records.registered_points(guide, data, q, guide.target(run.target)[None, :])[0]
    target = run.target or reflector_target(guide)
    p_model = target_positions(guide, q, target)[0]
    if not rows:
        return p_model
    T = kabsch_levelled(target_positions(guide, data.q, target), data.p_world)
    return T[:3, :3] @ p_model + T[:3, 3]
