"""What can be checked of the packaging without a Docker engine (none on the development
machines): the image runs as a non-root user with a healthcheck and installs pinned versions
that satisfy pyproject.toml; the compose files restart their services, check their health
and take the database password from a secret; pymodbus is new enough for the driver."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
yaml = pytest.importorskip("yaml")


def _dependencies() -> list[Requirement]:
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    reqs = [Requirement(r) for r in doc["project"]["dependencies"]]
    return reqs + [Requirement(r) for r in doc["project"]["optional-dependencies"]["fleet"]]


def _lock() -> dict[str, Version]:
    pins = {}
    for line in (ROOT / "docker" / "requirements.lock").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, version = line.partition("==")
        assert sep, f"docker/requirements.lock: {line!r} is not pinned with =="
        pins[canonicalize_name(name)] = Version(version)
    return pins


def test_pymodbus_is_pinned_to_what_the_driver_needs():
    # drivers/modbus_robot.py passes device_id=, which pymodbus has from 3.10 (slave= before)
    assert "device_id=" in (ROOT / "drivers" / "modbus_robot.py").read_text()
    spec = next(r for r in _dependencies() if r.name == "pymodbus").specifier
    assert not spec.contains("3.9.2") and spec.contains("3.10.0")


def test_the_lock_pins_every_dependency_within_its_range():
    pins = _lock()
    env = {"platform_machine": "x86_64", "python_version": "3.11", "sys_platform": "linux"}
    for req in _dependencies():
        if req.marker is not None and not req.marker.evaluate(env):
            continue
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not in docker/requirements.lock: run bash docker/lock.sh"
        assert req.specifier.contains(pins[name], prereleases=True), (
            f"docker/requirements.lock pins {req.name}=={pins[name]}, outside {req.specifier}: run bash docker/lock.sh"
        )


def test_the_image_installs_the_lock_and_runs_as_a_user_with_a_healthcheck():
    text = (ROOT / "docker" / "Dockerfile").read_text()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert any(re.search(r"pip install .*-r docker/requirements\.lock", ln) for ln in lines)
    assert any("--no-deps" in ln and "pip install" in ln for ln in lines)  # nothing resolved outside the lock
    users = [ln.split()[1] for ln in lines if ln.startswith("USER ")]
    assert users and users[-1] not in ("root", "0")
    assert any(ln.startswith("HEALTHCHECK") for ln in lines) and "/api/v1/health" in text
    cmd = [ln for ln in lines if ln.startswith("CMD ")]
    assert cmd and "serve" in cmd[-1]


@pytest.mark.parametrize("name", ["compose.yaml", "compose.fleet.yaml"])
def test_compose_restarts_checks_health_and_keeps_the_password_in_a_secret(name):
    text = (ROOT / "docker" / name).read_text()
    doc = yaml.safe_load(text)
    assert doc["secrets"]["db_password"]["file"]
    for svc_name, svc in doc["services"].items():
        one_shot = "profiles" in svc  # the nightly job: started by cron, not kept running
        assert svc.get("restart") == ("no" if one_shot else "unless-stopped"), svc_name
        env = svc.get("environment") or {}
        url = env.get("RECAL_DATABASE_URL")
        if url is not None:
            assert ":" not in url.split("://", 1)[1].split("@", 1)[0], f"{svc_name}: a password in RECAL_DATABASE_URL"
            assert env.get("RECAL_DATABASE_PASSWORD_FILE") == "/run/secrets/db_password", svc_name
            assert "db_password" in svc["secrets"], svc_name
    db = doc["services"]["db"]
    assert "POSTGRES_PASSWORD" not in db["environment"] and db["environment"]["POSTGRES_PASSWORD_FILE"]
    assert db["healthcheck"]["test"]
    cells = [s for n, s in doc["services"].items() if n.startswith("cell")]
    assert cells and all("29999" in " ".join(s["healthcheck"]["test"]) for s in cells)


def test_python_dash_m_recal_is_packaged():
    # contracts §6: `python -m recal` is the same CLI as `recal`; a wheel must carry the `recal` package
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "recal*" in doc["tool"]["setuptools"]["packages"]["find"]["include"]
    assert "from service.cli import main" in (ROOT / "recal" / "__main__.py").read_text()
    assert doc["project"]["scripts"]["recal"] == "service.cli:main"


def test_the_image_copies_every_package():
    # a package left out of the image is silently missing from its install (`python -m recal` there)
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in doc["tool"]["setuptools"]["packages"]["find"]["include"]]
    text = (ROOT / "docker" / "Dockerfile").read_text()
    for package in packages:
        assert re.search(rf"^COPY {package} \./{package}$", text, re.M), f"docker/Dockerfile does not copy {package}/"
