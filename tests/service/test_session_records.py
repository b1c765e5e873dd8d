"""A session's typed records (service.models: SessionPlan, ControllerEvent, VerifyResult) go to
their JSON and back unchanged, through the store too, and the public ``plan_info`` is the three
together as contracts.md shows it."""

from __future__ import annotations

from dataclasses import replace

from sqlmodel import Session

from service import kinds  # noqa: F401  (registers the kinds: verifications reads which store results)
from service.models import (
    Cell,
    ControllerEvent,
    ImportedFile,
    RunSession,
    SessionPlan,
    VerifyResult,
    public_plan_info,
)
from service.store import make_engine, migrate, verifications

PLAN = SessionPlan(
    joints=(2, 3),
    repeats=3,
    payloads=((5.0, 0.0, 0.0, 0.1),),
    nominal_version=2,
    swept_joint=(2, 2, 3),
    from_dry_run=7,
    imported=ImportedFile("run.csv", 3),
    method="random",
    limits_checked=True,
    planner={"predicted_rms_m": 1e-4, "shortfall": None, "joint_spans_deg": [1.0, 2.0]},
)
EVENT = ControllerEvent(version=2, changed=True, warning="it changed", figures={"moved_mm": 0.4})
RESULT = VerifyResult(
    calibration_id=4,
    n=3,
    rms=0.1,
    max=0.2,
    p95=0.19,
    mean=0.09,
    unit="mm",
    registered={"rms": 0.05, "max": 0.1},
    outside_calibrated_region=1,
    candidate={"calibration_id": 5, "passed": True},
)


def test_each_record_round_trips_through_its_json():
    assert SessionPlan.from_json(PLAN.to_json()) == PLAN
    assert ControllerEvent.from_json(EVENT.to_json()) == EVENT
    assert VerifyResult.from_json(RESULT.to_json()) == RESULT
    assert SessionPlan.from_json(None) == SessionPlan() and SessionPlan().to_json() == {}
    assert PLAN.visits == 3 and SessionPlan().visits == 1
    # a document with figures the types do not name keeps them (a stored result of another version)
    doc = {**RESULT.to_json(), "later_figure": 1.5}
    assert VerifyResult.from_json(doc).to_json() == doc


def test_the_planners_figures_join_the_request():
    asked = SessionPlan(joints=(1,), repeats=2)
    planned = asked.planned(
        {"method": "random", "limits_checked": True, "poses": 4}, swept_joint=[1, 1], nominal_version=3
    )
    assert planned == replace(
        asked, method="random", limits_checked=True, swept_joint=(1, 1), nominal_version=3, planner={"poses": 4}
    )


def test_the_public_plan_info_is_the_three_records_together():
    public = public_plan_info(PLAN, EVENT, RESULT)
    assert public == {
        **{k: v for k, v in PLAN.to_json().items() if k != "swept_joint"},
        "controller_model": {"version": 2, "changed": True, "warning": "it changed", "moved_mm": 0.4},
        "verify": RESULT.to_json(),
    }
    assert public["payloads"] == [[5.0, 0.0, 0.0, 0.1]] and public["imported"] == {"name": "run.csv", "rows": 3}
    assert public_plan_info(SessionPlan(), None, None) is None


def test_records_round_trip_through_the_store(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with Session(engine) as db:
        cell = Cell(name="c", model={}, devices={})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="verify", state="completed")
        run.record_plan(PLAN)
        run.record_controller(EVENT)
        run.record_verify(RESULT)
        db.add(run)
        db.commit()
        run_id = run.id
    with Session(engine) as db:
        stored = db.get(RunSession, run_id)
        assert stored.session_plan() == PLAN
        assert stored.controller() == EVENT
        assert stored.verify_result() == RESULT
        assert [(sid, v) for sid, _, v in verifications(db, stored.cell_id)] == [(run_id, RESULT)]
    engine.dispose()
