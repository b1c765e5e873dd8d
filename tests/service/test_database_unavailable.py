"""A database that refuses connections (down, or out of them: "too many clients") makes the API
answer ``503`` with ``Retry-After``, a plain message and no traceback in the log, and the
service answers normally again once the database takes connections."""

from __future__ import annotations

import logging

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.pool import NullPool

from calibration.model import model_to_dict
from calibration.robots import nominal

from .conftest import POSTGRES_URL, auth


@pytest.fixture
def admin():
    engine = create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT", poolclass=NullPool)
    yield engine
    engine.dispose()


@pytest.mark.parametrize("database_url", ["postgres"], indirect=True)
def test_a_database_out_of_connections_gives_503_then_recovers(settings, admin, caplog):
    from fastapi.testclient import TestClient
    from sqlmodel import Session

    from service.api.app import create_app
    from service.store import create_token, make_engine

    name = settings.database_url.rpartition("/")[2]
    with TestClient(create_app(settings)) as client:
        engine = make_engine(settings.database_url)
        with Session(engine) as db:
            token = create_token(db, role="technician", name="t")[1]
        engine.dispose()
        assert client.get("/api/v1/cells", headers=auth(token)).status_code == 200

        with admin.connect() as conn:  # no new connections (superusers' neither), and the open ones cut
            conn.execute(text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS false'))
            conn.execute(text(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{name}'"))
        caplog.clear()
        try:
            with caplog.at_level(logging.WARNING):
                r = client.post(
                    "/api/v1/cells", headers=auth(token), json={"name": "c", "model": model_to_dict(nominal("ur5e"))}
                )
                listed = client.get("/api/v1/cells", headers=auth(token))
        finally:
            with admin.connect() as conn:
                conn.execute(text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true'))
        for resp in (r, listed):
            assert resp.status_code == 503, resp.text
            assert resp.headers["retry-after"] == "2"
            assert resp.json()["detail"] == "the database is unavailable or overloaded: try again shortly"
        assert not [rec for rec in caplog.records if rec.exc_info], "a busy database is not a traceback"
        assert any("database unavailable on GET /api/v1/cells" in rec.getMessage() for rec in caplog.records)
        assert client.get("/api/v1/cells", headers=auth(token)).status_code == 200
