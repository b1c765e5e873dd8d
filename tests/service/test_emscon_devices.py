"""A cell's Leica tracker (``devices.emscon``): checked at registration, used by tracker sessions,
tested by the connection test against the emScon fake; the session's beam recoveries in the
store (schema v4)."""

from __future__ import annotations

import dataclasses

import pytest
from sqlalchemy import inspect, text
from sqlmodel import Session

from calibration.robots import nominal
from fakes.leica_tracker import LeicaTrackerFake
from fakes.world import SimCell
from service.devices import DeviceConfigError, emscon_config, parse_devices
from service.models import RunSession
from service.store import SCHEMA_VERSION, make_engine, migrate

from .conftest import auth, register_cell


@pytest.fixture
def client(idle_app, tokens):
    with idle_app() as c:
        yield c


@pytest.mark.parametrize(
    "emscon, field, message",
    [
        ("10.0.0.5:port", "body.devices.emscon", "expected HOST:PORT"),
        ({"host": "10.0.0.5", "port": "700"}, "body.devices.emscon.port", "expected an integer"),
        ({"port": 700}, "body.devices.emscon.host", "missing"),
        ({"host": "10.0.0.5", "reflektor": "RRR 1.5in"}, "body.devices.emscon.reflektor", "did you mean 'reflector'"),
        ({"host": "10.0.0.5", "environment": "outside"}, "body.devices.emscon.environment", "'meteo' or 'config'"),
        (["10.0.0.5"], "body.devices.emscon", 'expected "HOST:PORT" or an object'),
    ],
)
def test_a_bad_emscon_entry_is_refused_naming_the_field(client, tokens, emscon, field, message):
    cell = register_cell(client, tokens["technician"], "leica")
    r = client.patch(
        f"/api/v1/cells/{cell['id']}", json={"devices": {"emscon": emscon}}, headers=auth(tokens["technician"])
    )
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail["field"] == field and message in detail["message"], detail


def test_emscon_entries_make_tracker_configurations():
    def emscon(entry, **kw):
        return emscon_config(parse_devices({"emscon": entry}).emscon_settings, **kw)

    c = emscon(
        {
            "host": "10.0.0.5",
            "reflector": "RRR 0.5in",
            "environment": "config",
            "temperature_c": 21,
            "measure_time_s": 1.0,
        },
        timeout_s=3.0,
    )
    assert (c.host, c.port, c.reflector, c.environment, c.temperature_c, c.timeout_s) == (
        "10.0.0.5",
        700,
        "RRR 0.5in",
        "config",
        21.0,
        3.0,
    )
    assert emscon("10.0.0.5:7000").port == 7000
    assert (emscon("10.0.0.5").host, emscon("10.0.0.5").port) == ("10.0.0.5", 700)
    with pytest.raises(DeviceConfigError, match=r"devices.emscon.use_adm: expected true or false"):
        parse_devices({"emscon": {"host": "h", "use_adm": 1}})
    assert (
        parse_devices({"emscon": "h:700"}).has_tracker
        and parse_devices({"tracker": "socket://h:1"}).has_tracker
        and not parse_devices({"cmm": "socket://h:1294"}).has_tracker
    )


def test_connection_test_reports_the_emscon_tracker(client, tokens):
    cell_sim = SimCell(dataclasses.replace(nominal("ur5e"), targets={"smr": [0.0, 0.0, 0.05]}), seed=2)
    fake = LeicaTrackerFake(cell_sim, port=0)
    fake.start()
    try:
        cell = register_cell(client, tokens["technician"], "leica")
        t = auth(tokens["technician"])
        r = client.patch(
            f"/api/v1/cells/{cell['id']}", json={"devices": {"emscon": f"127.0.0.1:{fake.port}"}}, headers=t
        )
        assert r.status_code == 200, r.text
        res = client.post(f"/api/v1/cells/{cell['id']}/devices/test?timeout_s=5", headers=t).json()
        (tracker,) = res["results"]
        assert tracker["device"] == "laser tracker" and tracker["ok"], tracker
        assert "Leica, emScon 3.8.400, tracker 750123" in tracker["answer"]
        assert "reflector RRR 1.5in" in tracker["answer"] and "ready" in tracker["answer"]
        assert tracker["details"]["environment"] == {
            "temperature_c": 20.0,
            "pressure_mbar": 1013.25,
            "humidity_pct": 50.0,
        }
        assert len(tracker["details"]["position_mm"]) == 3
        # a tracker session is accepted on a cell whose only tracker is on emScon
        r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 5}, headers=t)
        assert r.status_code == 201, r.text
        assert r.json()["beam_recoveries"] == 0
    finally:
        fake.stop()


def test_version_3_store_gets_beam_recoveries(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:
        conn.execute(text("ALTER TABLE session DROP COLUMN beam_recoveries"))
        conn.execute(text("UPDATE schema_version SET version = 3"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP)"
            )
        )
        conn.execute(
            text(
                "INSERT INTO session (cell_id, kind, state, planned, device, dry_run, created_by, "
                "created_at, updated_at) VALUES (1, 'pose', 'completed', 5, 'tracker', false, '', "
                "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
            )
        )
    assert migrate(engine) == SCHEMA_VERSION >= 4
    assert "beam_recoveries" in {c["name"] for c in inspect(engine).get_columns("session")}
    with Session(engine) as db:
        assert db.get(RunSession, 1).beam_recoveries == 0
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()


@pytest.mark.parametrize("radius", [0.0, -0.0125, 12.5, "12.5mm", True])
def test_a_cmm_ball_radius_that_no_tooling_ball_has_is_refused(client, tokens, radius):
    cell = register_cell(client, tokens["technician"], "cmm-balls")
    r = client.patch(
        f"/api/v1/cells/{cell['id']}",
        json={"devices": {"cmm": "socket://127.0.0.1:1294", "cmm_ball_radius_m": radius}},
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 422, r.text
    assert r.json()["detail"]["field"] == "body.devices.cmm_ball_radius_m", r.json()


def test_the_cmm_ball_radius_comes_from_the_cells_devices():
    from service.devices import DEFAULT_BALL_RADIUS_M

    assert parse_devices({"cmm": "socket://127.0.0.1:1294"}).cmm_ball_radius_m == DEFAULT_BALL_RADIUS_M == 0.0125
    assert parse_devices({"cmm": "socket://127.0.0.1:1294", "cmm_ball_radius_m": 0.01}).cmm_ball_radius_m == 0.01
