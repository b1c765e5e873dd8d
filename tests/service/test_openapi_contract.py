"""The API as documented (issues 12 and 22): a bounded schemathesis run against the service's own
OpenAPI document, every check and every phase (the stateful one included), a fixed seed, zero
failures, on SQLite and on PostgreSQL (whose 32-bit ids once answered 500 where SQLite's did not). The service runs on loopback
(uvicorn in a thread) on a store with one of everything (a cell, a calibrated session, a task
file, a compensation), so that ids 1 (the lowest the schema allows, which schemathesis's
coverage phase tries) reach real resources and their answers are checked against their schemas.

What the schema cannot say: a cell's nominal model (``recal.model/1``, checked by its own
parser: joint counts against regions, known conventions) and a task file's content (and, for a
registered one, whether its name, encoding and other files go together: a KRL .src with its .dat,
ISO-8859-1 for a program only, every character in its encoding). For the
operations that take them, a schema-valid request may be refused with 422 naming the field,
and schemathesis is told so (``positive_data_acceptance``), per operation; every other check
runs everywhere."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlmodel import Session

from .conftest import NoMotion, auth, register_cell

SEED = 1
MAX_EXAMPLES = 10  # about half a minute on a quiet 2-core machine
SEMANTIC_BODIES = (
    "POST /api/v1/cells",
    "PATCH /api/v1/cells/{cell_id}",
    "POST /api/v1/cells/{cell_id}/sessions",
    "POST /api/v1/calibrations/{calibration_id}/compensate",
    "POST /api/v1/calibrations/{calibration_id}/compensate-backup",
    "POST /api/v1/cells/{cell_id}/tasks",
    "POST /api/v1/cells/{cell_id}/measurements",
    "PUT /api/v1/cells/{cell_id}/controller-model",
)

CONFIG = "\n".join(
    f'''
[[operations]]
include-name = "{name}"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "403", "404", "409", "422"]
'''
    for name in SEMANTIC_BODIES
)


@pytest.mark.slow
@pytest.mark.parametrize("database_url", ["sqlite", "postgresql"], indirect=True)
def test_the_api_keeps_its_openapi_contract_under_fuzzing(settings, tmp_path, stored_session):
    import uvicorn
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.processes import free_port
    from service.store import create_token, make_engine, migrate

    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        token = create_token(db, role="admin", name="fuzzer")[1]
        # far from the ids the fuzzer tries (1, the maximum, small randoms): DELETE /tokens/{id}
        # would otherwise revoke the fuzzer's own token half-way
        db.exec(text("UPDATE token SET id = 4611686018427387904 WHERE name = 'fuzzer'"))
        db.commit()
    engine.dispose()
    app = create_app(settings, runner_factory=NoMotion)
    with TestClient(app) as client:  # one of everything, id 1
        cell = register_cell(client, token, "fuzzed")["id"]
        stored_session(cell, seed=2)
        task = "name,q1,q2,q3,q4,q5,q6\nP,10,-80,90,0,90,0\n"
        assert (
            client.post(
                f"/api/v1/cells/{cell}/tasks", json={"name": "t.csv", "content": task}, headers=auth(token)
            ).status_code
            == 201
        )
        assert client.post("/api/v1/calibrations/1/compensate", content=task, headers=auth(token)).status_code == 200
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings, runner_factory=NoMotion),
            host="127.0.0.1",
            port=port,
            log_level="warning",
            access_log=False,
        )
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the service did not start"
        time.sleep(0.02)
    try:
        (tmp_path / "schemathesis.toml").write_text(CONFIG)
        st = Path(sys.executable).with_name("st")
        r = subprocess.run(
            [
                str(st),
                "--config-file",
                str(tmp_path / "schemathesis.toml"),
                "run",
                f"http://127.0.0.1:{port}/openapi.json",
                "--checks",
                "all",
                "--seed",
                str(SEED),
                "--max-examples",
                str(MAX_EXAMPLES),
                "--workers",
                "1",
                "--phases",
                "examples,coverage,fuzzing,stateful",
                "-H",
                f"Authorization: Bearer {token}",
                "--no-color",
            ],
            capture_output=True,
            text=True,
            timeout=600,
            cwd=tmp_path,
        )
    finally:
        server.should_exit = True
        thread.join(10)
    assert r.returncode == 0, r.stdout[-8000:] + r.stderr[-2000:]  # st exits 1 on any failure
    import re

    assert re.search(r"Operations:\s+(\d+) selected / \1 total", r.stdout), r.stdout[:2000]  # every operation
