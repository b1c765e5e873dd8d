"""Schema version 2 on a store made by version 1: ``session.requested`` appears, and the store
itself refuses a second active session on a cell (for any number of API processes)."""

from __future__ import annotations

import pytest
from sqlalchemy import inspect, text
from sqlalchemy.exc import IntegrityError
from sqlmodel import Session

from service.models import Cell, RunSession
from service.store import SCHEMA_VERSION, make_engine, migrate

V3_COLUMNS = [
    ("session", "device_state"),
    ("cell", "model_version"),
    ("calibration", "nominal_version"),
    ("calibration", "predicted"),
]


def test_version_1_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 1 made
        conn.execute(text("DROP INDEX IF EXISTS ix_calibration_current"))  # v9 indexes columns dropped here
        for table, column in V3_COLUMNS:
            conn.execute(text(f"ALTER TABLE {table} DROP COLUMN {column}"))
        conn.execute(text("DROP INDEX uq_session_active_cell"))
        conn.execute(text("ALTER TABLE session DROP COLUMN requested"))
        conn.execute(text("UPDATE schema_version SET version = 1"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP)"
            )
        )
        for state in ("running", "planned", "completed"):
            conn.execute(
                text(
                    "INSERT INTO session (cell_id, kind, state, planned, device, dry_run, created_by, "
                    "created_at, updated_at) VALUES (1, 'pose', :s, 5, 'tracker', false, '', "
                    "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
                ),
                {"s": state},
            )
    assert migrate(engine) == SCHEMA_VERSION >= 2
    assert "requested" in {c["name"] for c in inspect(engine).get_columns("session")}
    with Session(engine) as db:
        states = [db.get(RunSession, i).state for i in (1, 2, 3)]
        assert states == ["interrupted", "planned", "completed"]  # the newer active one kept
        db.add(RunSession(cell_id=1, kind="verify"))
        with pytest.raises(IntegrityError):
            db.commit()
        db.rollback()
        db.add(RunSession(cell_id=1, kind="verify", dry_run=True))  # dry runs move nothing: allowed
        db.commit()
        assert db.get(Cell, 1).name == "c"
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
