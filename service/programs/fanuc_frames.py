"""A Fanuc controller's user and tool frames from its backup: the ``$MNUFRAME`` and ``$MNUTOOL``
position arrays that a backup writes as text (``SYSFRAME.VA``, also read from ``FRAMEVAR.VA``)::

    [*SYSTEM*]$MNUFRAME  Storage: SHADOW  Access: RW  : ARRAY[1,9] OF POSITION
        [1,1] =
      Group: 1   Config: N D B, 0, 0, 0
      X:   100.000   Y:     0.000   Z:     0.000
      W:     0.000   P:     0.000   R:     0.000
        [1,2] = '' Uninitialized

An element is ``[group, frame number]``, an optional comment, then X, Y, Z (mm) and W, P, R (deg).
Only group 1 is read (the arm; the TP reader compensates ``GP1``). An ``Uninitialized`` element
is not a frame: a program selecting it is refused, naming its line and frame, never given the
null frame.
"""

from __future__ import annotations

import re

# a record starts at the beginning of a line: [PROGRAM]NAME or [*SYSTEM*]$NAME
_RECORD_RE = re.compile(r"^\[[^\]\n]*\]\$?(\w+)", re.M)
_ELEMENT_RE = re.compile(r"^\s*\[(\d+),(\d+)\]\s*=([^\n]*)", re.M)
_FIELD_RE = re.compile(r"\b([XYZWPR]):\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)")
ARRAYS = {"MNUFRAME": "bases", "MNUTOOL": "tools"}


def read_frame_data(text: str, name: str = "SYSFRAME.VA") -> dict[str, dict[int, tuple[float, ...]]]:
    """``{"bases": {n: (X, Y, Z, W, P, R)}, "tools": {...}}`` of group 1 from a ``.VA`` dump's
    text (module docstring); ``name`` is how errors name the file. Raises ``ValueError`` for an
    element that is set but lacks one of its six numbers."""
    out: dict[str, dict[int, tuple[float, ...]]] = {"bases": {}, "tools": {}}
    records = list(_RECORD_RE.finditer(text))
    for k, rec in enumerate(records):
        kind = ARRAYS.get(rec.group(1).upper())
        if kind is None:
            continue
        body = text[rec.end() : records[k + 1].start() if k + 1 < len(records) else len(text)]
        elements = list(_ELEMENT_RE.finditer(body))
        for j, el in enumerate(elements):
            group, number = int(el.group(1)), int(el.group(2))
            if group != 1 or "uninitialized" in el.group(3).lower():
                continue
            chunk = body[el.end() : elements[j + 1].start() if j + 1 < len(elements) else len(body)]
            fields = {f.group(1): float(f.group(2)) for f in _FIELD_RE.finditer(chunk)}
            if len(fields) != 6:
                missing = ", ".join(c for c in "XYZWPR" if c not in fields)
                raise ValueError(f"{name}: ${rec.group(1)}[{group},{number}]: expected X, Y, Z, W, P, R; no {missing}")
            out[kind][number] = tuple(fields[c] for c in "XYZWPR")
    return out
