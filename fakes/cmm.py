"""A simulated coordinate measuring machine with an I++ DME server (VDMA 8722) on TCP.

The CMM probes the true tooling balls on the simulated robot's tool: ball centres
``cell.balls_tool`` (tool frame) placed in the world (= CMM machine frame) by the true robot
pose now, radius ``cell.ball_radius_m``. ``PtMeas(X(x), Y(y), Z(z), IJK(i, j, k))`` starts at
the nominal point plus ``Tool.PtMeasPar.Approach`` along ``IJK`` and travels against ``IJK``
for up to ``Approach + Search``. The probe tip (a ball of the active tool's radius) touches a
tooling ball where the travel line meets the sphere of radius ``ball + tip`` around its
centre; the contact is disturbed along the surface normal by ``cell.noise.cmm_m``, and the
reported point is the tip centre moved by the tip radius along the travel direction: the
probe-radius compensation of a real CMM for single points (along the nominal vector).

The server (one session per connection; machine state - homed, position, tool and its
parameters - is shared, as on a real machine)::

    TTTTT Method(args)  ->  TTTTT &  ,  TTTTT # data ... ,  TTTTT %
                        or  TTTTT &  ,  TTTTT ! Error(sev, nnnn, "Method", "text") ,  TTTTT %

Methods: ``StartSession EndSession GetDMEVersion ClearAllErrors SetCoordSystem(MachineCsy)
Home IsHomed EnumTools FindTool ChangeTool SetProp GetProp OnPtMeasReport Get GoTo PtMeas`` and the fast-queue
``GetErrStatusE AbortE GetPropE`` (tags ``Ennnn``). Lengths are millimetres. The machine starts
not homed. After an error of severity >= 2 every command but ``ClearAllErrors``,
``EndSession`` and the fast queue gets ``0514 Use ClearAllErrors to continue``.

Errors raised by the simulation: 1003 no touch (no tooling ball on the path, or
``cell.faults.no_touch_at`` counted per ``PtMeas`` with ``cell.count("cmm.ptmeas")``), 1008
target out of machine volume (``cell.cmm_volume_m``, checked for the start and the end of the
probing path and for ``GoTo``), 1001 illegal touch (the approach point is inside a ball, or the
robot carrying the balls is moving), 1502 tool not found, 0508 bad context (no session, not
homed), 0501 unsupported command, 0509 bad argument, 0510 bad property.

Link faults (``cell.faults``, counted per command with ``cell.count("cmm.request")``):
``delay_s`` before the acknowledgement (of every command, or only of those in ``delay_at``),
``garble_at`` / ``garble_rate`` (the first reply line after the acknowledgement is
corrupted), ``drop_connection_at`` (the connection is closed instead of answering).
:meth:`IppCmmFake.send_event` pushes an unsolicited ``E0000`` line to every session.

Run it alone: ``python -m fakes.cmm --robot ur5e --ball ball1=0.05,0,0.03 ...``.
"""

from __future__ import annotations

import re
import threading
import time

import numpy as np

from calibration.errors import RecalError
from fakes._lineserver import Client, DropConnection, LineServer, garble
from fakes.world import SimCell

MM = 1e-3

_COMMAND = re.compile(r"^(?P<tag>\d{5}|E\d{4}) (?P<method>[A-Za-z][A-Za-z0-9_]*)\((?P<args>.*)\)\s*$")
_ITEM = re.compile(r"\s*(?P<name>[A-Za-z][A-Za-z0-9_.]*)\((?P<args>[^()]*)\)\s*(?:,|$)")
_FAST = {"GetErrStatusE", "AbortE", "GetPropE"}
_PROPS = {
    "Tool.PtMeasPar.Approach",
    "Tool.PtMeasPar.Search",
    "Tool.PtMeasPar.Retract",
    "Tool.PtMeasPar.Speed",
    "Tool.PtMeasPar.Accel",
    "Tool.GoToPar.Speed",
    "Tool.GoToPar.Accel",
}
_REPORT_ITEMS = {"X", "Y", "Z", "IJK", "ER", "R", "Tool.A", "Tool.B", "Tool.C"}


class IppError(RecalError):
    """An I++ error to send as ``! Error(severity, number, method, text)``."""

    def __init__(self, severity: int, number: int, text: str):
        super().__init__(text)
        self.severity = severity
        self.number = number
        self.text = text


def _items(text: str) -> list[tuple[str, list]]:
    """``X(1), IJK(0,0,1), Tool.PtMeasPar.Approach()`` -> [(name, [args...]), ...]."""
    out = []
    pos = 0
    text = text.strip()
    while pos < len(text):
        m = _ITEM.match(text, pos)
        if not m or m.end() == pos:
            raise IppError(3, 509, f"Bad argument: cannot parse {text[pos:]!r}")
        args = []
        for raw in m.group("args").split(","):
            raw = raw.strip()
            if raw:
                try:
                    args.append(float(raw))
                except ValueError:
                    raise IppError(3, 509, f"Bad argument: {raw!r} is not a number") from None
        out.append((m.group("name"), args))
        pos = m.end()
    return out


def _string_arg(text: str) -> str:
    m = re.fullmatch(r'\s*"([^"]*)"\s*', text)
    if not m:
        raise IppError(3, 509, f"Bad argument: expected a quoted name, got {text!r}")
    return m.group(1)


def _f(v: float) -> str:
    return f"{v:.6f}"


class IppCmmFake(LineServer):
    """The CMM of a simulated cell (see the module docstring)."""

    device_name = "cmm"

    def __init__(
        self,
        cell: SimCell,
        host: str = "127.0.0.1",
        port: int = 1294,
        *,
        tools: dict[str, float] | None = None,
        homed: bool = False,
        ptmeas_time_s: float = 1.0,
        home_time_s: float = 10.0,
        tool_change_time_s: float = 2.0,
        dme_version: str = "1.4.3",
    ):
        super().__init__(host, port)
        self.cell = cell
        self.tools = dict(tools) if tools is not None else {"RefTool": 1.5e-3, "Probe2mm": 1.0e-3}
        self.homed = homed
        self.ptmeas_time_s = ptmeas_time_s
        self.home_time_s = home_time_s
        self.tool_change_time_s = tool_change_time_s
        self.dme_version = dme_version
        self.tool = next(iter(self.tools))
        self.props_mm = {
            "Tool.PtMeasPar.Approach": 2.0,
            "Tool.PtMeasPar.Search": 4.0,
            "Tool.PtMeasPar.Retract": 2.0,
            "Tool.PtMeasPar.Speed": 5.0,
            "Tool.PtMeasPar.Accel": 50.0,
            "Tool.GoToPar.Speed": 100.0,
            "Tool.GoToPar.Accel": 500.0,
        }
        self.position_mm = np.zeros(3)
        self._machine = threading.RLock()

    def endpoint(self) -> dict:
        return {"cmm": f"socket://{self.host}:{self.port}"}

    def send_event(self, body: str, *, error: tuple[int, int, str] | None = None) -> None:
        """Push ``E0000 # body`` (or, with ``error=(severity, number, text)``,
        ``E0000 ! Error(...)``) to every client that has a session."""
        if error is not None:
            sev, num, text = error
            line = f'E0000 ! Error({sev}, {num:04d}, "{body}", "{text}")'
        else:
            line = f"E0000 # {body}"
        for client in self.clients():
            if client.state.get("session"):
                client.send_line(line)

    # ----------------------------------------------------------------- protocol

    def on_connect(self, client: Client) -> None:
        client.state.update(session=False, error=False, report=["X", "Y", "Z"])

    def handle_line(self, client: Client, line: str) -> None:
        if not line.strip():
            return
        n = self.cell.count("cmm.request")
        faults = self.cell.faults
        if n in faults.drop_connection_at:
            raise DropConnection
        m = _COMMAND.match(line)
        delay_s = faults.reply_delay_s(n)
        if delay_s > 0:
            time.sleep(delay_s)
        if not m or m.group("tag") == "00000":
            snippet = line[:40].replace('"', "'")
            client.send_line(f'E0000 ! Error(2, 0001, "", "Illegal tag or command syntax: {snippet}")')
            return
        tag, method, args = m.group("tag"), m.group("method"), m.group("args")
        garbled = n in faults.garble_at or self.cell.chance(faults.garble_rate)
        client.send_line(f"{tag} &")  # received; the work follows
        replies = []
        try:
            data = self._dispatch(client, tag, method, args)
            replies += [f"{tag} # {d}" for d in data]
        except IppError as err:
            text = err.text.replace('"', "'")  # I++ strings have no escapes
            replies.append(f'{tag} ! Error({err.severity}, {err.number:04d}, "{method}", "{text}")')
            if err.severity >= 2:
                client.state["error"] = True
        replies.append(f"{tag} %")
        if garbled:
            replies[0] = garble(replies[0])
        for r in replies:
            client.send_line(r)

    def _dispatch(self, client: Client, tag: str, method: str, args: str) -> list[str]:
        st = client.state
        if tag.startswith("E"):
            if method not in _FAST:
                raise IppError(3, 507, f"Illegal command: {method} is not a fast-queue command")
            return self._fast(client, method, args)
        if method == "StartSession":
            st.update(session=True, error=False, report=["X", "Y", "Z"])
            return []
        if method == "GetDMEVersion":
            return [f'DMEVersion("{self.dme_version}")']
        if not st["session"]:
            raise IppError(3, 508, "Bad context: no session (send StartSession first)")
        if method == "EndSession":
            st["session"] = False
            return []
        if method == "ClearAllErrors":
            st["error"] = False
            return []
        if st["error"]:
            raise IppError(2, 514, "Use ClearAllErrors to continue")
        handler = getattr(self, f"_m_{method}", None)
        if handler is None:
            raise IppError(3, 501, f"Unsupported command {method}")
        return handler(client, args)

    def _fast(self, client: Client, method: str, args: str) -> list[str]:
        if method == "GetErrStatusE":
            return [f"ErrStatus({1 if client.state['error'] else 0})"]
        if method == "GetPropE":
            return self._m_GetProp(client, args)
        return []  # AbortE: nothing runs concurrently in this fake

    # ----------------------------------------------------------------- methods

    def _m_Home(self, client: Client, args: str) -> list[str]:
        self._wait(self.home_time_s)
        with self._machine:
            self.homed = True
            self.position_mm = self._home_position_mm()
        return []

    def _m_SetCoordSystem(self, client: Client, args: str) -> list[str]:
        if args.strip() != "MachineCsy":
            raise IppError(
                3, 506, f"Argument not supported: this CMM measures in MachineCsy only, not {args.strip()!r}"
            )
        return []

    def _m_IsHomed(self, client: Client, args: str) -> list[str]:
        return [f"IsHomed({1 if self.homed else 0})"]

    def _m_EnumTools(self, client: Client, args: str) -> list[str]:
        return [f'"{name}"' for name in self.tools]

    def _m_FindTool(self, client: Client, args: str) -> list[str]:
        name = _string_arg(args)
        if name not in self.tools:
            raise IppError(3, 1502, f"Tool not found: {name}")
        return []

    def _m_ChangeTool(self, client: Client, args: str) -> list[str]:
        name = _string_arg(args)
        if name not in self.tools:
            raise IppError(3, 1502, f"Tool not found: {name}")
        self._wait(self.tool_change_time_s)
        with self._machine:
            self.tool = name
        return []

    def _m_SetProp(self, client: Client, args: str) -> list[str]:
        for name, values in _items(args):
            if name not in _PROPS:
                raise IppError(3, 510, f"Bad property {name}")
            if len(values) != 1 or not values[0] > 0:
                raise IppError(3, 509, f"Bad argument: {name} needs one positive number")
            with self._machine:
                self.props_mm[name] = values[0]
        return []

    def _m_GetProp(self, client: Client, args: str) -> list[str]:
        out = []
        for name, values in _items(args):
            if name not in _PROPS or values:
                raise IppError(3, 510, f"Bad property {name}")
            out.append(f"{name}({_f(self.props_mm[name])})")
        return [", ".join(out)]

    def _m_OnPtMeasReport(self, client: Client, args: str) -> list[str]:
        report = []
        for name, values in _items(args):
            if name not in _REPORT_ITEMS or values:
                raise IppError(3, 509, f"Bad argument: {name}() cannot be reported")
            report.append(name)
        client.state["report"] = report
        return []

    def _m_Get(self, client: Client, args: str) -> list[str]:
        out = []
        for name, _ in _items(args):
            if name not in ("X", "Y", "Z"):
                raise IppError(3, 509, f"Bad argument: {name}")
            out.append(f"{name}({_f(self.position_mm['XYZ'.index(name)])})")
        return [", ".join(out)]

    def _m_GoTo(self, client: Client, args: str) -> list[str]:
        self._require_homed()
        target = self.position_mm.copy()
        for name, values in _items(args):
            if name not in ("X", "Y", "Z") or len(values) != 1:
                raise IppError(3, 509, f"Bad argument: {name}")
            target["XYZ".index(name)] = values[0]
        self._check_volume(target * MM)
        self._wait(1.0)
        with self._machine:
            self.position_mm = target
        return []

    def _m_PtMeas(self, client: Client, args: str) -> list[str]:
        self._require_homed()
        nominal_mm = self.position_mm.copy()
        ijk = None
        for name, values in _items(args):
            if name in ("X", "Y", "Z") and len(values) == 1:
                nominal_mm["XYZ".index(name)] = values[0]
            elif name == "IJK" and len(values) == 3:
                ijk = np.array(values)
            else:
                raise IppError(3, 509, f"Bad argument: {name}")
        if ijk is None:  # no vector: approach along the line from where the probe is
            ijk = self.position_mm - nominal_mm
        norm = float(np.linalg.norm(ijk))
        if norm == 0:
            raise IppError(2, 1010, "Vector has no norm")
        n = ijk / norm
        k = self.cell.count("cmm.ptmeas")
        touched_m, probe_m = self._touch(nominal_mm * MM, n, no_touch=k in self.cell.faults.no_touch_at)
        self._wait(self.ptmeas_time_s)
        with self._machine:
            self.position_mm = (probe_m + n * self.props_mm["Tool.PtMeasPar.Retract"] * MM) / MM
        values = {
            "X": _f(touched_m[0] / MM),
            "Y": _f(touched_m[1] / MM),
            "Z": _f(touched_m[2] / MM),
            "IJK": ", ".join(f"{v:.6f}" for v in n),
            "ER": _f(self.tools[self.tool] / MM),
            "R": _f(0.0),
            "Tool.A": _f(0.0),
            "Tool.B": _f(0.0),
            "Tool.C": _f(0.0),
        }
        return [", ".join(f"{name}({values[name]})" for name in client.state["report"])]

    # ----------------------------------------------------------------- simulation

    def _touch(self, nominal_m: np.ndarray, n: np.ndarray, *, no_touch: bool) -> tuple[np.ndarray, np.ndarray]:
        """Probe from ``nominal + approach*n`` along ``-n``; return (reported point, tip centre) in m."""
        approach = self.props_mm["Tool.PtMeasPar.Approach"] * MM
        search = self.props_mm["Tool.PtMeasPar.Search"] * MM
        d = -n
        start = nominal_m + approach * n
        end = nominal_m - search * n
        self._check_volume(start)
        self._check_volume(end)
        if self.cell.is_moving():
            raise IppError(2, 1001, "Illegal touch: the part moved during probing")
        if no_touch:
            raise IppError(2, 1003, "No touch")
        tip_m = self.tools[self.tool]
        contact_radius = self.cell.ball_radius_m + tip_m
        T = self.cell.T_world_tool()
        best = None
        for p_tool in self.cell.balls_tool.values():
            centre = T[:3, :3] @ np.asarray(p_tool, float) + T[:3, 3]
            w = start - centre
            c = w @ w - contact_radius**2
            if c <= 0:
                raise IppError(2, 1001, "Illegal touch: the probe hit the part before the approach point")
            b = w @ d
            disc = b * b - c
            if disc < 0:
                continue
            s = -b - np.sqrt(disc)
            if 0 <= s <= approach + search and (best is None or s < best[0]):
                best = (s, centre)
        if best is None:
            raise IppError(2, 1003, "No touch")
        s, centre = best
        tip_centre = start + s * d
        normal = (tip_centre - centre) / np.linalg.norm(tip_centre - centre)
        tip_centre = tip_centre + normal * float(self.cell.normal(self.cell.noise.cmm_m))
        return tip_centre + tip_m * d, tip_centre

    def _check_volume(self, p_m: np.ndarray) -> None:
        volume = self.cell.cmm_volume_m
        if volume is None:
            return
        lo, hi = (np.asarray(v, float) for v in volume)
        if np.any(p_m < lo) or np.any(p_m > hi):
            raise IppError(3, 1008, "Target position out of machine volume")

    def _require_homed(self) -> None:
        if not self.homed:
            raise IppError(3, 508, "Bad context: the machine is not homed")

    def _home_position_mm(self) -> np.ndarray:
        volume = self.cell.cmm_volume_m
        if volume is None:
            return np.zeros(3)
        lo, hi = (np.asarray(v, float) for v in volume)
        return np.array([lo[0], lo[1], hi[2]]) / MM

    def _wait(self, simulated_s: float) -> None:
        if self.cell.time_scale > 0:
            time.sleep(simulated_s * self.cell.time_scale)


# What `recal fake-cell` starts (fakes/cell.py finds this line): the key of its --no-KEY flag, its
# place in the start order, the class, and its keyword arguments from the command line.
CELL_FAKE = {"key": "cmm", "order": 50, "cls": IppCmmFake}


def main(argv: list[str] | None = None) -> int:
    from fakes._standalone import run_fake

    return run_fake(IppCmmFake, default_port=1294, argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
