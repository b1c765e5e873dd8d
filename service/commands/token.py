"""``recal token create --role ROLE [--name NAME]``: print a new API token once (contracts §9)."""

from __future__ import annotations


def add_parser(s) -> None:
    sub = s.add_subparsers(dest="action", required=True)
    c = sub.add_parser("create", help="create a token and print it (it is not shown again)")
    c.add_argument("--role", required=True, choices=["viewer", "technician", "job", "admin"])
    c.add_argument("--name", default="")


def run(args) -> int:
    from sqlmodel import Session

    from service.settings import Settings
    from service.store import audit, create_token, make_engine, migrate

    settings = Settings.from_env()
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        tok, plain = create_token(db, role=args.role, name=args.name)
        audit(
            db,
            actor="recal token (local)",
            action="create token",
            subject=f"token {tok.id}",
            detail={"role": tok.role, "name": tok.name},
        )
    engine.dispose()
    print(plain)
    return 0
