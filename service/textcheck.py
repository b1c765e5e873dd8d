"""Text that can be stored can be read (issue 22): what every text field must be before it is
kept. A lone surrogate (JSON's ``"\\ud800"``, valid JSON, not text) cannot be encoded as UTF-8,
so PostgreSQL refuses the row and SQLite keeps it escaped, after which every answer that holds it
fails; a NUL is not text to PostgreSQL either. Checked at the boundary (the API's requests, the
model files the CLI reads), once, for every string a document holds, keys included."""

from __future__ import annotations

# A name (of a cell, a file, a target, a joint) is at most this many characters: a file name's
# limit on every filesystem the service runs on (a 10,000-character `name=` was a 500).
MAX_NAME_CHARS = 255
# Any other single query or path parameter, and any key of a JSON object.
MAX_PARAM_CHARS = 2048


def text_fault(s: str) -> str | None:
    """What is wrong with ``s`` as stored text, or None: an unpaired surrogate or a NUL."""
    if "\x00" in s:
        return f"expected text without NUL characters (one at character {s.index(chr(0)) + 1})"
    try:
        s.encode("utf-8")
    except UnicodeEncodeError as exc:
        return (
            f"expected text (UTF-8): character {exc.start + 1} is an unpaired surrogate "
            f"U+{ord(s[exc.start]):04X}, which no text encoding can store"
        )
    return None


def document_faults(doc, loc: tuple = (), *, lengths: bool = True) -> list[tuple[tuple, str]]:
    """``(location, message)`` of every string of a JSON document (keys too) that cannot be
    stored as text, and (``lengths``) of every key or ``name`` over its length; ``loc`` the
    document's own."""
    out: list[tuple[tuple, str]] = []
    if isinstance(doc, str):
        fault = text_fault(doc)
        if fault:
            out.append((loc, fault))
        elif lengths and loc and loc[-1] == "name" and len(doc) > MAX_NAME_CHARS:
            out.append((loc, f"expected a name of at most {MAX_NAME_CHARS} characters, got {len(doc)}"))
    elif isinstance(doc, dict):
        for k, v in doc.items():
            key = str(k)
            fault = text_fault(key)
            if fault:
                out.append(((*loc, ascii(key)), f"key: {fault}"))
                continue
            if lengths and len(key) > MAX_PARAM_CHARS:
                out.append(((*loc, key[:40] + "..."), f"key: expected at most {MAX_PARAM_CHARS} characters"))
                continue
            out += document_faults(v, (*loc, key), lengths=lengths)
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += document_faults(v, (*loc, i), lengths=lengths)
    return out


def parameter_fault(name: str, value: str) -> str | None:
    """What is wrong with a query or path parameter's text, or None."""
    fault = text_fault(value)
    if fault:
        return fault
    limit = MAX_NAME_CHARS if name == "name" else MAX_PARAM_CHARS
    if len(value) > limit:
        return f"expected at most {limit} characters, got {len(value)}"
    return None
