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
(:class:`EmbeddedRunner`); ``run_session`` is the whole job, so a worker process can run it too
(``service.fleet``, docs/fleet.md). A session whose database goes away is not at fault: a
measurement commit is retried (the unique constraint (session, seq, target) makes a retried
commit that had in fact gone through harmless), and if the store stays away ``run_session``
raises and the process running it decides (the session ends ``interrupted``, never ``failed``).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from dataclasses import replace

import numpy as np
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlmodel import Session, select

from calibration.model import model_from_dict
from drivers.errors import DeviceError, DeviceUnavailableError, RobotStoppedError

from . import analysis, records
from .cell_preparation import CellPreparation, TcpSample, no_payload_interface, prepare_cell
from .control import Control, DeviceOpenError, SessionStopped, heavy_slot, retry
from .devices import CellDevices, DeviceConfigError, instrument_sigma, open_robot, stored_devices
from .kinds import Step, finish_session, kind_of
from .models import TERMINAL, Cell, Measurement, RunSession, utcnow
from .plans import UnsafePlan, approach_configurations, check_configurations, plan_session
from .settings import Settings
from .store import (
    acquire_lease,
    database_unavailable,
    held_by_other,
    release_lease,
    set_state,
    set_state_unless,
)

__all__ = [
    "Control",
    "DeviceOpenError",
    "EmbeddedRunner",
    "SessionStopped",
    "commit_measurements",
    "open_session_devices",
    "run_session",
    "store_abort",
]

log = logging.getLogger("recal.sessions")


def open_session_devices(cell: Cell, run: RunSession, settings: Settings) -> CellDevices:
    """The devices a session needs: the robot, then its kind's instrument (opened in the worker,
    closed when it ends). Raises :class:`DeviceOpenError` naming the device that could not be
    opened."""
    kind = kind_of(run.kind)
    devs = CellDevices()
    device = "robot"
    try:
        devs.robot = open_robot(stored_devices(cell.devices), timeout_s=settings.device_timeout_s)
        device = kind.instrument(run)
        kind.open_instrument(devs, cell, run, settings)
    except (DeviceError, DeviceConfigError, OSError) as exc:
        devs.close()
        raise DeviceOpenError(device, exc) from exc
    except BaseException:
        devs.close()
        raise
    return devs


def ensure_plan(db: Session, run: RunSession, cell: Cell, control: Control | None = None) -> RunSession:
    """Plan the session once (a resumed session keeps its plan) and check it. Between the
    planning's phases ``control.check()`` stops it (abort, pause, the process stopping). The plan
    predicts with the session's instrument's declared sigma, stored with it (``instrument_sigma``)."""
    model = model_from_dict(cell.model)
    if run.plan is None:
        asked = run.session_plan()
        sigma = asked.instrument_sigma or instrument_sigma(cell.devices, kind_of(run.kind).instrument(run))
        plan = plan_session(
            kind_of(run.kind).plan,
            model,
            run.planned,
            region=cell.allowed_region,
            target=run.target,
            joints=None if asked.joints is None else list(asked.joints),
            seed=run.id or 0,
            sigma_m=sigma.sigma_m,
            repeats=asked.visits,
            between=None if control is None else control.check,
        )
        run.plan = plan.q.tolist()
        planned = asked.planned(plan.info, swept_joint=plan.joint.tolist(), nominal_version=cell.model_version)
        run.record_plan(replace(planned, instrument_sigma=sigma))
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
    return run.session_plan().visits


def _device_state(what: str, detail: str) -> dict:
    return {"state": what, "detail": detail}


def stopped_device_state(
    run: RunSession, devices: CellDevices | None, final: str, reason: str | None, exc: BaseException | None = None
) -> dict:
    """``session.device_state`` when the session stops: what the robot and the instrument are
    doing, as far as this process knows (the robot is asked only after a safety stop)."""
    key = kind_of(run.kind).instrument(run)
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
        # each device's own state and detail: the one that failed says why, the other only that
        # the session stopped because of it (the tracker once showed "ready" with the robot's error)
        other = f"the session is {final}: the {exc.device} failed" if connected else reason or final
        if exc.device == "robot":
            robot = _device_state(what, str(cause))
            instrument = _device_state(instrument["state"], other)
        else:
            instrument = _device_state(what, str(cause))
            robot = _device_state(robot["state"], other)
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
        ended = _lease_and_plan(db, run, cell, settings, control, owner, leased)
        if ended is not None:
            return ended
        set_state(db, run, "running", None)
        try:
            devices = _open_with_retries(open_devices, cell, run, settings, control)
        except (DeviceError, DeviceConfigError, OSError) as exc:
            reason = _open_failure_reason(exc)
            _end(db, run, owner, "paused", reason, stopped_device_state(run, None, "paused", reason, exc))
            return "paused"
        control.devices = devices
        final, reason, stop = _measure_and_finish(db, run, cell, devices, settings, control, owner)
        return _close_and_end(db, run, devices, control, owner, final, reason, stop)


def _lease_and_plan(
    db: Session, run: RunSession, cell: Cell, settings: Settings, control: Control, owner: str, leased: bool
) -> str | None:
    """Take the cell's lease (unless ``leased``) and plan the session once: the state it ended
    in when it cannot go on (another session drives the cell, an unsafe plan, a stop while
    planning, a dry run planned), else None."""
    if not leased and not acquire_lease(db, run, owner, ttl_s=settings.effective_lease_ttl_s):
        db.refresh(run)
        if held_by_other(run, owner):  # another process runs this very session: leave it alone
            return run.state
        set_state(db, run, "paused", "another session is driving this cell")
        return "paused"
    try:
        with heavy_slot(control, stoppable=True):
            ensure_plan(db, run, cell, control)
    except UnsafePlan as exc:
        _end(db, run, owner, "failed", f"unsafe plan: {exc}", None)
        return "failed"
    except SessionStopped as exc:  # asked to stop while planning: nothing moved
        _end(db, run, owner, *_stop_outcome(exc, control), None)
        return run.state
    if run.dry_run:
        run.record_plan(replace(run.session_plan(), dry_run=True))
        db.add(run)
        _end(db, run, owner, "completed", "dry run: planned and checked, nothing moved", None)
        return "completed"
    return None


def _measure_and_finish(
    db: Session, run: RunSession, cell: Cell, devices: CellDevices, settings: Settings, control: Control, owner: str
) -> tuple[str, str | None, SessionStopped | None]:
    """Prepare the cell, measure every configuration, and finish (identify): the final state,
    its reason and the stop that ended it (None). Never raises for the session's sake; a lost
    database is raised (module docstring)."""
    try:
        # the controller's kinematics and the device checks, before the first move (cell_preparation)
        prepared = prepare_cell(db, run, cell, devices)
        tcp_samples = _measure_all(db, run, cell, devices, settings, control, owner, prepared)
        # a robot that reports its TCP pose: the controller's model fitted from it at those poses
        prepared.after_measuring(db, run, cell, devices, tcp_samples)
        control.begin_finishing()  # from here on an abort no longer stops it (Control)
        with heavy_slot(control, stoppable=False):  # every pose is measured: identify them
            finish_session(db, run, cell, settings)
    except SessionStopped as exc:
        final, reason = _stop_outcome(exc, control)
        if final == "aborted" and devices.robot is not None:
            try:
                devices.robot.stop()
            except Exception:  # noqa: BLE001 - stopping is best effort; the state is what matters
                pass
        return final, reason, exc
    except analysis.AnalysisError as exc:
        return "failed", str(exc), None
    except Exception as exc:  # the session must end in a state, never a traceback
        if database_unavailable(exc):
            raise  # not the session's fault: whoever runs it marks it interrupted (module docstring)
        log.error("session %s failed:\n%s", run.id, traceback.format_exc())
        if control.abort.is_set() and not control.finishing:  # said aborted already (EmbeddedRunner.abort)
            return "aborted", "aborted on request", None
        return "failed", f"internal error: {type(exc).__name__}: {exc}", None
    return "completed", None, None


def _close_and_end(
    db: Session,
    run: RunSession,
    devices: CellDevices,
    control: Control,
    owner: str,
    final: str,
    reason: str | None,
    stop: SessionStopped | None,
) -> str:
    """Close the devices and store the session's end; the state it ended in."""
    # An aborted session is over for good (nothing resumes it) and its robot stands still:
    # it is said aborted at once, before its devices close (which can take a while on real
    # ones), so that the abort is answered quickly; it keeps the cell's lease until they are
    # closed, so that no other session opens them meanwhile (store.acquire_lease). Any other
    # end closes the devices first, so that whoever resumes the session finds them free.
    early = final == "aborted"
    try:
        state = stopped_device_state(run, devices, final, reason or "session completed", stop)
        if not early:
            _close_devices(devices, control)
        db.refresh(run, with_for_update=True)
        if run.lease_owner not in (None, owner):
            db.rollback()  # another process took the session over (ours had expired): its state is not ours to write
            return run.state
        _end(db, run, owner, final, reason, state, keep_lease=early)
        control.ended.set()
    finally:
        _close_devices(devices, control)
    if early:
        release_lease(db, run, owner)
    return run.state


def _close_devices(devices: CellDevices, control: Control) -> None:
    devices.close()  # idempotent
    control.devices = None


def _open_with_retries(open_devices, cell: Cell, run: RunSession, settings: Settings, control: Control) -> CellDevices:
    """The session's devices, opened again ``device_retries`` times with back-off when the first
    try meets a passing fault (a connection dropped or a garbled packet while it was set up),
    as a measurement is retried: such a fault paused the session before its first pose, and a
    resume was needed for what a second try does. A safety stop, a configuration the service
    cannot read or an abort is not retried."""
    for attempt in range(settings.device_retries + 1):
        try:
            return open_devices(cell, run, settings)
        except DeviceOpenError as exc:
            cause = exc.cause
            transient = isinstance(cause, (DeviceError, OSError)) and not isinstance(cause, RobotStoppedError)
            if not transient or attempt == settings.device_retries or control.abort.is_set():
                raise
            log.warning("opening the %s failed (attempt %d): %s", exc.device, attempt + 1, cause)
            time.sleep(settings.retry_backoff_s * (attempt + 1))
    raise AssertionError("unreachable")  # the loop returns or raises


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


def _end(
    db: Session,
    run: RunSession,
    owner: str,
    state: str,
    reason: str | None,
    device_state: dict | None,
    *,
    keep_lease: bool = False,
) -> None:
    """The session stops: its state (and the devices' state, when known), and the cell's lease
    given back (a resume may start at once), unless ``keep_lease`` (its devices are still open:
    the caller gives it back once they are closed, ``store.release_lease``)."""
    if run.lease_owner == owner and not keep_lease:
        run.lease_expires = utcnow()
    if device_state is not None:
        run.device_state = device_state
    set_state(db, run, state, reason)


def _measure_all(
    db: Session,
    run: RunSession,
    cell: Cell,
    devices: CellDevices,
    settings: Settings,
    control: Control,
    owner: str,
    prepared: CellPreparation,
) -> list[TcpSample]:
    """Move to and measure every configuration of the plan not measured yet. Returns, for a
    robot that reports its TCP pose (``prepared.read_tcp_pose``), the poses it reported where it
    stood: (q, T_base_tcp) pairs, else an empty list."""
    model = model_from_dict(cell.model)
    read_tcp = prepared.read_tcp_pose
    tcp_registers: list[TcpSample] = []
    plan = np.asarray(run.plan, dtype=float)
    approach = approach_configurations(model, cell.allowed_region, plan) if _repeats(run) > 1 else None
    swept = run.session_plan().swept_joint or [0] * len(plan)
    done = set(db.exec(select(Measurement.seq).where(Measurement.session_id == run.id)).all())
    todo = [seq for seq in range(len(plan)) if seq not in done]
    speed = settings.max_joint_speed_rad_s
    accel = settings.max_joint_accel_rad_s2
    timeout_s = max(60.0, settings.device_timeout_s)
    kind = kind_of(run.kind)
    key = kind.instrument(run)
    guide = analysis.guide_model(db, cell)  # where the CMM should look for the balls, the tracker for the reflector

    def move(q):
        check_configurations(model, q[None, :], cell.allowed_region)
        retry(
            lambda: devices.robot.move_joints(q, speed_rad_s=speed, accel_rad_s2=accel, timeout_s=timeout_s),
            "move",
            settings,
            control,
        )

    step = Step(db=db, run=run, devices=devices, settings=settings, control=control, guide=guide)
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
        q_read = retry(devices.robot.read_joints, "read joints", settings, control)
        if read_tcp is not None:
            try:  # standing still: the registers belong to these joints
                tcp_registers.append((np.asarray(q_read, dtype=float), read_tcp()))
            except (DeviceError, ValueError, OSError):
                pass  # only the controller model's fit misses this configuration, not the session
        rows = kind.measure_one(step, seq, q_read, int(swept[seq]))
        following = todo[k + 1] if k + 1 < len(todo) else None
        if control.abort.is_set():  # aborted while it measured: the pose is kept, the robot goes no further
            robot = _device_state("ready", "stopped on abort")
        elif following is not None:
            robot = _device_state("moving", f"to configuration {following + 1} of {len(plan)}")
        else:
            robot = _device_state("ready", f"at configuration {seq + 1} of {len(plan)}, the last")
        state = {
            "robot": robot,
            key: _device_state("ready", f"measured configuration {seq + 1}"),
            "at": utcnow().isoformat(),
        }
        # before the next move, with the devices' state in the same transaction: a crash loses nothing reported
        commit_measurements(db, rows, settings, control, run=run, device_state=state)
        if seq % 10 == 0 and not acquire_lease(db, run, owner, ttl_s=settings.effective_lease_ttl_s):
            raise SessionStopped("interrupted", "another process holds this cell now; resume the session to continue")
    return tcp_registers


def _set_payload(devices: CellDevices, model, payload: np.ndarray, settings: Settings, control: Control) -> None:
    """Tell the controller the payload now mounted (its centre of gravity from the tool frame to
    the flange, as the controller takes it). In the simulated cell this mounts it; on a real cell
    the payload is mounted by hand first: a session with payloads is for a cell set up to change
    it."""
    from calibration.transforms import pose_to_matrix

    F = pose_to_matrix(model.tool)
    cog_flange = F[:3, :3] @ payload[1:] + F[:3, 3]
    try:
        retry(lambda: devices.robot.set_payload(float(payload[0]), cog_flange), "set payload", settings, control)
    except NotImplementedError as exc:  # declared it takes one (cell_preparation checked), found it does not
        raise no_payload_interface(devices.robot, exc) from None


def commit_measurements(
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


def store_abort(engine: Engine, session_id: int, control: Control) -> None:
    """Store the session aborted now, with its devices' state, for an abort that will certainly
    end it so (:meth:`Control.request_abort` said so; the robot has been told to stop), so that
    the abort is answered without waiting for the session's thread, which may be in the middle of
    an instrument's measurement. That thread ends it the same way (``run_session``)."""
    try:
        with Session(engine) as db:
            run = db.get(RunSession, session_id)
            state = stopped_device_state(run, control.devices, "aborted", "aborted on request")
            if set_state_unless(db, run, TERMINAL, "aborted", "aborted on request", device_state=state):
                control.ended.set()
    except Exception:  # the session's thread stores it all the same
        log.warning("session %s: storing the abort early failed", session_id, exc_info=True)


class EmbeddedRunner:
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
        except Exception as exc:  # noqa: BLE001 - the session must end in a state, never a traceback
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
        finally:
            control.ended.set()

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
        """Ask the session to stop and stop the robot now. A session that will certainly end
        aborted (it has not started identifying: :meth:`Control.request_abort`) is stored aborted
        here at once, so that the abort is answered without waiting for the session's thread to
        notice (it may be in the middle of an instrument's measurement, up to a second on a real
        tracker); the thread then ends it the same way and keeps the cell until its devices are
        closed (``run_session``)."""
        t = self._threads.get(session_id)
        if t is None or not t[0].is_alive():
            return False
        control = t[1]
        certain = control.request_abort()
        devs = control.devices
        if devs is not None and devs.robot is not None:
            try:
                devs.robot.stop()
            except Exception:  # noqa: BLE001 - the worker stops the robot again on its way out
                pass
        if certain:
            store_abort(self.engine, session_id, control)
        return True

    def wait(self, session_id: int, timeout_s: float | None = None) -> None:
        """Return once the session's final state is stored (an aborted session's devices may
        still be closing: its lease keeps the cell meanwhile), or after ``timeout_s``."""
        t = self._threads.get(session_id)
        if t is not None:
            t[1].ended.wait(timeout_s)

    def not_ready(self) -> str | None:
        """Why this runner cannot take a session now (``/ready``), or None."""
        return "shutting down" if self._stopping else None

    def shutdown(self, timeout_s: float = 5.0) -> None:
        self._stopping = True
        for _thread, control in list(self._threads.values()):
            control.pause.set()
        for thread, _ in list(self._threads.values()):
            thread.join(timeout_s)
