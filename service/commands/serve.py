"""``recal serve [--host 127.0.0.1] [--port 8000]``: the REST API (docs/contracts.md §9, docs/service.md).

The database comes from ``RECAL_DATABASE_URL`` (any SQLAlchemy URL); without it, an embedded
SQLite file in ``RECAL_HOME`` (default ``~/.recal``). Its log (stderr): JSON lines, or text
(``--log-format``, default ``RECAL_LOG_FORMAT``), uvicorn's own lines included (service/logs.py)."""

from __future__ import annotations


def add_parser(s) -> None:
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    s.add_argument(
        "--log-format",
        choices=["json", "text"],
        help="the log's lines on stderr: JSON objects (default) or text (default: $RECAL_LOG_FORMAT, else json)",
    )


def run(args) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.cli import Fail
    from service.logs import configure, log_format
    from service.settings import Settings, SettingsError

    try:
        settings = Settings.from_env()
        fmt = args.log_format or log_format()
    except (
        SettingsError,
        ValueError,
    ) as exc:  # refuse to start on an absurd setting (a speed cap above what drivers allow...)
        raise Fail(str(exc)) from None
    config = configure(args.log_level, fmt)
    app = create_app(settings)
    # uvicorn's access log writes each request's full URL; the service's own (recal.access,
    # service/api/middleware.py) writes one structured line per request with secrets redacted.
    # uvicorn's other lines go through the same handler and format (its log_config).
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, access_log=False, log_config=config)
    return 0
