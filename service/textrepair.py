"""Stored text that cannot be read, found and repaired (issue 22). The API refuses such text
at the boundary (service/textcheck.py); a store written before that check may still hold some
(a model name with a lone surrogate kept by a PATCH that answered 500, after which every read of
the cell answered 500). :func:`unreadable_text` finds it, the service reports it when it starts,
and ``recal repair-text`` (:func:`repair_text`) replaces each bad character with U+FFFD."""

from __future__ import annotations

from sqlalchemy import JSON, Text, cast, func, or_
from sqlmodel import Session, select

from .models import AuditEntry, Calibration, Cell, Compensation, RunSession, TaskFile, Token
from .store import audit
from .textcheck import document_faults

# The columns that hold text a person or a client wrote (names, models, devices, task files,
# reasons, the audit's words), per table: what a request could have put there.
TEXT_COLUMNS = {
    Cell: ("name", "site", "model", "devices"),
    TaskFile: ("name", "content", "files"),
    Token: ("name",),
    AuditEntry: ("actor", "action", "subject", "detail"),
    RunSession: ("target", "reason", "created_by"),
    Compensation: ("name", "created_by"),
    Calibration: ("model",),
}


def unreadable_text(db: Session) -> list[dict]:
    """Every stored value that holds text no encoding can store (a lone surrogate, a NUL):
    ``{"table", "id", "column", "field", "message"}``.

    Run at every start, so its cost must not grow with what the store holds: the database picks
    the few rows that could hold such text (:func:`_suspect`), and only those are read, one
    column at a time (never a compensation's output or a whole audit log into memory)."""
    out = []
    sqlite = db.get_bind().dialect.name == "sqlite"
    for table, columns in TEXT_COLUMNS.items():
        for column in columns:
            suspect = _suspect(getattr(table, column), sqlite=sqlite)
            if suspect is None:
                continue
            rows = db.exec(select(table.id, getattr(table, column)).where(suspect).order_by(table.id))
            for row_id, value in rows:
                for loc, message in document_faults(value, (), lengths=False):
                    field = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)
                    out.append(
                        {
                            "table": table.__tablename__,
                            "id": row_id,
                            "column": column,
                            "field": column + field,
                            "message": message,
                        }
                    )
    return out


# JSON keeps a lone surrogate or a NUL as an escape (json.dumps writes non-ASCII as escapes):
# "\ud800".."\udfff" or "\u0000". A valid pair (an emoji) matches too and is let go by the exact
# check; nothing unreadable escapes the filter.
_JSON_ESCAPES = tuple(f"\\u{p}" for p in ("d8", "d9", "da", "db", "dc", "dd", "de", "df", "0000"))


def _suspect(column, *, sqlite: bool):
    """A SQL condition true for every value of ``column`` that may hold unreadable text, or None
    when the column cannot hold any. A plain text column cannot hold a lone surrogate (the driver
    refuses to encode it) and, on PostgreSQL, no NUL either; SQLite keeps a NUL."""
    if isinstance(column.type, JSON):
        text = func.lower(cast(column, Text))
        return or_(*(text.contains(e, autoescape=True) for e in _JSON_ESCAPES))
    return column.contains("\x00", autoescape=True) if sqlite else None


def _repaired(value):
    """``value`` with every unpaired surrogate and NUL replaced by U+FFFD, keys included."""
    if isinstance(value, str):
        return "".join("\ufffd" if ch == "\x00" or 0xD800 <= ord(ch) <= 0xDFFF else ch for ch in value)
    if isinstance(value, dict):
        return {_repaired(k): _repaired(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_repaired(v) for v in value]
    return value


def repair_text(db: Session, *, actor: str) -> list[dict]:
    """Repair what :func:`unreadable_text` finds (U+FFFD for each bad character), audited; the
    list of what was repaired."""
    found = unreadable_text(db)
    for key in {(f["table"], f["id"], f["column"]) for f in found}:
        table = next(t for t in TEXT_COLUMNS if t.__tablename__ == key[0])
        row = db.get(table, key[1])
        setattr(row, key[2], _repaired(getattr(row, key[2])))
        db.add(row)
    db.commit()
    if found:
        audit(
            db,
            actor=actor,
            action="repair text",
            subject="store",
            detail={"repaired": [f["field"] for f in found][:50]},
        )
    return found
