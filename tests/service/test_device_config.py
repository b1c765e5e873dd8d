"""A cell's device configuration (``service/device_config.py``): the one parser of the
``devices`` document, every shape it accepts (the fake cell's endpoint line, contracts §7, and
the same shape for real equipment), each field's refusal naming the field, and its JSON Schema
served to the page (``GET /api/v1/schemas/devices``)."""

from __future__ import annotations

import re

import pytest
from pydantic import ValidationError

from service.devices import DEFAULT_BALL_RADIUS_M, DeviceConfigError, DevicesConfig, parse_devices, stored_devices

from .conftest import auth, register_cell

# contracts §7, as `recal fake-cell` prints it (the Leica tracker included)
ENDPOINT_LINE = {
    "ready": True,
    "rtde": "127.0.0.2",
    "modbus": "127.0.0.2:502",
    "tracker": "socket://127.0.0.2:10001",
    "emscon": "127.0.0.2:700",
    "cmm": "socket://127.0.0.2:1294",
    "can": {"interface": "socketcand", "channel": "vcan0", "host": "127.0.0.2", "port": 29536},
    "encoders": {"1": 17, "2": 18},
    "resolvers": {"1": 33},
}

ACCEPTED = [
    ENDPOINT_LINE,
    {},
    {"rtde": "192.168.1.10", "emscon": "192.168.0.1:700"},  # README, "Real equipment"
    {"rtde": "x", "tracker": "socket://127.0.0.1:9"},
    {"rtde": "ur10e.cell-3.plant", "modbus": "[fe80::1]:502"},
    {"emscon": "192.168.0.1"},  # port 700
    {
        "emscon": {
            "host": "10.0.0.5",
            "port": 700,
            "reflector": "RRR 0.5in",
            "measure_time_s": 1,
            "use_adm": False,
            "environment": "config",
            "temperature_c": 21.5,
            "pressure_mbar": 990,
            "humidity_pct": 40,
            "initialize_timeout_s": 90,
        }
    },
    {"tracker": "/dev/ttyUSB0", "cmm": "loop://"},
    {"tracker": "COM3", "cmm": "socket://cmm:1294", "cmm_ball_radius_m": 0.01},
    {"can": {"interface": "socketcan", "channel": "can0"}, "encoders": {"1": 17}, "resolvers": {"6": 38}},
    {"can": {"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 500000}, "encoders": {"3": 21}},
    {"can": {"interface": "socketcand", "channel": "vcan0", "host": "h", "port": 29536, "tcp_tune": False}},
]


@pytest.mark.parametrize("doc", ACCEPTED)
def test_every_accepted_shape_round_trips(doc):
    config = parse_devices(doc)
    assert parse_devices(config.document()) == config
    assert parse_devices(doc) == config  # the same document, the same configuration
    with pytest.raises(ValidationError, match="frozen"):  # what was checked stays so
        config.rtde = "elsewhere"  # type: ignore[misc]


def test_the_endpoint_line_reads_as_the_devices_it_names():
    c = parse_devices(ENDPOINT_LINE)
    assert c.kinds() == ["rtde", "modbus", "emscon", "tracker", "cmm", "can"]
    assert c.has("tracker") and c.has("cmm") and c.has("encoder")
    assert c.instrument_address("tracker") == "127.0.0.2:700"  # sessions measure with the Leica
    assert c.address("tracker") == "socket://127.0.0.2:10001"
    assert (c.emscon_settings.host, c.emscon_settings.port) == ("127.0.0.2", 700)
    assert c.encoders == {"1": 17, "2": 18} and c.resolvers == {"1": 33}
    assert c.cmm_ball_radius_m == DEFAULT_BALL_RADIUS_M == 0.0125


def test_what_forms_and_json_writers_send_reads_as_the_same_configuration():
    # empty fields, whole numbers written as floats or digit strings (accepted before the model)
    assert parse_devices({"rtde": "h", "modbus": "", "tracker": None}) == parse_devices({"rtde": "h"})
    a = parse_devices({"emscon": {"host": "h", "port": 700.0}, "can": {"interface": "socketcan", "channel": "c"}})
    assert a.emscon.port == 700
    b = parse_devices({"can": {"interface": "socketcand", "host": "h", "port": "29536"}, "encoders": {1: "17"}})
    assert b.can.port == 29536 and b.encoders == {"1": 17}


@pytest.mark.parametrize(
    "doc, field, message",
    [
        ([1], "devices", "expected an object"),
        ({"tracer": "socket://h:1"}, "devices.tracer", "unknown key; did you mean 'tracker'?"),
        ({"ball_radius_m": 0.01}, "devices.ball_radius_m", "did you mean 'cmm_ball_radius_m'?"),
        ({"ready": "yes"}, "devices.ready", "expected true or false"),
        ({"rtde": 5}, "devices.rtde", "expected a string, got 5"),
        ({"rtde": "192.168.1.10:30004"}, "devices.rtde", "no port: RTDE uses 30004"),
        ({"modbus": "x"}, "devices.modbus", "expected HOST:PORT, e.g. 192.168.1.10:502, got 'x'"),
        ({"modbus": "h:70000"}, "devices.modbus", "expected HOST:PORT"),
        ({"emscon": ["h"]}, "devices.emscon", 'expected "HOST:PORT" or an object'),
        ({"emscon": "h:port"}, "devices.emscon", "expected HOST:PORT of the emScon server"),
        ({"emscon": {"port": 700}}, "devices.emscon.host", "missing"),
        ({"emscon": {"host": "h", "port": 0}}, "devices.emscon.port", "greater than or equal to 1"),
        ({"emscon": {"host": "h", "port": "700"}}, "devices.emscon.port", "expected an integer"),
        ({"emscon": {"host": "h", "reflektor": "x"}}, "devices.emscon.reflektor", "did you mean 'reflector'?"),
        ({"emscon": {"host": "h", "reflector": ""}}, "devices.emscon.reflector", "non-empty"),
        ({"emscon": {"host": "h", "measure_time_s": 0}}, "devices.emscon.measure_time_s", "greater than 0"),
        ({"emscon": {"host": "h", "use_adm": 1}}, "devices.emscon.use_adm", "expected true or false"),
        ({"emscon": {"host": "h", "environment": "outside"}}, "devices.emscon.environment", "'meteo' or 'config'"),
        ({"emscon": {"host": "h", "temperature_c": 300}}, "devices.emscon.temperature_c", "less than or equal"),
        ({"emscon": {"host": "h", "pressure_mbar": 10}}, "devices.emscon.pressure_mbar", "greater than or equal"),
        ({"emscon": {"host": "h", "humidity_pct": 120}}, "devices.emscon.humidity_pct", "less than or equal"),
        ({"emscon": {"host": "h", "initialize_timeout_s": -1}}, "devices.emscon.initialize_timeout_s", "greater"),
        ({"tracker": "socket://h"}, "devices.tracker", "expected socket://HOST:PORT or a serial port"),
        ({"tracker": "tracker-pc:10001"}, "devices.tracker", "expected socket://HOST:PORT"),
        ({"cmm": "192.168.1.30:1294"}, "devices.cmm", "expected socket://HOST:PORT of the I++ DME server"),
        ({"can": "can0"}, "devices.can", "expected an object"),
        ({"can": {"interface": "socketcand", "channel": "vcan0"}}, "devices.can.host", "socketcand bus needs"),
        ({"can": {"interface": "socketcan", "chanel": "can0"}}, "devices.can.chanel", "did you mean 'channel'?"),
        ({"can": {"interface": "", "channel": "c"}}, "devices.can.interface", "non-empty"),
        ({"can": {"interface": "pcan", "channel": "c", "bitrate": -1}}, "devices.can.bitrate", "greater than 0"),
        ({"encoders": {"1": 17}}, "devices.can", "need the CAN bus"),
        ({"can": {"interface": "socketcan", "channel": "c"}, "encoders": {"x": 1}}, "devices.encoders.x", "joint"),
        ({"can": {"interface": "socketcan", "channel": "c"}, "encoders": {"1": 300}}, "devices.encoders.1", "127"),
        ({"can": {"interface": "socketcan", "channel": "c"}, "resolvers": {"1": True}}, "devices.resolvers.1", ""),
        (
            {"can": {"interface": "socketcan", "channel": "c"}, "encoders": {"1": 17}, "resolvers": {"2": 17}},
            "devices.resolvers.2",
            "node 17 is already encoders.1",
        ),
        ({"cmm_ball_radius_m": 0.0}, "devices.cmm_ball_radius_m", "greater than or equal to 0.0005"),
        ({"cmm_ball_radius_m": 12.5}, "devices.cmm_ball_radius_m", "less than or equal to 0.1"),
        ({"cmm_ball_radius_m": "12.5mm"}, "devices.cmm_ball_radius_m", "expected a number"),
        ({"cmm_ball_radius_m": True}, "devices.cmm_ball_radius_m", "expected a number"),
    ],
)
def test_each_fields_error_names_the_field(doc, field, message):
    with pytest.raises(DeviceConfigError) as info:
        parse_devices(doc)
    assert (info.value.field, str(info.value).split(": ", 1)[0]) == (field, field), str(info.value)
    assert message in info.value.message, str(info.value)


def test_a_stored_document_from_before_the_check_still_reads():
    # registered when any key passed: sessions still open its devices; the rules that were not
    # checked then (the encoders' bus, one node per id) are the opening's to refuse
    old = {"rtde": "h", "note": "line 3", "encoders": {"1": 17}}
    with pytest.raises(DeviceConfigError, match=r"devices.note: unknown key"):
        parse_devices(old)
    assert stored_devices(old) == DevicesConfig(rtde="h", encoders={"1": 17})
    # a value no device can have is refused either way
    with pytest.raises(DeviceConfigError, match=r"devices.modbus"):
        stored_devices({"modbus": "x"})


def test_the_schema_says_what_the_parser_checks():
    from service.device_config import devices_json_schema

    schema = devices_json_schema()
    assert schema["additionalProperties"] is False
    assert set(schema["properties"]) == set(DevicesConfig.model_fields)
    radius = schema["properties"]["cmm_ball_radius_m"]
    assert (radius["default"], radius["minimum"], radius["maximum"]) == (0.0125, 0.0005, 0.1)
    # the page checks a field with the schema's pattern: the same verdict as the parser's
    modbus = schema["properties"]["modbus"]["anyOf"][0]
    for value, ok in [("192.168.1.10:502", True), ("h:0", False), ("h:65536", False), ("x", False)]:
        assert bool(re.match(modbus["pattern"], value)) is ok, value
        try:
            parse_devices({"modbus": value})
            assert ok, value
        except DeviceConfigError as exc:
            assert not ok and modbus["x-expected"] in exc.message, (value, exc)


@pytest.fixture
def client(idle_app, tokens):
    with idle_app() as c:
        yield c


def test_the_schema_is_served_to_readers(client, tokens):
    r = client.get("/api/v1/schemas/devices", headers=auth(tokens["viewer"]))
    assert r.status_code == 200, r.text
    schema = r.json()
    assert schema["title"] == "Cell devices" and "cmm_ball_radius_m" in schema["properties"]
    assert set(schema["$defs"]) >= {"EmsconSettings", "CanBus"}
    assert client.get("/api/v1/schemas/devices").status_code == 401
    doc = client.get("/openapi.json", headers=auth(tokens["viewer"])).json()
    ok = doc["paths"]["/api/v1/schemas/devices"]["get"]["responses"]["200"]["content"]["application/json"]
    assert ok["schema"] == {"$ref": "#/components/schemas/JsonSchema"}


@pytest.mark.parametrize(
    "devices, field, message",
    [
        ({"tracer": "socket://h:1"}, "body.devices.tracer", "did you mean 'tracker'?"),
        ({"modbus": "x"}, "body.devices.modbus", "expected HOST:PORT"),
        ({"can": {"interface": "socketcand", "channel": "vcan0"}}, "body.devices.can.host", "socketcand"),
        (
            {"tracker": "socket://h:1", "tracker_sigma_um": 0},
            "body.devices.tracker_sigma_um",
            "greater than or equal to 0.1",
        ),
        ({"cmm": "socket://h:1", "cmm_sigma_um": 5000}, "body.devices.cmm_sigma_um", "less than or equal to 1000"),
        ({"emscon": "h:700", "emscon_sigma_um": "twelve"}, "body.devices.emscon_sigma_um", "expected a number"),
    ],
)
def test_a_bad_devices_document_is_refused_naming_the_field(client, tokens, devices, field, message):
    t = auth(tokens["technician"])
    cell = register_cell(client, tokens["technician"], "good")
    body = {"name": "bad", "model": cell["model"], "devices": devices}
    for r in (
        client.post("/api/v1/cells", json=body, headers=t),
        client.patch(f"/api/v1/cells/{cell['id']}", json={"devices": devices}, headers=t),
    ):
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert detail["field"] == field and message in detail["message"], detail
    # the endpoint line registers as it is, and is stored as it was sent
    r = client.patch(f"/api/v1/cells/{cell['id']}", json={"devices": ENDPOINT_LINE}, headers=t)
    assert r.status_code == 200 and r.json()["devices"] == ENDPOINT_LINE, r.text
    summary = client.get(f"/api/v1/cells/{cell['id']}/summary", headers=t).json()
    assert summary["devices"] == ["rtde", "modbus", "emscon", "tracker", "cmm", "can"]
    assert summary["devices_error"] is None


def test_the_served_schema_offers_each_instruments_own_sigma_in_um(client, tokens):
    schema = client.get("/api/v1/schemas/devices", headers=auth(tokens["technician"])).json()
    for key in ("emscon", "tracker", "cmm"):
        field = schema["properties"][f"{key}_sigma_um"]
        assert field["x-page-unit"] == "µm" and field["x-instrument"] == key, field
        assert "µm" in field["description"] and "0.1 to 1000" in field["description"]


def test_an_instruments_own_sigma_registers_and_is_stored_as_sent(client, tokens):
    t = auth(tokens["technician"])
    cell = register_cell(client, tokens["technician"], "own-sigma")
    devices = {"tracker": "socket://127.0.0.1:1", "tracker_sigma_um": 12}
    r = client.patch(f"/api/v1/cells/{cell['id']}", json={"devices": devices}, headers=t)
    assert r.status_code == 200 and r.json()["devices"] == devices, r.text


def test_a_sessions_plan_through_the_api_uses_the_documents_own_sigma(idle_app, tokens, settings):
    from sqlmodel import Session

    from service.models import Cell, RunSession
    from service.session_loop import ensure_plan
    from service.store import make_engine

    t = auth(tokens["technician"])
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "own-sigma-plan")
        devices = {"tracker": "socket://127.0.0.1:1", "tracker_sigma_um": 12}
        assert client.patch(f"/api/v1/cells/{cell['id']}", json={"devices": devices}, headers=t).status_code == 200
        r = client.post(f"/api/v1/cells/{cell['id']}/sessions", json={"kind": "pose", "count": 30}, headers=t)
        assert r.status_code == 201, r.text
        # the session's plan, made as its runner makes it before anything moves (no motion here)
        engine = make_engine(settings.effective_database_url)
        try:
            with Session(engine) as db:
                run = db.get(RunSession, r.json()["id"])
                stored = dict(ensure_plan(db, run, db.get(Cell, cell["id"])).plan_info["instrument_sigma"])
        finally:
            engine.dispose()
        plan = client.get(f"/api/v1/sessions/{r.json()['id']}/plan", headers=t).json()
    assert stored["sigma_m"] == pytest.approx(12e-6) and "tracker_sigma_um" in stored["source"], stored
    assert plan["predicted"]["sigma"] == pytest.approx(0.012), plan
    assert plan["predicted"]["sigma_source"].startswith("the cell's devices document: tracker_sigma_um")
