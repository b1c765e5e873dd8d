"""``recal repair-text [--check]``: find stored text that cannot be read (a lone surrogate or a
NUL, kept before the API refused them) and replace each bad character with U+FFFD, audited
(docs/service.md). ``--check`` only lists it: exit 3 when there is any, 0 when there is none."""

from __future__ import annotations


def add_parser(s) -> None:
    s.add_argument("--check", action="store_true", help="only list the stored text that cannot be read")


def run(args) -> int:
    from sqlmodel import Session

    from service.settings import Settings
    from service.store import make_engine, migrate
    from service.textrepair import repair_text, unreadable_text

    settings = Settings.from_env()
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    try:
        with Session(engine) as db:
            found = unreadable_text(db) if args.check else repair_text(db, actor="recal repair-text (local)")
    finally:
        engine.dispose()
    for f in found:
        print(f"{f['table']} {f['id']}: {f['field']}: {f['message']}")
    if args.check:
        print(
            f"{len(found)} stored value(s) cannot be read"
            + ("; run `recal repair-text` to repair them" if found else "")
        )
        return 3 if found else 0
    print(f"repaired {len(found)} stored value(s) (each bad character is now U+FFFD)")
    return 0
