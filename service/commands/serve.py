"""``recal serve [--host 127.0.0.1] [--port 8000]``: the REST API (docs/contracts.md §9, docs/service.md).

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
    from service.cli import Fail
    from service.settings import Settings, SettingsError

    try:
        settings = Settings.from_env()
    except SettingsError as exc:  # refuse to start on an absurd setting (a speed cap above what drivers allow...)
        raise Fail(str(exc)) from None
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    app = create_app(settings)
    # uvicorn's access log writes each request's full URL; the service's own (recal.access,
    # service/api/middleware.py) writes one structured line per request with secrets redacted.
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, access_log=False)
    return 0
