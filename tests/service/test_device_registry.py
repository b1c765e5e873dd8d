"""The device registry (issue 23): one table from a configuration key to its field, driver, fake,
connection test and page field; a new instrument touches its driver, its fake, its tests, its
docs and the registry alone.

The stub instrument below is added to a copy of the packages exactly as docs/architecture.md
("Adding an instrument") says, and the copy is then used end to end in a fresh interpreter: the
devices document takes the new key, the served schema lists it for the page, ``recal fake-cell``
finds its fake, and the connection test reaches the fake through the driver."""

from __future__ import annotations

import filecmp
import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fakes.cell import FAKES
from service.device_config import DEVICES, DevicesConfig, devices_json_schema, parse_devices

ROOT = Path(__file__).resolve().parents[2]


def _load(path: str):
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def test_every_device_field_has_one_entry_whose_driver_and_fake_exist():
    # not devices of their own (an instrument's own figure is a setting of its device)
    settings = {
        "ready",
        "encoders",
        "resolvers",
        "cmm_ball_radius_m",
        "emscon_sigma_um",
        "tracker_sigma_um",
        "cmm_sigma_um",
    }
    assert [e.key for e in DEVICES] == [k for k in DevicesConfig.model_fields if k not in settings]
    fake_classes = {fake["cls"] for fake in FAKES}
    for entry in DEVICES:
        assert isinstance(_load(entry.driver), type), entry.driver
        assert _load(entry.fake) in fake_classes, f"{entry.fake} has no CELL_FAKE line: fake-cell cannot start it"


def test_the_served_schema_lists_the_registry_for_the_page():
    schema = devices_json_schema()
    assert [d["key"] for d in schema["x-devices"]] == [e.key for e in DEVICES]
    for entry in DEVICES:
        assert schema["properties"][entry.key]["x-label"] == entry.label


def test_a_cell_opens_the_first_device_of_each_role_in_the_registrys_order():
    both = parse_devices({"modbus": "10.0.0.1:502", "rtde": "10.0.0.2", "tracker": "socket://10.0.0.3:1"})
    assert both.kinds() == ["rtde", "modbus", "tracker"]
    assert [e.key for e in both.present("robot")] == ["rtde", "modbus"]
    assert both.instrument_address("tracker") == "socket://10.0.0.3:1"


# --------------------------------------------------------------------------- a stub instrument

STUB_DRIVER = '''"""A stub gauge: one line over TCP (the example of docs/architecture.md)."""

import socket


class StubGauge:
    name = "stub gauge"

    def __init__(self, url: str, timeout_s: float):
        host, _, port = url.removeprefix("socket://").rpartition(":")
        self.sock = socket.create_connection((host, int(port)), timeout=timeout_s)

    def identity(self) -> str:
        self.sock.sendall(b"*IDN?\\n")
        return self.sock.makefile().readline().strip()

    def close(self) -> None:
        self.sock.close()
'''

STUB_FAKE = '''"""The stub gauge's fake: answers *IDN? (the example of docs/architecture.md)."""

import socketserver
import threading


class StubGaugeFake:
    def __init__(self, cell, host="127.0.0.1", port=0, answer="STUB,GAUGE,1"):
        class Handler(socketserver.StreamRequestHandler):
            def handle(self):
                for _line in self.rfile:
                    self.wfile.write(answer.encode() + b"\\n")

        self.server = socketserver.ThreadingTCPServer((host, port), Handler)
        self.server.daemon_threads = True

    def start(self):
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def stop(self):
        self.server.shutdown()
        self.server.server_close()

    def endpoint(self):
        host, port = self.server.server_address[:2]
        return {"gauge": f"socket://{host}:{port}"}


CELL_FAKE = {
    "key": "gauge",
    "order": 70,
    "cls": StubGaugeFake,
    "kwargs": lambda args: {"answer": args.gauge_answer},
    "options": [("--gauge-answer", {"default": "STUB,GAUGE,1", "help": "what the stub gauge answers"})],
}
'''

STUB_FIELD = """    gauge: SerialUrl | None = Field(None, title="Stub gauge", description="socket://HOST:PORT of the gauge")
"""

STUB_ENTRY = """    DeviceEntry(
        key="gauge",
        role="cmm",
        label="stub gauge",
        driver="drivers.stub_gauge:StubGauge",
        fake="fakes.stub_gauge:StubGaugeFake",
        open=lambda config, timeout_s: __import__("drivers.stub_gauge").stub_gauge.StubGauge(config.gauge, timeout_s),
        test=lambda config, timeout_s: {"ok": True, "name": "stub gauge", "answer": _stub_identity(config, timeout_s)},
        sigma_m=lambda config: 7e-6,  # the gauge's own figure: sessions plan and weigh with it
    ),
"""

STUB_TEST_FN = """

def _stub_identity(config: DevicesConfig, timeout_s: float) -> str:
    gauge = DEVICE_BY_KEY["gauge"].open(config, timeout_s)
    try:
        return gauge.identity()
    finally:
        gauge.close()
"""

USE_IT = """
import json
from fakes.cell import FAKES, build_parser
from fakes.world import SimCell
from calibration.robots import nominal
from service.device_config import parse_devices, devices_json_schema
from service.devicetest import test_devices

entry = next(f for f in FAKES if f["key"] == "gauge")
args = build_parser().parse_args(["--truth", "truth.json", "--gauge-answer", "GAUGE,2"])
fake = entry["cls"](SimCell(nominal("ur5e")), "127.0.0.1", **entry["kwargs"](args))
fake.start()
try:
    config = parse_devices(fake.endpoint())
    rows = test_devices(config, timeout_s=3)
    print(json.dumps({
        "kinds": config.kinds(),
        "has_cmm": config.has("cmm"),
        "page": [d["key"] for d in devices_json_schema()["x-devices"]],
        "rows": rows,
    }))
finally:
    fake.stop()
"""


def _add_stub_instrument(tree: Path) -> None:
    """What docs/architecture.md says a new instrument is: a driver, a fake, and in the registry a
    field of DevicesConfig with its entry (its test and its docs page are files of their own)."""
    (tree / "drivers" / "stub_gauge.py").write_text(STUB_DRIVER)
    (tree / "fakes" / "stub_gauge.py").write_text(STUB_FAKE)
    registry = tree / "service" / "device_registry.py"
    text = registry.read_text()
    field_at = text.index("    can: CanBus | None = Field(")
    text = text[:field_at] + STUB_FIELD + text[field_at:]
    end = text.index("\n)\n\nDEVICE_BY_KEY")
    text = text[: end + 1] + STUB_ENTRY + text[end + 1 :]
    registry.write_text(text + STUB_TEST_FN)


def _changed(original: Path, copy: Path) -> list[str]:
    out = []
    for path in sorted(copy.rglob("*.py")):
        rel = path.relative_to(copy)
        if not (original / rel).exists() or not filecmp.cmp(original / rel, path, shallow=False):
            out.append(str(rel))
    return out


def test_a_stub_instrument_is_its_driver_its_fake_and_one_registry_entry(tmp_path):
    for package in ("calibration", "drivers", "fakes", "service"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    _add_stub_instrument(tmp_path)
    assert _changed(ROOT, tmp_path) == ["drivers/stub_gauge.py", "fakes/stub_gauge.py", "service/device_registry.py"]

    done = subprocess.run(
        [sys.executable, "-c", USE_IT], cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    assert seen["kinds"] == ["gauge"] and seen["has_cmm"]
    assert seen["page"][-1] == "gauge"
    # the fake's own command-line option (declared on its CELL_FAKE line) reached it through fake-cell's parser
    assert seen["rows"] == [
        {"device": "stub gauge", "address": seen["rows"][0]["address"], "elapsed_ms": seen["rows"][0]["elapsed_ms"]}
        | {"ok": True, "name": "stub gauge", "answer": "GAUGE,2"}
    ]


# A session planned on a cell whose measuring device is the stub gauge (its entry declares 7 um),
# and one planned the same way on a cell that names no such device (the library's 20 um stand in):
# what each stores with its plan, and what its plan's page predicts, then again after the cell's
# devices changed (the figure stays the one of its time).
PLAN_WITH_IT = """
import json, sys, tempfile
from pathlib import Path
from sqlmodel import Session
from calibration.robots import nominal_document
from service.models import Cell, RunSession
from service.session_loop import ensure_plan
from service.results import plan_preview
from service.settings import Settings
from service.store import make_engine, migrate

def planned(devices, home):
    engine = make_engine(f"sqlite:///{home}/recal.db")
    migrate(engine)
    settings = Settings(home=Path(home))
    with Session(engine) as db:
        cell = Cell(name="c", model=nominal_document("ur5e"), devices=devices)
        db.add(cell)
        db.commit()
        db.refresh(cell)
        run = RunSession(cell_id=cell.id, kind="pose", device="cmm", planned=30)
        db.add(run)
        db.commit()
        db.refresh(run)
        run = ensure_plan(db, run, cell)
        before = plan_preview(db, run, cell, settings)["predicted"]
        cell.devices = {"cmm": "socket://127.0.0.1:1294"}
        db.add(cell)
        db.commit()
        after = plan_preview(db, run, cell, settings)["predicted"]
    engine.dispose()
    return {"stored": run.plan_info["instrument_sigma"], "before": before, "after": after}

out = {}
for name, devices in (("gauge", {"gauge": "socket://127.0.0.1:1"}), ("none", {})):
    with tempfile.TemporaryDirectory() as home:
        out[name] = planned(devices, home)
print(json.dumps(out))
"""


def test_a_stub_instruments_own_sigma_drives_the_plan_and_its_predicted_accuracy(tmp_path):
    for package in ("calibration", "drivers", "fakes", "service"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    _add_stub_instrument(tmp_path)

    done = subprocess.run(
        [sys.executable, "-c", PLAN_WITH_IT], cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    gauge, none = seen["gauge"], seen["none"]
    assert gauge["stored"] == {"sigma_m": 7e-6, "source": "the driver's default: stub gauge"}
    assert none["stored"]["sigma_m"] == 20e-6 and "library's default" in none["stored"]["source"]
    # the page's figure (mm) and its note are the gauge's, and stay so when the cell's devices change
    for shown in (gauge["before"], gauge["after"]):
        assert shown["sigma"] == 0.007 and shown["sigma_source"] == "the driver's default: stub gauge"
        assert "0.007 mm noise per axis (the driver's default: stub gauge)" in shown["note"]
    # the same plan (the same seed and model) predicts in proportion to the instrument's noise
    assert gauge["before"]["rms"] / none["before"]["rms"] == pytest.approx(7 / 20, rel=1e-4)


def _plan_with(devices: dict, home) -> tuple[dict, dict]:
    """The stored plan's instrument figure and the page's predicted accuracy of a pose session
    measured with the cell's tracker, its devices document ``devices``."""
    from sqlmodel import Session

    from calibration.robots import nominal_document
    from service.models import Cell, RunSession
    from service.results import plan_preview
    from service.session_loop import ensure_plan
    from service.settings import Settings
    from service.store import make_engine, migrate

    engine = make_engine(f"sqlite:///{home}/recal.db")
    migrate(engine)
    try:
        with Session(engine) as db:
            cell = Cell(name="c", model=nominal_document("ur5e"), devices=devices)
            db.add(cell)
            db.commit()
            db.refresh(cell)
            run = RunSession(cell_id=cell.id, kind="pose", device="tracker", planned=30)
            db.add(run)
            db.commit()
            db.refresh(run)
            run = ensure_plan(db, run, cell)
            predicted = plan_preview(db, run, cell, Settings(home=Path(home)))["predicted"]
            return dict(run.plan_info["instrument_sigma"]), predicted
    finally:
        engine.dispose()


def test_the_devices_documents_own_sigma_drives_the_plan_and_is_recorded_as_its_source(tmp_path):
    (tmp_path / "own").mkdir()
    (tmp_path / "vendor").mkdir()
    own, own_predicted = _plan_with({"tracker": "socket://127.0.0.1:1", "tracker_sigma_um": 12}, tmp_path / "own")
    vendor, vendor_predicted = _plan_with({"tracker": "socket://127.0.0.1:1"}, tmp_path / "vendor")
    assert own["sigma_m"] == pytest.approx(12e-6) and own["source"].startswith("the cell's devices document")
    assert "tracker_sigma_um" in own["source"]
    assert vendor["sigma_m"] == pytest.approx(20e-6) and vendor["source"].startswith("the driver's default")
    assert own_predicted["sigma"] == pytest.approx(0.012) and "devices document" in own_predicted["note"]
    # the same plan predicts in proportion to the instrument's noise
    assert own_predicted["rms"] / vendor_predicted["rms"] == pytest.approx(12 / 20, rel=1e-4)
