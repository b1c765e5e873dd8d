"""``recal backup --out FILE``: a consistent copy of the embedded store while the service runs.

SQLite's online backup API (``sqlite3.Connection.backup``) copies the database page by page
under its own locks, so sessions may keep committing measurements meanwhile and the copy is a
consistent snapshot (a plain file copy of a WAL database is not: the newest pages may still be
in ``recal.db-wal``). The copy is written next to ``FILE`` and renamed into place, so a failed
backup never leaves a partial file. A PostgreSQL store is backed up with ``pg_dump``
(docs/service.md, "Backup and retention"); this verb says so and exits 2.
"""

from __future__ import annotations

import os
import sqlite3
import tempfile
from pathlib import Path


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
    try:
        pages = backup_sqlite(source, out)
    except sqlite3.Error as exc:
        raise Fail(f"{source}: cannot back it up: {exc}") from None
    print(f"recal backup: {source} -> {out} ({pages} pages, {out.stat().st_size} bytes)")
    return 0


def backup_sqlite(source: Path, out: Path) -> int:
    """Copy the SQLite database ``source`` to ``out`` with the online backup API (a temporary
    file renamed into place); returns the number of pages copied."""
    fd, tmp = tempfile.mkstemp(dir=out.parent if str(out.parent) else ".", prefix=f".{out.name}.", suffix=".tmp")
    os.close(fd)
    try:
        src = sqlite3.connect(source, timeout=30)
        dst = sqlite3.connect(tmp)
        try:
            # 1024 pages a step: other connections (the service committing) get the lock between steps
            src.backup(dst, pages=1024)
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
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
