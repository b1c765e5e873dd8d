"""Calibrations are activated, not overwritten (issue 27): a cell's first calibration becomes
current at once; a later one waits as a candidate until a verify session passes it (its RMS on
fresh configurations no larger than the current model's on the same measurements) or a
technician activates it; any can be retired; each change is audited with who made it."""

from __future__ import annotations

from sqlmodel import Session

from service.models import RunSession
from service.store import make_engine

from .conftest import auth, register_cell


def _audit(c, tokens, action: str) -> list[dict]:
    rows = c.get("/api/v1/audit", headers=auth(tokens["admin"])).json()
    return [r for r in rows if r["action"] == action]


def test_later_calibrations_wait_until_activated_or_retired(idle_app, tokens, stored_session, settings):
    t, viewer, job = auth(tokens["technician"]), auth(tokens["viewer"]), auth(tokens["job"])
    with idle_app() as c:
        cell = register_cell(c, tokens["technician"], "activation")["id"]
        _, first = stored_session(cell, seed=2, n=40)
        # the first calibration of a cell with no current model: nothing to protect, current at once
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == first
        assert c.get(f"/api/v1/calibrations/{first}", headers=t).json()["status"] == "current"
        made = [a for a in _audit(c, tokens, "activate calibration") if a["subject"] == f"calibration {first}"]
        assert made and made[0]["actor"] == "technician-user" and "first calibration" in made[0]["detail"]["why"]

        _, quick = stored_session(cell, seed=3, n=20)  # a quick test session: it does not replace the first
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == first
        assert c.get(f"/api/v1/calibrations/{quick}", headers=t).json()["status"] == "candidate"
        listed = {r["id"]: r["status"] for r in c.get(f"/api/v1/cells/{cell}/calibrations", headers=t).json()}
        assert listed == {first: "current", quick: "candidate"}
        # both can be compared
        assert c.get(f"/api/v1/calibrations/{first}/compare/{quick}", headers=t).status_code == 200

        # roles as the cell's other changes: a viewer and a nightly job may not
        assert c.post(f"/api/v1/calibrations/{quick}/activate", headers=viewer).status_code == 403
        assert c.post(f"/api/v1/calibrations/{quick}/activate", headers=job).status_code == 403
        r = c.post(f"/api/v1/calibrations/{quick}/activate", headers=t)
        assert r.status_code == 200 and r.json()["status"] == "current", r.text
        assert r.json()["activated_by"] == "technician-user"
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == quick
        assert c.get(f"/api/v1/calibrations/{first}", headers=t).json()["status"] == "superseded"
        done = [a for a in _audit(c, tokens, "activate calibration") if a["subject"] == f"calibration {quick}"]
        assert done[0]["actor"] == "technician-user" and done[0]["detail"]["previous"] == first

        # retiring the current one brings back the one activated before it
        r = c.post(f"/api/v1/calibrations/{quick}/retire", headers=t)
        assert r.status_code == 200 and r.json()["status"] == "retired" and r.json()["retired_by"] == "technician-user"
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == first
        retired = [a for a in _audit(c, tokens, "retire calibration") if a["subject"] == f"calibration {quick}"]
        assert retired[0]["actor"] == "technician-user" and retired[0]["detail"]["current"] == first
        # a retired calibration no longer waits to be verified, and is still readable
        assert c.get(f"/api/v1/calibrations/{quick}", headers=t).json()["model"]

        # not while a session drives the cell (it works with the model it started with)
        with Session(make_engine(settings.effective_database_url)) as db:
            run = RunSession(cell_id=cell, kind="verify", state="running", planned=3)
            db.add(run)
            db.commit()
            r = c.post(f"/api/v1/calibrations/{quick}/activate", headers=t)
            assert r.status_code == 409 and f"session {run.id} is driving" in r.text
            run.state = "completed"
            db.add(run)
            db.commit()
        assert c.post(f"/api/v1/calibrations/{quick}/activate", headers=t).json()["status"] == "current"
        assert c.get("/api/v1/calibrations/99999/activate", headers=t).status_code == 405
        assert c.post("/api/v1/calibrations/99999/activate", headers=t).status_code == 404


def test_a_verify_session_activates_a_candidate_that_passes(idle_app, tokens, stored_session):
    t = auth(tokens["technician"])
    with idle_app() as c:
        cell = register_cell(c, tokens["technician"], "verified")["id"]
        _, first = stored_session(cell, seed=2, n=40, truth_seed=1)
        # the robot changed (truth 5): the new calibration waits
        _, new = stored_session(cell, seed=3, n=30, truth_seed=5)
        assert c.get(f"/api/v1/calibrations/{new}", headers=t).json()["status"] == "candidate"

        # measured on the old robot (truth 1) the candidate does worse than the current: it stays a candidate
        sid, _ = stored_session(cell, kind="verify", seed=4, n=12, truth_seed=1)
        v = c.get(f"/api/v1/sessions/{sid}", headers=t).json()["plan_info"]["verify"]
        assert v["calibration_id"] == new and v["candidate"]["passed"] is False
        assert v["candidate"]["against"]["calibration_id"] == first
        assert v["candidate"]["against"]["rms"] < v["rms"]
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == first

        # on the robot as it is now (truth 5) it does better: it passes and becomes current
        sid, _ = stored_session(cell, kind="verify", seed=5, n=12, truth_seed=5)
        v = c.get(f"/api/v1/sessions/{sid}", headers=t).json()["plan_info"]["verify"]
        assert v["calibration_id"] == new and v["candidate"]["passed"] is True and v["candidate"]["activated"]
        assert v["rms"] <= v["candidate"]["against"]["rms"]
        assert c.get(f"/api/v1/cells/{cell}", headers=t).json()["last_calibration_id"] == new
        why = [a for a in _audit(c, tokens, "activate calibration") if a["subject"] == f"calibration {new}"]
        assert why[0]["actor"] == "technician-user" and f"verify session {sid} passed" in why[0]["detail"]["why"]

        # a verify session with no candidate checks the current calibration, as before
        sid, _ = stored_session(cell, kind="verify", seed=6, n=12, truth_seed=5)
        v = c.get(f"/api/v1/sessions/{sid}", headers=t).json()["plan_info"]["verify"]
        assert v["calibration_id"] == new and "candidate" not in v
