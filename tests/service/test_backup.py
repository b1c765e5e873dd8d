"""``recal backup``: a consistent copy of the embedded SQLite store while the service writes to
it (SQLite's online backup API); a PostgreSQL store is pointed to pg_dump."""

from __future__ import annotations

import sqlite3
import threading

from sqlmodel import Session

from service.cli import main as recal
from service.models import Token
from service.settings import Settings
from service.store import create_token, make_engine, migrate


def test_backup_copies_the_store_while_it_is_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RECAL_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("RECAL_DATABASE_URL", raising=False)
    engine = make_engine(Settings.from_env().effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        for i in range(50):
            create_token(db, role="viewer", name=f"before-{i}")
    stop = threading.Event()

    def writer():  # the service keeps committing during the backup (WAL: newest pages in recal.db-wal)
        with Session(engine) as db:
            i = 0
            while not stop.is_set():
                create_token(db, role="viewer", name=f"during-{i}")
                i += 1

    t = threading.Thread(target=writer)
    t.start()
    try:
        out = tmp_path / "backup" / "recal-copy.db"
        out.parent.mkdir()
        assert recal(["backup", "--out", str(out)]) == 0, capsys.readouterr().err
    finally:
        stop.set()
        t.join()
        engine.dispose()
    assert "recal backup:" in capsys.readouterr().out
    copy = sqlite3.connect(out)
    assert copy.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    names = {r[0] for r in copy.execute(f"SELECT name FROM {Token.__tablename__}")}
    assert {f"before-{i}" for i in range(50)} <= names  # everything committed before the backup
    assert copy.execute("PRAGMA journal_mode").fetchone()[0] == "delete"  # one self-contained file
    copy.close()
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temporary file left


def test_backup_of_a_postgresql_store_points_to_pg_dump(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RECAL_DATABASE_URL", "postgresql+psycopg://recal:secret@db:5432/recal")
    out = tmp_path / "copy.db"
    assert recal(["backup", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pg_dump" in err and "secret" not in err and err.count("\n") == 1
    assert not out.exists()


def test_backup_without_a_database_says_where_it_looked(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RECAL_HOME", str(tmp_path / "empty"))
    monkeypatch.delenv("RECAL_DATABASE_URL", raising=False)
    assert recal(["backup", "--out", str(tmp_path / "copy.db")]) == 2
    err = capsys.readouterr().err
    assert "no database" in err and str(tmp_path / "empty") in err
