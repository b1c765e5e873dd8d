"""How a running session is controlled from outside and how it calls its devices: the requests
it honours between two steps (:class:`Control`: pause, abort, interrupt, the lease), how it
stops (:class:`SessionStopped`), the retries of a device call (:func:`retry`), and the process's
slots for heavy work (:func:`heavy_slot`). The session loop and every session kind
(:mod:`service.kinds`) share these."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

from calibration.errors import RecalError
from drivers.errors import DeviceError, RobotStoppedError

from .devices import CellDevices
from .settings import Settings

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
    cannot be reached raises (the worker waits for it, module docstring). ``ended``: set once
    the session's final state is committed (an aborted session's devices may still be closing).

    An abort is *certain* (:meth:`request_abort`) until the session starts its last step
    (:meth:`begin_finishing`, under the same lock): from then on an identification that is under
    way is not interrupted and the session completes."""

    pause: threading.Event = field(default_factory=threading.Event)
    abort: threading.Event = field(default_factory=threading.Event)
    devices: CellDevices | None = None
    interrupt: threading.Event = field(default_factory=threading.Event)
    interrupt_reason: str = ""
    lease_valid_until: float = math.inf
    renew: Callable[[], object] | None = None
    heavy: threading.Semaphore | None = None  # the process's slots for planning and identification
    ended: threading.Event = field(default_factory=threading.Event)  # the session's final state is stored
    finishing: bool = False  # the session has measured everything and is finishing (identifying)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def request_abort(self) -> bool:
        """Ask the session to abort. True when it will certainly end ``aborted`` (it has not
        started its last step), so that whoever asked may say so at once."""
        with self._lock:
            self.abort.set()
            return not self.finishing

    def begin_finishing(self) -> None:
        """Every configuration is measured: :meth:`check` once more, then the last step, which
        an abort no longer interrupts."""
        with self._lock:
            self.check()
            self.finishing = True

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


def retry(fn: Callable, what: str, settings: Settings, control: Control, device: str = "robot"):
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
