"""ABB RAPID modules (``.mod``, ``.modx``, ``.prg``).

Targets: ``robtarget`` ``[[x, y, z], [q1, q2, q3, q4], [cf1, cf4, cf6, cfx], [eax_a, ..., eax_f]]``
(mm; quaternion scalar first; configuration; external axes, left untouched) and ``jointtarget``
``[[rax_1, ..., rax_6], [eax_a, ...]]`` (degrees), declared (``CONST``/``PERS``/``VAR``, with
``LOCAL`` or ``TASK``, arrays ``name{k}`` included) or written inline as the target of ``MoveJ``,
``MoveL``, ``MoveC`` (both points) and ``MoveAbsJ``, their ``DO`` and ``Sync`` variants,
``TriggJ``/``TriggL``/``TriggC`` and ``ArcL``/``ArcC`` (whose tool is their last argument). A statement runs to its ``;`` across lines;
``!`` starts a comment; RAPID is not case sensitive.

Frames: a move's tool (``tool0``, the flange, or a ``tooldata`` declared in the file, held by the
robot) and its ``\\WObj`` (``wobj0`` or absent: the robot's base frame; or a ``wobjdata`` declared
in the file, not held by the robot, not moved by a mechanical unit: ``uframe · oframe``). A move
whose tool or work object Recal cannot resolve refuses the file, naming the line. A declared
robtarget takes the frames of the moves that use it; one used with different frames, or by no
move, is left alone and reported, as are targets computed by an expression (``Offs``, ``RelTool``,
``CRobT``) and other uses of a target's name.

Configuration monitoring: after ``ConfL\\Off`` (until ``ConfL\\On``) a linear or circular move
does not hold its target's confdata, and after ``ConfJ\\Off`` a joint move does not: the
controller takes the configuration nearest the start, as for a KRL or TP target without
configuration data (service.programs.retarget.controller_solutions); the confdata is kept as
written. The state follows the module's text (a controller starts a program with both on); a
target used by several moves takes its first move's.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from calibration.errors import RecalError
from calibration.transforms import homogeneous, quat_to_matrix

from ..files import InputError
from .base import Number, Program, Target, Uninterpreted, read_text
from .tokens import IDENT_RE, RAPID, Source, split_top_level, trim

# instruction -> (number of targets, index of the tool among the positional arguments; -1: the last)
MOVES = {
    "movej": (1, 3),
    "movel": (1, 3),
    "movec": (2, 4),
    "moveabsj": (1, 3),
    "movejdo": (1, 3),
    "moveldo": (1, 3),
    "movecdo": (2, 4),
    "movejsync": (1, 3),
    "movelsync": (1, 3),
    "movecsync": (2, 4),
    "triggj": (1, -1),
    "triggl": (1, -1),
    "triggc": (2, -1),
    "arcl": (1, -1),
    "arcc": (2, -1),
}
# ConfL\Off / ConfJ\Off (and \On): whether the controller holds a linear (and circular) or a
# joint move to the target's written configuration
_CONF_RE = RAPID.pattern(r"^\s*(ConfL|ConfJ)\s*\\\s*(On|Off)\s*$")
_JOINT_MOVES = ("movej", "movejdo", "movejsync", "triggj")
_MOVE_RE = RAPID.pattern(r"(?<![\w\\])(" + "|".join(sorted(MOVES, key=len, reverse=True)) + r")(?=[\s\\,])")
_DECL_RE = RAPID.pattern(
    r"^[ \t]*(?:(local|task)\s+)?(const|pers|var)\s+([a-z_]\w*)\s+([a-z_]\w*)\s*(\{[^}]*\})?\s*", re.MULTILINE
)
_REF_RE = re.compile(r"([A-Za-z_]\w*)\s*(?:\{\s*(\d+)\s*\})?")
TYPES = ("robtarget", "jointtarget", "tooldata", "wobjdata")


def _declaration_match(chunk: str) -> re.Match | None:
    """A statement's declaration of a robtarget, jointtarget, tooldata or wobjdata."""
    d = _DECL_RE.search(chunk)
    return d if d and d.group(3).lower() in TYPES else None


class _Bad(RecalError, ValueError):
    """A malformed aggregate at ``offset`` (caught here and reported as the file's InputError)."""

    def __init__(self, offset, message):
        self.offset, self.message = offset, message


def _value(code: str, i: int):
    """The aggregate or leaf starting at ``i`` (whitespace skipped): a list of nodes, or a leaf
    ``(start, end)``; and the index after it."""
    n = len(code)
    while i < n and code[i].isspace():
        i += 1
    if i < n and code[i] == "[":
        items: list = []
        i += 1
        while True:
            while i < n and code[i].isspace():
                i += 1
            if i < n and code[i] == "]" and not items:
                return items, i + 1
            node, i = _value(code, i)
            items.append(node)
            while i < n and code[i].isspace():
                i += 1
            if i < n and code[i] == ",":
                i += 1
                continue
            if i < n and code[i] == "]":
                return items, i + 1
            raise _Bad(i, "expected ',' or ']' in an aggregate")
    s, depth = i, 0
    while i < n:
        ch = code[i]
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
        elif depth == 0 and ch in ",];":
            break
        i += 1
    e = i
    while e > s and code[e - 1].isspace():
        e -= 1
    return (s, e), i


def _split_args(code: str, s: int, e: int) -> list[tuple[int, int]]:
    """Top-level comma-separated pieces of ``code[s:e]``, trimmed."""
    return [trim(code, a, b) for a, b in split_top_level(code, s, e)]


def _options(code: str, s: int, e: int) -> tuple[tuple[int, int], dict[str, str]]:
    """An argument ``main\\Opt:=value\\Switch``: the main part and its options (lowercase names)."""
    parts = split_top_level(code, s, e, "\\")
    main = trim(code, *parts[0])
    opts = {}
    for a, b in parts[1:]:
        t = code[a:b].strip()
        k, _, v = t.partition(":=")
        opts[k.strip().lower()] = v.strip()
    return main, opts


class _Reader(Source):
    """A RAPID file, and how its aggregates are read."""

    def __init__(self, path, text: str):
        super().__init__(RAPID, path, text)

    def numbers(self, node, count, what, offset):
        if not isinstance(node, list):
            self.fail(offset, f"{what}: expected [{count} numbers], got {self.code[node[0] : node[1]]!r}")
        if len(node) != count:
            self.fail(offset, f"{what}: expected {count} values, got {len(node)}")
        out = []
        for leaf in node:
            if isinstance(leaf, list):
                self.fail(offset, f"{what}: expected a number, got an aggregate")
            t = self.text[leaf[0] : leaf[1]]
            try:
                float(t)
            except ValueError:
                self.fail(leaf[0], f"{what}: expected a number, got {t!r}")
            out.append(Number(0, leaf[0], leaf[1], t))
        return tuple(out)

    def pose(self, node, kind, name, offset):
        """A ``pose`` ``[[x,y,z],[q1..q4]]`` (mm, quaternion) -> (4, 4) SI."""
        what = f"{kind} {name}"
        if not isinstance(node, list) or len(node) < 2:
            self.fail(offset, f"{what}: expected [[x, y, z], [q1, q2, q3, q4]]")
        p = self.numbers(node[0], 3, f"{what}: position", offset)
        qn = node[1]
        if isinstance(qn, list) and len(qn) != 4:
            self.fail(offset, f"{what}: expected 4 quaternion values, got {len(qn)}")
        q = self.numbers(qn, 4, f"{what}: quaternion", offset)
        return self._matrix(p, q, what, offset), p, q

    def _matrix(self, p, q, what, offset):
        qv = np.array([n.value for n in q])
        norm = float(np.linalg.norm(qv))
        if abs(norm - 1.0) > 1e-3:
            self.fail(offset, f"{what}: the quaternion has norm {norm:.6g}; expected a unit quaternion")
        return homogeneous(quat_to_matrix(qv), np.array([n.value for n in p]) * 1e-3)


def _module_frames(path) -> dict:
    """The ``tooldata`` and ``wobjdata`` another module of the task declares (not ``LOCAL``):
    lowercase name -> declaration, with the module's reader."""
    r = _Reader(path, read_text(path))
    code, out = r.code, {}
    for s0, stmt_end in r.statements():
        d = _DECL_RE.search(code[s0:stmt_end])
        if not d or d.group(3).lower() not in ("tooldata", "wobjdata") or d.group(5):
            continue
        if (d.group(1) or "").lower() == "local":
            continue  # visible in its own module only
        after = s0 + d.end()
        if not code.startswith(":=", after):
            continue
        try:
            node, _ = _value(code, after + 2)
        except _Bad as exc:
            r.fail(exc.offset, f"{d.group(3)} {d.group(4)}: {exc.message}")
        out[d.group(4).lower()] = {
            "type": d.group(3).lower(),
            "node": node,
            "offset": after,
            "name": d.group(4),
            "r": r,
        }
    return out


def _declared_frame(r: _Reader, dd: dict, typ: str, name: str) -> np.ndarray:
    """A declared ``tooldata`` (the tool in the flange) or ``wobjdata`` (``uframe · oframe``) as
    (4, 4) SI, read from the module ``r`` that declares it."""
    node, text = dd["node"], r.text
    hold = node[0] if isinstance(node, list) and node else None
    held = isinstance(hold, tuple) and text[hold[0] : hold[1]].strip().upper() == "TRUE"
    if typ == "tooldata":
        if not held:
            r.fail(dd["offset"], f"tooldata {name}: a stationary tool (robhold FALSE) is not supported")
        T, _, _ = r.pose(node[1], "tooldata", name, dd["offset"])
        return T
    if held:
        r.fail(dd["offset"], f"wobjdata {name}: a work object held by the robot (robhold TRUE) is not supported")
    if len(node) < 5:
        r.fail(dd["offset"], f"wobjdata {name}: expected [robhold, ufprog, ufmec, uframe, oframe]")
    ufprog = text[node[1][0] : node[1][1]].strip().upper() if isinstance(node[1], tuple) else ""
    if ufprog == "FALSE":
        r.fail(
            dd["offset"], f"wobjdata {name}: a user frame moved by a mechanical unit (ufprog FALSE) is not supported"
        )
    U, _, _ = r.pose(node[3], "wobjdata", name, dd["offset"])
    O, _, _ = r.pose(node[4], "wobjdata", name, dd["offset"])
    return U @ O


def _source(sources: dict, name: str | None) -> str:
    """Where a frame declared outside the module came from, for the report: `` (user.sys)`` or
    `` (--tool-frame)``; nothing for the module's own."""
    src = sources.get((name or "").lower())
    if src is None:
        return ""
    return f" ({src if src.startswith('-') else Path(src).name})"


def _named_frame(vals) -> np.ndarray:
    x, y, z, *q = vals
    qv = np.array(q, dtype=float)
    n = float(np.linalg.norm(qv))
    if abs(n - 1.0) > 1e-3:
        raise ValueError(f"the quaternion has norm {n:.6g}; expected a unit quaternion")
    return homogeneous(quat_to_matrix(qv / n), np.array([x, y, z]) * 1e-3)


def parse(path, data: bytes | None = None, *, n_joints: int = 6, frames=None) -> Program:
    """Parse a RAPID module (see the module docstring). ``frames``
    (:class:`~.frames.Frames`): the task's other modules, whose ``tooldata``/``wobjdata`` the
    moves may use, and tools and work objects given by name (``--tool-frame``/``--work-object``)."""
    if n_joints != 6:
        raise InputError(path, f"RAPID programs are compensated for six-axis arms; the model has {n_joints} joints")
    module = _Module(path, read_text(path, data), frames)
    for s0, stmt_end in module.r.statements():
        module.statement(s0, stmt_end)
    module.resolve_frames()
    module.move_targets()
    module.declared_targets()
    module.undeclared_uses()
    module.other_uses()
    return module.program()


class _Move(NamedTuple):
    """A move statement: its offset, instruction, target argument spans, tool and work object."""

    offset: int
    mv: str
    targets: list[tuple[int, int]]
    tool: str
    wobj: str | None


class _Use(NamedTuple):
    """A move's use of a declared target: its line, instruction, target kind and frames."""

    line: int
    mv: str
    kind: str
    T_tool: np.ndarray
    T_work: np.ndarray
    frames: str
    tool: str
    wobj: str | None


class _Module:
    """One RAPID module being read: its declarations (``decls``: lowercase name -> {type, node,
    offset, name}), its moves in program order and the configuration monitoring each sees, the
    frames they use, and what was found: targets (``out``), statements left alone (``skipped``)."""

    def __init__(self, path, text: str, frames):
        self.r = _Reader(path, text)
        self.decls: dict[str, dict] = {}
        self.moves: list[_Move] = []
        self.skipped: list[Uninterpreted] = []
        self.expected: set[int] = set()  # offsets of identifiers that are a target's own use
        self.monitored = {"confl": True, "confj": True}  # a program starts with both on
        self.conf_off: dict[int, bool] = {}  # a move's offset -> its target's confdata is not held
        self.frames = frames
        self.sources: dict[str, str] = {}  # a frame declared elsewhere -> where (a module, an option)
        self.others: dict[str, dict] = {}  # the task's other modules' tooldata and wobjdata
        self.given: dict[str, dict] = {}  # tools and work objects given by name
        self.resolved: list[tuple[np.ndarray, np.ndarray, str]] = []
        self.out: list[Target] = []
        self.uses: dict[str, list[_Use]] = {}
        self.first_move: dict[str, int] = {}  # a declared target's first move (offset): its place in the motions
        self.names_done: set[str] = set()

    # ------------------------------------------------------------------ statements in program order

    def statement(self, s0: int, stmt_end: int) -> None:
        """One statement, by the first rule of :data:`STATEMENTS` that matches its code."""
        chunk = self.r.code[s0:stmt_end]
        for _kind, match, handler in self.STATEMENTS:
            m = match(chunk)
            if m:
                handler(self, s0, stmt_end, m)
                return

    def _conf(self, s0: int, stmt_end: int, c: re.Match) -> None:
        self.monitored[c.group(1).lower()] = c.group(2).lower() == "on"

    def _declaration(self, s0: int, stmt_end: int, d: re.Match) -> None:
        r, code = self.r, self.r.code
        typ, name = d.group(3).lower(), d.group(4)
        after = s0 + d.end()
        self.expected.add(s0 + d.start(4))
        if not code.startswith(":=", after):
            return  # declared without a value: nothing to compensate
        try:
            node, _ = _value(code, after + 2)
        except _Bad as exc:
            r.fail(exc.offset, f"{typ} {name}: {exc.message}")
        if not d.group(5):
            self.decls[name.lower()] = {"type": typ, "node": node, "offset": after, "name": name}
            return
        if not isinstance(node, list):
            r.fail(after, f"{typ} {name}: expected an array aggregate")
        for k, el in enumerate(node, start=1):
            self.decls[f"{name.lower()}{{{k}}}"] = {"type": typ, "node": el, "offset": after, "name": f"{name}{{{k}}}"}

    def _move(self, s0: int, stmt_end: int, m: re.Match) -> None:
        code = self.r.code
        mv = m.group(1)
        start = s0 + m.end()
        args = [a for a in _split_args(code, start, stmt_end) if not code[a[0] : a[1]].startswith("\\")]
        n_t, tool_i = MOVES[mv.lower()]
        need = max(tool_i + 1, n_t + 2)
        if len(args) < need:
            self.r.fail(
                s0 + m.start(),
                f"{mv}: expected at least {need} arguments (target(s), speed, zone, tool), got {len(args)}",
            )
        tool_i = tool_i if tool_i >= 0 else len(args) - 1
        tool_main, _ = _options(code, *args[tool_i])
        opts = {}
        for a in args:
            opts.update(_options(code, *a)[1])
        targets = [_options(code, *args[k])[0] for k in range(n_t)]
        self.moves.append(_Move(s0 + m.start(), mv, targets, code[tool_main[0] : tool_main[1]], opts.get("wobj")))
        joint = mv.lower() in _JOINT_MOVES
        off = not self.monitored["confj" if joint else "confl"]
        self.conf_off[s0 + m.start()] = off if mv.lower() != "moveabsj" else False

    # a statement's kind -> its handler: the first rule whose match finds the statement's code reads it
    STATEMENTS = (
        ("configuration monitoring", _CONF_RE.match, _conf),
        ("declaration", _declaration_match, _declaration),
        ("move", _MOVE_RE.search, _move),
    )

    # ------------------------------------------------------------------ frames

    def resolve_frames(self) -> None:
        """Each move's tool and work object: this module's declarations first (they hide the
        task's), then the task's other modules in the order given, then --tool-frame/--work-object."""
        for mod in reversed(getattr(self.frames, "modules", ()) or ()):
            self.others.update(_module_frames(mod))
        given = {
            "tooldata": getattr(self.frames, "named_tools", {}) or {},
            "wobjdata": getattr(self.frames, "named_wobjs", {}) or {},
        }
        self.given = {typ: {k.lower(): (k, v) for k, v in d.items()} for typ, d in given.items()}
        for mv in self.moves:
            T_tool = self.frame(mv.tool, "tooldata", mv.offset, mv.mv)
            T_work = self.frame(mv.wobj, "wobjdata", mv.offset, mv.mv)
            t_src = _source(self.sources, mv.tool)
            w_src = _source(self.sources, mv.wobj)
            self.resolved.append((T_tool, T_work, f"tool {mv.tool}{t_src}, wobj {mv.wobj or 'wobj0'}{w_src}"))

    def frame(self, name: str | None, typ: str, offset: int, mv: str) -> np.ndarray:
        r = self.r
        if name is None or name.lower() in (("tool0",) if typ == "tooldata" else ("wobj0",)):
            return np.eye(4)
        if not IDENT_RE.fullmatch(name):
            r.fail(offset, f"{mv}: {typ} {name!r} is an expression; Recal resolves only {typ} declared in this file")
        dd = self.decls.get(name.lower())
        if dd is not None and dd["type"] == typ:
            return _declared_frame(r, dd, typ, name)
        dd = self.others.get(name.lower())
        if dd is not None and dd["type"] == typ:
            self.sources[name.lower()] = dd["r"].path
            return _declared_frame(dd["r"], dd, typ, name)
        flag = "--tool-frame" if typ == "tooldata" else "--work-object"
        if name.lower() in self.given[typ]:
            self.sources[name.lower()] = flag
            try:
                return _named_frame(self.given[typ][name.lower()][1])
            except ValueError as exc:
                raise InputError(flag, f"{name}: {exc}") from None
        r.fail(
            offset,
            f"{mv}: {typ} {name} is not declared in this module"
            + (" nor in the modules given" if self.others else "")
            + f"; pass the module that declares it (--module SYSMOD.sys) or {flag} {name}=X,Y,Z,Q1,Q2,Q3,Q4",
        )

    # ------------------------------------------------------------------ targets

    def move_targets(self) -> None:
        """Each move's targets: an inline one read, a name noted as a use (resolved after), an
        expression left alone."""
        r, code = self.r, self.r.code
        for move, (T_tool, T_work, fr) in zip(self.moves, self.resolved):
            off, mv = move.offset, move.mv
            kind = "jointtarget" if mv.lower() == "moveabsj" else "robtarget"
            for a, b in move.targets:
                t = code[a:b]
                ln = r.line(a)
                if t.startswith("["):
                    try:
                        node, _ = _value(code, a)
                    except _Bad as exc:
                        r.fail(exc.offset, f"{mv}: inline {kind}: {exc.message}")
                    t_in = _target(r, kind, node, None, mv, a, T_tool, T_work, fr)
                    self.out.append(dataclasses.replace(t_in, seq=off, config_off=self.conf_off[off]))
                    continue
                ref = _REF_RE.fullmatch(t)
                if ref:
                    key = ref.group(1).lower() + (f"{{{ref.group(2)}}}" if ref.group(2) else "")
                    self.expected.add(a)
                    self.uses.setdefault(key, []).append(_Use(ln, mv, kind, T_tool, T_work, fr, move.tool, move.wobj))
                    self.first_move.setdefault(key, off)
                    continue
                why = f"the {mv} target is computed by an expression: not compensated"
                self.skipped.append(Uninterpreted(ln, r.line_text(ln), why))

    def declared_targets(self) -> None:
        """Each declared robtarget or jointtarget with the frames of the moves that use it; one
        used with different frames, or by no move, is left alone and reported."""
        r = self.r
        for key, dd in self.decls.items():
            if dd["type"] not in ("robtarget", "jointtarget"):
                continue
            ln = r.line(dd["offset"])
            us = self.uses.get(key, [])
            if not us:
                why = (
                    f"{dd['type']} {dd['name']} is not the target of a move in this file: its "
                    f"tool and work object are unknown"
                )
                self.skipped.append(Uninterpreted(ln, r.line_text(ln), why))
                continue
            combos = {(u.tool or "tool0").lower() + "|" + (u.wobj or "wobj0").lower() for u in us}
            if dd["type"] == "robtarget" and len(combos) > 1:
                why = (
                    f"robtarget {dd['name']} is used with different tools or work objects "
                    f"(lines {', '.join(str(u.line) for u in us)}): not compensated"
                )
                self.skipped.append(Uninterpreted(ln, r.line_text(ln), why))
                continue
            u = us[0]
            if u.kind != dd["type"]:
                r.fail(dd["offset"], f"{dd['type']} {dd['name']}: used as a {u.kind} by {u.mv} (line {u.line})")
            t_dd = _target(r, u.kind, dd["node"], dd["name"], u.mv, dd["offset"], u.T_tool, u.T_work, u.frames)
            off = self.first_move[key]
            self.out.append(dataclasses.replace(t_dd, seq=off, config_off=self.conf_off[off]))
            self.names_done.add(dd["name"].split("{")[0].lower())

    def undeclared_uses(self) -> None:
        """Names used as targets that this module does not declare: left alone, saying why."""
        for key, us in self.uses.items():
            if key not in self.decls:
                for u in us:
                    why = f"{key} is not declared in this file: not compensated"
                    self.skipped.append(Uninterpreted(u.line, self.r.line_text(u.line), why))

    def other_uses(self) -> None:
        """Other uses of a compensated target's name (``Offs(p10, ...)``): they see the new value."""
        r = self.r
        for tok in r.identifiers():
            if tok.text.lower() in self.names_done and tok.start not in self.expected:
                ln = r.line(tok.start)
                why = (
                    f"uses target {tok.text} in an expression: this use sees the compensated "
                    f"value and is not itself compensated"
                )
                self.skipped.append(Uninterpreted(ln, r.line_text(ln), why))

    def program(self) -> Program:
        self.out.sort(key=lambda t: t.line)
        seen, dedup = set(), []
        for u in sorted(self.skipped, key=lambda u: u.line):
            if (u.line, u.reason) not in seen:
                seen.add((u.line, u.reason))
                dedup.append(u)
        return Program((self.r.path,), (self.r.text,), "abb", self.out, dedup)


def _target(r: _Reader, kind, node, name, mv, offset, T_tool, T_work, frames) -> Target:
    label = f"{kind} {name or '(inline)'}"
    ln = r.line(offset)
    if kind == "jointtarget":
        if not isinstance(node, list) or len(node) < 1:
            r.fail(offset, f"{label}: expected [[rax_1, ..., rax_6], [eax_a, ..., eax_f]]")
        joints = r.numbers(node[0], 6, f"{label}: robot axes", offset)
        q = np.radians([n.value for n in joints])
        return Target("joints", 0, ln, name, mv, q=q, joints=joints, T_work=T_work, T_tool=T_tool, frames=frames)
    if not isinstance(node, list) or len(node) < 3:
        r.fail(offset, f"{label}: expected [[x, y, z], [q1, q2, q3, q4], [cf1, cf4, cf6, cfx], [external axes]]")
    P, p, q = r.pose(node, "robtarget", name or "(inline)", offset)
    conf = r.numbers(node[2], 4, f"{label}: configuration [cf1, cf4, cf6, cfx]", offset)
    cv = []
    for n in conf:
        v = n.value
        if v != math.floor(v):
            r.fail(n.start, f"{label}: configuration: expected whole numbers, got {n.text!r}")
        cv.append(int(v))
    if not 0 <= cv[3] <= 7:
        r.fail(conf[3].start, f"{label}: cfx: expected 0..7, got {cv[3]}")
    ctext = "[" + ",".join(n.text for n in conf) + "]"
    return Target(
        "pose",
        0,
        ln,
        name,
        mv,
        P=P,
        rotation="quat",
        position=p,
        orientation=q,
        config=tuple(cv),
        config_text=ctext,
        T_work=T_work,
        T_tool=T_tool,
        frames=frames,
    )
