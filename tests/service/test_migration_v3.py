"""Schema version 3 on a store made by version 2: sessions get ``device_state``, cells
``model_version`` (1), calibrations ``nominal_version`` (1: every existing one was identified from
the cell's first nominal model) and ``predicted``; what was stored stays readable."""

from __future__ import annotations

from sqlalchemy import inspect, text
from sqlmodel import Session

from service.models import Calibration, Cell, RunSession
from service.store import SCHEMA_VERSION, current_calibration, make_engine, migrate

V3_COLUMNS = [
    ("session", "device_state"),
    ("cell", "model_version"),
    ("calibration", "nominal_version"),
    ("calibration", "predicted"),
]


def test_version_2_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 2 made, with a cell, a session and a calibration
        conn.execute(text("DROP INDEX IF EXISTS ix_calibration_current"))  # v9 indexes columns dropped here
        for table, column in V3_COLUMNS:
            conn.execute(text(f"ALTER TABLE {table} DROP COLUMN {column}"))
        conn.execute(text("UPDATE schema_version SET version = 2"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO session (cell_id, kind, state, planned, device, dry_run, created_by, "
                "created_at, updated_at) VALUES (1, 'pose', 'completed', 5, 'tracker', false, '', "
                "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO calibration (cell_id, session_id, kind, model, report, created_at) "
                "VALUES (1, 1, 'pose', '{}', '{}', CURRENT_TIMESTAMP)"
            )
        )
    assert migrate(engine) == SCHEMA_VERSION >= 3
    for table, column in V3_COLUMNS:
        assert column in {c["name"] for c in inspect(engine).get_columns(table)}
    with Session(engine) as db:
        cell = db.get(Cell, 1)
        assert cell.model_version == 1 and db.get(RunSession, 1).device_state is None
        cal = db.get(Calibration, 1)
        assert cal.nominal_version == 1 and cal.predicted is None
        assert current_calibration(db, cell).id == 1  # still the cell's calibration
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
