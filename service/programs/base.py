"""What every program format shares: a target (numbers and where they are), a parsed program,
the byte-preserving rewrite, and how a new number is written."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..files import MAX_MAGNITUDE, MAX_MAGNITUDE_SI, InputError, magnitude_problem, read_bounded, replace_spans

# The fewest decimals a rewritten number gets (written precision is kept where it has more):
# 0.5 µm for millimetres, 5e-6° (under 0.1 µm per metre of reach) for degrees, 5e-9 for quaternion
# components. A program written with 2 decimals of mm would otherwise round a compensation of a
# few tens of µm away.
MIN_DECIMALS = {"mm": 3, "deg": 5, "quat": 8}


@dataclass(frozen=True, eq=False)
class Number:
    """One number in a file: ``file`` index, ``(start, end)`` character offsets, its text."""

    file: int
    start: int
    end: int
    text: str

    @property
    def value(self) -> float:
        return float(self.text)


@dataclass(frozen=True, eq=False)
class Target:
    """A target to compensate. ``kind`` ``"pose"`` or ``"joints"``; ``line`` (1-based) and
    ``file`` (index into the program's files) of its definition; ``name`` (a declared target)
    or ``None`` (inline); ``move`` the instruction that uses it first.

    Pose: ``P`` (4, 4) the tool pose in the work frame, SI; ``rotation`` how the orientation is
    written (``"quat"``, ``"kuka_abc"``, ``"fanuc_wpr"``) and ``position``/``orientation`` its
    numbers; ``config`` the written configuration (brand terms, or ``None`` when the target has
    none) and ``config_text`` as written. Joints: ``q`` (6,) readings in rad and ``joints`` its
    numbers. ``T_work`` (4, 4) the work frame (wobj, base, user frame) in the robot's base frame,
    ``T_tool`` (4, 4) the tool in the flange frame, ``frames`` how they were named; ``seq`` its
    place in the program's motions where that is not its line (:func:`motion_order`);
    ``config_off`` the controller does not monitor its configuration (RAPID ``ConfL\\Off``)."""

    kind: str
    file: int
    line: int
    name: str | None
    move: str
    P: np.ndarray | None = None
    rotation: str | None = None
    position: tuple[Number, ...] = ()
    orientation: tuple[Number, ...] = ()
    config: tuple | None = None
    config_text: str | None = None
    q: np.ndarray | None = None
    joints: tuple[Number, ...] = ()
    T_work: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_tool: np.ndarray = field(default_factory=lambda: np.eye(4))
    frames: str = ""
    seq: int | None = None
    # the written configuration does not choose the solution (RAPID ConfL\Off/ConfJ\Off at the
    # move that uses it): the controller's rule for a target without one applies, and it is kept
    # as written
    config_off: bool = False


def motion_order(t: Target) -> tuple:
    """Where a target comes in the program's motions: ``seq`` (KRL: the offset in the ``.src`` of
    the move that first uses it, since its declaration may be in the ``.dat``), else its line."""
    return (t.seq if t.seq is not None else -1, t.file, t.line)


@dataclass(frozen=True)
class Uninterpreted:
    """A line left alone, and why."""

    line: int
    text: str
    reason: str
    file: int = 0


@dataclass(frozen=True, eq=False)
class Program:
    """A parsed program: ``paths`` and ``texts`` of its files (the first is the program; KRL's
    ``.dat`` second), ``brand`` (``abb``, ``kuka``, ``fanuc``), targets in program order, lines
    left alone."""

    paths: tuple[str, ...]
    texts: tuple[str, ...]
    brand: str
    targets: list[Target]
    uninterpreted: list[Uninterpreted]

    def rewrite(self, edits: list[tuple[Number, str]]) -> list[bytes]:
        """Each file with the numbers of ``edits`` replaced by their new text, every other
        character as it was; bytes as read."""
        return [
            replace_spans(text, [(n.start, n.end, t) for n, t in edits if n.file == k])
            for k, text in enumerate(self.texts)
        ]


def read_text(path, data: bytes | None = None) -> str:
    """A file's text, UTF-8 with undecodable bytes kept as surrogates (so every byte comes back)."""
    if data is None:
        data = read_bounded(path)
    return data.decode("utf-8", "surrogateescape")


def written(number: Number, value: float, unit: str) -> str:
    """``value`` written like ``number`` was: as many decimals (at least :data:`MIN_DECIMALS`),
    no exponent, and no sign on a zero."""
    t = number.text.lower()
    mant = t.split("e")[0]
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    d = max(decimals, MIN_DECIMALS[unit])
    s = f"{float(value):.{d}f}"
    if float(s) == 0.0:
        s = s.lstrip("-")
    if t.startswith("+") and not s.startswith("-"):
        s = "+" + s
    return s


def refuse_numbers_beyond_a_cell(prog: Program) -> Program:
    """``prog``, or ``InputError`` naming the file, line and number of the first target no robot
    cell can have: a written number beyond ±``MAX_MAGNITUDE`` or not finite, or a position, frame
    or joint beyond ``MAX_MAGNITUDE_SI`` (m, rad). The bound URScript's reader applies, for every
    program language alike (a KRL ``PTP {X 1e200, ...}`` was once left alone and answered 200)."""
    for t in prog.targets:
        where = t.name or t.move
        for number in (*t.position, *t.orientation, *t.joints):
            try:
                problem = magnitude_problem(number.value)
            except ValueError:  # written otherwise (KRL's 'B...' status bits): the parser read it
                continue
            if problem:
                raise InputError(prog.paths[t.file], f"{where}: {problem}", line=t.line)
        si = [t.q] if t.q is not None else []
        si += [T[:3, 3] for T in (t.P, t.T_work, t.T_tool) if T is not None]
        for values in si:
            values = np.asarray(values, dtype=float)
            if not np.all(np.isfinite(values)) or np.any(np.abs(values) > MAX_MAGNITUDE_SI):
                v = float(values[np.argmax(np.where(np.isfinite(values), np.abs(values), np.inf))])
                raise InputError(
                    prog.paths[t.file],
                    f"{where}: {v:g} is beyond any robot cell; expected a magnitude of at most "
                    f"{MAX_MAGNITUDE_SI:g} in metres and radians (numbers up to {MAX_MAGNITUDE:g} as written)",
                    line=t.line,
                )
    return prog
