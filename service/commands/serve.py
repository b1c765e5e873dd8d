"""``recal serve [--host 127.0.0.1] [--port 8000]``: the REST API (contracts §9).

The database comes from ``RECAL_DATABASE_URL`` (any SQLAlchemy URL); without it, an embedded
SQLite file in ``RECAL_HOME`` (default ``~/.recal``)."""

from __future__ import annotations


def add_parser(s) -> None:
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def run(args) -> int:
    import logging

    import uvicorn

    from service.api.app import create_app
    from service.settings import Settings

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = Settings.from_env()
    app = create_app(settings)
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    return 0
