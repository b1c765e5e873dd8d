"""Task files of ``recal compensate``: task CSVs (contracts §5) and Universal Robots URScript
programs.

Task CSV. One row per task point: ``x, y, z, qw, qx, qy, qz`` (desired tool pose in the world
frame, the model's length unit) and/or ``q1..qN`` (the configuration the program was taught or
planned with, the model's units). A row may leave the pose empty (a taught point: only its
joints) but not leave part of a group empty. The output has the input columns (their text as it
was, except the replaced ones), then ``q1..qN`` (joints mode) or ``x..qz`` (targets mode) where
the input had none, then ``converged``, ``residual``, ``flags``.

URScript. Pose targets ``p[x, y, z, rx, ry, rz]`` are in the robot's base frame, metres and a
rotation vector in radians (whatever the model's units); joint targets ``[q1, ..., q6]`` are
readings in radians. :func:`parse_urscript` finds the targets of ``movej``, ``movel``, ``movep``
and ``movec``: literals in the call, variables assigned a literal once in the file
(``global Waypoint_1_p = p[...]``, ``Waypoint_1_q = [...]``), and the pose and ``qnear`` of
``get_inverse_kin(pose, qnear=q)`` in a move (what PolyScope writes). Everything else is left
alone and reported with its line number and text — a target computed by an expression
(``pose_trans(...)``, ``pose_add``, a variable assigned twice or from a function), an argument
list continued on the next line, a target variable also used in an expression, ``set_tcp``,
``servoj`` and the like — instead of guessing. :meth:`Script.rewrite` replaces only the
characters of the target numbers; every other byte (comments, whitespace, line endings,
``a=``/``v=``/``r=`` parameters, encoding) stays as it was.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.model import KinematicModel
from calibration.transforms import homogeneous, matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotvec_to_matrix

from .files import MAX_MAGNITUDE_SI, InputError, Table, read_bounded, read_table, replace_spans

POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
RESULT_COLUMNS = ("converged", "residual", "flags")
SCRIPT_SUFFIXES = (".script", ".urscript")


def is_script(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a URScript program (by its suffix)."""
    return Path(path).suffix.lower() in SCRIPT_SUFFIXES


# =============================================================================== task CSV


@dataclass(frozen=True, eq=False)
class Task:
    """A task CSV read for a model, SI. ``T_world_tool`` (N, 4, 4) desired poses (identity where
    a row has none); ``has_pose`` (N,); ``quat`` (N, 4) the rows' quaternions (NaN where none);
    ``q`` (N, n) readings (NaN where none); ``has_q`` (N,)."""

    path: str
    table: Table
    T_world_tool: np.ndarray
    has_pose: np.ndarray
    quat: np.ndarray
    q: np.ndarray
    has_q: np.ndarray

    def __len__(self) -> int:
        return len(self.table.rows)

    def where(self, i: int) -> dict:
        """Row and line of task point ``i`` (for errors and reports)."""
        return {"row": i + 1, "line": self.table.lines[i]}


def _group(table: Table, names: list[str], scales: list[float], what: str) -> tuple[np.ndarray, np.ndarray]:
    """Columns ``names`` as floats (N, k) (NaN where empty) and which rows have them all; a row
    with some but not all is an error naming the first empty cell."""
    vals = np.stack([table.numbers(c, scale=s, allow_empty=True) for c, s in zip(names, scales)], axis=1)
    empty = np.isnan(vals)
    partial = empty.any(axis=1) & ~empty.all(axis=1)
    if np.any(partial):
        r = int(np.nonzero(partial)[0][0])
        col = names[int(np.nonzero(empty[r])[0][0])]
        raise InputError(
            table.path,
            f"expected a number ({what} needs all of {', '.join(names)}, or none of them)",
            row=r + 1,
            line=table.lines[r],
            column=col,
        )
    return vals, ~empty.any(axis=1)


def read_task(path: str | os.PathLike, model: KinematicModel) -> Task:
    """Read a task CSV (contracts §5) for ``model``; errors name the file, row, line and column."""
    table = read_table(path)
    n = model.n_joints
    u = model.units
    present = [c for c in POSE_COLUMNS if table.has(c)]
    if present and len(present) != len(POSE_COLUMNS):
        missing = [c for c in POSE_COLUMNS if c not in present]
        raise InputError(path, f"missing column {missing[0]!r}: a desired pose needs all of {', '.join(POSE_COLUMNS)}")
    qcols = sorted((h for h in table.header if h[:1] == "q" and h[1:].isdigit()), key=lambda h: int(h[1:]))
    bad = [h for h in qcols if not 1 <= int(h[1:]) <= n]
    if bad:
        raise InputError(path, f"column {bad[0]!r}: the model has {n} joints (q1..q{n})")
    if qcols and len(qcols) != n:
        missing = [f"q{i}" for i in range(1, n + 1) if f"q{i}" not in qcols]
        raise InputError(path, f"missing joint column {missing[0]!r}: the model has {n} joints (q1..q{n})")
    if not present and not qcols:
        raise InputError(
            path,
            f"expected the columns {', '.join(POSE_COLUMNS)} (desired tool pose) and/or "
            f"q1..q{n} (taught or planned joints); the header has: {', '.join(table.header)}",
        )
    N = len(table.rows)
    if present:
        L = u.length_m
        vals, has_pose = _group(table, list(POSE_COLUMNS), [L, L, L, 1, 1, 1, 1], "a desired pose")
        quat = vals[:, 3:]
        norms = np.linalg.norm(quat, axis=1)
        off = has_pose & (np.abs(norms - 1.0) > 1e-3)
        if np.any(off):
            r = int(np.nonzero(off)[0][0])
            raise InputError(
                path,
                f"the quaternion has norm {norms[r]:.6g}; expected a unit quaternion",
                row=r + 1,
                line=table.lines[r],
                column="qw",
            )
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
        T[has_pose] = homogeneous(quat_to_matrix(quat[has_pose]), vals[has_pose, :3])
    else:
        has_pose = np.zeros(N, dtype=bool)
        quat = np.full((N, 4), np.nan)
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
    if qcols:
        scales = [u.angle_rad if j.revolute else u.length_m for j in model.joints]
        q, has_q = _group(table, [f"q{i}" for i in range(1, n + 1)], scales, "a joint vector")
    else:
        q, has_q = np.full((N, n), np.nan), np.zeros(N, dtype=bool)
    empty = ~has_pose & ~has_q
    if np.any(empty):
        r = int(np.nonzero(empty)[0][0])
        col = "x" if present else "q1"
        raise InputError(
            path, "the row has neither a desired pose nor joints", row=r + 1, line=table.lines[r], column=col
        )
    return Task(str(path), table, T, has_pose, quat, q, has_q)


def _num(v: float, digits: int = 12) -> str:
    s = f"{float(v):.{digits}g}"
    return "0" if s in ("-0", "0") else s


def format_task(
    task: Task,
    model: KinematicModel,
    mode: str,
    q: np.ndarray,
    T_command: np.ndarray,
    converged: np.ndarray,
    residual_m: np.ndarray,
    flags: list[str],
) -> str:
    """The compensated task CSV (contracts §5) in ``model``'s units: the input columns (text as
    read) with ``q1..qN`` (``mode == "joints"``) or ``x..qz`` (``"targets"``) replaced — appended
    where the input had none — then ``converged``, ``residual``, ``flags``. Quaternions keep the
    sign of the input's where it had one."""
    import csv
    import io

    n = model.n_joints
    u = model.units
    header = [h for h in task.table.header if h not in RESULT_COLUMNS]
    replaced = [f"q{i}" for i in range(1, n + 1)] if mode == "joints" else list(POSE_COLUMNS)
    out_header = header + [c for c in replaced if c not in header] + list(RESULT_COLUMNS)
    src = task.table.index
    if mode == "joints":
        scales = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
        new = q / scales
    else:
        quat = matrix_to_quat(T_command[:, :3, :3])
        flip = np.nansum(quat * task.quat, axis=1) < 0
        quat[flip] *= -1.0
        new = np.concatenate([T_command[:, :3, 3] / u.length_m, quat], axis=1)
    L = u.length_m
    # whole columns of text first (cheaper than a dict per row), then the rows
    cols = {c: [_num(v) for v in new[:, k]] for k, c in enumerate(replaced)}
    cols["converged"] = ["1" if c else "0" for c in converged]
    cols["residual"] = [_num(v, 6) for v in np.asarray(residual_m) / L]
    cols["flags"] = list(flags)
    getters = [(cols[c], None) if c in cols else (None, src[c]) for c in out_header]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(out_header)
    w.writerows(
        [
            [made[i] if made is not None else (row[k] if k < len(row) else "") for made, k in getters]
            for i, row in enumerate(task.table.rows)
        ]
    )
    return buf.getvalue()


# =============================================================================== URScript


_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_NUM_RE = re.compile(_NUM)
_LIST_RE = re.compile(rf"\[\s*{_NUM}(?:\s*,\s*{_NUM})*\s*\]")
_POSE_RE = re.compile(rf"p\s*(\[\s*{_NUM}(?:\s*,\s*{_NUM})*\s*\])")
_IDENT_RE = re.compile(r"[A-Za-z_]\w*")
_MOVE_RE = re.compile(r"\b(movej|movel|movep|movec|servoj|servoc|speedj|speedl|set_tcp)\s*\(")
_ASSIGN_RE = re.compile(r"^(\s*(?:global\s+|local\s+)?)([A-Za-z_]\w*)(\s*)=(?!=)")
_LINE_RE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n|$)")
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


def _code_end(line: str) -> int:
    """Where the code of a line ends: at a ``#`` outside a string literal."""
    in_str = False
    for i, ch in enumerate(line):
        if ch == '"':
            in_str = not in_str
        elif ch == "#" and not in_str:
            return i
    return len(line)


def _mask_strings(code: str) -> str:
    """``code`` with the insides of string literals blanked (same length), so that nothing in a
    string is taken for a call, a target or a variable."""
    out, in_str = [], False
    for ch in code:
        if ch == '"':
            in_str = not in_str
            out.append(ch)
        else:
            out.append(" " if in_str else ch)
    return "".join(out)


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


def _strip(code: str, s: int, e: int) -> tuple[int, int]:
    while s < e and code[s].isspace():
        s += 1
    while e > s and code[e - 1].isspace():
        e -= 1
    return s, e


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
    s, e = _strip(code, *parsed[0][0])
    lit = _literal(code, s, e, 0, 0)
    return lit.values if lit is not None and lit.kind == "pose" and len(lit.values) == 6 else None


def parse_urscript(path: str | os.PathLike, n_joints: int = 6, data: bytes | None = None) -> Script:
    """Find the move targets of a URScript program (see the module docstring); ``data`` the
    file's bytes (read from ``path`` when not given)."""
    if data is None:
        data = read_bounded(path)
    text = data.decode("utf-8", "surrogateescape")
    lines = [(m.start(), m.end()) for m in _LINE_RE.finditer(text) if m.end() > m.start()]
    skipped: list[Uninterpreted] = []
    assigns: dict[str, list[tuple[int, Literal | None]]] = {}
    uses: list[tuple[int, str, object, object]] = []  # (line, move, pose-or-target ref, qnear ref)
    expected: set[tuple[int, int]] = set()  # identifier occurrences that are targets or assignments
    codes = []
    for ln, (ls, le) in enumerate(lines, start=1):
        raw = text[ls:le].rstrip("\r\n")
        code = _mask_strings(raw[: _code_end(raw)])
        codes.append((ls, code))
        m = _ASSIGN_RE.match(code)
        if m:
            name = m.group(2)
            s, e = _strip(code, m.end(), len(code))
            assigns.setdefault(name, []).append((ln, _literal(code, s, e, ls, ln, name)))
            expected.add((ls + m.start(2), ls + m.end(2)))
        for mv in _MOVE_RE.finditer(code):
            fn = mv.group(1)
            if fn == "set_tcp":
                skipped.append(
                    Uninterpreted(
                        ln,
                        raw.strip(),
                        "set_tcp changes the TCP: targets are compensated for the model's tool, which must be this TCP",
                        _tcp_literal(code, mv.end() - 1),
                    )
                )
                continue
            if fn not in _TARGET_MOVES:
                skipped.append(Uninterpreted(ln, raw.strip(), f"{fn} targets are not compensated"))
                continue
            parsed = _args(code, mv.end() - 1)
            if parsed is None:
                skipped.append(Uninterpreted(ln, raw.strip(), f"the {fn} call does not close on this line"))
                continue
            args, _ = parsed
            for k in range(min(_TARGET_MOVES[fn], len(args))):
                s, e = _strip(code, *args[k])
                ref = _target_ref(code, s, e, ls, ln, expected)
                if isinstance(ref, str) and ref.startswith("!"):
                    skipped.append(Uninterpreted(ln, raw.strip(), ref[1:]))
                else:
                    uses.append((ln, fn, ref[0], ref[1]))
    # resolve variables
    resolved: dict[str, Literal] = {}

    def resolve(ref, ln, raw):
        if ref is None or isinstance(ref, Literal):
            return ref
        name = ref
        if name in resolved:
            return resolved[name]
        entries = assigns.get(name, [])
        if not entries:
            reason = f"target variable {name} is not assigned in this file"
        elif len(entries) > 1:
            reason = (
                f"target variable {name} is assigned more than once (lines {', '.join(str(e[0]) for e in entries)})"
            )
        elif entries[0][1] is None:
            reason = f"target variable {name} is computed by an expression (line {entries[0][0]})"
            a_ln = entries[0][0]
            if not any(u.line == a_ln for u in skipped):
                skipped.append(
                    Uninterpreted(
                        a_ln, _line(text, lines, a_ln), f"{name}: a target computed by an expression is not compensated"
                    )
                )
        else:
            lit = entries[0][1]
            if lit.kind == "joints" and len(lit.values) != n_joints:
                reason = f"{name} has {len(lit.values)} numbers; the model has {n_joints} joints"
            elif lit.kind == "pose" and len(lit.values) != 6:
                reason = f"{name} is a pose with {len(lit.values)} numbers (expected 6)"
            else:
                resolved[name] = lit
                return lit
        skipped.append(Uninterpreted(ln, raw, reason))
        return None

    targets: list[ScriptTarget] = []
    by_pose: dict[int, ScriptTarget] = {}
    joint_only: dict[int, ScriptTarget] = {}
    for ln, fn, pref, jref in uses:
        raw = _line(text, lines, ln)
        pose = resolve(pref, ln, raw)
        joints = resolve(jref, ln, raw)
        if pref is not None and pose is None:
            continue
        if pose is not None and pose.kind == "joints" and jref is None:
            pose, joints = None, pose  # a move whose target is a joint vector
        if pose is not None and pose.kind != "pose":
            skipped.append(Uninterpreted(ln, raw, "get_inverse_kin's first argument is not a pose"))
            continue
        if joints is not None and (joints.kind != "joints" or len(joints.values) != n_joints):
            skipped.append(Uninterpreted(ln, raw, f"expected a joint vector of {n_joints} numbers"))
            continue
        if pose is not None and len(pose.values) != 6:
            skipped.append(Uninterpreted(ln, raw, f"a pose has 6 numbers, this one {len(pose.values)}"))
            continue
        if pose is not None:
            if id(pose) not in by_pose:
                t = ScriptTarget(ln, fn, pose, joints)
                by_pose[id(pose)] = t
                targets.append(t)
            elif by_pose[id(pose)].joints is None and joints is not None:
                old = by_pose[id(pose)]
                new = ScriptTarget(old.line, old.move, pose, joints)
                targets[targets.index(old)] = new
                by_pose[id(pose)] = new
        elif joints is not None and id(joints) not in joint_only:
            t = ScriptTarget(ln, fn, None, joints)
            joint_only[id(joints)] = t
            targets.append(t)
    # a joint vector that is the qnear of a pose is compensated with that pose
    partners = {id(t.joints) for t in targets if t.pose is not None and t.joints is not None}
    targets = [t for t in targets if not (t.pose is None and id(t.joints) in partners)]
    # other uses of target variables: reported, since they see the compensated value
    names = {lit.name for t in targets for lit in (t.pose, t.joints) if lit is not None and lit.name}
    for ln, (ls, code) in enumerate(codes, start=1):
        for m in _IDENT_RE.finditer(code):
            if m.group() in names and (ls + m.start(), ls + m.end()) not in expected:
                skipped.append(
                    Uninterpreted(
                        ln,
                        _line(text, lines, ln),
                        f"uses target variable {m.group()} in an expression: this use sees the "
                        f"compensated value and is not itself compensated",
                    )
                )
                break
    for t in targets:  # numbers no robot cell can have (1e308) are a slip: named, never compensated
        for lit in (t.pose, t.joints):
            if lit is not None and np.any(np.abs(lit.values) > MAX_MAGNITUDE_SI):
                v = float(lit.values[np.argmax(np.abs(lit.values))])
                raise InputError(
                    path,
                    f"{_line(text, lines, lit.line).strip()}: {v:g} is beyond any robot cell; expected "
                    f"a magnitude of at most {MAX_MAGNITUDE_SI:g} (URScript: metres, radians)",
                    line=lit.line,
                )
    skipped.sort(key=lambda u: u.line)
    dedup, seen = [], set()
    for u in skipped:
        if (u.line, u.reason) not in seen:
            seen.add((u.line, u.reason))
            dedup.append(u)
    return Script(str(path), text, targets, dedup, lines)


def _line(text: str, lines: list[tuple[int, int]], ln: int) -> str:
    s, e = lines[ln - 1]
    return text[s:e].rstrip("\r\n").strip()


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
            a, b = _strip(code, a, b)
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


def pose_to_matrix_ur(pose6: np.ndarray) -> np.ndarray:
    """A URScript pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) (..., 6) -> (..., 4, 4)."""
    pose6 = np.asarray(pose6, dtype=float)
    return homogeneous(rotvec_to_matrix(pose6[..., 3:]), pose6[..., :3])


def matrix_to_pose_ur(T: np.ndarray, like: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 4) -> URScript poses (N, 6). With ``like`` (N, 6), each rotation vector is the
    equivalent one (angle ± 2πk along the same axis) nearest the original, so that a rewritten
    program keeps its style (UR writes e.g. ``[0, 3.14, 0]`` or ``[0, -3.14, 0]``)."""
    T = np.asarray(T, dtype=float)
    rv = matrix_to_rotvec(T[..., :3, :3])
    if like is not None:
        like = np.asarray(like, dtype=float)[..., 3:]
        ang = np.linalg.norm(rv, axis=-1, keepdims=True)
        axis = np.where(ang > 1e-12, rv / np.where(ang > 1e-12, ang, 1.0), 0.0)
        best = rv.copy()
        for k in (-2, -1, 1, 2):
            cand = axis * (ang + 2.0 * np.pi * k)
            closer = np.linalg.norm(cand - like, axis=-1) < np.linalg.norm(best - like, axis=-1)
            best = np.where(closer[..., None], cand, best)
        rv = best
    return np.concatenate([T[..., :3, 3], rv], axis=-1)
