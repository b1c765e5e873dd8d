"""Fixtures for the service: an app on a fresh database (SQLite file, or PostgreSQL when
RECAL_TEST_POSTGRES_URL is set), tokens of every role."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text
from sqlmodel import Session

from service.settings import Settings
from service.store import create_token, make_engine, migrate

POSTGRES_URL = os.environ.get("RECAL_TEST_POSTGRES_URL")


@pytest.fixture(params=["sqlite", "postgres"])
def database_url(request, tmp_path: Path):
    """A fresh, empty database for one test."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'recal.db'}"
        return
    if not POSTGRES_URL:
        pytest.skip("PostgreSQL tests need RECAL_TEST_POSTGRES_URL (.ci/run sets it)")
    name = f"recal_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    base, _, _ = POSTGRES_URL.rpartition("/")
    try:
        yield f"{base}/{name}"
    finally:
        with admin.connect() as conn:
            conn.execute(text(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{name}'"))
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}"'))
        admin.dispose()


@pytest.fixture
def settings(database_url, tmp_path) -> Settings:
    return Settings(home=tmp_path, database_url=database_url, settle_s=0.0, retry_backoff_s=0.01, device_retries=1,
                    device_timeout_s=5.0)


@pytest.fixture
def tokens(settings) -> dict[str, str]:
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    out = {}
    with Session(engine) as db:
        for role in ("viewer", "technician", "job", "admin"):
            out[role] = create_token(db, role=role, name=f"{role}-user")[1]
    engine.dispose()
    return out


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}
