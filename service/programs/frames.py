"""Frames a KRL or TP program selects by number but does not contain: given on the command line
(``--tool-frame [N=]X,Y,Z,A,B,C``, ``--base-frame ...``) or read from KUKA's ``$config.dat``
(``TOOL_DATA[N]``, ``BASE_DATA[N]``). Values are kept as written (mm, degrees); each language
reads the angles in its own convention (KUKA A, B, C; Fanuc W, P, R)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

# DOTALL: an option with a line break in it (a pasted value) is refused in words, not matched
# to nothing
_OPT_RE = re.compile(r"\s*(?:(\d+)\s*=)?\s*(.*)", re.DOTALL)


def parse_frame_option(option: str, flag: str) -> tuple[int | None, tuple[float, ...]]:
    """``[N=]X,Y,Z,A,B,C`` -> (N or None, six numbers)."""
    m = _OPT_RE.fullmatch(option)
    assert m is not None  # (.*) with DOTALL matches any text
    try:
        vals = tuple(float(v) for v in m.group(2).split(","))
        if not all(math.isfinite(v) for v in vals):
            raise ValueError
    except ValueError:
        raise ValueError(f"{flag}: expected [N=]X,Y,Z,A,B,C (six numbers, mm and degrees), got {option!r}") from None
    if len(vals) != 6:
        raise ValueError(f"{flag}: expected six numbers X,Y,Z,A,B,C, got {len(vals)} in {option!r}")
    return (int(m.group(1)) if m.group(1) else None), vals


_NAMED_RE = re.compile(r"^\s*([A-Za-z_]\w*)\s*=\s*(.*)$")


def parse_named_pose(option: str, flag: str) -> tuple[str, tuple[float, ...]]:
    """RAPID's ``NAME=X,Y,Z,Q1,Q2,Q3,Q4`` (mm; quaternion scalar first, as RAPID writes a pose)
    -> (name, seven numbers)."""
    m = _NAMED_RE.match(option)
    if not m:
        raise ValueError(f"{flag}: expected NAME=X,Y,Z,Q1,Q2,Q3,Q4 (a RAPID name, mm and a quaternion), got {option!r}")
    try:
        vals = tuple(float(v) for v in m.group(2).split(","))
    except ValueError:
        raise ValueError(f"{flag}: expected NAME=X,Y,Z,Q1,Q2,Q3,Q4 (seven numbers), got {option!r}") from None
    if len(vals) != 7:
        raise ValueError(f"{flag}: expected seven numbers X,Y,Z,Q1,Q2,Q3,Q4 after {m.group(1)}=, got {len(vals)}")
    return m.group(1), vals


@dataclass(frozen=True)
class Frames:
    """``tools`` and ``bases``: number (``None``: unnumbered) -> X, Y, Z, A, B, C as written;
    ``config_dat``: the path of a ``$config.dat`` (KRL), or ``None``. RAPID: ``modules``, the
    paths of the task's other modules (their ``tooldata`` and ``wobjdata``: a backup keeps them
    in a system or data module), and ``named_tools``/``named_wobjs``, name -> X, Y, Z, Q1..Q4."""

    tools: dict = field(default_factory=dict)
    bases: dict = field(default_factory=dict)
    config_dat: str | None = None
    modules: tuple = ()
    named_tools: dict = field(default_factory=dict)
    named_wobjs: dict = field(default_factory=dict)

    @classmethod
    def from_options(
        cls,
        tools: list[str],
        bases: list[str],
        config_dat: str | None = None,
        *,
        modules: list[str] = (),
        rapid: bool = False,
        wobjs: list[str] = (),
    ) -> Frames:
        """``rapid``: ``--tool-frame`` is ``NAME=X,Y,Z,Q1..Q4`` (a RAPID tooldata), as is
        ``--work-object`` (a wobjdata: its user and object frames in one)."""
        if rapid:
            if bases:
                raise ValueError(
                    "--base-frame: RAPID names its work objects: give --work-object NAME=X,Y,Z,Q1,Q2,Q3,Q4"
                )
            nt = dict(parse_named_pose(o, "--tool-frame") for o in tools)
            nw = dict(parse_named_pose(o, "--work-object") for o in wobjs)
            return cls({}, {}, config_dat, tuple(modules), nt, nw)
        if wobjs:
            raise ValueError("--work-object is RAPID's: for KRL and TP give --base-frame [N=]X,Y,Z,A,B,C")
        t = dict(parse_frame_option(o, "--tool-frame") for o in tools)
        b = dict(parse_frame_option(o, "--base-frame") for o in bases)
        return cls(t, b, config_dat, tuple(modules))
