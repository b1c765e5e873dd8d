"""A cell's records: a session's measurements as the CSV `recal identify` reads, externally
measured CSVs imported into a cell's history, and the admin's audited deletion of sessions and
cells (issue 12, operations)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from sqlmodel import Session, select

from service.models import AuditEntry, Calibration, Measurement, RunSession
from service.store import make_engine

from .conftest import auth, register_cell


@pytest.fixture
def app(idle_app, tokens):
    with idle_app() as client:
        yield client


def _csv(client, token, session_id) -> str:
    r = client.get(f"/api/v1/sessions/{session_id}/measurements.csv", headers=auth(token))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/csv")
    return r.text


def test_session_measurements_as_csv_are_what_recal_identify_reads(app, tokens, stored_session, settings, tmp_path):
    cell = register_cell(app, tokens["technician"], "c1")
    sid, cal_id = stored_session(cell["id"], n=30)
    text = _csv(app, tokens["viewer"], sid)
    (tmp_path / "meas.csv").write_text(text)
    (tmp_path / "nominal.json").write_text(json.dumps(cell["model"]))
    # the CSV, in the cell's units (mm, deg), has the stored values
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        rows = db.exec(select(Measurement).where(Measurement.session_id == sid).order_by(Measurement.seq)).all()
    engine.dispose()
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    assert header[:9] == ["q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z"] and "target" in header
    first = dict(zip(header, lines[1].split(",")))
    assert float(first["x"]) == pytest.approx(rows[0].x * 1e3, rel=1e-9)
    assert float(first["q2"]) == pytest.approx(np.degrees(rows[0].q[1]), rel=1e-9)
    assert float(first["sigma"]) == pytest.approx(0.02) and first["target"] == "smr"
    # and `recal identify` identifies the same robot from it as the service did
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "identify",
            "--model",
            str(tmp_path / "nominal.json"),
            "--data",
            str(tmp_path / "meas.csv"),
            "--out",
            str(tmp_path / "cal.json"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    cal = app.get(f"/api/v1/calibrations/{cal_id}", headers=auth(tokens["viewer"])).json()
    assert json.loads((tmp_path / "cal.json").read_text())["identification"]["residuals"]["rms"] == pytest.approx(
        cal["report"]["residuals"]["rms"], rel=0.05
    )


def test_an_external_csv_imported_into_a_cell_becomes_a_calibration_in_its_history(app, tokens, stored_session):
    source = register_cell(app, tokens["technician"], "measured-elsewhere")
    sid, _ = stored_session(source["id"], n=30)
    text = _csv(app, tokens["viewer"], sid)
    cell = register_cell(app, tokens["technician"], "c2")
    r = app.post(
        f"/api/v1/cells/{cell['id']}/measurements?kind=pose&name=tracker-2024.csv",
        content=text,
        headers={**auth(tokens["technician"]), "Content-Type": "text/csv"},
    )
    assert r.status_code == 201, r.text
    s = r.json()
    assert s["state"] == "completed" and s["measured"] == 30 and s["calibration_id"] is not None
    assert s["plan_info"]["imported"] == {"name": "tracker-2024.csv", "rows": 30}
    cals = app.get(f"/api/v1/cells/{cell['id']}/calibrations", headers=auth(tokens["viewer"])).json()
    assert [c["id"] for c in cals] == [s["calibration_id"]]
    cal = app.get(f"/api/v1/calibrations/{s['calibration_id']}", headers=auth(tokens["viewer"])).json()
    assert cal["report"]["residuals"]["rms"] < 0.06  # mm: the simulated tracker's noise
    # verify: the imported calibration checked against more external data
    v = app.post(
        f"/api/v1/cells/{cell['id']}/measurements?kind=verify", content=text, headers=auth(tokens["technician"])
    ).json()
    assert v["kind"] == "verify" and v["plan_info"]["verify"]["rms"] < 0.06


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda ln: ln.replace(ln.split(",")[6], "abc", 1), "row 3 (line 5), column 'x': expected a number"),
        (lambda ln: ",".join(["5000"] + ln.split(",")[1:]), "row 3 (line 5), column 'q1': 5000 is outside joint"),
    ],
)
def test_a_bad_imported_row_is_422_naming_row_and_column_and_stores_nothing(app, tokens, stored_session, edit, message):
    cell = register_cell(app, tokens["technician"], "c3")
    sid, _ = stored_session(cell["id"], n=20)
    lines = _csv(app, tokens["viewer"], sid).splitlines()
    lines[4] = edit(lines[4])  # comment, header, rows 1, 2, 3
    r = app.post(
        f"/api/v1/cells/{cell['id']}/measurements?name=bad.csv",
        content="\n".join(lines) + "\n",
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 422 and "bad.csv" in r.text and message in r.text, r.text
    sessions = app.get(f"/api/v1/cells/{cell['id']}/sessions", headers=auth(tokens["viewer"])).json()
    assert [s["id"] for s in sessions] == [sid]


def test_only_an_admin_deletes_and_each_deletion_is_audited(app, tokens, stored_session, settings):
    cell = register_cell(app, tokens["technician"], "c4")
    pose_id, cal_id = stored_session(cell["id"], n=30)
    verify_id, _ = stored_session(cell["id"], kind="verify", n=10, seed=2)
    for role in ("viewer", "technician", "job"):
        assert app.delete(f"/api/v1/sessions/{verify_id}", headers=auth(tokens[role])).status_code == 403
        assert app.delete(f"/api/v1/cells/{cell['id']}", headers=auth(tokens[role])).status_code == 403
    admin = auth(tokens["admin"])
    # the session a calibration was identified from keeps its measurements as long as the calibration
    r = app.delete(f"/api/v1/sessions/{pose_id}", headers=admin)
    assert r.status_code == 409 and f"calibration {cal_id}" in r.json()["detail"]
    r = app.delete(f"/api/v1/sessions/{verify_id}", headers=admin)
    assert r.status_code == 200 and r.json()["measurements"] == 10
    assert app.get(f"/api/v1/sessions/{verify_id}", headers=admin).status_code == 404
    assert app.delete(f"/api/v1/sessions/{verify_id}", headers=admin).status_code == 404
    r = app.delete(f"/api/v1/cells/{cell['id']}", headers=admin)
    assert r.status_code == 200, r.text
    assert r.json() | {} == {
        "deleted": f"cell {cell['id']}",
        "name": "c4",
        "sessions": 1,
        "calibrations": 1,
        "measurements": 30,
        "task_files": 0,
    }
    assert app.get(f"/api/v1/cells/{cell['id']}", headers=admin).status_code == 404
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        assert db.exec(select(Measurement)).all() == [] and db.exec(select(Calibration)).all() == []
        assert db.exec(select(RunSession)).all() == []
        entries = {(e.action, e.subject): e for e in db.exec(select(AuditEntry)).all()}
    engine.dispose()
    assert entries[("delete session", f"session {verify_id}")].actor == "admin-user"
    assert entries[("delete cell", f"cell {cell['id']}")].detail["measurements"] == 30


def test_a_cell_with_a_session_under_way_is_not_deleted(app, tokens):
    cell = register_cell(app, tokens["technician"], "c5")
    s = app.post(
        f"/api/v1/cells/{cell['id']}/sessions",
        json={"kind": "pose", "count": 30, "dry_run": True},
        headers=auth(tokens["technician"]),
    ).json()  # stays planned: the app's sessions never run
    assert s["state"] == "planned", s
    r = app.delete(f"/api/v1/cells/{cell['id']}", headers=auth(tokens["admin"]))
    assert r.status_code == 409 and f"session {s['id']}" in r.json()["detail"]
    assert app.delete(f"/api/v1/sessions/{s['id']}", headers=auth(tokens["admin"])).status_code == 409
