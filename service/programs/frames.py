"""Frames a KRL or TP program selects by number but does not contain: given on the command line
(``--tool-frame [N=]X,Y,Z,A,B,C``, ``--base-frame ...``) or read from KUKA's ``$config.dat``
(``TOOL_DATA[N]``, ``BASE_DATA[N]``). Values are kept as written (mm, degrees); each language
reads the angles in its own convention (KUKA A, B, C; Fanuc W, P, R)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_OPT_RE = re.compile(r"^\s*(?:(\d+)\s*=)?\s*(.*)$")


def parse_frame_option(option: str, flag: str) -> tuple[int | None, tuple[float, ...]]:
    """``[N=]X,Y,Z,A,B,C`` -> (N or None, six numbers)."""
    m = _OPT_RE.match(option)
    try:
        vals = tuple(float(v) for v in m.group(2).split(","))
    except ValueError:
        raise ValueError(f"{flag}: expected [N=]X,Y,Z,A,B,C (six numbers, mm and degrees), got {option!r}") from None
    if len(vals) != 6:
        raise ValueError(f"{flag}: expected six numbers X,Y,Z,A,B,C, got {len(vals)} in {option!r}")
    return (int(m.group(1)) if m.group(1) else None), vals


@dataclass(frozen=True)
class Frames:
    """``tools`` and ``bases``: number (``None``: unnumbered) -> X, Y, Z, A, B, C as written;
    ``config_dat``: the path of a ``$config.dat`` (KRL), or ``None``."""

    tools: dict = field(default_factory=dict)
    bases: dict = field(default_factory=dict)
    config_dat: str | None = None

    @classmethod
    def from_options(cls, tools: list[str], bases: list[str], config_dat: str | None = None) -> Frames:
        t = dict(parse_frame_option(o, "--tool-frame") for o in tools)
        b = dict(parse_frame_option(o, "--base-frame") for o in bases)
        return cls(t, b, config_dat)
