"""Issue 27 on the page, in a real (headless) browser against the real service; the sessions are
stored and analysed as the session loop analyses them (no cell process needed):

- calibrations are activated, not overwritten: a second calibration waits until it is activated
  (or a verify session passes it), and can be retired, from the cell's page, audited with who;
- a session's page shows only figures of calibrations that existed when it ran (a verify session
  made before the first calibration is not charted against it);
- a paused session's progress, its chart and its last reading count the same poses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from sqlmodel import Session, select

from service.models import AuditEntry

pytestmark = pytest.mark.slow


def _robot(seed: int):
    from calibration.robots import nominal
    from calibration.simulate import perturbed

    nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = dataclasses.replace(perturbed(nom, np.random.default_rng(seed)), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0]))
    return nom, truth


def _rows(session_id: int, data) -> list:
    """``data``'s rows as a session stores them (with the tracker's stated 20 um)."""
    from service import records

    return records.measurement_rows(session_id, dataclasses.replace(data, sigma=np.full(len(data), 20e-6)))


def _store(
    engine, settings, cell_id: int, kind: str, data, *, state: str = "completed", planned: int | None = None, keep=None
):
    """A session of the cell that measured ``data`` (its first ``keep`` rows); finished (analysed,
    as the session loop finishes one) when ``state`` is completed, else left in ``state``.
    Returns (session id, calibration id)."""
    from service import kinds
    from service.models import Cell, RunSession

    with Session(engine) as db:
        cell = db.get(Cell, cell_id)
        run = RunSession(
            cell_id=cell_id,
            kind=kind,
            state="running" if state == "completed" else state,
            planned=planned or len(data),
            target="smr",
            created_by="technician-anna",
            plan=data.q.tolist(),
            plan_info={"method": "random"},
        )
        db.add(run)
        db.commit()
        db.refresh(run)
        db.add_all(_rows(run.id, data)[:keep])
        db.commit()
        if state == "completed":
            kinds.finish_session(db, run, cell, settings)
            run.state = "completed"
            db.add(run)
            db.commit()
        return run.id, run.calibration_id


def _measured(truth, nom, n: int, seed: int):
    from calibration.simulate import random_configurations, simulate_measurements

    rng = np.random.default_rng(seed)
    return simulate_measurements(truth, random_configurations(nom, n, rng), rng, targets=("smr",))


def _confirm(page) -> None:
    page.click("dialog.confirm[open] [data-action=confirm]")
    page.wait_for_selector("dialog.confirm", state="detached")


def test_a_later_calibration_is_activated_and_retired_on_the_page(page, web, tmp_path):
    from calibration.model import model_to_dict
    from service.client import Api

    nom, truth = _robot(3)
    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        api = Api(url, token)
        cell = api.call("POST", "/cells", {"name": "press-7", "model": model_to_dict(nom), "devices": {}})["id"]
        _, first = _store(engine, settings, cell, "pose", _measured(truth, nom, 40, 1))
        quick_session, quick = _store(engine, settings, cell, "pose", _measured(truth, nom, 20, 2))  # a quick test
        web.sign_in_at(page, url, token)
        page.goto(f"{url}/#/sessions/{quick_session}")
        page.wait_for_selector("#done-banner")
        assert f"not in use yet: the cell still works with calibration {first}" in page.inner_text("#done-banner")
        page.goto(f"{url}/#/cells/{cell}")
        # the verified 40-pose calibration is still the cell's; the quick one waits
        page.wait_for_selector("#candidate")
        assert page.inner_text("#last-calibration") == f"calibration {first}"
        note = page.inner_text("#candidate")
        assert note.startswith(f"Calibration {quick}") and "not in use yet" in note and "verify session" in note
        status = page.inner_text(f".calibrations [data-calibration='{quick}']")
        assert status == "not in use yet" and page.inner_text(f".calibrations [data-calibration='{first}']") == "in use"

        page.click("#activate-candidate")
        _confirm(page)
        page.wait_for_selector(f"#last-calibration:text-is('calibration {quick}')")
        assert page.query_selector("#candidate") is None
        assert page.inner_text(f".calibrations [data-calibration='{first}']") == "earlier"
        assert api.call("GET", f"/cells/{cell}")["last_calibration_id"] == quick

        page.click(f"#retire-{quick}")
        _confirm(page)
        page.wait_for_selector(f"#last-calibration:text-is('calibration {first}')")
        assert page.inner_text(f".calibrations [data-calibration='{quick}']") == "retired"
        with Session(engine) as db:  # the audit log (an admin's to read) says who did it
            rows = db.exec(select(AuditEntry).where(AuditEntry.subject == f"calibration {quick}")).all()
        assert [(r.action, r.actor) for r in rows] == [
            ("activate calibration", "technician-anna"),
            ("retire calibration", "technician-anna"),
        ]


def test_a_session_page_shows_only_calibrations_of_its_time(page, web, tmp_path):
    from calibration.model import model_to_dict
    from service.client import Api

    nom, truth = _robot(4)
    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        api = Api(url, token)
        cell = api.call("POST", "/cells", {"name": "weld-2", "model": model_to_dict(nom), "devices": {}})["id"]
        before, _ = _store(engine, settings, cell, "verify", _measured(truth, nom, 12, 1))  # not calibrated yet
        _, cal = _store(engine, settings, cell, "pose", _measured(truth, nom, 40, 2))
        after, _ = _store(engine, settings, cell, "verify", _measured(truth, nom, 12, 3))
        web.sign_in_at(page, url, token)

        page.goto(f"{url}/#/sessions/{before}")
        page.wait_for_selector("#done-banner")
        assert page.inner_text("#done-banner").startswith("Not calibrated yet.")
        page.wait_for_selector("#residuals svg")
        chart = page.inner_text("#residuals")
        assert f"calibration {cal}" not in chart and "nominal model" in chart, chart

        page.goto(f"{url}/#/sessions/{after}")
        page.wait_for_selector("#residuals svg")
        assert f"calibration {cal}, which this session checks" in page.inner_text("#residuals")
        assert page.inner_text("#done-banner").startswith("Checked.")


def test_a_paused_session_counts_its_poses_once(page, web, tmp_path):
    from calibration.model import model_to_dict
    from service.client import Api

    nom, truth = _robot(5)
    data = _measured(truth, nom, 8, 1)
    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        api = Api(url, token)
        cell = api.call("POST", "/cells", {"name": "paint-1", "model": model_to_dict(nom), "devices": {}})["id"]
        sid, _ = _store(engine, settings, cell, "verify", data, state="paused", planned=60, keep=7)
        web.sign_in_at(page, url, token)
        page.goto(f"{url}/#/sessions/{sid}")
        page.wait_for_selector("#residuals svg")
        assert page.inner_text("#progress").startswith("7 of 60 poses")
        assert "pose 7 at" in page.inner_text("#device-state")
        # every state the page shows from now on: the progress and the last reading side by side
        page.evaluate("""() => {
            window.seen = [];
            const look = () => window.seen.push([document.querySelector('#progress').textContent,
                ((document.querySelector('#device-state') || {}).textContent || '').match(/pose (\\d+) at/)?.[1]]);
            new MutationObserver(look).observe(document.body, {subtree: true, childList: true, characterData: true});
        }""")
        with Session(engine) as db:  # the 8th pose is stored (as a session's last pose is, just before it pauses)
            db.add(_rows(sid, data)[7])
            db.commit()
        page.wait_for_selector("#progress:text-matches('^8 of 60 poses')")
        page.wait_for_selector("#device-state:has-text('pose 8 at')")
        seen = page.evaluate("window.seen")
        mismatched = [s for s in seen if s[1] is not None and not s[0].startswith(f"{s[1]} of 60")]
        assert seen and not mismatched, mismatched
        assert api.call("GET", f"/sessions/{sid}/live")["measured"] == 8
