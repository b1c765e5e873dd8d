"""Universal Robots URScript programs (``.script``, ``.urscript``).

Pose targets ``p[x, y, z, rx, ry, rz]`` are in the robot's base frame, metres and a rotation
vector in radians (whatever the model's units); joint targets ``[q1, ..., q6]`` are readings in
radians. :func:`parse` finds the targets of ``movej``, ``movel``, ``movep`` and ``movec``:
literals in the call, variables assigned a literal once in the file (``global Waypoint_1_p =
p[...]``, ``Waypoint_1_q = [...]``), and the pose and ``qnear`` of ``get_inverse_kin(pose,
qnear=q)`` in a move (what PolyScope writes). Everything else is left alone and reported with its
line number and text — a target computed by an expression (``pose_trans(...)``, ``pose_add``, a
variable assigned twice or from a function), an argument list continued on the next line, a
target variable also used in an expression, ``set_tcp``, ``servoj`` and the like — instead of
guessing. :meth:`Script.rewrite` replaces only the characters of the target numbers; every other
byte (comments, whitespace, line endings, ``a=``/``v=``/``r=`` parameters, encoding) stays as it
was.

The file is read through the programs' shared tokenizer (:mod:`.tokens`: ``#`` comments, ``"``
strings, case-sensitive names, a statement a line); each line by its rule table: an assignment,
then each call by its name (:data:`_Reader.CALLS`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..files import MAX_MAGNITUDE_SI, InputError, read_bounded, replace_spans
from .tokens import SIGNED_NUMBER, URSCRIPT, Source, trim

_NUM = SIGNED_NUMBER
_NUM_RE = re.compile(_NUM)
_LIST_RE = re.compile(rf"\[\s*{_NUM}(?:\s*,\s*{_NUM})*\s*\]")
_POSE_RE = re.compile(rf"p\s*(\[\s*{_NUM}(?:\s*,\s*{_NUM})*\s*\])")
_IDENT_RE = URSCRIPT.pattern(r"[A-Za-z_]\w*")
_ASSIGN_RE = URSCRIPT.pattern(r"^(\s*(?:global\s+|local\s+)?)([A-Za-z_]\w*)(\s*)=(?!=)")
_TARGET_MOVES = {"movej": 1, "movel": 1, "movep": 1, "movec": 2}


@dataclass(frozen=True, eq=False)
class Literal:
    """A target literal in a program: ``kind`` ``"pose"`` (6 values: m, m, m and a rotation
    vector in rad) or ``"joints"`` (rad); ``spans`` the (start, end) character offsets of each
    number in the text; ``line`` 1-based; ``name`` the variable it is assigned to, if any."""

    kind: str
    line: int
    spans: tuple[tuple[int, int], ...]
    values: np.ndarray
    name: str | None = None


@dataclass(frozen=True, eq=False)
class ScriptTarget:
    """One target to compensate, in program order: a ``pose`` literal (with the ``joints`` of its
    ``qnear`` when given) or a ``joints`` literal alone; ``line`` and ``move`` of its first use."""

    line: int
    move: str
    pose: Literal | None
    joints: Literal | None


@dataclass(frozen=True)
class Uninterpreted:
    """A line the parser left alone, and why."""

    line: int
    text: str
    reason: str
    # a set_tcp's pose literal (m, rotation vector): the compensation drops the flag when it is
    # the model's own tool (issue 27)
    tcp: np.ndarray | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True, eq=False)
class Script:
    """A parsed URScript program. ``text`` is the file decoded as UTF-8 with undecodable bytes
    kept as surrogates, so that :meth:`rewrite` gives back every byte."""

    path: str
    text: str
    targets: list[ScriptTarget]
    uninterpreted: list[Uninterpreted]
    lines: list[tuple[int, int]] = field(repr=False)

    def line_text(self, line: int) -> str:
        s, e = self.lines[line - 1]
        return self.text[s:e].rstrip("\r\n")

    def rewrite(self, replacements: dict[int, np.ndarray], literals: dict[int, Literal]) -> bytes:
        """The program with the numbers of ``literals[k]`` replaced by ``replacements[k]``
        (same count), every other character as it was; bytes as read."""
        edits = []
        for k, values in replacements.items():
            lit = literals[k]
            if len(values) != len(lit.spans):
                raise ValueError(f"line {lit.line}: {len(lit.spans)} numbers, {len(values)} replacements")
            edits += [(s, e, _fixed(v)) for (s, e), v in zip(lit.spans, values)]
        return replace_spans(self.text, edits)


def _fixed(v: float, decimals: int = 10) -> str:
    """A number as URScript reads it, without an exponent: up to ``decimals`` decimals."""
    s = f"{float(v):.{decimals}f}".rstrip("0")
    s = s + "0" if s.endswith(".") else s
    return "0.0" if s in ("-0.0", "0.0") else s


def _args(code: str, open_idx: int) -> tuple[list[tuple[int, int]], int] | None:
    """Top-level arguments (start, end) of the call whose ``(`` is at ``open_idx``, and the index
    of its ``)``; ``None`` when the call does not close on this line."""
    depth, start, out, in_str = 0, open_idx + 1, [], False
    for i in range(open_idx, len(code)):
        ch = code[i]
        if ch == '"':
            in_str = not in_str
        if in_str:
            continue
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth -= 1
            if depth == 0:
                out.append((start, i))
                return out, i
        elif ch == "," and depth == 1:
            out.append((start, i))
            start = i + 1
    return None


def _literal(code: str, s: int, e: int, offset: int, line: int, name: str | None = None) -> Literal | None:
    """A pose or list literal exactly filling ``code[s:e]``, else ``None``."""
    text = code[s:e]
    m = _POSE_RE.fullmatch(text)
    kind = "pose" if m else "joints" if _LIST_RE.fullmatch(text) else None
    if kind is None:
        return None
    spans = tuple((offset + s + n.start(), offset + s + n.end()) for n in _NUM_RE.finditer(text))
    values = np.array([float(code[a - offset : b - offset]) for a, b in spans])
    return Literal(kind, line, spans, values, name)


def _tcp_literal(code: str, open_idx: int) -> np.ndarray | None:
    """The pose a ``set_tcp(p[...])`` call sets (m, rotation vector), or ``None`` when its
    argument is anything but one pose literal (a variable, an expression)."""
    parsed = _args(code, open_idx)
    if parsed is None or len(parsed[0]) != 1:
        return None
    s, e = trim(code, *parsed[0][0])
    lit = _literal(code, s, e, 0, 0)
    return lit.values if lit is not None and lit.kind == "pose" and len(lit.values) == 6 else None


def parse(path: str | os.PathLike, data: bytes | None = None, *, n_joints: int = 6) -> Script:
    """Find the move targets of a URScript program (see the module docstring); ``data`` the
    file's bytes (read from ``path`` when not given)."""
    if data is None:
        data = read_bounded(path)
    reader = _Reader(Source(URSCRIPT, path, data.decode("utf-8", "surrogateescape")), n_joints)
    for ln, s, code in reader.src.lines():
        reader.line(ln, s, code)
    reader.targets_of_uses()
    reader.other_uses()
    reader.refuse_numbers_beyond_a_cell()
    return reader.script()


class _Reader:
    """One URScript program being read: the literals assigned to each name (``assigns``), the
    moves' target references (``uses``: line, move, pose-or-target ref, qnear ref), what was
    found (``targets``) and the lines left alone (``skipped``)."""

    def __init__(self, src: Source, n_joints: int):
        self.src, self.n_joints = src, n_joints
        self.skipped: list[Uninterpreted] = []
        self.assigns: dict[str, list[tuple[int, Literal | None]]] = {}
        self.uses: list[tuple[int, str, object, object]] = []
        self.expected: set[tuple[int, int]] = set()  # identifier occurrences that are targets or assignments
        self.resolved: dict[str, Literal] = {}
        self.targets: list[ScriptTarget] = []

    # ------------------------------------------------------------------ each line

    def line(self, ln: int, s: int, code: str) -> None:
        """A line: an assignment (a literal kept by name), then each call by :data:`CALLS`."""
        m = _ASSIGN_RE.match(code)
        if m:
            name = m.group(2)
            a, e = trim(code, m.end(), len(code))
            self.assigns.setdefault(name, []).append((ln, _literal(code, a, e, s, ln, name)))
            self.expected.add((s + m.start(2), s + m.end(2)))
        for call in _CALL_RE.finditer(code):
            self.CALLS[call.group(1)](self, ln, s, code, call)

    def _set_tcp(self, ln: int, s: int, code: str, call: re.Match) -> None:
        why = "set_tcp changes the TCP: targets are compensated for the model's tool, which must be this TCP"
        self.skipped.append(Uninterpreted(ln, self.src.line_text(ln), why, _tcp_literal(code, call.end() - 1)))

    def _not_a_target_move(self, ln: int, s: int, code: str, call: re.Match) -> None:
        self.skipped.append(Uninterpreted(ln, self.src.line_text(ln), f"{call.group(1)} targets are not compensated"))

    def _move(self, ln: int, s: int, code: str, call: re.Match) -> None:
        fn = call.group(1)
        parsed = _args(code, call.end() - 1)
        if parsed is None:
            self.skipped.append(Uninterpreted(ln, self.src.line_text(ln), f"the {fn} call does not close on this line"))
            return
        args, _ = parsed
        for k in range(min(_TARGET_MOVES[fn], len(args))):
            a, e = trim(code, *args[k])
            ref = _target_ref(code, a, e, s, ln, self.expected)
            if isinstance(ref, str) and ref.startswith("!"):
                self.skipped.append(Uninterpreted(ln, self.src.line_text(ln), ref[1:]))
            else:
                self.uses.append((ln, fn, ref[0], ref[1]))

    # a call's name -> its handler (the names, in this order, are what a line is searched for)
    CALLS: ClassVar[dict[str, Callable[[_Reader, int, int, str, re.Match], None]]] = {
        "movej": _move,
        "movel": _move,
        "movep": _move,
        "movec": _move,
        "servoj": _not_a_target_move,
        "servoc": _not_a_target_move,
        "speedj": _not_a_target_move,
        "speedl": _not_a_target_move,
        "set_tcp": _set_tcp,
    }

    # ------------------------------------------------------------------ after the lines

    def resolve(self, ref, ln: int, raw: str) -> Literal | None:
        """The literal a target reference names (a literal itself, or a variable assigned one
        literal once), else ``None`` with the reason noted."""
        if ref is None or isinstance(ref, Literal):
            return ref
        name = ref
        if name in self.resolved:
            return self.resolved[name]
        entries = self.assigns.get(name, [])
        if not entries:
            reason = f"target variable {name} is not assigned in this file"
        elif len(entries) > 1:
            reason = (
                f"target variable {name} is assigned more than once (lines {', '.join(str(e[0]) for e in entries)})"
            )
        elif entries[0][1] is None:
            reason = f"target variable {name} is computed by an expression (line {entries[0][0]})"
            a_ln = entries[0][0]
            if not any(u.line == a_ln for u in self.skipped):
                why = f"{name}: a target computed by an expression is not compensated"
                self.skipped.append(Uninterpreted(a_ln, self.src.line_text(a_ln), why))
        else:
            lit = entries[0][1]
            n_joints = self.n_joints
            if lit.kind == "joints" and len(lit.values) != n_joints:
                reason = f"{name} has {len(lit.values)} numbers; the model has {n_joints} joints"
            elif lit.kind == "pose" and len(lit.values) != 6:
                reason = f"{name} is a pose with {len(lit.values)} numbers (expected 6)"
            else:
                self.resolved[name] = lit
                return lit
        self.skipped.append(Uninterpreted(ln, raw, reason))
        return None

    def _mismatch(self, pose: Literal | None, joints: Literal | None) -> str | None:
        """Why a move's pose and joints are not a target, or ``None``."""
        if pose is not None and pose.kind != "pose":
            return "get_inverse_kin's first argument is not a pose"
        if joints is not None and (joints.kind != "joints" or len(joints.values) != self.n_joints):
            return f"expected a joint vector of {self.n_joints} numbers"
        if pose is not None and len(pose.values) != 6:
            return f"a pose has 6 numbers, this one {len(pose.values)}"
        return None

    def targets_of_uses(self) -> None:
        """The targets in program order: a pose once (with the first ``qnear`` given for it), a
        joint vector alone once, unless it is a pose's ``qnear`` (compensated with that pose)."""
        targets = self.targets
        by_pose: dict[int, ScriptTarget] = {}
        joint_only: dict[int, ScriptTarget] = {}
        for ln, fn, pref, jref in self.uses:
            raw = self.src.line_text(ln)
            pose = self.resolve(pref, ln, raw)
            joints = self.resolve(jref, ln, raw)
            if pref is not None and pose is None:
                continue
            if pose is not None and pose.kind == "joints" and jref is None:
                pose, joints = None, pose  # a move whose target is a joint vector
            why = self._mismatch(pose, joints)
            if why:
                self.skipped.append(Uninterpreted(ln, raw, why))
                continue
            if pose is not None:
                if id(pose) not in by_pose:
                    by_pose[id(pose)] = ScriptTarget(ln, fn, pose, joints)
                    targets.append(by_pose[id(pose)])
                elif by_pose[id(pose)].joints is None and joints is not None:
                    old = by_pose[id(pose)]
                    by_pose[id(pose)] = ScriptTarget(old.line, old.move, pose, joints)
                    targets[targets.index(old)] = by_pose[id(pose)]
            elif joints is not None and id(joints) not in joint_only:
                joint_only[id(joints)] = ScriptTarget(ln, fn, None, joints)
                targets.append(joint_only[id(joints)])
        partners = {id(t.joints) for t in targets if t.pose is not None and t.joints is not None}
        self.targets = [t for t in targets if not (t.pose is None and id(t.joints) in partners)]

    def other_uses(self) -> None:
        """Other uses of target variables: reported, since they see the compensated value."""
        names = {lit.name for t in self.targets for lit in (t.pose, t.joints) if lit is not None and lit.name}
        for ln, s, code in self.src.lines():
            for tok in self.src.identifiers(s, s + len(code)):
                if tok.text in names and (tok.start, tok.end) not in self.expected:
                    why = (
                        f"uses target variable {tok.text} in an expression: this use sees the "
                        f"compensated value and is not itself compensated"
                    )
                    self.skipped.append(Uninterpreted(ln, self.src.line_text(ln), why))
                    break

    def refuse_numbers_beyond_a_cell(self) -> None:
        """Numbers no robot cell can have (1e308) are a slip: named, never compensated."""
        for t in self.targets:
            for lit in (t.pose, t.joints):
                if lit is not None and np.any(np.abs(lit.values) > MAX_MAGNITUDE_SI):
                    v = float(lit.values[np.argmax(np.abs(lit.values))])
                    raise InputError(
                        self.src.path,
                        f"{self.src.line_text(lit.line)}: {v:g} is beyond any robot cell; expected "
                        f"a magnitude of at most {MAX_MAGNITUDE_SI:g} (URScript: metres, radians)",
                        line=lit.line,
                    )

    def script(self) -> Script:
        self.skipped.sort(key=lambda u: u.line)
        dedup, seen = [], set()
        for u in self.skipped:
            if (u.line, u.reason) not in seen:
                seen.add((u.line, u.reason))
                dedup.append(u)
        return Script(self.src.path, self.src.text, self.targets, dedup, self.src.spans())


_CALL_RE = URSCRIPT.pattern(r"\b(" + "|".join(_Reader.CALLS) + r")\s*\(")


def _target_ref(code: str, s: int, e: int, offset: int, ln: int, expected: set):
    """What a move argument names: ``(pose_ref, joints_ref)`` where each is a :class:`Literal`, a
    variable name or ``None``; or ``"!reason"`` when it is something else."""
    lit = _literal(code, s, e, offset, ln)
    if lit is not None:
        return (lit, None)
    text = code[s:e]
    if _IDENT_RE.fullmatch(text):
        expected.add((offset + s, offset + e))
        return (text, None)
    m = re.match(r"get_inverse_kin\s*\(", text)
    if m:
        parsed = _args(code, s + m.end() - 1)
        if parsed is None or parsed[1] != e - 1:
            return "!get_inverse_kin(...) is followed by an expression"
        pose_ref, q_ref = None, None
        for k, (a, b) in enumerate(parsed[0]):
            a, b = trim(code, a, b)
            kw = re.match(r"([A-Za-z_]\w*)\s*=(?!=)\s*", code[a:b])
            key = kw.group(1) if kw else ("x" if k == 0 else "qnear" if k == 1 else None)
            if kw:
                a += kw.end()
            if key == "x":
                pose_ref = _ref(code, a, b, offset, ln, expected)
            elif key == "qnear":
                q_ref = _ref(code, a, b, offset, ln, expected)
            elif key == "tcp":
                return "!get_inverse_kin with tcp=: the pose is for another TCP"
        for ref in (pose_ref, q_ref):
            if isinstance(ref, str) and ref.startswith("!"):
                return ref
        if pose_ref is None:
            return "!get_inverse_kin without a pose"
        return (pose_ref, q_ref)
    return "!the target is computed by an expression"


def _ref(code: str, s: int, e: int, offset: int, ln: int, expected: set):
    lit = _literal(code, s, e, offset, ln)
    if lit is not None:
        return lit
    if _IDENT_RE.fullmatch(code[s:e]):
        expected.add((offset + s, offset + e))
        return code[s:e]
    return "!the target is computed by an expression"
