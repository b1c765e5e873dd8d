"""``recal backup``: a consistent copy of the embedded SQLite store while the service writes to
it (SQLite's online backup API); a PostgreSQL store is pointed to pg_dump."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

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


def _source_store(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("RECAL_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("RECAL_DATABASE_URL", raising=False)
    engine = make_engine(Settings.from_env().effective_database_url)
    migrate(engine)
    engine.dispose()


def test_the_next_backup_removes_what_a_killed_one_left_and_no_more(tmp_path, monkeypatch, capsys):
    import fcntl

    _source_store(tmp_path, monkeypatch)
    d = tmp_path / "backup"
    d.mkdir()
    out = d / "recal-2026-11-28.db"
    # what a backup killed by SIGKILL leaves (tempfile's names, and SQLite's journal beside the copy)
    left = [".recal-2026-11-28.db.k1l2e3d4.tmp", ".recal-2026-11-28.db.k1l2e3d4.tmp-journal"]
    orphan = ".recal-2026-11-28.db.gone0000.tmp-journal"
    running = d / ".recal-2026-11-28.db.running1.tmp"  # a backup to the same file under way: its lock held
    yesterday = ".recal-2026-11-27.db.y1e2s3t4.tmp"  # a killed backup of another day, still empty
    # not ours: not named as our copies, or not a SQLite database
    others = [".recal-2026-11-27.db.x1y2z3w4.tmp", "recal-2026-11-27.db", "notes.tmp", ".a.tmp", ".b.db.longer123.tmp"]
    for name in [*left, orphan, running.name, *others]:
        (d / name).write_bytes(
            b"SQLite format 3\x00" + b"x" * 4096 if ".tmp" in name and "x1y2" not in name else b"x" * 4096
        )
    (d / yesterday).write_bytes(b"")
    fd = os.open(running, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        assert recal(["backup", "--out", str(out)]) == 0, capsys.readouterr().err
    finally:
        os.close(fd)
    printed = capsys.readouterr().out
    assert "removed 4 files an interrupted backup left" in printed
    assert all(n in printed for n in [*left, orphan, yesterday])
    assert sorted(p.name for p in d.iterdir()) == sorted([out.name, running.name, *others])


def test_a_backup_stopped_by_sigterm_leaves_no_temporary_file(tmp_path, monkeypatch):
    _source_store(tmp_path, monkeypatch)
    db = tmp_path / "home" / "recal.db"
    locker = sqlite3.connect(db, timeout=0)  # the source held exclusively: the backup waits for it
    locker.execute("PRAGMA journal_mode=DELETE")
    locker.execute("BEGIN EXCLUSIVE")
    d = tmp_path / "backup"
    d.mkdir()
    recal_exe = Path(sys.executable).parent / "recal"
    proc = subprocess.Popen([recal_exe, "backup", "--out", str(d / "copy.db")], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not list(d.glob(".copy.db.*.tmp")):  # the backup has begun its copy
            assert proc.poll() is None and time.monotonic() < deadline, "the backup did not start"
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        locker.rollback()
        locker.close()
    assert "stopped by SIGTERM" in proc.stderr.read()
    assert list(d.iterdir()) == []
