"""The event stream's tickets live in the database (issue 12): a fleet runs several API processes
on one database (docs/fleet.md), and the page's ticket request and its stream may reach
different ones. A ticket is good once, in any of them, and not after it expires."""

from __future__ import annotations

from datetime import timedelta

from sqlmodel import Session

from service.api.deps import Tickets
from service.models import Cell, RunSession, utcnow
from service.store import make_engine

from .conftest import auth


def _ended_session(settings, name: str = "tickets") -> int:
    """A session (of a new cell ``name``) that has ended: its stream sends one event and closes."""
    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        cell = Cell(name=name, model={}, devices={})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="verify", state="aborted", reason="aborted on request")
        db.add(run)
        db.commit()
        sid = run.id
    engine.dispose()
    return sid


def test_a_ticket_from_one_api_process_opens_the_stream_once_in_another(idle_app, tokens, settings):
    with idle_app() as first, idle_app() as second:  # two API processes of one fleet, one database
        sid = _ended_session(settings)

        def ticket() -> str:
            r = first.post(f"/api/v1/sessions/{sid}/events/ticket", headers=auth(tokens["viewer"]))
            assert r.status_code == 201, r.text
            return r.json()["ticket"]

        def stream(client, plain: str):
            return client.get(f"/api/v1/sessions/{sid}/events?ticket={plain}")

        plain = ticket()
        r = stream(second, plain)
        assert r.status_code == 200, r.text
        assert "event: progress" in r.text and '"state": "aborted"' in r.text
        # used up, in every process
        for client in (second, first):
            again = stream(client, plain)
            assert again.status_code == 401 and "used or expired" in again.json()["detail"]

        # expiry: the stream's process 29 s later accepts a new ticket, 31 s later refuses one
        later = second.app.state.tickets = Tickets(ttl_s=30.0, clock=lambda: utcnow() + timedelta(seconds=29))
        assert stream(second, ticket()).status_code == 200
        later.clock = lambda: utcnow() + timedelta(seconds=31)
        assert stream(second, ticket()).status_code == 401


def test_a_ticket_opens_only_its_own_session_stream(idle_app, tokens, settings):
    with idle_app() as client:
        sid = _ended_session(settings)
        other = _ended_session(settings, "other")
        plain = client.post(f"/api/v1/sessions/{sid}/events/ticket", headers=auth(tokens["viewer"])).json()["ticket"]
        assert client.get(f"/api/v1/sessions/{other}/events?ticket={plain}").status_code == 401
        # presenting it used it up
        assert client.get(f"/api/v1/sessions/{sid}/events?ticket={plain}").status_code == 401
