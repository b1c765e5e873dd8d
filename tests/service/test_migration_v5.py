"""Schema version 5 on a store made by version 4: the ``controller_model`` table (the UR
controller's own kinematics of each cell, versioned); what was stored stays readable."""

from __future__ import annotations

from sqlalchemy import inspect, text
from sqlmodel import Session

from service.models import Cell
from service.store import SCHEMA_VERSION, add_controller_model, current_controller_model, make_engine, migrate


def test_version_4_store_is_upgraded_and_keeps_versions_per_cell(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 4 made, with a cell
        conn.execute(text("DROP TABLE controller_model"))
        conn.execute(text("UPDATE schema_version SET version = 4"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at, model_version) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
    assert migrate(engine) == SCHEMA_VERSION >= 5
    assert inspect(engine).has_table("controller_model")
    with Session(engine) as db:
        assert db.get(Cell, 1).name == "c" and current_controller_model(db, 1) is None
        first = add_controller_model(db, cell_id=1, model={"name": "a"}, session_id=None)
        second = add_controller_model(db, cell_id=1, model={"name": "b"}, moved_m=2e-3)
        assert (first.version, second.version) == (1, 2)
        latest = current_controller_model(db, 1)
        assert latest.model == {"name": "b"} and latest.moved_m == 2e-3
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
