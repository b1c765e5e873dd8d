"""Ids as documented (issue 22, case 2): 1 to 2**63 - 1 on SQLite and PostgreSQL alike. Every
route with an id in its path or query (enumerated from the app, so that routes added later are
swept too) answers 404 for an id that names nothing up to 2**63 - 1 and 422 naming the parameter
beyond; never a 5xx. Schema version 8 makes a version 7 store's ids 64-bit and keeps its rows."""

from __future__ import annotations

import re

import pytest
from sqlalchemy import inspect, text
from sqlmodel import Session

from service.api.docs import is_id_parameter
from service.models import MAX_ID, Calibration, Cell, Measurement, RunSession
from service.store import SCHEMA_VERSION, _id_columns, make_engine, migrate

from .conftest import auth, register_cell

IN_RANGE = (2**31, MAX_ID)  # beyond PostgreSQL's INTEGER, and the largest id the docs promise
OUT_OF_RANGE = (2**63, -1, -(2**31) - 1, 0)


def _id_routes(client) -> list[tuple[str, str, list[str], list[str]]]:
    """``(method, path, path ids, query ids)`` of every API operation that takes an id (from the
    app's OpenAPI document: every route the app serves)."""
    out = []
    for path, ops in client.get("/openapi.json").json()["paths"].items():
        for method, op in ops.items():
            params = op.get("parameters", [])
            path_ids = [p["name"] for p in params if p["in"] == "path" and is_id_parameter(p["name"])]
            query_ids = [p["name"] for p in params if p["in"] == "query" and is_id_parameter(p["name"])]
            if path_ids or query_ids:
                out.append((method.upper(), path, path_ids, query_ids))
    return out


def _fill(path: str, ids: dict[str, int], name: str | None = None, value: int | None = None) -> str:
    return re.sub(r"\{([^}]+)\}", lambda m: str(value if m.group(1) == name else ids.get(m.group(1), 1)), path)


def test_every_id_route_answers_4xx_for_any_id(idle_app, tokens, stored_session):
    with idle_app(raise_server_exceptions=False) as c:
        h = auth(tokens["admin"])
        cell = register_cell(c, tokens["technician"], "ids")["id"]
        session, cal = stored_session(cell, seed=2, n=25)
        task = c.post(
            f"/api/v1/cells/{cell}/tasks",
            headers=h,
            json={"name": "t.csv", "content": "q1,q2,q3,q4,q5,q6\n1,2,3,4,5,6\n"},
        ).json()["id"]
        comp = c.post(f"/api/v1/calibrations/{cal}/compensate", headers=h, content="q1,q2,q3,q4,q5,q6\n1,2,3,4,5,6\n")
        ids = {
            "cell_id": cell,
            "session_id": session,
            "calibration_id": cal,
            "other_id": cal,
            "task_id": task,
            "compensation_id": int(comp.headers["x-recal-compensation"]),
            "token_id": 1,
        }
        routes = _id_routes(c)
        assert len(routes) >= 30, routes  # the sweep sees the routes (about 40 take an id)
        failures = []
        for method, path, path_ids, query_ids in routes:
            for name in path_ids:
                for value in IN_RANGE + OUT_OF_RANGE:
                    r = c.request(method, _fill(path, ids, name, value), headers=h)
                    if value in IN_RANGE:  # names nothing; a missing body may be refused first
                        ok = r.status_code == 404 or (
                            r.status_code == 422 and "path." not in r.text and "body" in r.text
                        )
                    else:
                        ok = r.status_code == 422 and f"path.{name}" in r.text
                    if not ok:
                        failures.append(f"{method} {path} {name}={value}: {r.status_code} {r.text[:160]}")
            for name in query_ids:
                for value in IN_RANGE + OUT_OF_RANGE:
                    r = c.request(method, _fill(path, ids) + f"?{name}={value}", headers=h)
                    ok = (
                        r.status_code == 404
                        if value in IN_RANGE
                        else r.status_code == 422 and f"query.{name}" in r.text
                    )
                    if not ok:
                        failures.append(f"{method} {path}?{name}={value}: {r.status_code} {r.text[:160]}")
        assert not failures, "\n".join(failures)


def test_ids_beyond_32_bits_are_stored_and_served(idle_app, settings, tokens):
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:  # rows as a store that has counted past 2**31 holds them
        db.add(Cell(id=2**40, name="far", model={}, devices={}))
        db.commit()
        db.add(RunSession(id=MAX_ID, cell_id=2**40, kind="pose", state="completed", dry_run=True))
        db.commit()
        db.add(Measurement(session_id=MAX_ID, seq=0, q=[0.0] * 6, x=1.0, y=2.0, z=3.0))
        db.commit()
    engine.dispose()
    with idle_app() as c:
        r = c.get(f"/api/v1/sessions/{MAX_ID}", headers=auth(tokens["viewer"]))
        assert r.status_code == 200 and r.json()["cell_id"] == 2**40, r.text
        assert len(c.get(f"/api/v1/sessions/{MAX_ID}/measurements", headers=auth(tokens["viewer"])).json()) == 1


def _back_to_version_7(conn) -> None:
    """The schema version 7 made on PostgreSQL: 32-bit ids and sequences (SQLite's are the same)."""
    if conn.dialect.name == "postgresql":
        for table, column in _id_columns():
            conn.execute(text(f'ALTER TABLE "{table}" ALTER COLUMN "{column}" TYPE INTEGER'))
            if column == "id":
                seq = conn.execute(text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": f'"{table}"'}).scalar()
                conn.execute(text(f"ALTER SEQUENCE {seq} AS INTEGER"))
    conn.execute(text("UPDATE schema_version SET version = 7"))


def test_version_7_store_gets_64_bit_ids_and_keeps_its_rows(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:
        _back_to_version_7(conn)
    with Session(engine) as db:
        cell = Cell(name="kept", model={"name": "ur5e"}, devices={"tracker": "socket://x"})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="pose", state="completed")
        db.add(run)
        db.commit()
        db.add(Calibration(cell_id=cell.id, session_id=run.id, model={"m": 1}, report={"r": 2}, rms=0.1))
        db.add(Measurement(session_id=run.id, seq=0, q=[0.5] * 6, x=1.0, y=2.0, z=3.0))
        db.commit()
        kept = (cell.id, run.id)
    if engine.dialect.name == "postgresql":  # what version 7 could not hold
        with pytest.raises(Exception, match="out of range"), Session(engine) as db:
            db.add(Cell(id=2**31, name="too far", model={}, devices={}))
            db.commit()
    assert migrate(engine) == SCHEMA_VERSION >= 8
    columns = {t: {c["name"]: c["type"] for c in inspect(engine).get_columns(t)} for t, _ in _id_columns()}
    for table, column in _id_columns():
        kind = str(columns[table][column])
        assert kind == ("BIGINT" if engine.dialect.name == "postgresql" else "INTEGER"), (table, column, kind)
    with engine.begin() as conn:
        if engine.dialect.name == "postgresql":  # the sequences count past 2**31 too
            conn.execute(text("SELECT setval(pg_get_serial_sequence('cell', 'id'), 2147483650)"))
        else:  # SQLite's rowid counts on from the largest
            conn.execute(
                text(
                    "INSERT INTO cell (id, name, site, model, devices, created_at, model_version) "
                    "VALUES (2147483650, 'placeholder', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
                )
            )
    with Session(engine) as db:
        assert (db.get(Cell, kept[0]).name, db.get(Cell, kept[0]).devices) == ("kept", {"tracker": "socket://x"})
        assert db.get(RunSession, kept[1]).cell_id == kept[0]
        cal = db.get(Calibration, 1)
        assert (cal.session_id, cal.model, cal.report, cal.rms) == (kept[1], {"m": 1}, {"r": 2}, 0.1)
        assert db.get(Measurement, 1).q == [0.5] * 6
        new = Cell(name="next", model={}, devices={})
        db.add(new)
        db.commit()
        assert new.id > 2**31
        db.add(RunSession(id=2**40, cell_id=new.id, kind="pose"))
        db.commit()
        assert db.get(RunSession, 2**40).cell_id == new.id
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
