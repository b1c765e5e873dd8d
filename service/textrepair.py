"""Stored text that cannot be read, found and repaired (issue 22). The API refuses such text
at the boundary (service/textcheck.py); a store written before that check may still hold some
(a model name with a lone surrogate kept by a PATCH that answered 500, after which every read of
the cell answered 500). :func:`unreadable_text` finds it, the service reports it when it starts,
and ``recal repair-text`` (:func:`repair_text`) replaces each bad character with U+FFFD."""

from __future__ import annotations

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
    ``{"table", "id", "column", "field", "message"}``."""
    out = []
    for table, columns in TEXT_COLUMNS.items():
        for row in db.exec(select(table)).all():
            for column in columns:
                for loc, message in document_faults(getattr(row, column), ()):
                    field = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)
                    out.append(
                        {
                            "table": table.__tablename__,
                            "id": row.id,
                            "column": column,
                            "field": column + field,
                            "message": message,
                        }
                    )
    return out


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
