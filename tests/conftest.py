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
# wait on sockets and simulated time, so two workers use both cores). RECAL_TEST_NET is the first
# three octets of the loopback network of the simulated cells (default 127.0.0; each test picks
# the fourth; read by the folders' conftests). A run in one process (the serial run too) uses it as
# it is; worker gwN adds 100 + N to its THIRD octet (mod 256): by default gw0 has 127.0.100.x and
# gw1 127.0.101.x, so the two never take each other's addresses. Two `make test` runs on one
# machine need third octets at least 2 apart. PostgreSQL databases are unique per test anyway.


def worker_net(net: str, worker: str) -> str:
    """The loopback network (three octets) of pytest-xdist worker ``worker`` (``gw0``, ``gw1``,
    ...; ``""`` outside xdist) for RECAL_TEST_NET ``net``.

    >>> worker_net("127.0.0", "gw1"), worker_net("127.0.80", "gw0"), worker_net("127.0.80", "")
    ('127.0.101', '127.0.180', '127.0.80')
    """
    if not worker.startswith("gw"):
        return net
    a, b, c = net.split(".")
    return f"{a}.{b}.{(int(c) + 100 + int(worker[2:])) % 256}"


os.environ["RECAL_TEST_NET"] = worker_net(
    os.environ.get("RECAL_TEST_NET", "127.0.0"), os.environ.get("PYTEST_XDIST_WORKER", "")
)

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
