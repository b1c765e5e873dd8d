"""Measurement imports of any allowed size, in bounded memory (issue 22, case 4): a 31,487-row
import grew the service to 16.5 GB and was killed, leaving a session ``completed`` with its
measurements and no calibration. The cost is now linear in rows (bench/import_scale.py), what
is larger than the limits is refused before anything is parsed, and an analysis that breaks or
is cut short leaves the session ``failed`` with the reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlmodel import Session, select

from calibration import residual_choice, residual_map
from calibration.model import model_from_dict
from calibration.robots import nominal_document
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from service import external, records
from service.api.app import create_app
from service.models import Calibration, Cell, Measurement, RunSession
from service.store import make_engine

from .conftest import NoMotion, auth, register_cell


def _measurement_csv(n: int, seed: int = 0) -> bytes:
    """A measurement CSV (contracts §3, mm and degrees) of ``n`` simulated tracker rows of a UR10e
    near its nominal model, a reflector 50 mm out: what another program's export looks like."""
    doc = nominal_document("ur10e")
    doc["targets"] = {"smr": [0, 0, 50]}
    nominal = model_from_dict(doc)
    rng = np.random.default_rng(seed)
    truth = dataclasses.replace(
        perturbed(nominal, np.random.default_rng(1), tool_length_m=0.0), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0])
    )
    data = simulate_measurements(truth, random_configurations(nominal, n, rng), rng, targets=("smr",))
    rows = records.measurement_rows(0, dataclasses.replace(data, sigma=np.full(n, 20e-6)))
    return records.measurements_csv(nominal, rows).encode()


def _app(settings, **limits):
    return TestClient(create_app(dataclasses.replace(settings, **limits), runner_factory=NoMotion))


def test_an_import_of_more_configurations_than_the_map_takes_ends_with_its_calibration(settings, tokens):
    with _app(settings) as app:
        cell = register_cell(app, tokens["technician"], "big")
        r = app.post(
            f"/api/v1/cells/{cell['id']}/measurements?kind=pose&name=big.csv",
            content=_measurement_csv(1500),
            headers=auth(tokens["technician"]),
        )
        assert r.status_code == 201, r.text
        s = r.json()
        assert s["state"] == "completed" and s["measured"] == 1500 and s["calibration_id"] is not None
        cal = app.get(f"/api/v1/calibrations/{s['calibration_id']}", headers=auth(tokens["viewer"])).json()
    assert cal["report"]["residuals"]["rms"] < 0.06  # mm: the simulated tracker's noise
    # every family cross-validated on all 1,500 configurations (the map fitted to at most
    # residual_map.MAX_MAP_CONFIGURATIONS of them, the trees to residual_choice.MAX_TREE_CONFIGURATIONS)
    fig = cal["report"]["residual_map"]
    assert residual_map.MAX_MAP_CONFIGURATIONS < 1500 <= residual_choice.MAX_TREE_CONFIGURATIONS
    assert fig["cv_rows"] == 1500 and set(fig["families"]) == set(residual_choice.FAMILIES)


def test_an_import_beyond_the_row_or_byte_limit_is_refused_before_anything_is_stored(settings, tokens):
    text = _measurement_csv(60)
    with _app(settings, max_import_rows=50, max_import_bytes=len(text) + 100) as app:
        cell = register_cell(app, tokens["technician"], "limits")
        url = f"/api/v1/cells/{cell['id']}/measurements?kind=pose"
        r = app.post(url, content=text, headers=auth(tokens["technician"]))
        assert r.status_code == 422 and "at most 50 rows" in r.text and "RECAL_MAX_IMPORT_ROWS" in r.text, r.text
        assert r.json()["detail"]["field"] == "body"
        r = app.post(url, content=text + b"#" * 200 + b"\n", headers=auth(tokens["technician"]))
        assert r.status_code == 413 and "RECAL_MAX_IMPORT_BYTES" in r.text, r.text
        assert app.get(f"/api/v1/cells/{cell['id']}/sessions", headers=auth(tokens["viewer"])).json() == []


class _Killed(BaseException):
    """What the kernel's kill looks like to the code after it: nothing after it runs."""


@pytest.mark.parametrize(
    "failure, reason",
    [(MemoryError, "the analysis failed: MemoryError"), (_Killed, external.INTERRUPTED)],
)
def test_an_import_whose_analysis_breaks_is_left_failed_with_the_reason(settings, tokens, monkeypatch, failure, reason):
    # the process stopping (or running out of memory) in the analysis is not something a fake
    # instrument can produce: the residual correction's cross-validation is made to raise it
    def broken(*a, **kw):
        raise failure("out of memory")

    monkeypatch.setattr(residual_choice, "choose_correction", broken)
    text = _measurement_csv(60)
    engine = make_engine(settings.effective_database_url)
    try:
        with Session(engine) as db:
            doc = nominal_document("ur10e")
            doc["targets"] = {"smr": [0, 0, 50]}
            cell = Cell(name="breaks", model=doc, devices={})
            db.add(cell)
            db.commit()
            db.refresh(cell)
            with pytest.raises(failure):
                external.import_measurements(db, cell, text, kind="pose", name="m.csv", actor="t", settings=settings)
        with Session(engine) as db:
            (run,) = db.exec(select(RunSession)).all()
            assert run.state == "failed" and run.reason.startswith(reason) and run.calibration_id is None
            assert len(db.exec(select(Measurement)).all()) == 60  # the data are kept: nothing is lost
            assert db.exec(select(Calibration)).all() == []
    finally:
        engine.dispose()
