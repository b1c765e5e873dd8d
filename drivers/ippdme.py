"""Coordinate measuring machine over I++ DME (VDMA 8722).

``IppDmeCmm`` is an I++ DME client. It talks to the CMM controller's I++ server (TCP, port
1294 by convention) through pyserial's ``serial_for_url`` (``socket://cmm-host:1294``; a serial
line or pty works the same way), implements :meth:`probe` of :class:`drivers.base.Cmm`, and
inherits ``measure_ball`` / ``measure_pose`` from there (sphere fit and Kabsch pose).

The wire, as implemented here (I++ DME 1.x/2.x core):

- a command is ``TTTTT Method(args)`` with a 5-digit tag ``00001``-``99999`` (``E0001``-
  ``E9999`` for fast-queue commands such as ``GetErrStatusE()``); lines are printable ASCII
  ending in CR LF;
- the server answers ``TTTTT &`` (received), ``TTTTT # data`` (zero or more data lines),
  ``TTTTT %`` (transaction complete) or ``TTTTT ! Error(F1, F2, F3, Text)`` with F1 the
  severity (0 info, 1 warning, 2 error, 3 critical, 9 fatal), F2 the 4-digit error number,
  F3 the method that failed;
- ``E0000`` lines are unsolicited events (``E0000 # ...`` data, ``E0000 ! Error(...)``).

Session on connect: ``StartSession()``, ``SetCoordSystem(MachineCsy)`` (the machine frame is
the world frame), ``GetDMEVersion()``, ``IsHomed()`` (and ``Home()``
when it is not homed and the config allows), ``FindTool("<tool>")``, ``ChangeTool("<tool>")``,
``SetProp(Tool.PtMeasPar.Approach(a))``, ``SetProp(Tool.PtMeasPar.Search(s))``,
``OnPtMeasReport(X(), Y(), Z(), IJK())``. Each probed point is
``PtMeas(X(x), Y(y), Z(z), IJK(i, j, k))`` where ``IJK`` is the surface normal the probe
approaches against (minus our approach direction); the reply ``# X(), Y(), Z(), IJK()`` is
the probe-radius-compensated surface point. I++ lengths are millimetres in the machine
coordinate system; the driver converts to and from metres. ``close()`` sends ``EndSession()``.

Errors (all from :mod:`drivers.errors`, with the I++ error number as ``code`` and the
``severity``, ``method`` and ``text`` as attributes of the exception):

- severity 0/1 are logged (and kept in :attr:`IppDmeCmm.warnings`), the transaction goes on;
- 1001 illegal touch, 1003 no touch, 1006 surface not found, 1008 out of machine volume,
  2500 machine limit -> ``MeasurementError``;
- errors that mean the server did not understand us (0001-0008, 0501-0510) -> ``ProtocolError``;
- any other -> ``DeviceFaultError``;
- severity >= 2 puts an I++ server into an error state: the driver sends ``ClearAllErrors()``
  before raising, so the next command works;
- an ``E0000`` error event of severity >= 2 during a transaction (an emergency stop, say)
  fails that transaction with ``DeviceFaultError`` even if it completes;
- no acknowledgement within ``timeout_s`` or no completion within ``move_timeout_s`` ->
  ``DeviceTimeoutError``; a garbled line -> ``ProtocolError``. Both close the session (the next
  call starts a new one), so nothing late is ever read as a new answer; replies are matched by
  tag, and lines of finished transactions are dropped;
- a dropped link -> one reconnect (a new session with the full set-up) and one resend of the
  command, then ``DeviceConnectionError``. Resending ``PtMeas`` is safe: it moves to the
  approach point again and probes the same nominal point.
"""

from __future__ import annotations

import collections
import logging
import re
import time
from dataclasses import dataclass

import numpy as np

from drivers._linelink import LineLink
from drivers.base import Cmm
from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceFaultError,
    DeviceTimeoutError,
    MeasurementError,
    ProtocolError,
)

log = logging.getLogger(__name__)

MM = 1e-3  # metres per millimetre

#: I++ error numbers meaning "this point cannot be measured".
MEASUREMENT_ERRORS = frozenset({1001, 1003, 1006, 1008, 2500})
#: I++ error numbers meaning "the server did not understand what we sent".
PROTOCOL_ERRORS = frozenset({1, 2, 3, 4, 5, 7, 8, 501, 502, 505, 506, 507, 508, 509, 510})

_RESPONSE = re.compile(r"^(?P<tag>\d{5}|E\d{4}) (?P<kind>[&#%!])(?: (?P<body>.*))?$")
_ERROR = re.compile(
    r'^Error\(\s*(?P<sev>\d+)\s*,\s*(?P<num>\d{1,4})\s*,\s*(?P<method>"[^"]*"|[^,]*?)\s*,\s*"(?P<text>[^"]*)"\s*\)$'
)
_ITEM = re.compile(r"\s*(?P<name>[A-Za-z][A-Za-z0-9_.]*)\((?P<args>[^()]*)\)\s*(?:,|$)")


# A bridge CMM's length-measuring error is a few micrometres (a Zeiss CONTURA's MPE_E0 = (1.8 +
# L/300) um, ISO 10360-2: 5.1 um over a metre). A tool pose fitted to tooling balls carries several
# touches and the balls' fit besides, and identification weighs its orientation with this figure
# over the balls' 0.1 m spacing (calibration.identify's sigma_rad default): twice that MPE, 10 um
# per axis. The simulated cell bears it out: a CMM session on the demo cell fits to chi2/dof 0.93
# with it (2.0 with 5 um, 0.64 with a tracker's 20 um). A machine's own figure: ``sigma_m``.
CMM_SIGMA_M = 10e-6


@dataclass(frozen=True, slots=True)
class IppDmeConfig:
    """How to reach an I++ DME server and how to probe.

    ``url``: pyserial URL of the I++ server (``socket://host:1294``); ``timeout_s``: deadline
    for the acknowledgement of every command and for the completion of commands that do not
    move; ``move_timeout_s``: deadline for ``Home``, ``ChangeTool`` and each ``PtMeas``;
    ``tool_name``: the probe to use (``FindTool`` / ``ChangeTool``); ``approach_m`` /
    ``search_m``: ``Tool.PtMeasPar.Approach`` / ``Search`` (the probe starts ``approach_m``
    before the nominal point and searches up to ``search_m`` past it); ``home_if_needed``:
    send ``Home()`` when ``IsHomed()`` says 0 (otherwise that is an error); ``reconnect``:
    reconnect once and resend when the link drops; ``sigma_m``: the per-axis standard uncertainty
    of a measured tool position (m), what sessions plan and weigh with (:data:`CMM_SIGMA_M`
    unless stated).
    """

    url: str = "socket://127.0.0.1:1294"
    timeout_s: float = 5.0
    move_timeout_s: float = 60.0
    tool_name: str = "RefTool"
    approach_m: float = 0.003
    search_m: float = 0.006
    home_if_needed: bool = True
    reconnect: bool = True
    baudrate: int = 115200
    sigma_m: float = CMM_SIGMA_M

    def __post_init__(self):
        for name in ("timeout_s", "move_timeout_s", "approach_m", "search_m", "sigma_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")
        if '"' in self.tool_name or not self.tool_name:
            raise ValueError(f"tool_name must be a non-empty name without quotes; got {self.tool_name!r}")


@dataclass(frozen=True, slots=True)
class IppError:
    """One ``Error(F1, F2, F3, Text)`` response."""

    severity: int
    number: int
    method: str
    text: str

    def describe(self) -> str:
        return f"I++ error {self.number:04d} (severity {self.severity}) in {self.method or '?'}: {self.text}"


@dataclass(frozen=True, slots=True)
class IppEvent:
    """An unsolicited ``E0000`` line: ``kind`` is ``"#"`` (data) or ``"!"`` (error)."""

    kind: str
    body: str
    timestamp_s: float
    error: IppError | None = None


def parse_items(body: str) -> dict[str, tuple]:
    """Parse an I++ data body ``X(1.0), Y(2.0), IJK(0,0,1)`` into ``{"X": (1.0,), ...}``.

    Arguments are numbers (floats) or quoted strings. Raises ``ValueError`` on anything else.
    """
    items: dict[str, tuple] = {}
    pos = 0
    body = body.strip()
    while pos < len(body):
        m = _ITEM.match(body, pos)
        if not m or m.end() == pos:
            raise ValueError(f"cannot parse {body[pos:]!r}")
        args = []
        for raw in m.group("args").split(","):
            raw = raw.strip()
            if not raw:
                continue
            if len(raw) >= 2 and raw[0] == raw[-1] == '"':
                args.append(raw[1:-1])
            else:
                args.append(float(raw))
        items[m.group("name")] = tuple(args)
        pos = m.end()
    return items


def parse_error(body: str) -> IppError:
    """Parse ``Error(F1, F2, F3, Text)``. Raises ``ValueError`` if it is not one."""
    m = _ERROR.match(body.strip())
    if not m:
        raise ValueError(f"not an I++ error: {body!r}")
    return IppError(int(m.group("sev")), int(m.group("num")), m.group("method").strip('"'), m.group("text"))


def _mm(v: float) -> str:
    return f"{v:.6f}"


class IppDmeCmm(Cmm):
    """A CMM behind an I++ DME server. Connects and starts a session on construction."""

    def __init__(self, config: IppDmeConfig):
        self.config = config
        self.name = f"cmm {config.url}"
        self._link = LineLink(config.url, device=self.name, timeout_s=config.timeout_s, baudrate=config.baudrate)
        self._tag = 0
        self._etag = 0
        self._closed = False
        self._event_error: IppError | None = None
        self._clearing = False
        self.events: collections.deque[IppEvent] = collections.deque(maxlen=200)
        self.warnings: collections.deque[IppError] = collections.deque(maxlen=200)
        self.dme_version: str | None = None
        self._connect()

    # ----------------------------------------------------------------- Cmm

    @property
    def sigma_m(self) -> float:
        """The per-axis standard uncertainty its configuration declares (m)."""
        return self.config.sigma_m

    def probe(self, p_world: np.ndarray, approach_world: np.ndarray) -> np.ndarray:
        """Probe each nominal point ``p_world`` (k, 3) m moving along ``approach_world`` (k, 3).

        Returns the probe-radius-compensated touched points (k, 3) m in the CMM frame.
        Raises ``MeasurementError`` on no touch or a target out of the machine volume.
        """
        p = np.asarray(p_world, dtype=float)
        a = np.asarray(approach_world, dtype=float)
        if p.ndim == 1:
            p, a = p[None], a.reshape(1, -1)
        if p.ndim != 2 or p.shape[1] != 3 or a.shape != p.shape:
            raise ValueError(f"`p_world` and `approach_world` must both have shape (k, 3); got {p.shape} and {a.shape}")
        norm = np.linalg.norm(a, axis=1)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(a))) or np.any(norm <= 0):
            raise ValueError("`p_world` and `approach_world` must be finite and every approach direction non-zero")
        ijk = -a / norm[:, None]  # I++ IJK: the surface normal, against which the probe travels
        touched = np.empty_like(p)
        for i in range(len(p)):
            touched[i] = self._pt_meas(p[i] / MM, ijk[i]) * MM
        return touched

    def close(self) -> None:
        """End the session (best effort) and close the link. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._link.is_open:
            try:
                self._transaction("EndSession()", timeout_s=min(self.config.timeout_s, 2.0))
            except DeviceError as exc:
                log.debug("%s: EndSession failed while closing: %s", self.name, exc)
        self._link.close()

    # ----------------------------------------------------------------- extra queries

    def position(self) -> np.ndarray:
        """The probe position (3,) m, from ``Get(X(), Y(), Z())``."""
        items = self._single_data(self._call("Get(X(), Y(), Z())"), "Get(X(), Y(), Z())", ("X", "Y", "Z"))
        return np.array([items["X"][0], items["Y"][0], items["Z"][0]]) * MM

    def error_status(self) -> bool:
        """``True`` if the server is in an error state (``GetErrStatusE()``, fast queue)."""
        data = self._call("GetErrStatusE()", event=True)
        items = self._single_data(data, "GetErrStatusE()", ("ErrStatus",))
        return bool(items["ErrStatus"][0])

    # ----------------------------------------------------------------- session

    def _connect(self) -> None:
        cfg = self.config
        self._link.open()
        self._event_error = None
        try:
            self._transaction("StartSession()")
            self._transaction("SetCoordSystem(MachineCsy)")
            try:
                data = self._transaction("GetDMEVersion()")
                self.dme_version = str(parse_items(data[0]).get("DMEVersion", ("?",))[0]) if data else None
            except (ProtocolError, ValueError, IndexError):
                self.dme_version = None
            homed = self._single_data(self._transaction("IsHomed()"), "IsHomed()", ("IsHomed",))["IsHomed"][0]
            if not homed:
                if not cfg.home_if_needed:
                    raise DeviceFaultError("the CMM is not homed and home_if_needed is off", device=self.name)
                log.info("%s: homing the CMM", self.name)
                self._transaction("Home()", timeout_s=cfg.move_timeout_s)
            self._transaction(f'FindTool("{cfg.tool_name}")')
            self._transaction(f'ChangeTool("{cfg.tool_name}")', timeout_s=cfg.move_timeout_s)
            self._transaction(f"SetProp(Tool.PtMeasPar.Approach({_mm(cfg.approach_m / MM)}))")
            self._transaction(f"SetProp(Tool.PtMeasPar.Search({_mm(cfg.search_m / MM)}))")
            self._transaction("OnPtMeasReport(X(), Y(), Z(), IJK())")
        except BaseException:
            self._link.close()
            raise
        log.info("%s: session started (I++ DME %s), tool %s", self.name, self.dme_version, cfg.tool_name)

    def _call(self, method_call: str, *, timeout_s: float | None = None, event: bool = False) -> list[str]:
        """Run one transaction, reconnecting once (new session) if the link dropped."""
        if self._closed:
            raise DeviceConnectionError("the driver is closed", device=self.name)
        attempts = 2 if self.config.reconnect else 1
        for attempt in range(attempts):
            try:
                if not self._link.is_open:
                    self._connect()
                return self._transaction(method_call, timeout_s=timeout_s, event=event)
            except DeviceConnectionError as exc:
                self._link.close()
                if attempt + 1 < attempts:
                    log.warning("%s: %s; reconnecting once and resending %s", self.name, exc, method_call)
                    continue
                detail = " after one reconnect" if attempts > 1 else ""
                raise DeviceConnectionError(f"{method_call} failed{detail}: {exc}", device=self.name) from exc
        raise AssertionError("unreachable")  # pragma: no cover

    def _pt_meas(self, p_mm: np.ndarray, ijk: np.ndarray) -> np.ndarray:
        x, y, z = (_mm(v) for v in p_mm)
        i, j, k = (f"{v:.9f}" for v in ijk)
        call = f"PtMeas(X({x}), Y({y}), Z({z}), IJK({i}, {j}, {k}))"
        data = self._call(call, timeout_s=self.config.move_timeout_s)
        items = self._single_data(data, "PtMeas", ("X", "Y", "Z"))
        return np.array([items["X"][0], items["Y"][0], items["Z"][0]])

    # ----------------------------------------------------------------- transactions

    def _next_tag(self, event: bool) -> str:
        if event:
            self._etag = self._etag % 9999 + 1
            return f"E{self._etag:04d}"
        self._tag = self._tag % 99999 + 1
        return f"{self._tag:05d}"

    def _transaction(self, method_call: str, *, timeout_s: float | None = None, event: bool = False) -> list[str]:
        """Send one command; return its data bodies once ``%`` arrives; errors become exceptions."""
        tag = self._next_tag(event)
        ack_limit_s = self.config.timeout_s
        done_limit_s = timeout_s or self.config.timeout_s
        ack_deadline = time.monotonic() + ack_limit_s
        done_deadline = time.monotonic() + done_limit_s
        self._event_error = None
        self._link.write_line(f"{tag} {method_call}")
        acked = False
        data: list[str] = []
        while True:
            deadline = done_deadline if acked else min(ack_deadline, done_deadline)
            remaining = max(deadline - time.monotonic(), 0.0)
            what = "completion" if acked else "acknowledgement"
            try:
                line = self._link.read_line(remaining, expecting=f"{what} of {tag} {method_call}")
            except DeviceTimeoutError as exc:
                self._link.close()  # the session state is unknown now: start afresh next time
                limit_s = done_limit_s if acked else min(ack_limit_s, done_limit_s)
                raise DeviceTimeoutError(
                    f"no {what} of {tag} {method_call} within {limit_s:g} s", device=self.name
                ) from exc
            except ProtocolError:
                self._link.close()
                raise
            m = _RESPONSE.match(line)
            if not m:
                self._link.close()
                raise ProtocolError(f"unparsable line {line!r} while waiting for {tag} {method_call}", device=self.name)
            rtag, kind, body = m.group("tag"), m.group("kind"), m.group("body") or ""
            if rtag == "E0000":
                self._on_event(kind, body)
                continue
            if rtag != tag:
                log.debug("%s: dropping line of a finished transaction: %r", self.name, line)
                continue
            if kind == "&":
                acked = True
            elif kind == "#":
                data.append(body)
            elif kind == "%":
                break
            else:  # "!"
                error = self._parse_error_body(body, tag, method_call)
                if error.severity < 2:
                    log.warning("%s: %s %s: %s", self.name, tag, method_call, error.describe())
                    self.warnings.append(error)
                    continue
                self._clear_errors()
                raise self._exception(error, method_call)
        if self._event_error is not None:
            error, self._event_error = self._event_error, None
            self._clear_errors()
            raise self._exception(error, method_call, during_event=True)
        return data

    def _on_event(self, kind: str, body: str) -> None:
        error = None
        if kind == "!":
            try:
                error = parse_error(body)
            except ValueError:
                self._link.close()
                raise ProtocolError(f"unparsable error event {body!r}", device=self.name) from None
            log.warning("%s: event: %s", self.name, error.describe())
            if error.severity >= 2:
                self._event_error = error
        else:
            log.info("%s: event %s %s", self.name, kind, body)
        self.events.append(IppEvent(kind, body, time.time(), error))

    def _parse_error_body(self, body: str, tag: str, method_call: str) -> IppError:
        try:
            return parse_error(body)
        except ValueError:
            self._link.close()
            raise ProtocolError(f"malformed error reply {body!r} to {tag} {method_call}", device=self.name) from None

    def _clear_errors(self) -> None:
        """``ClearAllErrors()`` after an error of severity >= 2; a failure closes the session."""
        if self._clearing or not self._link.is_open:
            return
        self._clearing = True
        try:
            self._transaction("ClearAllErrors()")
        except DeviceError as exc:
            log.warning("%s: ClearAllErrors failed (%s); the next call starts a new session", self.name, exc)
            self._link.close()
        finally:
            self._clearing = False

    def _exception(self, error: IppError, method_call: str, *, during_event: bool = False) -> DeviceError:
        where = "an event during " if during_event else ""
        message = f"{where}{method_call}: {error.describe()}"
        if error.number in MEASUREMENT_ERRORS and not during_event:
            exc: DeviceError = MeasurementError(message, device=self.name, code=error.number)
        elif error.number in PROTOCOL_ERRORS and not during_event:
            exc = ProtocolError(message, device=self.name, code=error.number)
        else:
            exc = DeviceFaultError(message, device=self.name, code=error.number)
        exc.severity = error.severity
        exc.method = error.method
        exc.text = error.text
        return exc

    def _single_data(self, data: list[str], what: str, keys: tuple[str, ...]) -> dict[str, tuple]:
        """Parse the one data line of a transaction and check it has ``keys``."""
        try:
            if len(data) != 1:
                raise ValueError(f"expected one data line, got {len(data)}")
            items = parse_items(data[0])
            for key in keys:
                value = items[key]
                if not value or not all(isinstance(v, float) and np.isfinite(v) for v in value):
                    raise ValueError(f"{key} is not a finite number")
        except (ValueError, KeyError) as exc:
            self._link.close()
            raise ProtocolError(
                f"bad data for {what}: {data!r} ({exc}); expected {', '.join(k + '(...)' for k in keys)}",
                device=self.name,
            ) from None
        return items
