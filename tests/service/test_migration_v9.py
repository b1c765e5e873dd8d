"""Schema version 9 on a store made by version 8: calibrations get ``activated_at``/``_by`` and
``retired_at``/``_by``; every existing calibration counts as activated when it was made, so the
cell's current calibration stays its newest one, and nothing is retired."""

from __future__ import annotations

from sqlalchemy import inspect, text
from sqlmodel import Session

from service.models import Calibration, Cell
from service.store import SCHEMA_VERSION, calibration_status, current_calibration, make_engine, migrate

V9_COLUMNS = ["activated_at", "activated_by", "retired_at", "retired_by"]


def test_version_8_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 8 made, with a cell and two calibrations
        conn.execute(text("DROP INDEX IF EXISTS ix_calibration_current"))  # v9 indexes columns dropped here
        for column in V9_COLUMNS:
            conn.execute(text(f"ALTER TABLE calibration DROP COLUMN {column}"))
        conn.execute(text("UPDATE schema_version SET version = 8"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at, model_version) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
        for _ in range(2):
            conn.execute(
                text(
                    "INSERT INTO calibration (cell_id, kind, model, report, created_at, nominal_version) "
                    "VALUES (1, 'pose', '{}', '{}', CURRENT_TIMESTAMP, 1)"
                )
            )
    assert migrate(engine) == SCHEMA_VERSION >= 9
    assert set(V9_COLUMNS) <= {c["name"] for c in inspect(engine).get_columns("calibration")}
    assert "ix_calibration_current" in {i["name"] for i in inspect(engine).get_indexes("calibration")}
    with Session(engine) as db:
        cell = db.get(Cell, 1)
        first, second = db.get(Calibration, 1), db.get(Calibration, 2)
        assert first.activated_at is not None and first.retired_at is None
        assert current_calibration(db, cell).id == 2  # the newest, as before the upgrade
        assert calibration_status(db, first) == "superseded" and calibration_status(db, second) == "current"
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
