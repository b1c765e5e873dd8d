"""Make the repository importable when the project is not installed (``pip install -e .``), and
the fixtures every test folder shares."""

import importlib.util
import os
import sys
import uuid
from pathlib import Path

import pytest

if importlib.util.find_spec("drivers") is None or importlib.util.find_spec("fakes") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
# pytest runs with --import-mode=importlib, which puts no test folder on sys.path: this one goes
# there so that test modules of every folder can import the contract suites written once here
# (runner_contract).
_TESTS = str(Path(__file__).resolve().parent)
if _TESTS not in sys.path:
    sys.path.insert(0, _TESTS)

# `make test` runs the suite in two pytest-xdist workers (the simulated cells and services mostly
# wait on sockets and simulated time, so two workers use both cores). Each worker gets its own
# loopback network for its simulated cells (RECAL_TEST_NET, read by the folders' conftests), so
# that the two never take each other's addresses; PostgreSQL databases are unique per test anyway.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw"):
    _a, _b, _c = os.environ.get("RECAL_TEST_NET", "127.0.0").split(".")
    os.environ["RECAL_TEST_NET"] = f"{_a}.{_b}.{(int(_c) + 100 + int(_WORKER[2:])) % 256}"

POSTGRES_URL = os.environ.get("RECAL_TEST_POSTGRES_URL")


class PostgresDatabases:
    """Creates empty PostgreSQL databases beside ``RECAL_TEST_POSTGRES_URL`` and drops them."""

    def __init__(self, url: str):
        self.url = url

    def _admin(self):
        from sqlalchemy import create_engine
        from sqlalchemy.pool import NullPool

        # no pool: a test may restart the server, and the drop at the end must still get through
        return create_engine(self.url, isolation_level="AUTOCOMMIT", poolclass=NullPool)

    def create(self, prefix: str = "recal_test") -> tuple[str, str]:
        """A new empty database: its name and its URL."""
        from sqlalchemy import text

        name = f"{prefix}_{uuid.uuid4().hex[:12]}"
        admin = self._admin()
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
        admin.dispose()
        return name, f"{self.url.rpartition('/')[0]}/{name}"

    def drop(self, name: str) -> None:
        """Drop ``name``, ending the sessions still connected to it."""
        from sqlalchemy import text

        admin = self._admin()
        with admin.connect() as conn:
            conn.execute(text(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{name}'"))
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}"'))
        admin.dispose()


@pytest.fixture(scope="session")
def postgres_databases() -> PostgresDatabases:
    """PostgreSQL databases for tests that need them; skipped, with the reason, without one."""
    if not POSTGRES_URL:
        pytest.skip("PostgreSQL tests need RECAL_TEST_POSTGRES_URL (.ci/run sets it)")
    return PostgresDatabases(POSTGRES_URL)
