"""Fleet tests (docs/fleet.md): real processes on one machine. A PostgreSQL database per test
module (created and dropped here), API processes (``recal serve`` with
``RECAL_ENGINE=procrastinate``), workers (``recal worker --site ...``) and simulated cells
(``recal fake-cell``), each cell on its own loopback address: 127.0.0.120-127.0.0.159 are this
folder's. Skipped, with the reason, without PostgreSQL or Procrastinate (the ``fleet`` extra)."""

from __future__ import annotations

import dataclasses
import importlib.util
import itertools
import json
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import create_engine, text
from sqlmodel import Session

from calibration import robots
from calibration.simulate import perturbed
from service.client import Api
from service.files import save_model
from service.models import RunSession
from service.processes import free_port, start_fake_cell, start_service, start_worker
from service.store import create_token, make_engine, migrate

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

POSTGRES_URL = os.environ.get("RECAL_TEST_POSTGRES_URL")
_hosts = itertools.count(120)


def next_host() -> str:
    n = next(_hosts)
    if n > 159:
        raise RuntimeError("tests/fleet ran out of loopback addresses (127.0.0.120-159)")
    return f"{NET}.{n}"


def _skip_reason() -> str | None:
    if importlib.util.find_spec("procrastinate") is None:
        return "the fleet needs Procrastinate: pip install -e '.[fleet]' (make test does)"
    if not POSTGRES_URL:
        return "fleet tests need PostgreSQL: set RECAL_TEST_POSTGRES_URL (.ci/run sets it)"
    try:
        eng = create_engine(POSTGRES_URL, connect_args={"connect_timeout": 3})
        with eng.connect() as conn:
            conn.execute(text("SELECT 1"))
        eng.dispose()
    except Exception as exc:  # noqa: BLE001 - any failure to reach the server is the skip's reason
        return f"fleet tests need PostgreSQL at RECAL_TEST_POSTGRES_URL: {type(exc).__name__}: {exc}"
    return None


@pytest.fixture(autouse=True, scope="session")
def _fleet_prerequisites():
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)


@pytest.fixture(scope="session")
def fleet_models(tmp_path_factory):
    """A nominal UR5e with a reflector, and a 'true' robot near it."""
    d = tmp_path_factory.mktemp("fleet-models")
    rng = np.random.default_rng(11)
    nominal = dataclasses.replace(robots.nominal("ur5e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.2, 0.4, -0.2, 0.003, 0.002, np.deg2rad(-60)]),
        targets={k: v + rng.normal(0, 0.5e-3, 3) for k, v in nominal.targets.items()},
    )
    save_model(d / "nominal.json", nominal)
    save_model(d / "truth.json", truth)
    return {"nominal": d / "nominal.json", "truth": d / "truth.json"}


class Fleet:
    """A fleet on this machine: its database, API processes, workers and cells."""

    def __init__(self, home: Path, db_url: str, models, *, ttl_s: float):
        self.home, self.db_url, self.models = home, db_url, models
        self.env = {
            "RECAL_DATABASE_URL": db_url,
            "RECAL_ENGINE": "procrastinate",
            "RECAL_SETTLE_S": "0",
            "RECAL_RETRY_BACKOFF_S": "0.05",
            "RECAL_DEVICE_RETRIES": "2",
            "RECAL_LEASE_TTL_S": str(ttl_s),
        }
        self.ttl_s = ttl_s
        engine = make_engine(db_url)
        migrate(engine)
        with Session(engine) as db:
            self.tokens = {
                r: create_token(db, role=r, name=f"{r}-user")[1] for r in ("viewer", "technician", "job", "admin")
            }
        engine.dispose()
        self.engine = make_engine(db_url)
        self.apis: list = []
        self.workers: dict = {}
        self.cells: list = []

    # processes
    def start_api(self):
        i = len(self.apis)
        self.apis.append(start_service(self.home, free_port(), env=self.env, log_path=self.home / f"api{i}.log"))
        return self.apis[-1]

    def start_worker(self, name: str, sites: list[str], concurrency: int = 4):
        self.workers[name] = start_worker(
            self.home, sites, env=self.env, name=name, concurrency=concurrency, log_path=self.home / f"{name}.log"
        )
        self.workers[name].sites = sites
        return self.workers[name]

    def api(self, i: int = 0, role: str = "technician") -> Api:
        return Api(self.apis[i].ready["url"], self.tokens[role])

    def add_cells(self, sites: list[str], *, time_scale: float = 0.0, threshold: float = 0.1) -> list[dict]:
        """Simulated cells (started in parallel), registered in ``sites`` (one cell each)."""
        hosts = [next_host() for _ in sites]

        def one(host):
            return start_fake_cell(
                self.models["truth"], host, time_scale=time_scale, log_path=self.home / f"cell-{host}.log"
            )

        with ThreadPoolExecutor(len(hosts)) as pool:
            fakes = list(pool.map(one, hosts))
        self.cells += fakes
        model = json.loads(self.models["nominal"].read_text())
        return [
            self.api(0).call(
                "POST",
                "/cells",
                {
                    "name": f"cell-{host}",
                    "site": site,
                    "model": model,
                    "devices": fake.ready,
                    "drift_threshold": threshold,
                },
            )
            for host, site, fake in zip(hosts, sites, fakes)
        ]

    # the store, read directly
    def session_row(self, sid: int) -> RunSession:
        with Session(self.engine) as db:
            return db.get(RunSession, sid)

    def owner_name(self, sid: int) -> str | None:
        owner = self.session_row(sid).lease_owner or ""
        for name, w in self.workers.items():
            if w.ready["owner"] == owner:
                return name
        return None

    def sql(self, query: str, **params):
        with self.engine.connect() as conn:
            return conn.execute(text(query), params).all()

    def stop(self):
        for w in self.workers.values():
            w.stop(20)
        for a in self.apis:
            a.stop()
        for c in self.cells:
            c.stop()
        self.engine.dispose()


@pytest.fixture(scope="module")
def make_fleet(tmp_path_factory, fleet_models, postgres_databases):
    """``make_fleet(ttl_s=...)``: a fresh fleet on its own database, stopped and dropped at the
    end of the module."""
    made = []

    def make(ttl_s: float = 5.0) -> Fleet:
        name, url = postgres_databases.create("recal_fleet")
        f = Fleet(tmp_path_factory.mktemp("fleet"), url, fleet_models, ttl_s=ttl_s)
        made.append((f, name))
        return f

    yield make
    for f, name in made:
        try:
            f.stop()
        finally:
            postgres_databases.drop(name)


@pytest.fixture(scope="module")
def fleet(make_fleet):
    """A fleet of two API processes and two workers (w1 serves north, south and east; w2 north and
    south), one per test module."""
    f = make_fleet(ttl_s=5.0)
    f.start_api()
    f.start_api()
    f.start_worker("w1", ["north", "south", "east"])
    f.start_worker("w2", ["north", "south"])
    return f
