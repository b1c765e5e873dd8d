"""A stored compensation is at most about twice its input (issue 22, case 5: one 4 MiB task
stored about 24 MB of output and a 60 MB report). The compensated file and its report are kept
compressed (service.packed); what the API answers is what it answered before."""

from __future__ import annotations

import json

from sqlalchemy import text as sql
from sqlmodel import Session

from calibration.model import model_from_dict
from service.store import make_engine

from .conftest import auth
from .test_compensate_api import _task


def test_a_stored_compensation_is_at_most_twice_its_input_and_reads_back_the_same(calibrated, tokens, settings):
    client, _, cal = calibrated
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    task, _, _ = _task(model, n=2000)
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=big.csv", content=task, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    comp = r.headers["x-recal-compensation"]
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:  # what the database holds, read as the database gives it
        output, report = db.execute(
            sql("SELECT output, report FROM compensation WHERE id = :i"), {"i": int(comp)}
        ).one()
    engine.dispose()
    report_text = report if isinstance(report, str) else json.dumps(report)
    stored = len(output.encode()) + len(report_text.encode())
    assert stored <= 2 * len(task.encode()), (stored, len(task))
    # the answers are those of the compensation itself: the file byte for byte, the whole report
    again = client.get(f"/api/v1/compensations/{comp}", headers=auth(tokens["viewer"]))
    assert again.content == r.content and again.headers["content-type"] == "text/plain; charset=utf-8"
    rep = client.get(f"/api/v1/compensations/{comp}/report", headers=auth(tokens["viewer"])).json()["report"]
    assert rep["format"] == "recal.compensation-report/1" and rep["task"] == "big.csv"
    assert rep["summary"]["points"] == 2000 and len(rep["points"]) == 2000
    assert [p["row"] for p in rep["points"][:3]] == [1, 2, 3] and "residual" in rep["points"][0]
