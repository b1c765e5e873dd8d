"""Stored text that cannot be read is found when the service starts and repaired by a documented
command; the audit log can be paged and pruned by an admin (issue 22, case 1). The bad row is
written straight into the store, as a PATCH that answered 500 once kept it (SQLite keeps JSON's
"\\ud800" escaped; PostgreSQL refuses it, so it cannot hold one)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlmodel import Session

from calibration.robots import nominal_document
from service.api.app import create_app
from service.models import AuditEntry, Cell, Token
from service.store import make_engine, migrate
from service.textrepair import unreadable_text

from .conftest import auth

RECAL = str(Path(sys.executable).with_name("recal"))


def _poison(settings) -> int:
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    model = nominal_document("ur5e")
    model["name"] = "ur\ud800x"
    with Session(engine) as db:
        cell = Cell(name="poisoned", model=model, devices={})
        db.add(cell)
        db.add(AuditEntry(actor="a", action="update cell", subject="cell", detail={"model": model}))
        db.commit()
        cid = int(cell.id)
    engine.dispose()
    return cid


def _repair(settings, *args):
    env = {**os.environ, "RECAL_DATABASE_URL": settings.effective_database_url, "RECAL_HOME": str(settings.home)}
    return subprocess.run([RECAL, "repair-text", *args], capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_unreadable_text_is_reported_at_start_and_repaired_by_recal_repair_text(settings, tokens, caplog):
    cid = _poison(settings)
    with (
        caplog.at_level(logging.ERROR, logger="recal.api"),
        TestClient(create_app(settings), raise_server_exceptions=False) as client,
    ):
        assert client.get("/api/v1/cells", headers=auth(tokens["viewer"])).status_code == 500  # what it broke
    reported = [r.getMessage() for r in caplog.records if "cannot be read" in r.getMessage()]
    assert reported and f"cell {cid} model.name" in reported[0] and "recal repair-text" in reported[0], reported

    check = _repair(settings, "--check")
    assert check.returncode == 3, check.stdout + check.stderr
    assert f"cell {cid}: model.name: expected text (UTF-8)" in check.stdout and "audit" in check.stdout, check.stdout
    done = _repair(settings)
    assert done.returncode == 0 and "repaired 2 stored value(s)" in done.stdout, done.stdout + done.stderr
    assert _repair(settings, "--check").returncode == 0

    with TestClient(create_app(settings)) as client:
        for role in ("viewer", "admin"):
            assert client.get("/api/v1/cells", headers=auth(tokens[role])).status_code == 200
        cell = client.get(f"/api/v1/cells/{cid}", headers=auth(tokens["viewer"])).json()
        assert cell["model"]["name"] == "ur\ufffdx"
        audit = client.get("/api/v1/audit", headers=auth(tokens["admin"]))
        assert audit.status_code == 200, audit.text
        assert audit.json()[0]["action"] == "repair text"


def test_the_start_up_scan_reads_only_what_could_be_unreadable(settings):
    """The scan runs at every start, so the database picks the candidate rows: a valid pair (an
    emoji, kept as two escapes), a long name and a thousand clean audit entries are not reported
    (a long name is readable); a NUL in an audit entry's detail is, on both databases (JSON keeps
    it as an escape), and a NUL in a plain text column where the database can hold one (SQLite)."""
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    model = nominal_document("ur5e")
    model["name"] = "ur \U0001f916 " + "x" * 300
    sqlite = engine.dialect.name == "sqlite"
    with Session(engine) as db:
        db.add(Cell(name="clean", model=model, devices={}))
        db.add_all(AuditEntry(actor="a", action="create token", subject=f"token {i}") for i in range(1000))
        bad = AuditEntry(actor="a", action="note", subject="x", detail={"note": ["ok", "nul\x00here"]})
        db.add(bad)
        token = Token(name="with\x00nul", role="viewer", hash="h" * 64)
        if sqlite:
            db.add(token)
        db.commit()
        found = unreadable_text(db)
        expected = [("audit", bad.id, "detail.note[1]")]
        if sqlite:
            expected.append(("token", token.id, "name"))
    engine.dispose()
    assert sorted((f["table"], f["id"], f["field"]) for f in found) == sorted(expected), found
    assert all("NUL" in f["message"] for f in found)


def test_the_audit_log_is_paged_and_pruned_by_an_admin(settings, tokens):
    with TestClient(create_app(settings)) as client:
        admin = auth(tokens["admin"])
        for i in range(5):
            r = client.post("/api/v1/tokens", json={"role": "viewer", "name": f"t{i}"}, headers=admin)
            assert r.status_code in (200, 201), r.text
        first = client.get("/api/v1/audit?limit=2", headers=admin).json()
        second = client.get(f"/api/v1/audit?limit=2&older_than={first[-1]['id']}", headers=admin).json()
        assert len(first) == len(second) == 2 and first[-1]["id"] > second[0]["id"] > second[1]["id"]
        every = client.get("/api/v1/audit?limit=5000", headers=admin).json()
        assert [e["id"] for e in every[:4]] == [e["id"] for e in first + second]
        future = (datetime.now(UTC) + timedelta(minutes=1)).isoformat()
        for role in ("viewer", "technician", "job"):
            r = client.delete("/api/v1/audit", params={"before": future}, headers=auth(tokens[role]))
            assert r.status_code == 403, r.text
        r = client.delete("/api/v1/audit", params={"before": future}, headers=admin)
        assert r.status_code == 200 and r.json()["deleted"] == len(every), r.text
        left = client.get("/api/v1/audit", headers=admin).json()
        assert [e["action"] for e in left] == ["prune audit"] and left[0]["detail"]["deleted"] == len(every)
