"""Settings read from the environment: a bad value names the variable and what was expected."""

from __future__ import annotations

import os

import pytest

from service.cli import main
from service.settings import Settings, SettingsError, worker_concurrency


def test_worker_concurrency_defaults_to_four_per_core_and_names_a_bad_value():
    cores = len(os.sched_getaffinity(0))
    assert worker_concurrency({}) == 4 * cores
    assert worker_concurrency({"RECAL_WORKER_CONCURRENCY": " 12 "}) == 12
    for raw, expected in (("many", "expected a whole number, got 'many'"), ("0", "expected at least 1, got 0")):
        with pytest.raises(SettingsError) as err:
            worker_concurrency({"RECAL_WORKER_CONCURRENCY": raw})
        assert str(err.value) == f"environment variable RECAL_WORKER_CONCURRENCY: {expected}"


def test_recal_worker_refuses_a_bad_concurrency_in_one_line(monkeypatch, capsys):
    monkeypatch.setenv("RECAL_WORKER_CONCURRENCY", "many")
    assert main(["worker", "--all-sites"]) == 2
    err = capsys.readouterr().err
    assert "RECAL_WORKER_CONCURRENCY: expected a whole number, got 'many'" in err and "Traceback" not in err


def test_a_bad_number_in_the_environment_names_the_variable():
    with pytest.raises(SettingsError) as err:
        Settings.from_env({"RECAL_LEASE_TTL_S": "soon"})
    assert "RECAL_LEASE_TTL_S" in str(err.value) and "expected a number" in str(err.value)


def test_the_database_password_comes_from_a_secret_file(tmp_path):
    secret = tmp_path / "db_password"
    secret.write_text("s3cr/t:@x\n")  # characters a URL must escape; the file's newline is not part of it
    s = Settings.from_env(
        {"RECAL_DATABASE_URL": "postgresql+psycopg://recal@db:5432/recal", "RECAL_DATABASE_PASSWORD_FILE": str(secret)}
    )
    from sqlalchemy.engine import make_url

    url = make_url(s.effective_database_url)
    assert url.password == "s3cr/t:@x" and url.username == "recal" and url.host == "db" and url.database == "recal"
    for env, expected in (
        ({"RECAL_DATABASE_PASSWORD_FILE": str(secret)}, "expected RECAL_DATABASE_URL too"),
        (
            {
                "RECAL_DATABASE_URL": "postgresql+psycopg://recal@db/recal",
                "RECAL_DATABASE_PASSWORD_FILE": str(tmp_path / "missing"),
            },
            "cannot read",
        ),
    ):
        with pytest.raises(SettingsError) as err:
            Settings.from_env(env)
        assert "RECAL_DATABASE_PASSWORD_FILE" in str(err.value) and expected in str(err.value)
