"""Schema version 10 on a store made by version 9: a session's controller event and a verify
session's result move out of ``plan_info`` into their own columns (``session.controller_event``,
``session.verify``); every stored session reads as before, its public ``plan_info`` unchanged."""

from __future__ import annotations

import json

from sqlalchemy import inspect, text
from sqlmodel import Session

from service import kinds  # noqa: F401  (registers the kinds: verifications reads which store results)
from service.models import RunSession
from service.store import SCHEMA_VERSION, make_engine, migrate, verifications

VERIFY = {"calibration_id": None, "n": 3, "rms": 0.2, "max": 0.3, "p95": 0.29, "mean": 0.19, "unit": "mm"}
CONTROLLER = {"version": 1, "changed": False, "warning": None, "moved_mm": None}
PLAN = {"method": "random", "limits_checked": True, "repeats": 2, "nominal_version": 1, "swept_joint": [0, 0]}


def test_version_9_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 9 made: the records inside plan_info
        for column in ("controller_event", "verify"):
            conn.execute(text(f"ALTER TABLE session DROP COLUMN {column}"))
        conn.execute(text("UPDATE schema_version SET version = 9"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at, model_version) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
        sessions = [
            ("verify", {**PLAN, "controller_model": CONTROLLER, "verify": VERIFY}),  # a verify session on a UR
            ("pose", {**PLAN, "controller_model": CONTROLLER}),
            ("pose", PLAN),  # nothing to move
            ("verify", None),  # no plan_info at all
        ]
        for kind, info in sessions:
            conn.execute(
                text(
                    "INSERT INTO session (cell_id, kind, state, planned, device, dry_run, plan_info, created_by, "
                    "created_at, updated_at, beam_recoveries) VALUES (1, :kind, 'completed', 2, 'tracker', "
                    "false, :info, 'anna', CURRENT_TIMESTAMP, CURRENT_TIMESTAMP, 0)"
                ),
                {"kind": kind, "info": None if info is None else json.dumps(info)},
            )
    assert migrate(engine) == SCHEMA_VERSION >= 10
    assert {"controller_event", "verify"} <= {c["name"] for c in inspect(engine).get_columns("session")}
    with Session(engine) as db:
        first, second, third, fourth = (db.get(RunSession, i) for i in (1, 2, 3, 4))
        assert first.verify_result().to_json() == VERIFY and first.verify_result().rms == 0.2
        assert first.controller().to_json() == CONTROLLER and first.controller().changed is False
        assert "verify" not in first.plan_info and "controller_model" not in first.plan_info
        assert first.session_plan().visits == 2 and first.session_plan().method == "random"
        public = {k: v for k, v in PLAN.items() if k != "swept_joint"}
        assert first.public_plan_info() == {**public, "controller_model": CONTROLLER, "verify": VERIFY}
        assert second.verify_result() is None and second.controller().to_json() == CONTROLLER
        assert third.public_plan_info() == public and third.controller() is None
        assert fourth.public_plan_info() is None and fourth.verify_result() is None
        assert [(sid, v.to_json()) for sid, _, v in verifications(db, 1)] == [(1, VERIFY)]
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
