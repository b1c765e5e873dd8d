"""``recal backup --out FILE``: a consistent copy of the embedded store while the service runs.

SQLite's online backup API (``sqlite3.Connection.backup``) copies the database page by page
under its own locks, so sessions may keep committing measurements meanwhile and the copy is a
consistent snapshot (a plain file copy of a WAL database is not: the newest pages may still be
in ``recal.db-wal``). The copy is written next to ``FILE`` (``.FILE.XXXXXXXX.tmp``, and SQLite's
``-journal`` beside it while it is written) and renamed into place, so a failed backup never
leaves a partial file: an error, Ctrl-C, SIGTERM or SIGHUP removes the temporary files, and
those a killed backup (SIGKILL, a power loss) left are removed by the next backup into the same
directory (each is locked while its backup runs, so a backup under way keeps its own). A PostgreSQL store is backed up with ``pg_dump``
(docs/service.md, "Backup and retention"); this verb says so and exits 2.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import sqlite3
import sys
import tempfile
from pathlib import Path

# What SQLite may write beside a database file while it is written (the temporary copy's too).
SQLITE_COMPANIONS = ("-journal", "-wal", "-shm")


def add_parser(s) -> None:
    s.add_argument("--out", required=True, help="file to write the copy of the database to (SQLite)")


def run(args) -> int:
    from sqlalchemy.engine import make_url

    from service.cli import Fail
    from service.files import check_output
    from service.settings import Settings

    settings = Settings.from_env()
    url = make_url(settings.effective_database_url)
    if not url.drivername.startswith("sqlite"):
        raise Fail(
            f"the store is {url.drivername.split('+')[0]} ({url.render_as_string(hide_password=True)}): back it "
            f"up with pg_dump (docs/service.md, 'Backup and retention'); recal backup copies the embedded "
            f"SQLite store"
        )
    source = Path(url.database or "")
    if not source.is_file():
        raise Fail(f"no database at {source} (RECAL_HOME={settings.home}); expected the service's recal.db")
    out = Path(args.out)
    check_output(out)
    if out.resolve() == source.resolve():
        raise Fail(f"--out {out}: that is the database itself; expected another file")
    stale = remove_stale_temporaries(out)
    if stale:
        print(f"recal backup: removed {len(stale)} files an interrupted backup left: {', '.join(stale)}")
    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        pages = backup_sqlite(source, out)
    except sqlite3.Error as exc:
        raise Fail(f"{source}: cannot back it up: {exc}") from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"recal backup: {source} -> {out} ({pages} pages, {out.stat().st_size} bytes)")
    return 0


def _stop(signum, _frame) -> None:
    """SIGTERM or SIGHUP during a backup: stop it as Ctrl-C does, so its temporary files go."""
    print(f"recal backup: stopped by {signal.Signals(signum).name}; no copy written", file=sys.stderr)
    raise SystemExit(128 + signum)


# A backup's temporary copy: ``.NAME.XXXXXXXX.tmp`` (tempfile's eight characters), for any NAME:
# the copies are usually dated, so the next backup is to another name than the killed one's.
TEMPORARY = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")


def _temporaries(out: Path) -> list[Path]:
    """The backups' temporary copies beside ``out``: named as ours and SQLite databases (or still
    empty: killed before the first page), never another program's file."""
    found = []
    for p in sorted(out.parent.iterdir()):
        if TEMPORARY.match(p.name) and p.is_file():
            with open(p, "rb") as f:
                head = f.read(16)
            if head in (b"", b"SQLite format 3\x00"):
                found.append(p)
    return found


def _remove(path: Path) -> list[str]:
    """Remove ``path`` and what SQLite wrote beside it; the names removed."""
    removed = []
    for p in [path, *(Path(f"{path}{suffix}") for suffix in SQLITE_COMPANIONS)]:
        try:
            p.unlink()
            removed.append(p.name)
        except FileNotFoundError:
            pass
    return removed


def remove_stale_temporaries(out: Path) -> list[str]:
    """Remove the temporary files backups beside ``out`` left when they were killed
    (``.NAME.XXXXXXXX.tmp`` and their journals), but not those of a backup still running (it
    holds a lock on its file); the names removed."""
    removed = []
    for tmp in _temporaries(out):
        try:
            fd = os.open(tmp, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue  # a backup under way
        try:
            removed += _remove(tmp)
        finally:
            os.close(fd)
    for suffix in SQLITE_COMPANIONS:  # journals whose temporary file is gone
        for orphan in out.parent.glob(f".*.tmp{suffix}"):
            base = Path(str(orphan)[: -len(suffix)])
            if TEMPORARY.match(base.name) and not base.exists():
                removed += _remove(orphan)
    return removed


def backup_sqlite(source: Path, out: Path) -> int:
    """Copy the SQLite database ``source`` to ``out`` with the online backup API (a temporary
    file renamed into place); returns the number of pages copied."""
    fd, tmp = tempfile.mkstemp(dir=out.parent if str(out.parent) else ".", prefix=f".{out.name}.", suffix=".tmp")
    # Held until the end: the next backup removes this file only if nothing holds it (a BSD lock,
    # apart from SQLite's own POSIX locks on the same file).
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        # A step that cannot read waits at most 1 s in SQLite (then the backup loop waits and tries
        # again, as long as it takes): a signal is handled between tries, not 30 s later.
        src = sqlite3.connect(source, timeout=1)
        dst = sqlite3.connect(tmp)
        try:
            # 1024 pages a step: other connections (the service committing) get the lock between
            # steps; the progress callback gives a signal (SIGTERM) its turn between them too
            src.backup(dst, pages=1024, progress=lambda *_: None)
            pages = dst.execute("PRAGMA page_count").fetchone()[0]
            dst.execute("PRAGMA journal_mode=DELETE")  # a single self-contained file
            ok = dst.execute("PRAGMA integrity_check").fetchone()[0]
        finally:
            dst.close()
            src.close()
        if ok != "ok":
            raise sqlite3.DatabaseError(f"the copy failed its integrity check: {ok}")
        os.replace(tmp, out)
        return int(pages)
    except BaseException:
        _remove(Path(tmp))
        raise
    finally:
        os.close(fd)
