"""Use cases of sessions, apart from HTTP: start one (checked before anything moves), the public
view of a session (one query, polled by pages and jobs), and the rules every route shares (a
session is active while planned or running; a cell runs one at a time). The routes
(``service/api/routes``) call these; refusals are :mod:`service.problems`."""

from __future__ import annotations

import time
from dataclasses import replace

from sqlalchemy import bindparam, delete, func
from sqlalchemy import select as sa_select
from sqlalchemy.exc import IntegrityError
from sqlmodel import Session, col, select

from calibration.model import model_from_dict

from .kinds import kind_of
from .models import (
    ACTIVE,
    TERMINAL,
    Cell,
    ControllerEvent,
    Measurement,
    RunSession,
    SessionCreate,
    SessionPlan,
    SessionPublic,
    Token,
    VerifyResult,
    public_plan_info,
    utcnow,
)
from .problems import Conflict, Invalid, NotFound
from .runners import SessionRunner
from .store import audit, measured_count, set_state_unless


def public_session(db, run: RunSession) -> SessionPublic:
    assert run.id is not None  # a stored session
    return SessionPublic(
        **run.model_dump(exclude={"plan", "plan_info", "controller_event", "verify", "lease_owner", "lease_expires"}),
        measured=measured_count(db, run.id),
        plan_info=run.public_plan_info(),
    )


# What GET /sessions/{id} and the progress events read: the public columns and the measured count
# in one query, without the plan (every configuration of the session) or an ORM object. Pages and
# nightly jobs poll this; bench/service.py measures it.
_PUBLIC = [
    c
    for c in RunSession.__table__.columns  # type: ignore[attr-defined]  # SQLAlchemy's, not in SQLModel's stubs
    if c.name in SessionPublic.model_fields
]
_MEASURED = (
    select(func.count(func.distinct(Measurement.seq)))
    .where(col(Measurement.session_id) == RunSession.id)
    .correlate(RunSession)
    .scalar_subquery()
    .label("measured")
)
_RECORDS = (col(RunSession.controller_event), col(RunSession.verify))  # plan_info's other parts (public_plan_info)
_READ_PUBLIC = sa_select(*_PUBLIC, *_RECORDS, _MEASURED).where(col(RunSession.id) == bindparam("session_id"))


def read_public_session(db, session_id: int) -> SessionPublic:
    row = db.connection().execute(_READ_PUBLIC, {"session_id": session_id}).mappings().first()
    if row is None:
        raise NotFound(f"no session {session_id}")
    doc = dict(row)
    controller, verify = doc.pop("controller_event"), doc.pop("verify")
    info = public_plan_info(
        SessionPlan.from_json(doc.pop("plan_info")),
        ControllerEvent.from_json(controller) if controller else None,
        VerifyResult.from_json(verify) if verify else None,
    )
    return SessionPublic(**doc, plan_info=info)


def get_cell(db, cell_id: int) -> Cell:
    cell = db.get(Cell, cell_id)
    if cell is None:
        raise NotFound(f"no cell {cell_id}")
    return cell


def get_run(db, session_id: int) -> RunSession:
    run = db.get(RunSession, session_id)
    if run is None:
        raise NotFound(f"no session {session_id}")
    return run


def start_session(db: Session, cell: Cell, body: SessionCreate, tok: Token, runner) -> SessionPublic:
    assert cell.id is not None  # a stored cell
    model = model_from_dict(cell.model)
    if body.target is not None and body.target not in model.targets:
        raise Invalid(
            "body.target",
            f"unknown target {body.target!r}; the cell's model has: {', '.join(sorted(model.targets)) or 'none'}",
        )
    joints = body.joints or []
    for i, j in enumerate(joints):
        if not 1 <= j <= model.n_joints or j in joints[:i]:
            raise Invalid(
                f"body.joints[{i}]", f"expected a joint number from 1 to {model.n_joints}, each once; got {j}"
            )
    kind = kind_of(body.kind)
    if not body.dry_run:  # a dry run moves and measures nothing: any cell can show a plan
        kind.check(cell, model, device=body.device, joints=body.joints, payloads=body.payloads)
        refuse_if_busy(db, cell.id)
    run = RunSession(
        cell_id=cell.id,
        kind=body.kind,
        planned=body.count,
        device=body.device,
        target=body.target if body.target is not None else kind.default_target(model, body.device),
        dry_run=body.dry_run,
        created_by=tok.name,
    )
    run.record_plan(requested_plan(body, model.units.length_m))
    detail = {"cell": cell.id, "kind": run.kind, "count": body.count, "dry_run": body.dry_run}
    return _commit_and_start(db, run, runner, tok, detail)


def requested_plan(body: SessionCreate, length_m: float) -> SessionPlan:
    """What a session request asks of its plan: the joints, the repeats and the payloads (SI: kg,
    then the centre of gravity in the tool frame, m, from the model's length unit ``length_m``)."""
    return SessionPlan(
        joints=tuple(body.joints) if body.joints else None,
        repeats=body.repeats if body.repeats > 1 else None,
        payloads=(
            tuple((p[0], p[1] * length_m, p[2] * length_m, p[3] * length_m) for p in body.payloads)
            if body.payloads
            else None
        ),
    )


def _commit_and_start(
    db: Session, run: RunSession, runner, tok: Token, detail: dict | None, action: str = "start session"
) -> SessionPublic:
    """Store ``run`` planned, audited, and start it (or queue it: :func:`commit_planned`)."""
    try:
        queued = commit_planned(db, run, runner)
    except IntegrityError:  # another request (any API process) started one on this cell meanwhile
        db.rollback()
        raise Conflict("another session is already driving this cell") from None
    db.refresh(run)
    assert run.id is not None  # committed
    if run.dry_run:  # after the new one has its id: on SQLite a deleted highest id would be given again
        forget_dry_runs(db, run.cell_id, keep=run.id)
    audit(db, actor=tok.name, action=action, subject=f"session {run.id}", detail=detail)
    if not queued:
        runner.start(run.id)
    return public_session(db, run)


def driving_session(
    db: Session, cell_id: int, *, dry_runs: bool = False, other_than: int | None = None
) -> RunSession | None:
    """The session driving the cell (planned or running), if any; dry runs (which move nothing)
    only if ``dry_runs``; never session ``other_than``."""
    where = [col(RunSession.cell_id) == cell_id, col(RunSession.state).in_(ACTIVE)]
    if not dry_runs:
        where.append(col(RunSession.dry_run) == False)  # noqa: E712 (SQL)
    if other_than is not None:
        where.append(col(RunSession.id) != other_than)
    return db.exec(select(RunSession).where(*where)).first()


RESUMABLE = ("paused", "interrupted", "planned")
ABORT_WAIT_S = 3.0  # how long an abort waits for the session to have stopped before answering


def resume_session(db: Session, run: RunSession, tok: Token, runner) -> SessionPublic:
    """Continue a paused or interrupted session (or one left planned) with the first
    configuration not yet measured. Refused (:class:`Conflict`) when the cell's nominal model
    was replaced since it was planned, or another session drives the cell."""
    if run.state not in RESUMABLE:
        raise Conflict(f"session {run.id} is {run.state}; only a paused or interrupted session can resume")
    planned_for = run.session_plan().nominal_version
    cell = get_cell(db, run.cell_id)
    if run.plan is not None and planned_for is not None and planned_for != cell.model_version:
        raise Conflict(
            f"session {run.id} was planned for the cell's nominal model version {planned_for}; "
            f"it has been replaced (version {cell.model_version}): start a new session"
        )
    busy = driving_session(db, run.cell_id, dry_runs=True, other_than=run.id)
    if busy is not None:
        raise Conflict(f"session {busy.id} is driving this cell")
    run.state, run.reason, run.updated_at = "planned", None, utcnow()
    return _commit_and_start(db, run, runner, tok, None, action="resume session")


def pause_session(db: Session, run: RunSession, tok: Token, runner) -> SessionPublic:
    """Pause a running session at its next step (a session nothing runs is paused here)."""
    if run.state not in ACTIVE:
        raise Conflict(f"session {run.id} is {run.state}; only a running session can pause")
    audit(db, actor=tok.name, action="pause session", subject=f"session {run.id}")
    if not runner.pause(run.id):  # nothing runs it: paused here
        set_state_unless(db, run, TERMINAL + ("paused", "interrupted"), "paused", "paused on request")
    db.refresh(run)
    return public_session(db, run)


def refuse_if_busy(db: Session, cell_id: int) -> None:
    """:class:`Conflict` when a session is driving the cell. The store's
    one-active-session-per-cell index has the last word (:func:`commit_planned`)."""
    busy = driving_session(db, cell_id)
    if busy is not None:
        raise Conflict(f"session {busy.id} is already driving this cell ({busy.state})")


def run_dry_plan(db: Session, dry: RunSession, cell: Cell, tok: Token, runner) -> SessionPublic:
    """Run the plan of a completed dry run for real: a new session measuring exactly the
    configurations that were shown and checked, after the same checks as any start."""
    assert cell.id is not None  # a stored cell
    if not dry.dry_run or dry.state != "completed" or not dry.plan:
        raise Conflict(
            f"session {dry.id} is not a completed dry run with a plan "
            f"(state {dry.state}{', ' + dry.reason if dry.reason else ''})"
        )
    shown = dry.session_plan()
    kind_of(dry.kind).check(
        cell,
        model_from_dict(cell.model),
        device=dry.device,
        joints=None if shown.joints is None else list(shown.joints),
        payloads=None if shown.payloads is None else [list(p) for p in shown.payloads],
    )
    refuse_if_busy(db, cell.id)
    run = RunSession(
        cell_id=cell.id,
        kind=dry.kind,
        planned=len(dry.plan),
        device=dry.device,
        target=dry.target,
        dry_run=False,
        created_by=tok.name,
        plan=dry.plan,
    )
    run.record_plan(replace(shown, dry_run=False, from_dry_run=dry.id))
    return _commit_and_start(
        db, run, runner, tok, {"cell": cell.id, "kind": run.kind, "count": run.planned, "plan_of": dry.id}
    )


def forget_dry_runs(db, cell_id: int, *, keep: int) -> None:
    """Delete the cell's finished dry runs but ``keep``. A dry run ("Show the plan") is a plan
    to confirm (and to run, ``POST /sessions/{id}/run``, as often as wanted), not a session: only
    the cell's latest is kept, and session lists leave it out. Dry runs have no measurements."""
    db.execute(
        delete(RunSession).where(
            col(RunSession.cell_id) == cell_id,
            col(RunSession.dry_run) == True,  # noqa: E712
            col(RunSession.state).not_in(ACTIVE),
            col(RunSession.id) != keep,
        )
    )
    db.commit()


def commit_planned(db, run: RunSession, runner: SessionRunner) -> bool:
    """Commit ``run``, planned. Where the runner queues sessions (the fleet), its job is queued in
    the same transaction, so that no session is ever stored planned without one; True then. Else
    (the embedded default) the caller starts it once committed."""
    db.add(run)
    db.flush()  # the id, for the job (and the one-active-session-per-cell index speaks here)
    queued = runner.queue(db, run)
    db.commit()
    return queued


def abort_session(db: Session, run: RunSession, tok: Token, runner) -> tuple[SessionPublic, float]:
    """Stop the robot now and end the session: the session as it ended (the runner stops the
    robot at once and the session at its next step, while planning within 0.1 s, and stores it
    aborted before its devices close; waited for up to ``ABORT_WAIT_S``), and the
    ``time.perf_counter()`` at which the robot had been told to stop. A session nothing runs
    (planned and never started, paused, interrupted) is aborted here."""
    if run.state in TERMINAL:
        raise Conflict(f"session {run.id} is {run.state} already")
    stopping = runner.abort(run.id)
    stopped_at = time.perf_counter()
    audit(db, actor=tok.name, action="abort session", subject=f"session {run.id}")
    if stopping:
        runner.wait(run.id, ABORT_WAIT_S)
    else:
        set_state_unless(db, run, TERMINAL, "aborted", "aborted on request")
    db.refresh(run)
    return public_session(db, run), stopped_at
