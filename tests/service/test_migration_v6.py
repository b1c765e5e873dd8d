"""Schema version 6 on a store made by version 5: the ``event_ticket`` table (the event
stream's tickets, shared by a fleet's API processes); a ticket then works on the upgraded store."""

from __future__ import annotations

from sqlalchemy import inspect, text
from sqlmodel import Session

from service.store import SCHEMA_VERSION, create_token, issue_ticket, make_engine, migrate, redeem_ticket


def test_version_5_store_is_upgraded_and_takes_tickets(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    with engine.begin() as conn:  # back to what version 5 made
        conn.execute(text("DROP TABLE event_ticket"))
        conn.execute(text("UPDATE schema_version SET version = 5"))
    assert not inspect(engine).has_table("event_ticket")
    assert migrate(engine) == SCHEMA_VERSION >= 6
    assert inspect(engine).has_table("event_ticket")
    with Session(engine) as db:
        tok, _ = create_token(db, role="viewer")
        plain = issue_ticket(db, token_id=tok.id, scope="events:1", ttl_s=30.0)
        assert redeem_ticket(db, plain, "events:1").id == tok.id
        assert redeem_ticket(db, plain, "events:1") is None
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
