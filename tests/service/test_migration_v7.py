"""Schema version 7 on a store made by version 6: compensations and task files get their
``encoding`` (every existing row UTF-8, as it was served) and task files their other ``files``
(none); what was stored reads and is served as before, and a new row keeps ISO-8859-1."""

from __future__ import annotations

from sqlalchemy import inspect, text
from sqlmodel import Session

from service.models import Compensation, TaskFile
from service.store import SCHEMA_VERSION, make_engine, migrate
from service.tasks import read_task, task_input

V7_COLUMNS = [("compensation", "encoding"), ("taskfile", "encoding"), ("taskfile", "files")]


def test_version_6_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 6 made, with a task file and a compensation
        for table, column in V7_COLUMNS:
            conn.execute(text(f"ALTER TABLE {table} DROP COLUMN {column}"))
        conn.execute(text("UPDATE schema_version SET version = 6"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at, model_version) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO taskfile (cell_id, name, content, mode, created_at) "
                "VALUES (1, 'm.mod', 'MODULE m\n! Düse\nENDMODULE\n', 'joints', CURRENT_TIMESTAMP)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO session (cell_id, kind, state, planned, device, dry_run, created_by, "
                "created_at, updated_at, beam_recoveries) VALUES (1, 'pose', 'completed', 5, 'tracker', false, '', "
                "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP, 0)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO calibration (cell_id, session_id, kind, model, report, created_at, nominal_version) "
                "VALUES (1, 1, 'pose', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO compensation (calibration_id, name, mode, output, created_by, created_at) "
                "VALUES (1, 'm.mod', 'joints', 'MODULE m\n! Düse\nENDMODULE\n', '', CURRENT_TIMESTAMP)"
            )
        )
    assert migrate(engine) == SCHEMA_VERSION >= 7
    for table, column in V7_COLUMNS:
        assert column in {c["name"] for c in inspect(engine).get_columns(table)}
    with Session(engine) as db:
        assert db.get(Compensation, 1).encoding == "utf-8"
        stored = read_task(db, 1, 1)
        assert (stored["encoding"], stored["files"]) == ("utf-8", [])
        assert task_input(db, 1) == {
            "text": "MODULE m\n! Düse\nENDMODULE\n",
            "companions": None,
            "encodings": {"m.mod": "utf-8"},
        }
        # a new row keeps a program that is not UTF-8 as a character per byte
        latin1 = "MODULE m\n! D\xfcse \x96\nENDMODULE\n"
        db.add(Compensation(calibration_id=1, name="n.mod", output=latin1, encoding="iso-8859-1"))
        db.add(
            TaskFile(
                cell_id=1,
                name="job.src",
                content=latin1,
                encoding="iso-8859-1",
                files=[{"name": "job.dat", "content": latin1, "encoding": "iso-8859-1"}],
            )
        )
        db.commit()
    with Session(engine) as db:
        rec = db.get(Compensation, 2)
        assert rec.output.encode(rec.encoding) == b"MODULE m\n! D\xfcse \x96\nENDMODULE\n"
        assert task_input(db, 2)["encodings"] == {"job.src": "iso-8859-1", "job.dat": "iso-8859-1"}
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
