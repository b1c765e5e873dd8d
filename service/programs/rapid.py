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
configuration data (service.programs.compensate.controller_solutions); the confdata is kept as
written. The state follows the module's text (a controller starts a program with both on); a
target used by several moves takes its first move's.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from calibration.errors import RecalError
from calibration.transforms import homogeneous, quat_to_matrix

from ..files import InputError
from .base import (
    Number,
    Program,
    Target,
    Uninterpreted,
    line_of,
    line_starts,
    line_text,
    mask_code,
    read_text,
)

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
_CONF_RE = re.compile(r"^\s*(ConfL|ConfJ)\s*\\\s*(On|Off)\s*$", re.IGNORECASE)
_JOINT_MOVES = ("movej", "movejdo", "movejsync", "triggj")
_MOVE_RE = re.compile(r"(?<![\w\\])(" + "|".join(sorted(MOVES, key=len, reverse=True)) + r")(?=[\s\\,])", re.IGNORECASE)
_DECL_RE = re.compile(
    r"^[ \t]*(?:(local|task)\s+)?(const|pers|var)\s+([a-z_]\w*)\s+([a-z_]\w*)\s*(\{[^}]*\})?\s*",
    re.IGNORECASE | re.MULTILINE,
)
_IDENT_RE = re.compile(r"[A-Za-z_]\w*")
_REF_RE = re.compile(r"([A-Za-z_]\w*)\s*(?:\{\s*(\d+)\s*\})?")
TYPES = ("robtarget", "jointtarget", "tooldata", "wobjdata")


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
        items, i = [], i + 1
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
    """Top-level comma-separated pieces of ``code[s:e]``."""
    out, depth, start = [], 0, s
    for i in range(s, e):
        ch = code[i]
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append((start, i))
            start = i + 1
    out.append((start, e))
    return [(a, b) for a, b in (_trim(code, a, b) for a, b in out)]


def _trim(code, s, e):
    while s < e and code[s].isspace():
        s += 1
    while e > s and code[e - 1].isspace():
        e -= 1
    return s, e


def _options(code: str, s: int, e: int) -> tuple[tuple[int, int], dict[str, str]]:
    """An argument ``main\\Opt:=value\\Switch``: the main part and its options (lowercase names)."""
    parts, depth, start = [], 0, s
    for i in range(s, e):
        ch = code[i]
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == "\\" and depth == 0:
            parts.append((start, i))
            start = i + 1
    parts.append((start, e))
    main = _trim(code, *parts[0])
    opts = {}
    for a, b in parts[1:]:
        t = code[a:b].strip()
        k, _, v = t.partition(":=")
        opts[k.strip().lower()] = v.strip()
    return main, opts


class _Reader:
    def __init__(self, path, text):
        self.path, self.text, self.code = path, text, mask_code(text, "!")
        self.starts = line_starts(text)

    def line(self, offset):
        return line_of(self.starts, offset)

    def fail(self, offset, message):
        raise InputError(self.path, message, line=self.line(offset))

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
    code, out, pos = r.code, {}, 0
    for stmt_end in [m.start() for m in re.finditer(";", code)] + [len(code)]:
        s0, pos = pos, stmt_end + 1
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
    text = read_text(path, data)
    r = _Reader(path, text)
    code = r.code
    decls: dict[str, dict] = {}  # lowercase name -> {type, node, offset, name}
    moves = []  # (offset, move, [target arg spans], tool name, wobj name)
    skipped: list[Uninterpreted] = []
    expected: set[int] = set()  # offsets of identifiers that are a target's own use
    monitored = {"confl": True, "confj": True}  # a program starts with both on
    conf_off: dict[int, bool] = {}  # a move's offset -> its target's confdata is not held
    pos = 0
    for stmt_end in [m.start() for m in re.finditer(";", code)] + [len(code)]:
        s0 = pos
        pos = stmt_end + 1
        chunk = code[s0:stmt_end]
        c = _CONF_RE.match(chunk)
        if c:
            monitored[c.group(1).lower()] = c.group(2).lower() == "on"
            continue
        d = _DECL_RE.search(chunk)
        if d and d.group(3).lower() in TYPES:
            typ, name = d.group(3).lower(), d.group(4)
            after = s0 + d.end()
            expected.add(s0 + d.start(4))
            if not code.startswith(":=", after):
                continue  # declared without a value: nothing to compensate
            try:
                node, _ = _value(code, after + 2)
            except _Bad as exc:
                r.fail(exc.offset, f"{typ} {name}: {exc.message}")
            if d.group(5):
                if not isinstance(node, list):
                    r.fail(after, f"{typ} {name}: expected an array aggregate")
                for k, el in enumerate(node, start=1):
                    decls[f"{name.lower()}{{{k}}}"] = {
                        "type": typ,
                        "node": el,
                        "offset": after,
                        "name": f"{name}{{{k}}}",
                    }
            else:
                decls[name.lower()] = {"type": typ, "node": node, "offset": after, "name": name}
            continue
        m = _MOVE_RE.search(chunk)
        if not m:
            continue
        mv = m.group(1)
        start = s0 + m.end()
        args = [a for a in _split_args(code, start, stmt_end) if not code[a[0] : a[1]].startswith("\\")]
        n_t, tool_i = MOVES[mv.lower()]
        need = max(tool_i + 1, n_t + 2)
        if len(args) < need:
            r.fail(
                s0 + m.start(),
                f"{mv}: expected at least {need} arguments (target(s), speed, zone, tool), got {len(args)}",
            )
        tool_i = tool_i if tool_i >= 0 else len(args) - 1
        tool_main, _ = _options(code, *args[tool_i])
        opts = {}
        for a in args:
            opts.update(_options(code, *a)[1])
        tool = code[tool_main[0] : tool_main[1]]
        wobj = opts.get("wobj")
        targets = []
        for k in range(n_t):
            (a, b), _ = _options(code, *args[k])
            targets.append((a, b))
        moves.append((s0 + m.start(), mv, targets, tool, wobj))
        joint = mv.lower() in _JOINT_MOVES
        conf_off[s0 + m.start()] = not monitored["confj" if joint else "confl"] if mv.lower() != "moveabsj" else False

    # frames: this module's declarations first (they hide the task's), then the task's other
    # modules in the order given, then --tool-frame/--work-object
    others: dict = {}
    for mod in reversed(getattr(frames, "modules", ()) or ()):
        others.update(_module_frames(mod))
    given = {"tooldata": getattr(frames, "named_tools", {}) or {}, "wobjdata": getattr(frames, "named_wobjs", {}) or {}}
    given = {typ: {k.lower(): (k, v) for k, v in d.items()} for typ, d in given.items()}
    sources: dict[str, str] = {}

    def frame(name, typ, offset, mv):
        if name is None or name.lower() in (("tool0",) if typ == "tooldata" else ("wobj0",)):
            return np.eye(4)
        if not _IDENT_RE.fullmatch(name):
            r.fail(offset, f"{mv}: {typ} {name!r} is an expression; Recal resolves only {typ} declared in this file")
        dd = decls.get(name.lower())
        if dd is None or dd["type"] != typ:
            dd = others.get(name.lower())
            if dd is not None and dd["type"] == typ:
                sources[name.lower()] = dd["r"].path
                return _declared_frame(dd["r"], dd, typ, name)
            if name.lower() in given[typ]:
                flag = "--tool-frame" if typ == "tooldata" else "--work-object"
                sources[name.lower()] = flag
                try:
                    return _named_frame(given[typ][name.lower()][1])
                except ValueError as exc:
                    raise InputError(flag, f"{name}: {exc}") from None
            flag = "--tool-frame" if typ == "tooldata" else "--work-object"
            r.fail(
                offset,
                f"{mv}: {typ} {name} is not declared in this module"
                + (" nor in the modules given" if others else "")
                + f"; pass the module that declares it (--module SYSMOD.sys) or {flag} {name}=X,Y,Z,Q1,Q2,Q3,Q4",
            )
        return _declared_frame(r, dd, typ, name)

    resolved_frames = []
    for off, mv, _targets, tool, wobj in moves:
        T_tool = frame(tool, "tooldata", off, mv)
        T_work = frame(wobj, "wobjdata", off, mv)
        t_src = _source(sources, tool)
        w_src = _source(sources, wobj)
        resolved_frames.append((T_tool, T_work, f"tool {tool}{t_src}, wobj {wobj or 'wobj0'}{w_src}"))
    out: list[Target] = []
    uses: dict[str, list] = {}
    first_move: dict[str, int] = {}  # a declared target's first move (offset): its place in the motions
    for (off, mv, targets, tool, wobj), (T_tool, T_work, fr) in zip(moves, resolved_frames):
        kind = "jointtarget" if mv.lower() == "moveabsj" else "robtarget"
        for a, b in targets:
            t = code[a:b]
            ln = r.line(a)
            if t.startswith("["):
                try:
                    node, _ = _value(code, a)
                except _Bad as exc:
                    r.fail(exc.offset, f"{mv}: inline {kind}: {exc.message}")
                t_in = _target(r, kind, node, None, mv, a, T_tool, T_work, fr)
                out.append(dataclasses.replace(t_in, seq=off, config_off=conf_off[off]))
                continue
            ref = _REF_RE.fullmatch(t)
            if ref:
                key = ref.group(1).lower() + (f"{{{ref.group(2)}}}" if ref.group(2) else "")
                expected.add(a)
                uses.setdefault(key, []).append((ln, mv, kind, T_tool, T_work, fr, tool, wobj))
                first_move.setdefault(key, off)
                continue
            skipped.append(
                Uninterpreted(
                    ln, line_text(text, r.starts, ln), f"the {mv} target is computed by an expression: not compensated"
                )
            )
    names_done = set()
    for key, dd in decls.items():
        if dd["type"] not in ("robtarget", "jointtarget"):
            continue
        ln = r.line(dd["offset"])
        us = uses.get(key, [])
        if not us:
            skipped.append(
                Uninterpreted(
                    ln,
                    line_text(text, r.starts, ln),
                    f"{dd['type']} {dd['name']} is not the target of a move in this file: its "
                    f"tool and work object are unknown",
                )
            )
            continue
        combos = {(u[6] or "tool0").lower() + "|" + (u[7] or "wobj0").lower() for u in us}
        if dd["type"] == "robtarget" and len(combos) > 1:
            skipped.append(
                Uninterpreted(
                    ln,
                    line_text(text, r.starts, ln),
                    f"robtarget {dd['name']} is used with different tools or work objects "
                    f"(lines {', '.join(str(u[0]) for u in us)}): not compensated",
                )
            )
            continue
        if us[0][2] != dd["type"]:
            r.fail(dd["offset"], f"{dd['type']} {dd['name']}: used as a {us[0][2]} by {us[0][1]} (line {us[0][0]})")
        _, mv, kind, T_tool, T_work, fr, _, _ = us[0]
        t_dd = _target(r, kind, dd["node"], dd["name"], mv, dd["offset"], T_tool, T_work, fr)
        off = first_move[key]
        out.append(dataclasses.replace(t_dd, seq=off, config_off=conf_off[off]))
        names_done.add(dd["name"].split("{")[0].lower())
    # undeclared names used as targets
    for key, us in uses.items():
        if key not in decls:
            for u in us:
                skipped.append(
                    Uninterpreted(
                        u[0], line_text(text, r.starts, u[0]), f"{key} is not declared in this file: not compensated"
                    )
                )
    # other uses of a compensated target's name (Offs(p10, ...)): they see the new value
    for m in _IDENT_RE.finditer(code):
        if m.group().lower() in names_done and m.start() not in expected:
            ln = r.line(m.start())
            skipped.append(
                Uninterpreted(
                    ln,
                    line_text(text, r.starts, ln),
                    f"uses target {m.group()} in an expression: this use sees the compensated "
                    f"value and is not itself compensated",
                )
            )
    out.sort(key=lambda t: t.line)
    seen, dedup = set(), []
    for u in sorted(skipped, key=lambda u: u.line):
        if (u.line, u.reason) not in seen:
            seen.add((u.line, u.reason))
            dedup.append(u)
    return Program((str(path),), (text,), "abb", out, dedup)


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
