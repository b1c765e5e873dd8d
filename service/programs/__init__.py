"""Robot programs compensated in place (contracts §5): ABB RAPID (:mod:`.rapid`), KUKA KRL
(:mod:`.krl`), Fanuc TP (:mod:`.fanuc_tp`) and URScript (:mod:`.urscript`), all read through
one tokenizer (:mod:`.tokens`) with a rule table per language.

Each language module parses a program into a :class:`~.base.Program`: the files' text (bytes
kept, undecodable ones as surrogates), its :class:`~.base.Target` s (where each number is, what
the target means in SI, its frames and its written configuration) and the lines left alone.
:func:`.compensate.compensate_program` computes the new numbers; :meth:`~.base.Program.rewrite`
puts them in place of the old ones, every other byte as it was.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

FORMATS = {
    "csv": (".csv",),
    "urscript": (".script", ".urscript"),
    "rapid": (".mod", ".modx", ".prg", ".sys", ".sysx"),
    "krl": (".src",),
    "fanuc-tp": (".ls",),
}
BRAND = {"rapid": "abb", "krl": "kuka", "fanuc-tp": "fanuc"}

# What each format's text starts with, for a file whose extension says nothing (a RAPID system
# module saved without one, a URScript named "program"): a TP listing's /PROG header, KRL's
# &ACCESS/&REL or DEF NAME( ), a RAPID MODULE, a URScript def NAME(): or move call, a task CSV's
# header naming x or q1. Checked in this order: KRL's DEF has no colon, URScript's has one.
_CONTENT = (
    ("fanuc-tp", re.compile(r"^\s*/PROG\s+\S", re.MULTILINE)),
    ("krl", re.compile(r"^\s*(?:&ACCESS\b|&REL\b|(?:GLOBAL\s+)?DEF\s+\w+\s*\([^)]*\)\s*(?:;.*)?$)", re.M | re.I)),
    ("rapid", re.compile(r"^\s*MODULE\s+\w+", re.MULTILINE | re.IGNORECASE)),
    ("urscript", re.compile(r"^\s*def\s+\w+\s*\([^)]*\)\s*:|\b(?:movej|movel|movep|movec)\s*\(", re.MULTILINE)),
)


def format_of(path: str | os.PathLike, given: str | None = None, text: str | None = None) -> str:
    """The task file's format: ``given`` (``--format``), else from the extension, else (``text``:
    the file's text) from the content, else refused naming ``--format``. Without ``text``, a
    file whose extension is none of the programs' is a task CSV."""
    if given:
        return given
    suffix = Path(path).suffix.lower()
    for name, suffixes in FORMATS.items():
        if suffix in suffixes:
            return name
    if text is None:
        return "csv"
    for name, pattern in _CONTENT:
        if pattern.search(text):
            return name
    header = next((ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), "")
    columns = {c.strip().lower() for c in header.split(",")}
    if "," in header and columns & {"x", "q1"}:
        return "csv"
    from ..files import InputError

    raise InputError(
        path,
        f"cannot tell its format from the extension ({suffix or 'none'}) or the content: give --format "
        f"{'|'.join(FORMATS)}",
    )


def parse(fmt: str, path: str | os.PathLike, **options):
    """Parse a RAPID, KRL or TP program (see each module's ``parse``; a target no robot cell can
    have is refused: ``base.refuse_numbers_beyond_a_cell``), or a URScript program
    (:func:`.urscript.parse`, its own target types and the same bound)."""
    if fmt == "urscript":
        from . import urscript

        return urscript.parse(path, n_joints=options.get("n_joints", 6))
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
