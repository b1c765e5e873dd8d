"""``recal worker --site SITE [--site ...]``: run the sessions of the cells of these sites
(the fleet, docs/fleet.md).

Needs ``RECAL_ENGINE=procrastinate`` (implied here) and ``RECAL_DATABASE_URL`` pointing at the
fleet's PostgreSQL store, and the ``fleet`` extra (``pip install 'recal[fleet]'``). Run it on
a machine that reaches the cells of its sites. When it is ready it prints one line of JSON
(``{"ready": true, "worker": ..., "owner": ..., "pid": ...}``); SIGTERM or SIGINT stop it: the
sessions it runs stop between two steps as ``interrupted``, to be resumed by any worker of
their site.
"""

from __future__ import annotations

import os
import socket


def add_parser(s) -> None:
    s.add_argument(
        "--site", action="append", default=[], metavar="SITE", help="a site whose cells this worker drives (repeatable)"
    )
    s.add_argument("--all-sites", action="store_true", help="drive the cells of every site (a one-worker fleet)")
    s.add_argument(
        "--name",
        default=os.environ.get("RECAL_WORKER_NAME") or socket.gethostname(),
        help="this worker's name in logs and leases (default: $RECAL_WORKER_NAME or the host name)",
    )
    s.add_argument(
        "--concurrency",
        type=int,
        default=None,
        help="sessions run at once (one thread and one database connection each; default "
        "$RECAL_WORKER_CONCURRENCY, else four per CPU core); more wait in the queue",
    )
    s.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def run(args) -> int:
    import dataclasses
    import logging

    from service.cli import Fail
    from service.settings import Settings, SettingsError, worker_concurrency

    if bool(args.site) == bool(args.all_sites):
        raise Fail("give the sites this worker serves (--site SITE, repeatable) or --all-sites")
    try:
        concurrency = args.concurrency if args.concurrency is not None else worker_concurrency(os.environ)
    except SettingsError as exc:
        raise Fail(str(exc)) from None
    if concurrency < 1:
        raise Fail(f"--concurrency: expected at least 1, got {concurrency}")
    try:
        import procrastinate  # noqa: F401
    except ImportError:
        raise Fail("the fleet needs Procrastinate: pip install 'recal[fleet]'") from None
    from service.fleet.jobs import FleetConfigError, libpq_url
    from service.fleet.worker import run_worker

    try:
        settings = dataclasses.replace(Settings.from_env(), engine="procrastinate")
    except SettingsError as exc:
        raise Fail(str(exc)) from None
    try:
        libpq_url(settings)
    except FleetConfigError as exc:
        raise Fail(str(exc)) from None
    from service.logs import configure

    try:
        configure(args.log_level)  # the service's format: JSON lines, or RECAL_LOG_FORMAT=text
    except ValueError as exc:
        raise Fail(str(exc)) from None
    if args.log_level != "debug":
        logging.getLogger("procrastinate").setLevel(logging.WARNING)
    return run_worker(
        settings, name=args.name, sites=None if args.all_sites else sorted(set(args.site)), concurrency=concurrency
    )
