"""The tokenizer every program language shares (KRL, RAPID, Fanuc TP, URScript).

A :class:`Language` says what differs between them: the character that starts a comment (to the
end of the line), the string quote, whether names are case sensitive, and what ends a statement
(RAPID's ``;``, else the line's end). A :class:`Source` is one file read in a language: its text
as read, its *code* (the text with comments and string contents blanked, same length and line
breaks, so that an offset in the code is the file's and a rewrite puts numbers back where they
were), its lines, its statements, its tokens (identifiers, numbers, strings, punctuation), and
errors that name the file and the line of an offset.

The parsers read the code with each language's rule table (a statement's kind -> its handler);
numbers are taken from the text, at the offsets the code gave.
"""

from __future__ import annotations

import bisect
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NoReturn

from ..files import InputError

LINE_RE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n|$)")
IDENT = r"[A-Za-z_]\w*"
IDENT_RE = re.compile(IDENT)
NUMBER = r"(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
SIGNED_NUMBER = rf"[+-]?{NUMBER}"  # a number as the languages write a target's components


@dataclass(frozen=True)
class Language:
    """What a program language's tokens look like: ``comment`` starts a comment to the end of the
    line; a string runs from ``quote`` to the next one on its line (or the line's end); names are
    ``case_sensitive`` or not (:meth:`pattern`); a statement ends at ``terminator`` (``None``: at
    the end of its line). ``None`` for ``comment`` or ``quote``: none is blanked."""

    name: str
    comment: str | None
    quote: str | None = '"'
    case_sensitive: bool = False
    terminator: str | None = None

    def pattern(self, regex: str, flags: int = 0) -> re.Pattern[str]:
        """``regex`` compiled as the language reads names (case insensitive unless it is not)."""
        return re.compile(regex, flags if self.case_sensitive else flags | re.IGNORECASE)


KRL = Language("krl", comment=";")
RAPID = Language("rapid", comment="!", terminator=";")
# what is read of a TP listing (its /POS section, /MN's frame selections) holds no comment and no
# string to blank: /MN's `!` comments are statements of their own, a /POS position's `!` is text
# (as written, a malformed position), and a label's "comment" is read by its pattern (P[n:"..."])
FANUC_TP = Language("fanuc-tp", comment=None, quote=None)
URSCRIPT = Language("urscript", comment="#", case_sensitive=True)


@dataclass(frozen=True)
class Token:
    """One token of the code: ``kind`` ``"ident"``, ``"number"``, ``"string"`` or ``"punct"``,
    its ``start`` and ``end`` offsets in the file and its ``text`` (as written)."""

    kind: str
    start: int
    end: int
    text: str


# a number before a name, so that ``1e5`` is one number (its ``e5`` no name); spaces skipped
_TOKEN_RE = re.compile(rf"\s*(?:(?P<number>{NUMBER})|(?P<ident>{IDENT})|(?P<punct>\S))")


def mask(text: str, lang: Language) -> str:
    """``text`` with comments and string contents blanked, same length and line breaks (the
    quotes kept): what a parser reads, so that its offsets are the file's."""
    if lang.comment is None and lang.quote is None:
        return text
    out = list(text)
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        if ch == lang.quote:
            j = i + 1
            while j < n and text[j] != lang.quote and text[j] not in "\r\n":
                out[j] = " "
                j += 1
            i = j + 1
        elif ch == lang.comment:
            while i < n and text[i] not in "\r\n":
                out[i] = " "
                i += 1
        else:
            i += 1
    return "".join(out)


def line_starts(text: str) -> list[int]:
    """The offset where each line of ``text`` starts (a line ends at ``\\r\\n``, ``\\r`` or ``\\n``)."""
    return [m.start() for m in LINE_RE.finditer(text) if m.end() > m.start()] or [0]


def line_of(starts: list[int], offset: int) -> int:
    """1-based line of a character offset."""
    return bisect.bisect_right(starts, offset)


def line_text(text: str, starts: list[int], line: int) -> str:
    """Line ``line`` (1-based) of ``text``, stripped."""
    s = starts[line - 1]
    e = starts[line] if line < len(starts) else len(text)
    return text[s:e].rstrip("\r\n").strip()


def trim(code: str, s: int, e: int) -> tuple[int, int]:
    """``(s, e)`` with the whitespace at both ends of ``code[s:e]`` left out."""
    while s < e and code[s].isspace():
        s += 1
    while e > s and code[e - 1].isspace():
        e -= 1
    return s, e


def split_top_level(code: str, s: int, e: int, sep: str = ",") -> list[tuple[int, int]]:
    """``(start, end)`` of the pieces of ``code[s:e]`` between the ``sep`` outside parentheses,
    brackets and braces (not trimmed)."""
    out, depth, start = [], 0, s
    for i in range(s, e):
        ch = code[i]
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == sep and depth == 0:
            out.append((start, i))
            start = i + 1
    out.append((start, e))
    return out


class Source:
    """One file read in a language: ``path``, ``text`` as read, ``code`` (:func:`mask`),
    ``starts`` of its lines, ``index`` among the program's files."""

    def __init__(self, lang: Language, path, text: str, index: int = 0):
        self.lang, self.path, self.text, self.index = lang, str(path), text, index
        self.code = mask(text, lang)
        self.starts = line_starts(text)

    def line(self, offset: int) -> int:
        """1-based line of an offset."""
        return line_of(self.starts, offset)

    def line_text(self, line: int) -> str:
        """Line ``line`` as written, stripped (what a report shows)."""
        return line_text(self.text, self.starts, line)

    def fail(self, offset: int, message: str) -> NoReturn:
        """Refuse the file: ``InputError`` naming it and the line of ``offset``."""
        raise InputError(self.path, message, line=self.line(offset))

    def spans(self) -> list[tuple[int, int]]:
        """``(start, end)`` of each line, its line break included."""
        return [(m.start(), m.end()) for m in LINE_RE.finditer(self.text) if m.end() > m.start()]

    def lines(self) -> Iterator[tuple[int, int, str]]:
        """Each line: its number, its start offset and its code (without the line break)."""
        for k, s in enumerate(self.starts):
            e = self.starts[k + 1] if k + 1 < len(self.starts) else len(self.text)
            yield k + 1, s, self.code[s:e].rstrip("\r\n")

    def statements(self) -> Iterator[tuple[int, int]]:
        """``(start, end)`` of each statement's code: up to the language's terminator (left out),
        the last one to the end of the file; a line each where the language has none."""
        if self.lang.terminator is None:
            for _ln, s, code in self.lines():
                yield s, s + len(code)
            return
        pos = 0
        for m in re.finditer(re.escape(self.lang.terminator), self.code):
            yield pos, m.start()
            pos = m.end()
        yield pos, len(self.code)

    def tokens(self, start: int = 0, end: int | None = None) -> Iterator[Token]:
        """The tokens of the code between ``start`` and ``end``: a string is its quotes with
        what they hold (blanked in the code, so its text is read from the file's)."""
        code, q = self.code, self.lang.quote
        i, stop = start, len(code) if end is None else end
        while i < stop:
            m = _TOKEN_RE.match(code, i, stop)
            if m is None:  # spaces to the end
                return
            kind = m.lastgroup or "punct"
            s, e = m.span(kind)
            if q is not None and code[s] == q:  # a string: to its closing quote, or the end of its line
                e = s + 1
                while e < stop and code[e] != q and code[e] not in "\r\n":
                    e += 1
                e = e + 1 if e < stop and code[e] == q else e
                kind = "string"
            yield Token(kind, s, e, self.text[s:e])
            i = e

    def identifiers(self, start: int = 0, end: int | None = None) -> Iterator[Token]:
        """The names among :meth:`tokens`."""
        return (t for t in self.tokens(start, end) if t.kind == "ident")
