"""KUKA KRL programs: a ``.src`` with its ``.dat`` (same name, same folder).

Targets: ``E6POS``/``POS``/``FRAME`` ``{X, Y, Z, A, B, C, S, T, E1..E6}`` (mm; A, B, C in degrees,
Euler ZYX; S and T the status and turn bits, also written ``'B110'``; E1..E6 left untouched) and
``E6AXIS``/``AXIS`` ``{A1..A6, E1..E6}`` (degrees), declared in ``DECL`` lines (several
declarators in one line included; ``GLOBAL``; ``NAME[k]={...}`` element lines) of the ``.dat``
or the ``.src``, or written inline in ``PTP``/``LIN``/``CIRC`` (and the spline moves ``SPTP``/``SLIN``/
``SCIRC``/``SPL``).
``;`` starts a comment: an inline form fold (``;FOLD PTP P1 ...``) is a comment, its body holds
the real move.

Frames, in program order of the ``.src``: ``$TOOL = TOOL_DATA[n]``, ``$BASE = BASE_DATA[n]``,
``$TOOL``/``$BASE = $NULLFRAME``, ``BAS(#TOOL, n)``/``BAS(#BASE, n)``, and the inline forms'
``FDAT_ACT = FP1`` with the ``.dat``'s ``DECL FDAT FP1={TOOL_NO 1, BASE_NO 2, ...}``, and the
``WITH`` clause of a move (KSS 8's spline inline forms: ``SPTP XP1 WITH $TOOL = STOOL2(FP1),
$BASE = SBASE(FP1.BASE_NO), $IPO_MODE = SIPO_MODE(FP1.IPO_FRAME), ...``; kept for the moves after
it, as ``BAS`` keeps them). FDATs come from the ``.dat`` or the ``$config.dat`` (``FHOME``); a
``$config.dat`` target (``XHOME``) is a global other programs share: reported, not rewritten.
Frame n comes
from ``--tool-frame n=X,Y,Z,A,B,C`` / ``--base-frame n=...`` or from ``TOOL_DATA[n]`` /
``BASE_DATA[n]`` of a ``$config.dat`` (``--config-dat``); before the program selects any, the
unnumbered ``--tool-frame``/``--base-frame`` or ``$NULLFRAME`` (the flange, the robot's base).
The base frame is taken in the robot's base frame (``$ROBROOT`` = ``$WORLD``). A move that uses a
frame Recal cannot resolve refuses the program, naming the line and the frame (an axis target
under such a frame is left alone and reported: it needs no Cartesian frame to be read).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from calibration.transforms import homogeneous
from calibration.vendors import kuka_abc_to_matrix

from ..files import InputError
from .base import Number, Program, Target, Uninterpreted, read_text
from .frames import Frames
from .tokens import KRL, Source, split_top_level

POSE_TYPES = ("e6pos", "pos", "frame")
AXIS_TYPES = ("e6axis", "axis")
_DECL_RE = KRL.pattern(r"^[ \t]*(?:decl\s+)?(?:global\s+)?(?:decl\s+)?(e6pos|pos|frame|e6axis|axis|fdat)\s+(.*)$")
_ELEM_RE = KRL.pattern(r"^[ \t]*([a-z_$]\w*)\s*\[\s*(\d+)\s*\]\s*=\s*(\{.*)$")
_MOVE_RE = KRL.pattern(
    r"^[ \t]*(ptp|lin|circ|sptp|slin|scirc|spl|ptp_rel|lin_rel|circ_rel|sptp_rel|slin_rel)\b\s*(.*)$"
)
_FRAME_SET_RE = KRL.pattern(r"^[ \t]*\$(tool|base)\s*=\s*(.*?)\s*$")
_DATA_RE = KRL.pattern(r"^(tool|base)_data\s*\[\s*(\d+)\s*\]$")
_BAS_RE = KRL.pattern(r"^[ \t]*bas\s*\(\s*#(tool|base)\s*,\s*(\d+)\s*\)")
_FDAT_ACT_RE = KRL.pattern(r"^[ \t]*fdat_act\s*=\s*([a-z_]\w*)\s*$")
_REF_RE = KRL.pattern(r"([a-z_]\w*)(?:\s*\[\s*(\d+)\s*\])?$")
_WITH_RE = KRL.pattern(r"\bwith\b")
_FDAT_CALL_RE = KRL.pattern(r"^(stool2|stool|sbase|sipo_mode)\s*\(\s*([a-z_]\w*)\s*(?:\.\s*([a-z_]\w*)\s*)?\)$")


def _krl_file(index: int, path, text: str) -> Source:
    """A KRL file (``index``: 0 the ``.src``, 1 its ``.dat``, -1 ``$config.dat``)."""
    return Source(KRL, path, text, index)


def _aggregate(f: Source, code: str, i: int, base: int, what: str):
    """``{[TYPE:] NAME value, ...}`` starting at ``code[i] == '{'`` (``base``: the line's offset):
    (dict lowercase name -> Number or text, end index)."""
    j = code.find("}", i)
    if j < 0:
        f.fail(base + i, f"{what}: expected '}}' closing the aggregate on this line")
    body = code[i + 1 : j]
    colon = re.match(r"\s*[a-z_]\w*\s*:", body, re.IGNORECASE)
    off = i + 1 + (colon.end() if colon else 0)
    items = {}
    pos = off
    for piece in body[off - i - 1 :].split(","):
        s = pos
        pos += len(piece) + 1
        m = re.match(r"(\s*)([a-z_]\w*)(\s+)(\S.*?)\s*$", piece, re.IGNORECASE)
        if not m:
            continue  # a component that is not NAME value (FDAT's POINT2[] " "): not a target's
        vs = s + m.start(4)
        ve = s + m.end(4)
        items[m.group(2).lower()] = Number(f.index, base + vs, base + ve, f.text[base + vs : base + ve])
    return items, j + 1


def _value(f: Source, item: Number, what: str, comp: str) -> float:
    t = item.text.strip()
    bits = re.fullmatch(r"'([bh])([0-9a-f]+)'", t, re.IGNORECASE)
    if bits:
        return float(int(bits.group(2), 2 if bits.group(1).lower() == "b" else 16))
    try:
        return float(t)
    except ValueError:
        f.fail(item.start, f"{what}: component {comp.upper()}: expected a number, got {t!r}")


def _frame(values) -> np.ndarray:
    x, y, z, a, b, c = values
    return homogeneous(kuka_abc_to_matrix(np.radians([a, b, c])), np.array([x, y, z]) * 1e-3)


def _config_frames(path) -> dict:
    """``TOOL_DATA[n]`` and ``BASE_DATA[n]`` of a ``$config.dat``: {("tool"|"base", n): values}."""
    f = _krl_file(0, path, read_text(path))
    out = {}
    for _ln, s, code in f.lines():
        m = _ELEM_RE.match(code)
        if m and m.group(1).lower() in ("tool_data", "base_data"):
            items, _ = _aggregate(f, code, m.start(3), s, f"{m.group(1)}[{m.group(2)}]")
            vals = []
            for k in "xyzabc":
                vals.append(_value(f, items[k], m.group(1), k) if k in items else 0.0)
            out[(m.group(1).lower()[:4], int(m.group(2)))] = tuple(vals)
    return out


def parse(
    path, data: bytes | None = None, *, n_joints: int = 6, frames: Frames | None = None, dat_data: bytes | None = None
) -> Program:
    """Parse a ``.src`` and the ``.dat`` beside it (``dat_data``: its bytes, when given): the
    declarations first, then the ``.src`` in program order (frame selections and moves), then
    each declared target with the frames of the moves that use it."""
    if n_joints != 6:
        raise InputError(path, f"KRL programs are compensated for six-axis arms; the model has {n_joints} joints")
    reader = _Reader(path, data, frames or Frames(), dat_data)
    for ln, s, code in reader.src.lines():
        reader.line(ln, s, code)
    reader.declared_targets()
    reader.undeclared_uses()
    reader.other_uses()
    return reader.program()


class _Reader:
    """One KRL program being read: its files and declarations, the tool and base the program
    has selected so far (``state``: ``("opt"|"num"|"null"|"lit"|"bad", value)`` per frame), and
    what was found: targets (``out``), lines left alone (``skipped``), the moves that use each
    declared name (``uses``)."""

    def __init__(self, path, data: bytes | None, frames: Frames, dat_data: bytes | None):
        self.frames = frames
        self.src = _krl_file(0, path, read_text(path, data))
        self.files = [self.src]
        dat_path = _dat_beside(Path(path))
        if dat_data is not None or dat_path is not None:
            dp = dat_path or Path(path).with_suffix(".dat")
            self.files.append(_krl_file(1, dp, read_text(dp, dat_data)))
        self.config = _config_frames(frames.config_dat) if frames.config_dat else {}
        self.decls: dict[str, dict] = {}
        self.fdat: dict[str, dict] = {}
        self.bare: dict[str, tuple] = {}  # declared without a value: name -> (file, offset, type)
        for f in self.files:
            _declarations(f, self.decls, self.fdat, self.bare, elements=True)
        # $config.dat's globals (XHOME, FHOME, ...): seen by every program; its targets are not
        # rewritten here (other programs share them), its FDATs give frames
        self.glob_decls: dict[str, dict] = {}
        if frames.config_dat:
            glob = _krl_file(-1, frames.config_dat, read_text(frames.config_dat))
            _declarations(glob, self.glob_decls, self.fdat, {}, elements=False)
        self.state: dict[str, tuple] = {"tool": ("opt", None), "base": ("opt", None)}
        self.out: list[Target] = []
        self.skipped: list[Uninterpreted] = []
        self.uses: dict[str, list] = {}
        self.expected: set[tuple[int, int]] = set()
        self.names_done: set[str] = set()

    # ------------------------------------------------------------------ frames

    def resolve(self, kind, ref, offset):
        """``(T, label)`` of the frame a state selects; refuses one Recal cannot resolve."""
        how, n = ref
        given = self.frames.tools if kind == "tool" else self.frames.bases
        if how == "null" or (how == "num" and n == 0):
            return np.eye(4), "$NULLFRAME"
        if how == "opt":
            vals = given.get(None)
            return (np.eye(4), "$NULLFRAME") if vals is None else (_frame(vals), f"--{kind}-frame")
        if how == "num":
            vals = given.get(n)
            if vals is not None:
                return _frame(vals), f"{kind.upper()}_DATA[{n}] (--{kind}-frame)"
            if (kind, n) in self.config:
                return _frame(self.config[(kind, n)]), f"{kind.upper()}_DATA[{n}] ($config.dat)"
            self.src.fail(
                offset,
                f"{kind.upper()}_DATA[{n}] is selected here but not given: pass --{kind}-frame "
                f"{n}=X,Y,Z,A,B,C or --config-dat $config.dat",
            )
        if how == "lit":
            return _frame(n), f"${kind.upper()} literal"
        self.src.fail(offset, n)

    def fdat_item(self, name, key):
        """FDAT ``name``'s ``key`` (its text), or a message saying why there is none."""
        fd = self.fdat.get(name.lower())
        if fd is None:
            if self.frames.config_dat:
                where = "the .dat or $config.dat"
            else:
                where = "the .dat (pass --config-dat for $config.dat's)"
            return None, f"FDAT {name} is not declared in {where}"
        item = fd["items"].get(key)
        if item is None:
            return None, f"FDAT {fd['name']} has no {key.upper()}"
        return item.text.strip(), None

    def frame_value(self, kind, val):
        """The state a ``$TOOL``/``$BASE`` assignment's value ``val`` selects (``("bad",
        message)`` where Recal cannot resolve it)."""
        val = val.strip()
        dm = _DATA_RE.match(val)
        if dm and dm.group(1).lower() == kind:
            return ("num", int(dm.group(2)))
        if val.upper() == "$NULLFRAME":
            return ("null", None)
        fm = _FDAT_CALL_RE.match(val)  # STOOL2(FP1), SBASE(FP1.BASE_NO): what KSS 8's inline forms write
        if fm and fm.group(1).lower() in (("stool", "stool2") if kind == "tool" else ("sbase",)):
            name, key = fm.group(2), (fm.group(3) or f"{kind}_no").lower()
            text, why = self.fdat_item(name, key)
            if why:
                return ("bad", f"${kind.upper()} = {val}: {why}")
            if kind == "tool":
                ipo, _ = self.fdat_item(name, "ipo_frame")
                if ipo is not None and ipo.upper() == "#TCP":
                    return ("bad", f"${kind.upper()} = {val}: FDAT {name} with IPO_FRAME #TCP (an external TCP)")
            try:
                return ("num", int(float(text)))
            except ValueError:
                return ("bad", f"${kind.upper()} = {val}: {key.upper()} {text!r} is not a number")
        return (
            "bad",
            f"${kind.upper()} = {val}: Recal cannot resolve this {kind} frame (use TOOL_DATA[n]/"
            f"BASE_DATA[n], BAS(#{kind.upper()}, n) or an inline FDAT)",
        )

    # ------------------------------------------------------------------ the .src in program order

    def line(self, ln: int, s: int, code: str) -> None:
        """One line of the ``.src``, by the first rule of :data:`STATEMENTS` it matches: a frame
        selection changes the state, a move is read."""
        for _kind, pattern, handler in self.STATEMENTS:
            m = pattern.match(code)
            if m:
                handler(self, ln, s, code, m)
                return

    def _frame_assignment(self, ln: int, s: int, code: str, m: re.Match) -> None:
        kind, val = m.group(1).lower(), m.group(2)
        if val.startswith("{"):
            items, _ = _aggregate(self.src, code, code.index("{"), s, f"${kind.upper()}")
            what = f"${kind.upper()}"
            self.state[kind] = (
                "lit",
                tuple(_value(self.src, items[k], what, k) if k in items else 0.0 for k in "xyzabc"),
            )
        else:
            self.state[kind] = self.frame_value(kind, val)

    def _bas(self, ln: int, s: int, code: str, m: re.Match) -> None:
        self.state[m.group(1).lower()] = ("num", int(m.group(2)))

    def _fdat_act(self, ln: int, s: int, code: str, m: re.Match) -> None:
        fd = self.fdat.get(m.group(1).lower())
        if fd is None:
            _, why = self.fdat_item(m.group(1), "tool_no")
            self.state["tool"] = self.state["base"] = ("bad", f"FDAT_ACT = {m.group(1)} (line {ln}): {why}")
            return
        for kind, key in (("tool", "tool_no"), ("base", "base_no")):
            if key in fd["items"]:
                self.state[kind] = ("num", int(_value(fd["file"], fd["items"][key], f"FDAT {fd['name']}", key)))
        ipo = fd["items"].get("ipo_frame")
        if ipo is not None and ipo.text.strip().upper() == "#TCP":
            self.state["tool"] = ("bad", f"FDAT {fd['name']} (line {ln}) with IPO_FRAME #TCP (an external TCP)")

    def _move(self, ln: int, s: int, code: str, m: re.Match) -> None:
        """A move: its target(s), the frames of its ``WITH`` clause, then each target read (an
        inline one) or noted as a use of a declared name (resolved after the whole ``.src``)."""
        mv = m.group(1).upper()
        raw = self.src.line_text(ln)
        if mv.endswith("_REL"):
            self.skipped.append(Uninterpreted(ln, raw, f"{mv} moves relative to where the robot is: not compensated"))
            return
        targets = self._move_targets(mv, s, code, m.start(2))
        if isinstance(targets, str):
            self.skipped.append(Uninterpreted(ln, raw, targets))
            return
        self._with_clause(code, targets[-1][1])
        frame_error = None
        try:
            tool = self.resolve("tool", self.state["tool"], s)
            base = self.resolve("base", self.state["base"], s)
        except InputError as exc:  # refused where a Cartesian target needs it
            frame_error, tool, base = exc, (None, None), (None, None)
        for a, b in targets:
            text = code[a:b]
            if text.startswith("{"):
                self._inline_target(ln, s, code, a, mv, raw, tool, base, frame_error)
                continue
            r = _REF_RE.match(text.replace(" ", ""))
            if text.startswith("$") or r is None:
                self.skipped.append(Uninterpreted(ln, raw, f"{text} is a system variable: not compensated"))
                continue
            key = r.group(1).lower() + (f"[{int(r.group(2))}]" if r.group(2) else "")
            self.expected.add((0, s + a))
            self.uses.setdefault(key, []).append((ln, mv, tool, base, s + a, frame_error))

    def _move_targets(self, mv: str, s: int, code: str, args_at: int) -> list[tuple[int, int]] | str:
        """``(start, end)`` in the line's code of the move's target (and, CIRC, its auxiliary
        point first), or why the move is left alone (a target that is an expression)."""
        first = _target_span(code, args_at)
        if first is None:
            return f"the {mv} target is an expression: not compensated"
        targets = [first]
        if mv in ("CIRC", "SCIRC"):
            c = re.match(r"\s*,\s*", code[first[1] :])
            if not c:
                self.src.fail(s + first[1], f"{mv}: expected ', target' after the auxiliary point")
            second = _target_span(code, first[1] + c.end())
            if second is None:
                return f"the {mv} target is an expression: not compensated"
            targets.append(second)
        return targets

    def _with_clause(self, code: str, after: int) -> None:
        """``SPTP XP1 WITH $TOOL = STOOL2(FP1), $BASE = SBASE(FP1.BASE_NO), ...``: the frames
        it selects are kept for the moves after it, as ``BAS`` keeps them."""
        w = _WITH_RE.search(code, after)
        if not w:
            return
        for ps, pe in split_top_level(code, w.end(), len(code)):
            part = code[ps:pe]
            a = re.match(r"\s*\$(tool|base|ipo_mode)\s*=\s*(.*?)\s*$", part, re.IGNORECASE)
            if not a:
                continue
            kind, val = a.group(1).lower(), a.group(2)
            if kind != "ipo_mode":
                self.state[kind] = self.frame_value(kind, val)
                continue
            im = _FDAT_CALL_RE.match(val)
            ipo = self.fdat_item(im.group(2), "ipo_frame")[0] if im else val
            if ipo is not None and ipo.strip().upper() == "#TCP":
                self.state["tool"] = ("bad", f"$IPO_MODE = {val}: #TCP (an external TCP)")

    def _inline_target(self, ln, s, code, a, mv, raw, tool, base, frame_error) -> None:
        items, _ = _aggregate(self.src, code, a, s, f"{mv} inline target")
        if frame_error is not None:
            if not any(k in items for k in ("a1", "a2", "a3")):
                raise frame_error
            self.skipped.append(Uninterpreted(ln, raw, f"{frame_error}: this axis target is not compensated"))
            return
        t = _target(self.src, None, None, items, mv, s + a, tool, base, inline=True, seq=s + a)
        if isinstance(t, str):
            self.skipped.append(Uninterpreted(ln, raw, t))
        else:
            self.out.append(t)

    # ------------------------------------------------------------------ after the .src

    def declared_targets(self) -> None:
        """Each declared target with the frames of the moves that use it; one used under two
        different frames, or not used at all, is left alone and reported."""
        for key, dd in self.decls.items():
            f = dd["file"]
            ln = f.line(dd["offset"])
            raw = f.line_text(ln)
            us = self.uses.get(key, [])
            if not us:
                if dd["type"] in POSE_TYPES + AXIS_TYPES:
                    why = (
                        f"{dd['type'].upper()} {dd['name']} is not the target of a move in this program: "
                        f"its frames are unknown"
                    )
                    self.skipped.append(Uninterpreted(ln, raw, why, f.index))
                continue
            bad = [u for u in us if u[5] is not None]
            if bad:
                if dd["type"] in POSE_TYPES:
                    raise bad[0][5]
                self.skipped.append(Uninterpreted(ln, raw, f"{bad[0][5]}: not compensated", f.index))
                continue
            if len({(u[2][1], u[3][1]) for u in us}) > 1 and dd["type"] in POSE_TYPES:
                lines = ", ".join(str(u[0]) for u in us)
                why = f"{dd['name']} is used with different tools or bases (lines {lines}): not compensated"
                self.skipped.append(Uninterpreted(ln, raw, why, f.index))
                continue
            _, mv, tool, base, first, _ = us[0]
            t = _target(f, dd["type"], dd["name"], dd["items"], mv, dd["offset"], tool, base, seq=first)
            if isinstance(t, str):
                self.skipped.append(Uninterpreted(ln, raw, t, f.index))
                continue
            self.out.append(t)
            self.names_done.add(key.split("[")[0])

    def undeclared_uses(self) -> None:
        """Moves to names this program does not declare with a value: left alone, saying why."""
        for key, us in self.uses.items():
            if key in self.decls:
                continue
            if key in self.glob_decls:
                why = f"{key.upper()} is a global of $config.dat (other programs share it): not compensated here"
            elif key.split("[")[0] in self.bare:
                why = (
                    f"{key.upper()} is declared without a value ({self.bare[key.split('[')[0]][2].upper()}, "
                    f"given at run time): not compensated"
                )
            else:
                why = f"{key.upper()} is not declared in this program's .src or .dat" + (
                    "" if self.frames.config_dat else " (pass --config-dat for $config.dat's globals)"
                )
                why += ": not compensated"
            for u in us:
                self.skipped.append(Uninterpreted(u[0], self.src.line_text(u[0]), why))

    def other_uses(self) -> None:
        """Other uses of a target's name in the ``.src`` (``XP1.Z = ...``): they see the new value."""
        src = self.src
        for ln, s, code in src.lines():
            if _DECL_RE.match(code) or _ELEM_RE.match(code):
                continue
            for tok in src.identifiers(s, s + len(code)):
                if tok.text.lower() in self.names_done and (0, tok.start) not in self.expected:
                    why = (
                        f"uses target {tok.text} in an expression: this use sees the "
                        f"compensated value and is not itself compensated"
                    )
                    self.skipped.append(Uninterpreted(ln, src.line_text(ln), why))
                    break

    # a line's kind -> its handler: the first rule whose pattern matches the line's code reads it
    STATEMENTS = (
        ("frame assignment", _FRAME_SET_RE, _frame_assignment),
        ("BAS", _BAS_RE, _bas),
        ("FDAT_ACT", _FDAT_ACT_RE, _fdat_act),
        ("move", _MOVE_RE, _move),
    )

    def program(self) -> Program:
        self.out.sort(key=lambda t: (t.file, t.line))
        seen, dedup = set(), []
        for u in sorted(self.skipped, key=lambda u: (u.file, u.line)):
            if (u.file, u.line, u.reason) not in seen:
                seen.add((u.file, u.line, u.reason))
                dedup.append(u)
        files = self.files
        return Program(tuple(f.path for f in files), tuple(f.text for f in files), "kuka", self.out, dedup)


def _target_span(code: str, at: int) -> tuple[int, int] | None:
    """``(start, end)`` of the target written at ``code[at:]``: an inline aggregate ``{...}`` or
    a name (``XP1``, ``P[3]``); None for an expression."""
    if code[at : at + 1] == "{":
        j = code.find("}", at)
        return (at, j + 1 if j >= 0 else len(code))
    t = re.match(r"[a-z_$]\w*(?:\s*\[\s*\d+\s*\])?", code[at:], re.IGNORECASE)
    return (at, at + t.end()) if t else None


_NAME_EQ_RE = KRL.pattern(r"\s*([a-z_]\w*)\s*=\s*")
_BARE_RE = KRL.pattern(r"\s*([a-z_$]\w*)\s*(?:\[[^\]]*\])?\s*(?=,|$)")


def _declarations(f: Source, decls: dict, fdat: dict, bare: dict, elements: bool) -> None:
    """The ``DECL`` lines of ``f`` (and, ``elements``, its ``NAME[k]={...}`` lines) into ``decls``
    (targets) and ``fdat``; names declared without a value into ``bare``."""
    for _ln, s, code in f.lines():
        m = _DECL_RE.match(code)
        if m:
            typ = m.group(1).lower()
            i = m.start(2)
            while True:  # NAME={...}, NAME2={...}, or NAME alone (a value assigned at run time)
                mm = _NAME_EQ_RE.match(code, i)
                if not mm:
                    b = _BARE_RE.match(code, i)
                    if b and b.group(1):
                        bare.setdefault(b.group(1).lower(), (f, s + b.start(1), typ))
                        c = re.compile(r"\s*,").match(code, b.end())
                        if c:
                            i = c.end()
                            continue
                    break
                name = mm.group(1)
                if mm.end() >= len(code) or code[mm.end()] != "{":
                    break
                items, i = _aggregate(f, code, mm.end(), s, f"{typ.upper()} {name}")
                entry = {"type": typ, "items": items, "file": f, "offset": s + mm.start(1), "name": name}
                (fdat if typ == "fdat" else decls)[name.lower()] = entry
                c = re.compile(r"\s*,").match(code, i)
                if not c:
                    break
                i = c.end()
            continue
        m = _ELEM_RE.match(code) if elements else None
        if m:
            base_name = m.group(1).lower()
            items, _ = _aggregate(f, code, m.start(3), s, f"{m.group(1)}[{m.group(2)}]")
            typ = "e6axis" if any(k.startswith("a") and k[1:].isdigit() for k in items) else "e6pos"
            decls[f"{base_name}[{int(m.group(2))}]"] = {
                "type": typ,
                "items": items,
                "file": f,
                "offset": s + m.start(1),
                "name": f"{m.group(1)}[{m.group(2)}]",
            }


def _dat_beside(src: Path) -> Path | None:
    for suffix in (".dat", ".DAT", ".Dat"):
        p = src.with_suffix(suffix)
        if p.exists():
            return p
    return None


def _target(f: Source, typ, name, items, mv, offset, tool, base, inline=False, seq=None):
    """A :class:`Target` from a KRL aggregate, or the reason it is left alone (a string)."""
    what = f"{(typ or 'inline').upper()} {name}" if name else f"{mv} inline target"
    is_axis = typ in AXIS_TYPES if typ else any(k in items for k in ("a1", "a2", "a3"))
    frames = f"tool {tool[1]}, base {base[1]}"
    ln = f.line(offset)
    if is_axis:
        need = [f"a{i}" for i in range(1, 7)]
        missing = [k for k in need if k not in items]
        if missing:
            if inline:
                return f"{what}: A1..A6 not all given (missing ones come from where the robot is): not compensated"
            f.fail(offset, f"{what}: expected component {missing[0].upper()}")
        nums = tuple(items[k] for k in need)
        q = np.radians([_value(f, n, what, k) for n, k in zip(nums, need)])
        return Target(
            "joints", f.index, ln, name, mv, q=q, joints=nums, T_work=base[0], T_tool=tool[0], frames=frames, seq=seq
        )
    need = list("xyzabc")
    missing = [k for k in need if k not in items]
    if missing:
        if inline:
            return (
                f"{what}: X, Y, Z, A, B, C not all given (missing ones come from where the robot is): not compensated"
            )
        f.fail(offset, f"{what}: expected component {missing[0].upper()}")
    v = [_value(f, items[k], what, k) for k in need]
    P = _frame(v)
    S = int(_value(f, items["s"], what, "s")) if "s" in items else None
    T = int(_value(f, items["t"], what, "t")) if "t" in items else None
    config = None if S is None and T is None else (S, T)
    ctext = (
        None
        if config is None
        else f"S {items['s'].text if S is not None else '-'}, T {items['t'].text if T is not None else '-'}"
    )
    return Target(
        "pose",
        f.index,
        ln,
        name,
        mv,
        P=P,
        rotation="kuka_abc",
        position=tuple(items[k] for k in "xyz"),
        orientation=tuple(items[k] for k in "abc"),
        config=config,
        config_text=ctext,
        T_work=base[0],
        T_tool=tool[0],
        frames=frames,
        seq=seq,
    )
