"""Sessions: plan, then for each configuration move, settle, measure and commit, then analyse.

Rules a robot cell needs (issue: sessions):

- every measurement is committed (its own transaction) before the next move, so a crash
  loses nothing the service reported as taken, and a resumed session continues with the
  first configuration not yet measured;
- every commanded configuration is checked against the model's joint limits and the cell's
  allowed region before anything moves, speeds and accelerations are capped by the settings;
- device faults are retried (``device_retries``, with back-off), then the session pauses with
  the reason; a protective or emergency stop pauses it at once. A tracker that lost the
  reflector (a beam break) is first pointed at where the reflector is: from the current model
  and the joint readings, its base placed where it fits the session's measurements so far, the
  tracker is pointed there and searches (``find_reflector``), then measures again; the session
  pauses only when that fails, and counts the recoveries (``session.beam_recoveries``). A retry calls the device
  again, and the drivers reconnect on that call where it is safe: the UR driver replaces a
  worker that lost its connection (a move in progress is not re-sent by the driver; the retry
  re-sends the same, already checked target), the tracker and CMM drivers close a link after
  a timeout or a garbled reply and reconnect on the next command, the Modbus driver repeats its
  idempotent requests on a new connection, the CANopen driver reconnects once on a lost bus;
- pause and abort take effect between two steps (planning included: between its phases);
  abort stops the robot at once;
- a dry run plans and checks, and moves nothing;
- ``session.device_state`` says what the devices were doing at the last committed pose (in the
  same transaction as its measurements), stop or fault, for the live page.

The embedded default runs each session in a thread of the service process
(:class:`Orchestrator`); ``run_session`` is the whole job, so a worker process can run it too
(``service.fleet``, docs/fleet.md). A session whose database goes away is not at fault: a
measurement commit is retried (the unique constraint (session, seq, target) makes a retried
commit that had in fact gone through harmless), and if the store stays away ``run_session``
raises and the process running it decides (the session ends ``interrupted``, never ``failed``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
import traceback
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlmodel import Session, select

from calibration.errors import RecalError
from calibration.model import model_from_dict
from drivers.base import SteerablePositionSensor
from drivers.errors import DeviceError, DeviceUnavailableError, MeasurementError, RobotStoppedError

from . import analysis, controller, records
from .devices import (
    CellDevices,
    DeviceConfigError,
    cmm_ball_radius_m,
    open_cmm,
    open_encoders,
    open_robot,
    open_tracker,
)
from .models import Cell, Measurement, RunSession, utcnow
from .plans import UnsafePlan, approach_configurations, check_configurations, plan_session
from .settings import Settings
from .store import acquire_lease, database_unavailable, held_by_other, set_state

log = logging.getLogger("recal.sessions")


@dataclass
class Control:
    """Requests from outside a running session (API threads, or a fleet worker's monitor).

    ``interrupt``: the process running the session is stopping (the session ends
    ``interrupted`` with ``interrupt_reason``); ``lease_valid_until`` (``time.monotonic()``):
    the moment after which this process may no longer be sure it alone holds the cell, so no
    further move is commanded (a fleet worker renews it; the embedded default never expires).
    ``renew``: called when that moment has come before the next move (a fleet worker's monitor
    thread was late, e.g. on a loaded machine): renews the hold in the store if this process
    still has it (moving ``lease_valid_until`` on), else sets ``interrupt``; a store that
    cannot be reached raises (the worker waits for it, module docstring)."""

    pause: threading.Event = field(default_factory=threading.Event)
    abort: threading.Event = field(default_factory=threading.Event)
    devices: CellDevices | None = None
    interrupt: threading.Event = field(default_factory=threading.Event)
    interrupt_reason: str = ""
    lease_valid_until: float = math.inf
    renew: Callable[[], object] | None = None
    heavy: threading.Semaphore | None = None  # the process's slots for planning and identification

    def check(self) -> None:
        """Raise :class:`SessionStopped` when the session must not make another move."""
        if self.abort.is_set():
            raise SessionStopped("aborted", "aborted on request")
        if time.monotonic() >= self.lease_valid_until and self.renew is not None and not self.interrupt.is_set():
            self.renew()  # the robot stands still meanwhile: slower, never two drivers
        if self.interrupt.is_set():
            raise SessionStopped("interrupted", self.interrupt_reason or "interrupted; resume it to continue")
        if time.monotonic() >= self.lease_valid_until:
            raise SessionStopped(
                "interrupted",
                "this worker's hold on the cell ran out before it was renewed; every "
                "measurement reported is kept: resume the session to continue",
            )
        if self.pause.is_set():
            raise SessionStopped("paused", "paused on request")


class SessionStopped(RecalError):
    """The session stops here: ``state`` and ``reason`` say how; ``device`` which device's fault
    (``robot``, ``tracker``, ``cmm``, ``encoder``) stopped it, if one did, and ``cause`` the error."""

    def __init__(self, state: str, reason: str, *, device: str | None = None, cause: Exception | None = None):
        self.state, self.reason, self.device, self.cause = state, reason, device, cause
        super().__init__(reason)


class DeviceOpenError(RecalError, ConnectionError):
    """One of the session's devices (``device``) could not be opened."""

    def __init__(self, device: str, cause: Exception):
        self.device, self.cause = device, cause
        super().__init__(str(cause))


def instrument_of(run: RunSession) -> str:
    """The session's measuring device: ``encoder`` (joint sessions), ``cmm`` or ``tracker``."""
    return "encoder" if run.kind == "joint" else "cmm" if run.device == "cmm" else "tracker"


def open_session_devices(cell: Cell, run: RunSession, settings: Settings) -> CellDevices:
    """The devices a session needs (opened in the worker, closed when it ends). Raises
    :class:`DeviceOpenError` naming the device that could not be opened."""
    devs = CellDevices()
    device = "robot"
    try:
        devs.robot = open_robot(cell.devices, timeout_s=settings.device_timeout_s)
        device = instrument_of(run)
        if run.kind == "joint":
            joints = (run.plan_info or {}).get("joints")
            devs.encoders = open_encoders(cell.devices, joints, timeout_s=settings.device_timeout_s)
        elif run.device == "cmm":
            devs.cmm_ball_radius_m = cmm_ball_radius_m(cell.devices)  # a bad value stops it before anything moves
            devs.cmm = open_cmm(cell.devices, timeout_s=settings.device_timeout_s)
        else:
            devs.tracker = open_tracker(cell.devices, timeout_s=settings.device_timeout_s)
    except (DeviceError, DeviceConfigError, OSError) as exc:
        devs.close()
        raise DeviceOpenError(device, exc) from exc
    except BaseException:
        devs.close()
        raise
    return devs


@contextmanager
def heavy_slot(control: Control, *, stoppable: bool):
    """One of the process's slots for heavy work (``control.heavy``: ``Settings.heavy_workers``
    of them), held while a session plans or identifies, so that many sessions finishing at once
    do not share the cores (and the API's GIL) all together. While it waits for a slot, a
    ``stoppable`` phase (planning) still stops on abort, pause or interrupt."""
    if control.heavy is None:
        yield
        return
    while not control.heavy.acquire(timeout=0.1):
        if stoppable:
            control.check()
    try:
        yield
    finally:
        control.heavy.release()


def _retry(fn: Callable, what: str, settings: Settings, control: Control, device: str = "robot"):
    """Call ``fn`` on ``device``; on a device fault call it again ``device_retries`` times with
    back-off (the drivers reconnect on that call where it is safe: module docstring), then give
    up by pausing the session. Protective and emergency stops are not retried."""
    last: Exception | None = None
    for attempt in range(settings.device_retries + 1):
        if control.abort.is_set():
            raise SessionStopped("aborted", "aborted on request")
        try:
            return fn()
        except RobotStoppedError as exc:
            raise SessionStopped("paused", f"{what}: {exc}", device=device, cause=exc) from exc
        except DeviceError as exc:
            last = exc
            log.warning("%s failed (attempt %d): %s", what, attempt + 1, exc)
            time.sleep(settings.retry_backoff_s * (attempt + 1))
    raise SessionStopped(
        "paused", f"{what} failed after {settings.device_retries + 1} attempts: {last}", device=device, cause=last
    )


def ensure_plan(db: Session, run: RunSession, cell: Cell, control: Control | None = None) -> RunSession:
    """Plan the session once (a resumed session keeps its plan) and check it. Between the
    planning's phases ``control.check()`` stops it (abort, pause, the process stopping)."""
    model = model_from_dict(cell.model)
    if run.plan is None:
        info = run.plan_info or {}
        plan = plan_session(
            run.kind,
            model,
            run.planned,
            region=cell.allowed_region,
            target=run.target,
            joints=info.get("joints"),
            seed=run.id or 0,
            repeats=int(info.get("repeats") or 1),
            between=None if control is None else control.check,
        )
        run.plan = plan.q.tolist()
        run.plan_info = {**info, **plan.info, "swept_joint": plan.joint.tolist(), "nominal_version": cell.model_version}
        run.planned = len(plan.q)
        db.add(run)
        db.commit()
        db.refresh(run)
    q = np.asarray(run.plan, dtype=float)
    check_configurations(model, q, cell.allowed_region)
    if _repeats(run) > 1:
        check_configurations(model, approach_configurations(model, cell.allowed_region, q), cell.allowed_region)
    return run


def _repeats(run: RunSession) -> int:
    return int((run.plan_info or {}).get("repeats") or 1)


def _device_state(what: str, detail: str) -> dict:
    return {"state": what, "detail": detail}


def stopped_device_state(
    run: RunSession, devices: CellDevices | None, final: str, reason: str | None, exc: BaseException | None = None
) -> dict:
    """``session.device_state`` when the session stops: what the robot and the instrument are
    doing, as far as this process knows (the robot is asked only after a safety stop)."""
    key = instrument_of(run)
    connected = devices is not None and devices.robot is not None
    robot = _device_state("ready" if connected else "not connected", reason or final)
    instrument = _device_state("ready" if connected else "not connected", reason or final)
    if isinstance(exc, DeviceOpenError):
        if exc.device == "robot" and isinstance(exc.cause, RobotStoppedError):
            robot = _device_state(_safety_state(None, exc.cause), str(exc.cause))
            instrument = _device_state("not connected", "not opened: the robot is stopped")
        elif exc.device == "robot":
            robot = _device_state("not connected", str(exc.cause))
        else:
            robot = _device_state("ready", f"connected; nothing moved: the {exc.device} could not be opened")
            instrument = _device_state("not connected", str(exc.cause))
    elif isinstance(exc, SessionStopped) and exc.device is not None and exc.cause is not None:
        cause = exc.cause
        if exc.device == "robot" and isinstance(cause, RobotStoppedError):
            what = _safety_state(devices, cause)
        elif isinstance(cause, (OSError, DeviceUnavailableError)):  # lost connection, timeout
            what = "not connected"
        else:
            what = "fault"
        if exc.device == "robot":
            robot = _device_state(what, str(cause))
        else:
            instrument = _device_state(what, str(cause))
    if final == "aborted" and connected:
        robot = _device_state("ready", "stopped on abort")
    return {"robot": robot, key: instrument, "at": utcnow().isoformat()}


def _safety_state(devices: CellDevices | None, exc: Exception) -> str:
    """``protective stop`` or ``emergency stop``: asked of the robot, else read from the error."""
    try:
        st = devices.robot.state()
        if st.emergency_stop:
            return "emergency stop"
        if st.protective_stop:
            return "protective stop"
    except Exception:  # noqa: BLE001 - the robot may not answer now; the error says enough
        pass
    text = str(exc).lower()
    if "emergency" in text:
        return "emergency stop"
    return "powered off" if "not running" in text else "protective stop"


def run_session(
    engine: Engine,
    settings: Settings,
    session_id: int,
    control: Control | None = None,
    *,
    owner: str = "embedded",
    open_devices=open_session_devices,
    leased: bool = False,
) -> str:
    """Run (or continue) one session to its end, a pause, or a failure. Returns the final state.
    ``leased``: ``owner`` has just taken the cell's lease for this session (a fleet worker's
    claim), so it is not taken again here."""
    control = control or Control()
    with Session(engine) as db:
        run = db.get(RunSession, session_id)
        cell = db.get(Cell, run.cell_id)
        if not leased and not acquire_lease(db, run, owner, ttl_s=settings.effective_lease_ttl_s):
            db.refresh(run)
            if held_by_other(run, owner):  # another process runs this very session: leave it alone
                return run.state
            set_state(db, run, "paused", "another session is driving this cell")
            return "paused"
        try:
            with heavy_slot(control, stoppable=True):
                run = ensure_plan(db, run, cell, control)
        except UnsafePlan as exc:
            _end(db, run, owner, "failed", f"unsafe plan: {exc}", None)
            return "failed"
        except SessionStopped as exc:  # asked to stop while planning: nothing moved
            _end(db, run, owner, *_stop_outcome(exc, control), None)
            return run.state
        if run.dry_run:
            run.plan_info = {**(run.plan_info or {}), "dry_run": True}
            db.add(run)
            _end(db, run, owner, "completed", "dry run: planned and checked, nothing moved", None)
            return "completed"
        set_state(db, run, "running", None)
        try:
            devices = open_devices(cell, run, settings)
        except (DeviceError, DeviceConfigError, OSError) as exc:
            reason = _open_failure_reason(exc)
            _end(db, run, owner, "paused", reason, stopped_device_state(run, None, "paused", reason, exc))
            return "paused"
        control.devices = devices
        final, reason, stop = "completed", None, None
        try:
            # a UR cell: the controller's own kinematics, read again (docs/devices/ur.md)
            controller.refresh_on_session_start(db, run, cell, devices.robot)
            _measure_all(db, run, cell, devices, settings, control, owner)
            with heavy_slot(control, stoppable=False):  # every pose is measured: identify them
                analysis.finish_session(db, run, cell, settings)
        except SessionStopped as exc:
            stop = exc
            final, reason = _stop_outcome(exc, control)
            if final == "aborted" and devices.robot is not None:
                try:
                    devices.robot.stop()
                except Exception:  # noqa: BLE001 - stopping is best effort; the state is what matters
                    pass
        except analysis.AnalysisError as exc:
            final, reason = "failed", str(exc)
        except Exception as exc:  # noqa: BLE001 - the session must end in a state, never a traceback
            if database_unavailable(exc):
                raise  # not the session's fault: whoever runs it marks it interrupted (module docstring)
            log.error("session %s failed:\n%s", session_id, traceback.format_exc())
            final, reason = "failed", f"internal error: {type(exc).__name__}: {exc}"
        try:
            state = stopped_device_state(run, devices, final, reason or "session completed", stop)
        finally:
            # Close the devices before saying the session stopped, so that whoever resumes it
            # finds them free.
            devices.close()
            control.devices = None
        db.refresh(run, with_for_update=True)
        if run.lease_owner not in (None, owner):
            db.rollback()  # another process took the session over (ours had expired): its state is not ours to write
            return run.state
        _end(db, run, owner, final, reason, state)
        return run.state


def _open_failure_reason(exc: BaseException) -> str:
    """Why a session could not start moving. A robot still held by a safety stop (a session
    resumed before the technician released it) is named with what releases it."""
    if isinstance(exc, DeviceOpenError) and isinstance(exc.cause, RobotStoppedError):
        return f"nothing moved: {exc.cause}"
    return f"cannot open the cell's devices: {exc}"


def _stop_outcome(exc: SessionStopped, control: Control) -> tuple[str, str]:
    if control.abort.is_set():  # the stop we caused ourselves is an abort, not a fault
        return "aborted", "aborted on request"
    return exc.state, exc.reason


def _end(db: Session, run: RunSession, owner: str, state: str, reason: str | None, device_state: dict | None) -> None:
    """The session stops: its state (and the devices' state, when known), and the cell's lease
    given back (a resume may start at once)."""
    if run.lease_owner == owner:
        run.lease_expires = utcnow()
    if device_state is not None:
        run.device_state = device_state
    set_state(db, run, state, reason)


def _measure_all(
    db: Session, run: RunSession, cell: Cell, devices: CellDevices, settings: Settings, control: Control, owner: str
) -> None:
    model = model_from_dict(cell.model)
    plan = np.asarray(run.plan, dtype=float)
    approach = approach_configurations(model, cell.allowed_region, plan) if _repeats(run) > 1 else None
    swept = (run.plan_info or {}).get("swept_joint") or [0] * len(plan)
    done = set(db.exec(select(Measurement.seq).where(Measurement.session_id == run.id)).all())
    todo = [seq for seq in range(len(plan)) if seq not in done]
    speed = settings.max_joint_speed_rad_s
    accel = settings.max_joint_accel_rad_s2
    timeout_s = max(60.0, settings.device_timeout_s)
    key = instrument_of(run)
    guide = analysis.guide_model(db, cell)  # where the CMM should look for the balls

    def move(q):
        check_configurations(model, q[None, :], cell.allowed_region)
        _retry(
            lambda: devices.robot.move_joints(q, speed_rad_s=speed, accel_rad_s2=accel, timeout_s=timeout_s),
            "move",
            settings,
            control,
        )

    payloads = records.payload_of(run, np.arange(len(plan)))
    mounted = None  # set at the first configuration, also after a resume

    for k, seq in enumerate(todo):
        control.check()
        if payloads is not None and (mounted is None or not np.array_equal(payloads[seq], mounted)):
            _set_payload(devices, model, payloads[seq], settings, control)
            mounted = payloads[seq]
        if approach is not None:  # a repeated visit: always from the same side (ISO 9283)
            move(approach[seq])
        move(plan[seq])
        if settings.settle_s > 0:
            time.sleep(settings.settle_s)
        q_read = _retry(devices.robot.read_joints, "read joints", settings, control)
        rows = _measure_one(run, devices, settings, control, seq, q_read, int(swept[seq]), model, guide, db=db)
        following = todo[k + 1] if k + 1 < len(todo) else None
        robot = (
            _device_state("moving", f"to configuration {following + 1} of {len(plan)}")
            if following is not None
            else _device_state("ready", f"at configuration {seq + 1} of {len(plan)}, the last")
        )
        state = {
            "robot": robot,
            key: _device_state("ready", f"measured configuration {seq + 1}"),
            "at": utcnow().isoformat(),
        }
        # before the next move, with the devices' state in the same transaction: a crash loses nothing reported
        _commit_measurements(db, rows, settings, control, run=run, device_state=state)
        if seq % 10 == 0 and not acquire_lease(db, run, owner, ttl_s=settings.effective_lease_ttl_s):
            raise SessionStopped("interrupted", "another process holds this cell now; resume the session to continue")


def _set_payload(devices: CellDevices, model, payload: np.ndarray, settings: Settings, control: Control) -> None:
    """Tell the controller the payload now mounted (its centre of gravity from the tool frame to
    the flange, as the controller takes it). In the simulated cell this mounts it; on a real cell
    the payload is mounted by hand first: a session with payloads is for a cell set up to change
    it."""
    from calibration.transforms import pose_to_matrix

    F = pose_to_matrix(model.tool)
    cog_flange = F[:3, :3] @ payload[1:] + F[:3, 3]
    try:
        _retry(lambda: devices.robot.set_payload(float(payload[0]), cog_flange), "set payload", settings, control)
    except NotImplementedError as exc:
        raise SessionStopped(
            "failed",
            f"{exc}: a session with payloads needs a controller that takes one (UR)",
            device="robot",
            cause=exc,
        ) from None


def _commit_measurements(
    db: Session,
    rows: list[Measurement],
    settings: Settings,
    control: Control,
    *,
    run: RunSession | None = None,
    device_state: dict | None = None,
) -> None:
    """Commit one configuration's measurements (and ``run.device_state``, in the same
    transaction), retrying while the database is unreachable (at most until the lease would
    run out: meanwhile the robot does not move)."""
    data = [r.model_dump(exclude={"id"}) for r in rows]
    deadline = min(control.lease_valid_until, time.monotonic() + settings.effective_lease_ttl_s)
    batch, attempt = rows, 0
    while True:
        try:
            if run is not None:
                run.device_state = device_state
                db.add(run)
            db.add_all(batch)
            db.commit()
            return
        except IntegrityError:
            _rollback(db)
            if attempt:  # an earlier attempt went through, only its answer was lost: the copy was refused
                return
            raise
        except DBAPIError as exc:
            if not database_unavailable(exc):
                raise
            _rollback(db)
            attempt += 1
            delay = min(0.2 * attempt, 2.0)
            if time.monotonic() + delay >= deadline:
                raise
            log.warning("committing a measurement failed (attempt %d), retrying: %s", attempt, exc.orig or exc)
            time.sleep(delay)
            batch = [Measurement(**d) for d in data]


def _rollback(db: Session) -> None:
    try:
        db.rollback()
    except Exception:  # noqa: BLE001 - a dead connection cannot roll back; the pool replaces it
        pass


def _measure_one(run, devices, settings, control, seq, q_read, joint, model, guide, *, db=None) -> list[Measurement]:
    qv = [float(v) for v in q_read]
    if run.kind == "joint":
        enc = devices.encoders.get(joint)
        if enc is None:
            raise SessionStopped("failed", f"no reference encoder on joint {joint}")
        reading = _retry(enc.read, f"read encoder on joint {joint}", settings, control, "encoder")
        return [
            Measurement(
                session_id=run.id, seq=seq, joint=joint, q=qv, x=0.0, y=0.0, z=0.0, reference=float(reading.angle_rad)
            )
        ]
    if devices.cmm is not None:
        balls = {k: v for k, v in guide.targets.items() if k.startswith("ball")}
        if len(balls) < 3:
            raise SessionStopped(
                "failed", "a CMM session needs at least three tooling balls (targets named ball*) in the cell's model"
            )
        from calibration.kinematics import fk
        from calibration.transforms import matrix_to_quat

        T_nom = fk(guide, np.asarray(qv)[None, :])[0]
        names = sorted(balls)
        pose = _retry(
            lambda: devices.cmm.measure_pose(np.array([balls[n] for n in names]), T_nom, devices.cmm_ball_radius_m),
            "CMM pose",
            settings,
            control,
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
        return [
            Measurement(
                session_id=run.id,
                seq=seq,
                joint=joint or None,
                q=qv,
                x=float(T[0, 3]),
                y=float(T[1, 3]),
                z=float(T[2, 3]),
                qw=float(qw),
                qx=float(qx),
                qy=float(qy),
                qz=float(qz),
                sigma=max(probing_m, 5e-6),
            )
        ]
    if isinstance(devices.tracker, SteerablePositionSensor) and db is not None:
        m = _measure_recovering_the_beam(db, run, devices.tracker, settings, control, seq, q_read, guide)
    else:
        m = _retry(devices.tracker.measure, "tracker measurement", settings, control, "tracker")
    return [
        Measurement(
            session_id=run.id,
            seq=seq,
            target=run.target or "",
            joint=joint or None,
            q=qv,
            x=float(m.p_world[0]),
            y=float(m.p_world[1]),
            z=float(m.p_world[2]),
            sigma=float(np.max(m.sigma)),
        )
    ]


def _measure_recovering_the_beam(db, run, tracker: SteerablePositionSensor, settings, control, seq, q_read, guide):
    """A tracker measurement at configuration ``seq``: as :func:`_retry` (``device_retries``
    more attempts), except that when the tracker says it lost the reflector it is first pointed
    at where the reflector is (:func:`_where_the_reflector_is`) and searches there. A reflector
    not found there pauses the session at once with the reason; a measurement that succeeds
    after a search counts as a recovery (``run.beam_recoveries``, committed with the row)."""
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
            p = _where_the_reflector_is(db, run, guide, q_read)
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


def _where_the_reflector_is(db, run, guide, q_read) -> np.ndarray:
    """Where the reflector is now, (3,) m, tracker frame: the current model (``guide``) at the
    joint readings, placed where it fits this session's measurements so far. From four of them
    on, its base and the reflector's mounting are fitted as the identification registers them;
    with one to three, a shift and a turn about the vertical (the tracker stands levelled, the
    robot on the floor); with none, the model as it is (right once the cell is calibrated)."""
    from calibration.kinematics import target_positions
    from calibration.registration import kabsch_levelled

    q = np.asarray(q_read, dtype=float)[None, :]
    try:
        data, rows = analysis.session_measurements(db, run)
    except analysis.AnalysisError:  # nothing measured yet
        rows = []
    if len(rows) >= 4:  # the rows' own target: the fitted common offset carries the reflector's mounting
        return records.registered_points(guide, data, q, guide.target(run.target)[None, :])[0]
    target = run.target or _reflector_target(guide)
    p_model = target_positions(guide, q, target)[0]
    if not rows:
        return p_model
    T = kabsch_levelled(target_positions(guide, data.q, target), data.p_world)
    return T[:3, :3] @ p_model + T[:3, 3]


def _reflector_target(model) -> str | None:
    """The model's reflector when the session names none: its one target that is not a tooling
    ball (what the cell's tracker follows), else the tool origin."""
    names = [k for k in model.targets if not k.startswith("ball")]
    return names[0] if len(names) == 1 else None


class Orchestrator:
    """Runs sessions in background threads of this process (the embedded default); a
    :class:`service.runners.SessionRunner`."""

    distributed = False  # its sessions end with the process: its start interrupts what was left running

    def __init__(
        self, engine: Engine, settings: Settings, *, owner: str = "embedded", open_devices=open_session_devices
    ):
        self.engine, self.settings, self.owner, self.open_devices = engine, settings, owner, open_devices
        self._threads: dict[int, tuple[threading.Thread, Control]] = {}
        self._lock = threading.Lock()
        self._stopping = False
        self._heavy = threading.BoundedSemaphore(settings.heavy_workers)

    def queue(self, db: Session, run: RunSession) -> bool:
        """Nothing to queue: the caller starts the session once it is committed."""
        return False

    def start(self, session_id: int) -> None:
        with self._lock:
            t = self._threads.get(session_id)
            if t is not None and t[0].is_alive():
                t[0].join(15.0)  # a session that just paused may still be closing its devices
                if t[0].is_alive():
                    return
            control = Control(heavy=self._heavy)
            thread = threading.Thread(
                target=self._run, args=(session_id, control), name=f"session-{session_id}", daemon=True
            )
            self._threads[session_id] = (thread, control)
            thread.start()

    def _run(self, session_id: int, control: Control) -> None:
        try:
            run_session(
                self.engine, self.settings, session_id, control, owner=self.owner, open_devices=self.open_devices
            )
        except Exception as exc:  # noqa: BLE001
            log.error("session %s crashed:\n%s", session_id, traceback.format_exc())
            # Never leave it planned or running with nobody on it (that would hold the cell):
            # the store failing under it is not the session's fault (interrupted, resumable).
            state, reason = (
                ("interrupted", f"the database failed during the session ({type(exc).__name__}); resume it to continue")
                if database_unavailable(exc)
                else ("failed", f"internal error: {type(exc).__name__}: {exc}")
            )
            try:
                with Session(self.engine) as db:
                    run = db.get(RunSession, session_id)
                    if run is not None and run.state in ("planned", "running"):
                        set_state(db, run, state, reason)
            except Exception:  # noqa: BLE001 - still unreachable: the next start interrupts it
                pass

    def is_active(self, session_id: int) -> bool:
        t = self._threads.get(session_id)
        return t is not None and t[0].is_alive()

    def pause(self, session_id: int) -> bool:
        t = self._threads.get(session_id)
        if t is None or not t[0].is_alive():
            return False
        t[1].pause.set()
        return True

    def abort(self, session_id: int) -> bool:
        """Ask the session to stop and stop the robot now."""
        t = self._threads.get(session_id)
        if t is None or not t[0].is_alive():
            return False
        t[1].abort.set()
        devs = t[1].devices
        if devs is not None and devs.robot is not None:
            try:
                devs.robot.stop()
            except Exception:  # noqa: BLE001 - the worker stops the robot again on its way out
                pass
        return True

    def wait(self, session_id: int, timeout_s: float | None = None) -> None:
        t = self._threads.get(session_id)
        if t is not None:
            t[0].join(timeout_s)

    def not_ready(self) -> str | None:
        """Why this runner cannot take a session now (``/ready``), or None."""
        return "shutting down" if self._stopping else None

    def shutdown(self, timeout_s: float = 5.0) -> None:
        self._stopping = True
        for thread, control in list(self._threads.values()):
            control.pause.set()
        for thread, _ in list(self._threads.values()):
            thread.join(timeout_s)
