"""Fixtures for the service: an app on a fresh database (SQLite file, or PostgreSQL when
RECAL_TEST_POSTGRES_URL is set), tokens of every role."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
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
    pg = request.getfixturevalue("postgres_databases")
    name, url = pg.create("recal_test")
    try:
        yield url
    finally:
        pg.drop(name)


@pytest.fixture
def settings(database_url, tmp_path) -> Settings:
    return Settings(
        home=tmp_path,
        database_url=database_url,
        settle_s=0.0,
        retry_backoff_s=0.01,
        device_retries=1,
        device_timeout_s=5.0,
    )


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


def register_cell(client, token: str, name: str, *, robot: str = "ur10e") -> dict:
    """A cell with ``robot``'s nominal model (a reflector 50 mm out) and no devices, registered
    through the API; its JSON."""
    from calibration.robots import nominal_document

    doc = nominal_document(robot)
    doc["targets"] = {"smr": [0, 0, 50]}
    r = client.post("/api/v1/cells", json={"name": name, "model": doc, "devices": {}}, headers=auth(token))
    assert r.status_code == 201, r.text
    return r.json()


class NoMotion:
    """A :class:`service.runners.SessionRunner` that runs nothing: sessions stay as the API left
    them (``started`` lists the ones the API asked it to run)."""

    owner = "no-motion"
    distributed = False

    def __init__(self, engine, settings):
        self.started: list[int] = []

    def queue(self, db, run):
        return False

    def start(self, session_id):
        self.started.append(session_id)

    def pause(self, session_id):
        return False

    def abort(self, session_id):
        return False

    def is_active(self, session_id):
        return False

    def not_ready(self):
        return None

    def wait(self, session_id, timeout_s=None):
        pass

    def shutdown(self, timeout_s=5.0):
        pass


@pytest.fixture
def idle_app(settings):
    """``idle_app(**testclient_kw)``: a TestClient of the app on ``settings`` whose sessions never
    run (:class:`NoMotion`); use it as a context manager (startup and shutdown run)."""
    from fastapi.testclient import TestClient

    from service.api.app import create_app

    return lambda **kw: TestClient(create_app(settings, runner_factory=NoMotion), **kw)


@pytest.fixture
def stored_session(settings):
    """``stored_session(cell_id, kind=..., seed=..., n=..., repeats=...)``: see :func:`store_session`."""
    return lambda cell_id, **kw: store_session(settings, cell_id, **kw)


@pytest.fixture
def calibrated(idle_app, tokens, stored_session):
    """``(client, cell id, calibration id)``: an idle app's client, a cell registered through it and
    a calibration from a stored pose session of that cell."""
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "calibrated")["id"]
        yield client, cell, stored_session(cell, seed=2)[1]


# The configuration a session measured around with ``region_deg`` (a 6-joint arm's working pose), degrees.
REGION_CENTRE_DEG = [0.0, -60.0, 90.0, -120.0, -90.0, 0.0]


def region_limits(region_deg: float):
    """(6, 2) rad: every joint within ``region_deg`` of REGION_CENTRE_DEG."""
    import numpy as np

    centre = np.deg2rad(REGION_CENTRE_DEG)
    return np.stack([centre - np.deg2rad(region_deg), centre + np.deg2rad(region_deg)], axis=1)


def session_truth(nominal, *, truth_seed: int = 1, sag: str | None = None, transmission_seed: int | None = None):
    """The simulated robot :func:`store_session` measures: ``(truth, transmission)`` (the latter
    None without ``transmission_seed``); see there."""
    import dataclasses

    import numpy as np

    from calibration.simulate import perturbed

    truth = dataclasses.replace(
        perturbed(nominal, np.random.default_rng(truth_seed), tool_length_m=0.0),
        base=np.array([1.5, -0.4, 0.2, 0.0, 0.0, 1.0]),
    )
    if sag is not None:
        from calibration.simulate import sagging

        truth = sagging(truth, sag, frames_of=dataclasses.replace(nominal, compliance=None))
    tx = None
    if transmission_seed is not None:
        from calibration.simulate import harmonic_drive_errors

        tx = harmonic_drive_errors(nominal, np.random.default_rng(transmission_seed))
    return truth, tx


def store_session(
    settings: Settings,
    cell_id: int,
    *,
    kind: str = "pose",
    seed: int = 0,
    n: int = 30,
    repeats: int = 1,
    truth_seed: int = 1,
    sag: str | None = None,
    region_deg: float | None = None,
    transmission_seed: int | None = None,
) -> tuple[int, int | None]:
    """A completed session of the cell stored as the session loop stores one: simulated tracker
    measurements (reflector ``smr``) of a robot near the cell's nominal model (link errors from
    ``truth_seed``), then the analysis (identification for ``pose``, accuracy for ``verify``,
    each configuration visited ``repeats`` times; ``sag``: the robot sags under gravity, one of
    ``calibration.simulate.SAGGING_ARMS``; ``region_deg``: every joint within that many degrees of
    one configuration, REGION_CENTRE_DEG, instead of the whole range; ``transmission_seed``: the
    robot's joints have harmonic-drive transmission errors drawn from it,
    ``calibration.simulate.harmonic_drive_errors``). Returns (session id, calibration id)."""
    import dataclasses

    import numpy as np

    from calibration.model import model_from_dict
    from calibration.simulate import random_configurations, simulate_measurements
    from service import kinds, records
    from service.models import Cell, RunSession

    engine = make_engine(settings.effective_database_url)
    try:
        with Session(engine) as db:
            cell = db.get(Cell, cell_id)
            nominal = model_from_dict(cell.model)
            rng = np.random.default_rng(seed)
            truth, tx = session_truth(nominal, truth_seed=truth_seed, sag=sag, transmission_seed=transmission_seed)
            limits = None if region_deg is None else region_limits(region_deg)
            q = np.repeat(random_configurations(nominal, n, rng, limits=limits), repeats, axis=0)
            data = simulate_measurements(truth, q, rng, targets=("smr",), transmission=tx)
            info = {"method": "random", "limits_checked": True, **({"repeats": repeats} if repeats > 1 else {})}
            run = RunSession(
                cell_id=cell_id,
                kind=kind,
                state="running",
                planned=len(q),
                target="smr",
                created_by="technician-user",
                plan=q.tolist(),
                plan_info=info,
            )
            db.add(run)
            db.commit()
            db.refresh(run)
            # the tracker's stated uncertainty on every row, as a session stores it
            db.add_all(records.measurement_rows(run.id, dataclasses.replace(data, sigma=np.full(len(data), 20e-6))))
            db.commit()
            kinds.finish_session(db, run, cell, settings)
            run.state = "completed"
            db.add(run)
            db.commit()
            return run.id, run.calibration_id
    finally:
        engine.dispose()
