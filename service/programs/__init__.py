"""Robot programs compensated in place (contracts §5): ABB RAPID (:mod:`.rapid`), KUKA KRL
(:mod:`.krl`), Fanuc TP (:mod:`.fanuc_tp`) and URScript (:mod:`service.taskfiles`).

Each language module parses a program into a :class:`~.base.Program`: the files' text (bytes
kept, undecodable ones as surrogates), its :class:`~.base.Target` s (where each number is, what
the target means in SI, its frames and its written configuration) and the lines left alone.
:func:`.compensate.compensate_program` computes the new numbers; :meth:`~.base.Program.rewrite`
puts them in place of the old ones, every other byte as it was.
"""

from __future__ import annotations

import os
from pathlib import Path

FORMATS = {
    "csv": (".csv",),
    "urscript": (".script", ".urscript"),
    "rapid": (".mod", ".modx", ".prg"),
    "krl": (".src",),
    "fanuc-tp": (".ls",),
}
BRAND = {"rapid": "abb", "krl": "kuka", "fanuc-tp": "fanuc"}


def format_of(path: str | os.PathLike, given: str | None = None) -> str:
    """The task file's format: ``given`` (``--format``), else from the extension (a task CSV when
    it is none of the programs')."""
    if given:
        return given
    suffix = Path(path).suffix.lower()
    for name, suffixes in FORMATS.items():
        if suffix in suffixes:
            return name
    return "csv"


def parse(fmt: str, path: str | os.PathLike, **options):
    """Parse a RAPID, KRL or TP program (see each module's ``parse``; a target no robot cell can
    have is refused: ``base.refuse_numbers_beyond_a_cell``), or a URScript program
    (:func:`service.taskfiles.parse_urscript`, its own target types and the same bound)."""
    if fmt == "urscript":
        from ..taskfiles import parse_urscript

        return parse_urscript(path, options.get("n_joints", 6))
    from .base import refuse_numbers_beyond_a_cell

    if fmt == "rapid":
        from . import rapid

        return refuse_numbers_beyond_a_cell(rapid.parse(path, **options))
    if fmt == "krl":
        from . import krl

        return refuse_numbers_beyond_a_cell(krl.parse(path, **options))
    if fmt == "fanuc-tp":
        from . import fanuc_tp

        return refuse_numbers_beyond_a_cell(fanuc_tp.parse(path, **options))
    raise ValueError(f"no program parser for {fmt!r}")
