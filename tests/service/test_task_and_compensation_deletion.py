"""Task files and compensations can be deleted, by the roles that may (audited), and a task file
that fails no longer stops the cell's other files from being compensated again (issue 22, case
3: a task CSV with a bare CR made /cells/{id}/tasks/compensate answer 500 for the whole cell,
and nothing could delete the file)."""

from __future__ import annotations

from sqlmodel import Session, select

from calibration.model import model_from_dict
from service.models import AuditEntry, TaskFile
from service.store import make_engine

from .conftest import auth
from .test_compensate_api import _task


def _register(client, token, cell, name, content):
    r = client.post(f"/api/v1/cells/{cell}/tasks", json={"name": name, "content": content}, headers=auth(token))
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _bare_cr(task: str) -> str:
    """The task with its second and third rows separated by a lone CR inside a LF file."""
    lines = task.splitlines()
    return "\n".join(lines[:2]) + "\n" + lines[2] + "\r" + "\n".join(lines[3:]) + "\n"


def _stored_before_the_check(settings, cell: int, name: str, content: str) -> int:
    engine = make_engine(settings.effective_database_url)
    try:
        with Session(engine) as db:
            t = TaskFile(cell_id=cell, name=name, content=content, mode="joints", encoding="utf-8")
            db.add(t)
            db.commit()
            return int(t.id)
    finally:
        engine.dispose()


def test_a_failing_task_file_is_reported_beside_the_others_and_can_be_deleted(calibrated, tokens, settings):
    client, cell, cal = calibrated
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    task, _, _ = _task(model)
    tech = tokens["technician"]
    # registration now refuses it (the reader the compensation uses, at the door) ...
    r = client.post(
        f"/api/v1/cells/{cell}/tasks", json={"name": "bare-cr.csv", "content": _bare_cr(task)}, headers=auth(tech)
    )
    assert r.status_code == 422 and "carriage return (CR) alone" in r.text, r.text
    # ... but a store may keep one registered before it did: stored as such a registration stored it
    bad = _stored_before_the_check(settings, cell, "bare-cr.csv", _bare_cr(task))
    good = _register(client, tech, cell, "weld.csv", task)
    r = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    by_id = {t["task_id"]: t for t in r.json()["tasks"]}
    assert set(by_id) == {bad, good}
    assert "error" in by_id[bad] and by_id[bad]["name"] == "bare-cr.csv" and by_id[bad]["error"]
    assert by_id[good]["summary"]["converged"] == 8 and "error" not in by_id[good]
    # the bad file is deleted (by a role that registers task files), then every file compensates
    for role in ("viewer", "job"):
        assert client.delete(f"/api/v1/cells/{cell}/tasks/{bad}", headers=auth(tokens[role])).status_code == 403
    r = client.delete(f"/api/v1/cells/{cell}/tasks/{bad}", headers=auth(tech))
    assert r.status_code == 200 and r.json()["deleted"] == f"task file {bad}", r.text
    assert client.delete(f"/api/v1/cells/{cell}/tasks/{bad}", headers=auth(tech)).status_code == 404
    assert client.get(f"/api/v1/cells/{cell}/tasks/{bad}", headers=auth(tech)).status_code == 404
    assert [t["id"] for t in client.get(f"/api/v1/cells/{cell}/tasks", headers=auth(tech)).json()] == [good]
    again = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"])).json()["tasks"]
    assert [(t["task_id"], "error" in t) for t in again] == [(good, False)]
    assert _audited(settings, "delete task file") == [(f"task file {bad}", "technician-user", "bare-cr.csv")]


def test_only_an_admin_deletes_a_stored_compensation(calibrated, tokens, settings):
    client, _, cal = calibrated
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    task, _, _ = _task(model)
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=weld.csv", content=task, headers=auth(tokens["job"]))
    comp = r.headers["x-recal-compensation"]
    for role in ("viewer", "technician", "job"):
        assert client.delete(f"/api/v1/compensations/{comp}", headers=auth(tokens[role])).status_code == 403
    assert client.get(f"/api/v1/compensations/{comp}", headers=auth(tokens["viewer"])).text == r.text
    d = client.delete(f"/api/v1/compensations/{comp}", headers=auth(tokens["admin"]))
    assert d.status_code == 200 and d.json()["calibration"] == cal and d.json()["name"] == "weld.csv", d.text
    assert client.get(f"/api/v1/compensations/{comp}", headers=auth(tokens["viewer"])).status_code == 404
    assert client.get(f"/api/v1/compensations/{comp}/report", headers=auth(tokens["viewer"])).status_code == 404
    assert client.delete(f"/api/v1/compensations/{comp}", headers=auth(tokens["admin"])).status_code == 404
    assert client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).status_code == 200
    assert _audited(settings, "delete compensation") == [(f"compensation {comp}", "admin-user", "weld.csv")]


def _audited(settings, action: str) -> list[tuple]:
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        rows = db.exec(select(AuditEntry).where(AuditEntry.action == action)).all()
        out = [(e.subject, e.actor, e.detail["name"]) for e in rows]
    engine.dispose()
    return out
