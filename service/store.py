"""Storage: the engine, schema migrations, and the data-access functions routes and the
session loop use (keyword-only arguments, one transaction each).

SQLite (the embedded default) runs in WAL mode with ``synchronous=FULL``: a measurement the
service reported as taken survives a crash or a power loss. PostgreSQL comes through
``RECAL_DATABASE_URL``.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import JSON, delete, event, func, inspect, text, update
from sqlalchemy import column as sa_column
from sqlalchemy import table as sa_table
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError, InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from sqlmodel import Session, SQLModel, create_engine, select

from .models import (
    ID_TYPE,
    ROLES,
    AuditEntry,
    Calibration,
    Cell,
    ControllerModel,
    EventTicket,
    Measurement,
    RunSession,
    SchemaVersion,
    Token,
    VerifyResult,
    identified_calibration_kinds,
    kinds_that,
    utcnow,
)


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite files get WAL, full sync and a busy timeout."""
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        # Pool as many connections as the server's threads may want at once (anyio's 40 request
        # threads and the sessions' own): an SQLite connection costs a file handle, but opening
        # one per request beyond a small pool (and its PRAGMAs) was a fifth of a polled GET's cost.
        engine = create_engine(
            url, connect_args={"check_same_thread": False, "timeout": 30}, pool_size=48, max_overflow=16
        )

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn, _record):
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=FULL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    # PostgreSQL: kept connections for the usual load, a few more at peaks; two API replicas and
    # two workers stay under the server's default max_connections (100).
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


# --------------------------------------------------------------------------- migrations


# Each migration takes a connection and brings the schema from version i to i + 1. Never edit
# a released migration: add a new one.
def _v1(conn) -> None:
    SQLModel.metadata.create_all(conn)


def _v2(conn) -> None:
    """Sessions run by other processes (docs/fleet.md): ``session.requested`` carries a pause or
    abort request to the process running the session; at most one active (planned or running,
    not a dry run) session per cell, enforced by the database for any number of API processes."""
    if "requested" not in {c["name"] for c in inspect(conn).get_columns("session")}:
        conn.execute(text("ALTER TABLE session ADD COLUMN requested VARCHAR"))
    active = "state IN ('planned', 'running') AND NOT dry_run"
    dupes = conn.execute(
        text(f"SELECT cell_id, MAX(id) FROM session WHERE {active} GROUP BY cell_id HAVING COUNT(*) > 1")
    )
    for cell_id, keep in dupes.all():  # cannot happen through the API; a damaged store could have them
        conn.execute(
            text(
                f"UPDATE session SET state = 'interrupted', reason = 'another session was driving this cell' "
                f"WHERE cell_id = :c AND id <> :k AND {active}"
            ),
            {"c": cell_id, "k": keep},
        )
    conn.execute(text(f"CREATE UNIQUE INDEX IF NOT EXISTS uq_session_active_cell ON session (cell_id) WHERE {active}"))


def _v3(conn) -> None:
    """The devices' state of each session for the live page (``session.device_state``); nominal
    models that can be replaced (``cell.model_version``, and ``calibration.nominal_version``: the
    one each calibration was identified from; every existing one was made from version 1); the
    predicted accuracy of each calibration, stored with it (``calibration.predicted``)."""
    columns = {
        table: {c["name"] for c in inspect(conn).get_columns(table)} for table in ("session", "cell", "calibration")
    }
    for table, column, ddl in (
        ("session", "device_state", "JSON"),
        ("cell", "model_version", "INTEGER NOT NULL DEFAULT 1"),
        ("calibration", "nominal_version", "INTEGER"),
        ("calibration", "predicted", "JSON"),
    ):
        if column not in columns[table]:
            conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {column} {ddl}"))
    conn.execute(text("UPDATE calibration SET nominal_version = 1 WHERE nominal_version IS NULL"))


def _v4(conn) -> None:
    """The beam breaks each session repaired by pointing the tracker at the reflector
    (``session.beam_recoveries``, shown on the live page)."""
    if "beam_recoveries" not in {c["name"] for c in inspect(conn).get_columns("session")}:
        conn.execute(text("ALTER TABLE session ADD COLUMN beam_recoveries INTEGER NOT NULL DEFAULT 0"))


def _v5(conn) -> None:
    """The UR controller's own kinematics of each cell, versioned (``controller_model``,
    issue 16)."""
    SQLModel.metadata.create_all(conn, tables=[ControllerModel.__table__])


def _v6(conn) -> None:
    """The event stream's tickets in the database (``event_ticket``), so that a ticket issued by
    one API process of a fleet is accepted by any other (issue 12)."""
    SQLModel.metadata.create_all(conn, tables=[EventTicket.__table__])


def _v7(conn) -> None:
    """Robot programs that are not UTF-8 kept as their bytes (issue 18): the encoding of each
    compensation's output and each task file (``compensation.encoding``, ``taskfile.encoding``;
    "iso-8859-1" is a character per byte, every existing row is UTF-8) and a task file's other
    files (``taskfile.files``: a KRL .src's .dat)."""
    columns = {table: {c["name"] for c in inspect(conn).get_columns(table)} for table in ("compensation", "taskfile")}
    for table, column, ddl in (
        ("compensation", "encoding", "VARCHAR NOT NULL DEFAULT 'utf-8'"),
        ("taskfile", "encoding", "VARCHAR NOT NULL DEFAULT 'utf-8'"),
        ("taskfile", "files", "JSON"),
    ):
        if column not in columns[table]:
            conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {column} {ddl}"))


def _id_columns() -> list[tuple[str, str]]:
    """Every id column and column that names an id: ``(table, column)``, read from the models
    (``models.ID_TYPE``), so that a table added later is covered too."""
    return [
        (table.name, column.name)
        for table in SQLModel.metadata.sorted_tables
        for column in table.columns
        if column.type is ID_TYPE
    ]


def _v8(conn) -> None:
    """Ids as documented, 1 to 2**63 - 1 (issue 22): every id and every column naming one is
    64-bit on PostgreSQL (its INTEGER and SERIAL stopped at 2**31 - 1, and a larger id in a path
    or query answered 500), and the ids' sequences count as far. SQLite's INTEGER is 64-bit
    already: nothing to do there. Rows are kept (ALTER ... TYPE BIGINT converts them in place)."""
    if conn.dialect.name != "postgresql":
        return
    existing = set(inspect(conn).get_table_names())
    for table, column in _id_columns():
        if table not in existing:
            continue
        conn.execute(text(f'ALTER TABLE "{table}" ALTER COLUMN "{column}" TYPE BIGINT'))
        if column == "id":
            sequence = conn.execute(text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": f'"{table}"'}).scalar()
            if sequence:
                conn.execute(text(f"ALTER SEQUENCE {sequence} AS BIGINT"))


def _v9(conn) -> None:
    """Calibrations are activated, not overwritten (issue 27): when each was made the cell's
    current one and by whom (``calibration.activated_at``, ``activated_by``), and when it was
    retired and by whom (``retired_at``, ``retired_by``). Every existing calibration became
    current when it was made (the newest was the cell's): it counts as activated then, so the
    cell's current calibration stays the one it was."""
    columns = {c["name"] for c in inspect(conn).get_columns("calibration")}
    stamp = "TIMESTAMP" if conn.dialect.name == "postgresql" else "DATETIME"
    for column, ddl in (
        ("activated_at", stamp),
        ("activated_by", "VARCHAR"),
        ("retired_at", stamp),
        ("retired_by", "VARCHAR"),
    ):
        if column not in columns:
            conn.execute(text(f"ALTER TABLE calibration ADD COLUMN {column} {ddl}"))
    conn.execute(text("UPDATE calibration SET activated_at = created_at WHERE activated_at IS NULL"))
    conn.execute(
        text(
            "CREATE INDEX IF NOT EXISTS ix_calibration_current "
            "ON calibration (cell_id, kind, nominal_version, retired_at, activated_at)"
        )
    )


def _v10(conn) -> None:
    """A session's records each in its place (issue 23): what it did with its UR controller's
    kinematics (``session.controller_event``) and a verify session's result (``session.verify``)
    move out of ``plan_info`` (its ``controller_model`` and ``verify`` keys), which keeps the plan
    alone. The public ``plan_info`` shows the three together as before."""
    columns = {c["name"] for c in inspect(conn).get_columns("session")}
    for column in ("controller_event", "verify"):
        if column not in columns:
            conn.execute(text(f"ALTER TABLE session ADD COLUMN {column} JSON"))
    # the table as this migration knows it (never the present model's, which may change later)
    session = sa_table(
        "session", sa_column("id"), *(sa_column(c, JSON) for c in ("plan_info", "controller_event", "verify"))
    )
    rows = conn.execute(select(session.c.id, session.c.plan_info).where(session.c.plan_info.is_not(None))).all()
    for sid, info in rows:
        if not isinstance(info, dict) or not ({"controller_model", "verify"} & info.keys()):
            continue
        plan = {k: v for k, v in info.items() if k not in ("controller_model", "verify")}
        conn.execute(
            update(session)
            .where(session.c.id == sid)
            .values(
                plan_info=plan or None,
                controller_event=info.get("controller_model") or None,
                verify=info.get("verify") or None,
            )
        )


def _v11(conn) -> None:
    """A calibration's parameter covariance stored once, in one shape (issue 23): the model's
    ``identification.covariance`` (calibration.report's block, SI), which ``recal predict`` and
    the result page read already; ``calibration.covariance``, its copy in another shape, goes.
    What only the copy had, the relations of the parameters the identification held (the next
    session's prior needs them), joins the block as ``held_relations``; a model without the
    block's covariance gets it from the copy. Nothing else of a stored model changes."""
    if "covariance" not in {c["name"] for c in inspect(conn).get_columns("calibration")}:
        return
    calibration = sa_table("calibration", sa_column("id"), sa_column("model", JSON), sa_column("covariance", JSON))
    rows = conn.execute(
        select(calibration.c.id, calibration.c.model, calibration.c.covariance).where(
            calibration.c.covariance.is_not(None)
        )
    ).all()
    for cal_id, model, copy in rows:
        merged = _covariance_in_block(model, copy)
        if merged is not None:
            conn.execute(update(calibration).where(calibration.c.id == cal_id).values(model=merged))
    conn.execute(text("ALTER TABLE calibration DROP COLUMN covariance"))


def _covariance_in_block(model, copy) -> dict | None:
    """``model`` (a stored model document) with what ``copy`` (a ``calibration.covariance`` of
    schema v10) adds to its ``identification.covariance``; None when it adds nothing."""
    if not isinstance(model, dict) or not isinstance(copy, dict) or not copy.get("names"):
        return None
    block = model.get("identification") if isinstance(model.get("identification"), dict) else {}
    cov = dict(block.get("covariance") or {})
    if not cov.get("names"):
        cov = {
            "units": "SI (m, rad; gains 1)",
            "names": copy["names"],
            "kinds": copy.get("kinds"),
            "matrix": copy["matrix"],
        }
        cov = {k: v for k, v in cov.items() if v is not None}
    elif not copy.get("held"):
        return None
    if copy.get("held"):
        cov["held_relations"] = copy["held"]
    return {**model, "identification": {**block, "covariance": cov}}


MIGRATIONS: list[Callable] = [_v1, _v2, _v3, _v4, _v5, _v6, _v7, _v8, _v9, _v10, _v11]
SCHEMA_VERSION = len(MIGRATIONS)


def migrate(engine: Engine) -> int:
    """Bring the database to the current schema; returns the version."""
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":  # several processes may start at once (docs/fleet.md)
            conn.execute(text("SELECT pg_advisory_xact_lock(72430111)"))
        if not inspect(conn).has_table("schema_version"):
            current = 0
        else:
            row = conn.execute(text("SELECT version FROM schema_version WHERE id = 1")).first()
            current = row[0] if row else 0
        if current > SCHEMA_VERSION:
            raise RuntimeError(f"the database schema is version {current}, newer than this Recal ({SCHEMA_VERSION})")
        for version in range(current, SCHEMA_VERSION):
            MIGRATIONS[version](conn)
        if current == 0:
            conn.execute(SchemaVersion.__table__.insert().values(id=1, version=SCHEMA_VERSION))
        elif current < SCHEMA_VERSION:
            conn.execute(text("UPDATE schema_version SET version = :v WHERE id = 1"), {"v": SCHEMA_VERSION})
    return SCHEMA_VERSION


# --------------------------------------------------------------------------- tokens


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def create_token(db: Session, *, role: str, name: str = "") -> tuple[Token, str]:
    """A new token: the record (with the hash only) and the token itself, shown once."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}; got {role!r}")
    plain = "rc_" + secrets.token_urlsafe(32)
    tok = Token(name=name or role, role=role, hash=hash_token(plain))
    db.add(tok)
    db.commit()
    db.refresh(tok)
    return tok, plain


def find_token(db: Session, plain: str) -> Token | None:
    tok = db.exec(select(Token).where(Token.hash == hash_token(plain))).first()
    return tok if tok is not None and not tok.revoked else None


def list_tokens(db: Session) -> list[Token]:
    return list(db.exec(select(Token).order_by(Token.id)).all())


def revoke_token(db: Session, token_id: int) -> bool:
    """Mark token ``token_id`` revoked (its hash stays, so it is known and refused); False when
    there is no such token."""
    t = db.get(Token, token_id)
    if t is None:
        return False
    t.revoked = True
    db.add(t)
    db.commit()
    return True


def verifications(db: Session, cell_id: int, *, limit: int | None = None) -> list[tuple[int, datetime, VerifyResult]]:
    """The cell's completed verify sessions that have a result, newest first (the last ``limit``
    verify sessions): ``(session id, when it ended, its result)`` (``session.verify``, model
    units). Columns only: the page's trend, the drift page and the certificate read these."""
    q = (
        select(RunSession.id, RunSession.updated_at, RunSession.verify)
        .where(
            RunSession.cell_id == cell_id,
            RunSession.kind.in_(kinds_that(lambda r: r.stores == "verification")),  # type: ignore[attr-defined]
            RunSession.state == "completed",
            RunSession.dry_run == False,  # noqa: E712 (SQL)
        )
        .order_by(RunSession.id.desc())
    )
    if limit is not None:
        q = q.limit(limit)
    out = []
    for sid, at, v in db.exec(q).all():
        if v:
            out.append((sid, at, VerifyResult.from_json(v)))
    return out


def audit_entries(db: Session, limit: int, *, before_id: int | None = None) -> list[AuditEntry]:
    """The newest ``limit`` audit entries (at most 5000), newest first; with ``before_id``, those
    older than that entry (the next page: pass the last id of a page)."""
    q = select(AuditEntry)
    if before_id is not None:
        q = q.where(AuditEntry.id < before_id)
    return list(db.exec(q.order_by(AuditEntry.id.desc()).limit(max(1, min(limit, 5000)))).all())


def prune_audit(db: Session, *, before: datetime, actor: str) -> int:
    """Delete the audit entries written before ``before``; the pruning itself is audited (an
    entry that stays). Returns how many were deleted."""
    old = db.exec(select(AuditEntry.id).where(AuditEntry.at < before)).all()
    for start in range(0, len(old), 1000):
        chunk = old[start : start + 1000]
        db.exec(delete(AuditEntry).where(AuditEntry.id.in_(chunk)))  # type: ignore[union-attr]
    db.commit()
    audit(
        db,
        actor=actor,
        action="prune audit",
        subject="audit",
        detail={"before": before.isoformat(), "deleted": len(old)},
    )
    return len(old)


def issue_ticket(db: Session, *, token_id: int, scope: str, ttl_s: float, now: datetime | None = None) -> str:
    """A new single-use ticket for ``scope`` with the rights of token ``token_id``, good for
    ``ttl_s`` seconds from ``now``; only its hash is stored. Expired tickets are dropped here."""
    now = now or utcnow()
    plain = secrets.token_urlsafe(24)
    db.exec(delete(EventTicket).where(EventTicket.expires_at < now))
    db.add(
        EventTicket(hash=hash_token(plain), token_id=token_id, scope=scope, expires_at=now + timedelta(seconds=ttl_s))
    )
    db.commit()
    return plain


def redeem_ticket(db: Session, plain: str, scope: str, *, now: datetime | None = None) -> Token | None:
    """The token whose rights ticket ``plain`` carries, if it is for ``scope``, unexpired, unused
    and its token not revoked; else None. Presenting a ticket uses it up, whatever the answer:
    its row is deleted, and of two API processes redeeming it at once only the one whose delete
    removed the row (rowcount 1) may accept it."""
    now = now or utcnow()
    row = db.exec(select(EventTicket).where(EventTicket.hash == hash_token(plain))).first()
    if row is None:
        return None
    ticket_id, token_id, ticket_scope, expires_at = row.id, row.token_id, row.scope, as_utc(row.expires_at)
    res = db.exec(delete(EventTicket).where(EventTicket.id == ticket_id))
    db.commit()
    if res.rowcount != 1 or ticket_scope != scope or expires_at <= now:
        return None
    tok = db.get(Token, token_id)
    return tok if tok is not None and not tok.revoked else None


def audit(db: Session, *, actor: str, action: str, subject: str, detail: dict | None = None) -> None:
    db.add(AuditEntry(actor=actor, action=action, subject=subject, detail=detail))
    db.commit()


# --------------------------------------------------------------------------- sessions


def measured_count(db: Session, session_id: int) -> int:
    """How many planned configurations have been measured (distinct ``seq``)."""
    return int(
        db.exec(select(func.count(func.distinct(Measurement.seq))).where(Measurement.session_id == session_id)).one()
    )


session_log = logging.getLogger("recal.sessions")
# States an operator must look at: a device fault pauses a session, a crash fails it.
_WARN_STATES = {"paused", "failed", "interrupted"}


def log_state(run: RunSession, state: str, reason: str | None) -> None:
    """One line on ``recal.sessions`` for a session's new state (service/logs.py): a warning when
    it needs someone (paused by a device fault, failed, interrupted), else information."""
    level = logging.WARNING if state in _WARN_STATES else logging.INFO
    session_log.log(
        level,
        "session %s (%s, cell %s): %s%s",
        run.id,
        run.kind,
        run.cell_id,
        state,
        f": {reason}" if reason else "",
        extra={"fields": {"session": run.id, "kind": run.kind, "cell": run.cell_id, "state": state, "reason": reason}},
    )


def set_state(db: Session, run: RunSession, state: str, reason: str | None = None) -> RunSession:
    run.state = state
    run.reason = reason
    run.updated_at = utcnow()
    db.add(run)
    db.commit()
    db.refresh(run)
    log_state(run, state, reason)
    return run


def set_state_unless(
    db: Session,
    run: RunSession,
    final: tuple[str, ...],
    state: str,
    reason: str | None,
    *,
    device_state: dict | None = None,
) -> bool:
    """``set_state`` in one conditional update, unless the session reached one of ``final``
    meanwhile (a session that just completed is not then marked aborted); with the devices'
    state when given. True if it changed."""
    values = {"state": state, "reason": reason, "updated_at": utcnow()}
    if device_state is not None:
        values["device_state"] = device_state
    res = db.exec(update(RunSession).where(RunSession.id == run.id, RunSession.state.not_in(final)).values(**values))
    db.commit()
    db.refresh(run)
    changed = res.rowcount > 0
    if changed:
        log_state(run, state, reason)
    return changed


def interrupt_unfinished(db: Session, *, owner: str | None = None) -> list[int]:
    """Mark sessions that were planned or running when the service stopped as ``interrupted``:
    nobody runs them any more, and an active session holds its cell (409 for every other).

    With ``owner``, only sessions leased by that owner (the process stopping); without, every
    planned or running one (the embedded single-process service starting: its threads died with
    it). A fleet's API processes never call it without ``owner``: a planned session there may be
    waiting in a worker's queue (its lease owner is ``queued:...``), the reaper handles those."""
    q = select(RunSession).where(RunSession.state.in_(("planned", "running")))
    if owner is not None:
        q = q.where(RunSession.lease_owner == owner)
    ids = []
    for run in db.exec(q).all():
        # nobody holds the devices any more: whatever the last pose said of them is history
        run.device_state = (
            {
                **{
                    k: {"state": "not connected", "detail": "the service stopped"}
                    for k in (run.device_state or {})
                    if k != "at"
                },
                "at": utcnow().isoformat(),
            }
            if run.device_state
            else None
        )
        set_state(
            db, run, "interrupted", f"the service stopped while this session was {run.state}; resume it to continue"
        )
        ids.append(run.id)
    return ids


def last_calibration(
    db: Session, cell_id: int, *, kind: str | None = None, nominal_version: int | None = None
) -> Calibration | None:
    """The cell's newest calibration (of ``kind``; identified from nominal model ``nominal_version``)."""
    q = select(Calibration).where(Calibration.cell_id == cell_id)
    if kind is not None:
        q = q.where(Calibration.kind == kind)
    if nominal_version is not None:
        q = q.where(Calibration.nominal_version == nominal_version)
    return db.exec(q.order_by(Calibration.id.desc())).first()


def current_calibration(db: Session, cell: Cell, *, at: datetime | None = None) -> Calibration | None:
    """The calibration the cell's robot is known by: of its pose calibrations identified from the
    cell's present nominal model (after the nominal is replaced, none until the next one), the
    one activated last that is not retired. With ``at``: the one that was so at that time (as far
    as the store knows: a calibration activated again counts from its last activation)."""
    q = select(Calibration.id).where(
        Calibration.cell_id == cell.id,
        Calibration.kind.in_(identified_calibration_kinds()),  # type: ignore[attr-defined]
        Calibration.nominal_version == cell.model_version,
        Calibration.activated_at.is_not(None),  # type: ignore[union-attr]
    )
    if at is None:
        q = q.where(Calibration.retired_at.is_(None))  # type: ignore[union-attr]
    else:
        q = q.where(
            Calibration.activated_at <= at,  # type: ignore[operator]
            Calibration.retired_at.is_(None) | (Calibration.retired_at > at),  # type: ignore[union-attr,operator]
        )
    # the id from the index (ix_calibration_current), then the one row: not every row's reports
    found = db.exec(q.order_by(Calibration.activated_at.desc(), Calibration.id.desc()).limit(1)).first()  # type: ignore[union-attr]
    return None if found is None else db.get(Calibration, found)


def candidate_calibration(db: Session, cell: Cell, *, made_by: datetime | None = None) -> Calibration | None:
    """The cell's newest pose calibration that waits to become current (never activated, not
    retired, newer than the current one; made by ``made_by`` when given), else None."""
    cur = current_calibration(db, cell)
    q = select(Calibration.id).where(
        Calibration.cell_id == cell.id,
        Calibration.kind.in_(identified_calibration_kinds()),  # type: ignore[attr-defined]
        Calibration.nominal_version == cell.model_version,
        Calibration.activated_at.is_(None),  # type: ignore[union-attr]
        Calibration.retired_at.is_(None),  # type: ignore[union-attr]
    )
    if cur is not None:
        q = q.where(Calibration.id > cur.id)
    if made_by is not None:
        q = q.where(Calibration.created_at <= made_by)
    found = db.exec(q.order_by(Calibration.id.desc()).limit(1)).first()
    return None if found is None else db.get(Calibration, found)


def calibration_status(db: Session, cal: Calibration) -> str | None:
    """``current``, ``candidate`` (never activated: waits for a verify session or an activation),
    ``superseded`` (current once, or made from an earlier nominal model) or ``retired``; None for
    a circle or joint calibration, which is never a cell's model."""
    if cal.retired_at is not None:
        return "retired"
    if cal.kind not in identified_calibration_kinds():
        return None
    cell = db.get(Cell, cal.cell_id)
    if cell is None or cal.nominal_version != cell.model_version:
        return "superseded"
    if cal.activated_at is None:
        return "candidate"
    cur = current_calibration(db, cell)
    return "current" if cur is not None and cur.id == cal.id else "superseded"


def activate_calibration(db: Session, cal: Calibration, *, actor: str, why: str) -> Calibration | None:
    """Make ``cal`` its cell's current calibration (a retired one is brought back), audited with
    ``why``; returns the calibration that was current before (None: the nominal model)."""
    cell = db.get(Cell, cal.cell_id)
    before = current_calibration(db, cell) if cell is not None else None
    cal.activated_at, cal.activated_by = utcnow(), actor
    cal.retired_at, cal.retired_by = None, None
    db.add(cal)
    db.commit()
    db.refresh(cal)
    detail = {"cell": cal.cell_id, "previous": None if before is None else before.id, "why": why}
    audit(db, actor=actor, action="activate calibration", subject=f"calibration {cal.id}", detail=detail)
    return before


def retire_calibration(db: Session, cal: Calibration, *, actor: str) -> Calibration | None:
    """Retire ``cal``: it no longer serves as its cell's model or prior (the one activated before
    it that is not retired does, else the nominal model); kept and readable. Audited; returns
    the cell's current calibration afterwards."""
    cal.retired_at, cal.retired_by = utcnow(), actor
    db.add(cal)
    db.commit()
    db.refresh(cal)
    cell = db.get(Cell, cal.cell_id)
    now = current_calibration(db, cell) if cell is not None else None
    detail = {"cell": cal.cell_id, "current": None if now is None else now.id}
    audit(db, actor=actor, action="retire calibration", subject=f"calibration {cal.id}", detail=detail)
    return now


def acquire_lease(
    db: Session, run: RunSession, owner: str, *, ttl_s: float = 30.0, closing_wait_s: float = 10.0
) -> bool:
    """Take (or renew) the exclusive right to drive ``run``'s cell. At most one session per cell
    holds a live lease; the check and the write happen in one transaction. An aborted session
    still holds its lease while it closes its devices (it is said aborted first, so that the
    abort is answered at once): that is waited for, up to ``closing_wait_s``, rather than
    refused, so a session started right after an abort runs."""
    deadline = time.monotonic() + closing_wait_s
    while True:
        got = _try_lease(db, run, owner, ttl_s)
        if got != "closing":
            return got
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)


def _try_lease(db: Session, run: RunSession, owner: str, ttl_s: float) -> bool | str:
    """``acquire_lease`` once: True, False, or ``"closing"`` (only an aborted session that is
    closing its devices holds the cell)."""
    # Lock the cell's row first: two processes taking leases on one cell queue up here.
    db.exec(select(Cell.id).where(Cell.id == run.cell_id).with_for_update()).first()
    now = utcnow()
    others = db.exec(
        select(RunSession).where(
            RunSession.cell_id == run.cell_id,
            RunSession.id != run.id,
            (RunSession.state == "running")
            | ((RunSession.state == "planned") & (RunSession.dry_run == False))  # noqa: E712 (SQL)
            | ((RunSession.state == "aborted") & (RunSession.lease_expires > now)),  # closing its devices
        )
    ).all()
    live = [o for o in others if o.lease_expires is not None and as_utc(o.lease_expires) > now]
    if live:
        db.rollback()
        return "closing" if all(o.state == "aborted" for o in live) else False
    db.refresh(run)
    if (
        run.lease_owner not in (None, owner) and run.lease_expires is not None and as_utc(run.lease_expires) > now
    ):  # another process holds this very session
        db.rollback()
        return False
    run.lease_owner = owner
    run.lease_expires = now + timedelta(seconds=ttl_s)
    db.add(run)
    db.commit()
    return True


def release_lease(db: Session, run: RunSession, owner: str) -> None:
    """Give back ``owner``'s lease on ``run``'s cell (an aborted session whose devices are now
    closed, :func:`acquire_lease`)."""
    db.exec(
        update(RunSession)
        .where(RunSession.id == run.id, RunSession.lease_owner == owner)
        .values(lease_expires=utcnow())
    )
    db.commit()


def as_utc(t: datetime | None) -> datetime | None:
    """A stored time as an aware UTC time (SQLite gives naive ones back); None stays None."""
    if t is None:
        return None
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def database_unavailable(exc: BaseException) -> bool:
    """The store cannot be reached (connection refused or lost, or no pooled connection free in
    time: a loaded machine), as opposed to a bad query."""
    return isinstance(exc, (OperationalError, InterfaceError, PoolTimeout)) or (
        isinstance(exc, DBAPIError) and bool(exc.connection_invalidated)
    )


def held_by_other(run: RunSession, owner: str) -> bool:
    """Another process (``lease_owner``) holds this session's lease, and the lease runs."""
    return (
        run.lease_owner not in (None, owner) and run.lease_expires is not None and as_utc(run.lease_expires) > utcnow()
    )


# --------------------------------------------------------------------------- controller models


def current_controller_model(db: Session, cell_id: int) -> ControllerModel | None:
    """The newest controller model read for the cell (``None``: never read)."""
    return db.exec(
        select(ControllerModel).where(ControllerModel.cell_id == cell_id).order_by(ControllerModel.version.desc())
    ).first()


def add_controller_model(
    db: Session, *, cell_id: int, model: dict, session_id: int | None = None, moved_m: float | None = None
) -> ControllerModel:
    """Store a new version of the cell's controller model."""
    last = current_controller_model(db, cell_id)
    rec = ControllerModel(
        cell_id=cell_id,
        version=1 if last is None else last.version + 1,
        model=model,
        session_id=session_id,
        moved_m=moved_m,
    )
    db.add(rec)
    db.commit()
    db.refresh(rec)
    return rec


def delete_session_rows(db: Session, session_id: int) -> int:
    """Delete a session and its measurements (not committed); returns how many measurements went."""
    n = db.exec(select(func.count()).select_from(Measurement).where(Measurement.session_id == session_id)).one()
    db.execute(delete(Measurement).where(Measurement.session_id == session_id))
    db.execute(delete(RunSession).where(RunSession.id == session_id))
    return int(n)
