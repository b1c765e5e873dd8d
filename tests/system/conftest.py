"""System tests: the real service process (``recal serve``) and a simulated cell process
(``recal fake-cell``) on loopback, driven through the REST API. Loopback addresses
127.0.0.100-127.0.0.119 and 127.0.0.160-127.0.0.199 are this folder's (the UR ports are fixed
per address, so each cell gets one of its own)."""

from __future__ import annotations

import itertools
import json
import os

import numpy as np
import pytest
from sqlmodel import Session

from calibration import robots
from calibration.simulate import perturbed
from service.client import Api
from service.files import save_model
from service.processes import free_port, start_fake_cell, start_service
from service.settings import Settings
from service.store import create_token, make_engine, migrate

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

_hosts = itertools.chain(range(100, 120), range(160, 200))

BALLS = {"ball1": [0.06, 0.0, 0.04], "ball2": [-0.03, 0.052, 0.04], "ball3": [-0.03, -0.052, 0.04]}


def next_host() -> str:
    n = next(_hosts, None)
    if n is None:
        raise RuntimeError("tests/system ran out of loopback addresses (100-119, 160-199)")
    return f"{NET}.{n}"


def emscon_sigma_m(rows: list[dict]) -> np.ndarray:
    """The per-axis sigma the simulated cell's Leica tracker (emScon) reports for stored rows:
    half its MPE at the row's range over sqrt(3), MPE = 15 um + 6 um/m (docs/devices/leica.md).
    A row measured through the line-protocol tracker has 20 um whatever the range."""
    from fakes.world import Noise

    noise = Noise()
    range_m = np.linalg.norm([[r["x"], r["y"], r["z"]] for r in rows], axis=1)
    return 0.5 * (noise.tracker_mpe_const_m + noise.tracker_mpe_per_m * range_m) / np.sqrt(3.0)


@pytest.fixture(scope="session")
def models(tmp_path_factory):
    """A nominal UR5e (with a reflector and three tooling balls) and a 'true' robot near it."""
    import dataclasses

    d = tmp_path_factory.mktemp("models")
    rng = np.random.default_rng(7)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), **{k: np.array(v) for k, v in BALLS.items()}}
    nominal = dataclasses.replace(robots.nominal("ur5e"), targets=targets)
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.2, 0.4, -0.2, 0.003, 0.002, np.deg2rad(-60)]),
        targets={k: v + rng.normal(0, 0.5e-3, 3) for k, v in targets.items()},
    )
    save_model(d / "nominal.json", nominal)
    save_model(d / "truth.json", truth)
    return {"nominal": d / "nominal.json", "truth": d / "truth.json", "truth_model": truth}


BOTH_DATABASES = pytest.mark.parametrize("db_url", ["sqlite", "postgres"], indirect=True)


@pytest.fixture
def db_url(request, tmp_path):
    """SQLite (the embedded default) unless a test asks for both with ``BOTH_DATABASES``."""
    if getattr(request, "param", "sqlite") == "sqlite":
        yield None  # the embedded default in RECAL_HOME
        return
    pg = request.getfixturevalue("postgres_databases")
    name, url = pg.create("recal_sys")
    try:
        yield url
    finally:
        pg.drop(name)


class Stack:
    """A running service with its home, tokens and the cells it was given."""

    def __init__(self, home, db_url, env):
        self.home, self.db_url, self.env = home, db_url, env
        self.port = free_port()
        self.service = None
        settings = Settings(home=home, database_url=db_url)
        engine = make_engine(settings.effective_database_url)
        migrate(engine)
        with Session(engine) as db:
            self.tokens = {
                r: create_token(db, role=r, name=f"{r}-user")[1] for r in ("viewer", "technician", "job", "admin")
            }
        engine.dispose()
        self.cells = []

    def start(self):
        env = dict(self.env)
        if self.db_url:
            env["RECAL_DATABASE_URL"] = self.db_url
        self.service = start_service(self.home, self.port, env=env, log_path=self.home / "service.log")
        return self

    def api(self, role="technician") -> Api:
        return Api(self.service.ready["url"], self.tokens[role])

    def stop(self):
        if self.service is not None:
            self.service.stop()

    def kill(self):
        self.service.kill()


@pytest.fixture
def stack_env() -> dict:
    """Settings of the service beyond the tests' defaults (a test parametrizes it)."""
    return {}


@pytest.fixture
def stack(tmp_path, db_url, stack_env):
    s = Stack(
        tmp_path,
        db_url,
        {"RECAL_SETTLE_S": "0", "RECAL_RETRY_BACKOFF_S": "0.05", "RECAL_DEVICE_RETRIES": "2", **stack_env},
    )
    s.start()
    yield s
    s.stop()
    for c in s.cells:
        c.stop()


@pytest.fixture
def register(stack, models):
    """``register(fake_args=..., time_scale=...)``: a simulated cell registered with the service."""
    return lambda **kw: _register(stack, models, **kw)


def _register(stack: Stack, models, *, fake_args=None, time_scale=0.0, name=None, truth=None) -> tuple[dict, object]:
    """Start a simulated cell (truth: ``truth`` or the session's) and register it with the
    service; returns (cell, fake process)."""
    host = next_host()
    fake = start_fake_cell(
        truth or models["truth"],
        host,
        time_scale=time_scale,
        extra=fake_args or [],
        log_path=stack.home / f"cell-{host}.log",
    )
    stack.cells.append(fake)
    cell = stack.api("technician").call(
        "POST",
        "/cells",
        {
            "name": name or f"cell-{host}",
            "model": json.loads(models["nominal"].read_text()),
            "devices": fake.ready,
            "drift_threshold": 0.1,
        },
    )
    return cell, fake
