"""``create_app(settings)``: the FastAPI application. Nothing is created at import time: the
engine, the migrations and the session loop start in the lifespan."""

from __future__ import annotations

import json
import logging
import typing
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from sqlmodel import Session
from starlette.exceptions import HTTPException as StarletteHTTPException

from ..heavy import HeavyPool
from ..models import MAX_ID
from ..problems import STATUS, Conflict, Invalid, NotFound, detail_of
from ..runners import runner_class
from ..settings import Settings
from ..store import database_unavailable, interrupt_unfinished, make_engine, migrate
from ..textcheck import document_faults, parameter_fault
from ..textrepair import unreadable_text
from . import docs, metrics
from .deps import current_token
from .docs import allowed_methods, document_errors, is_id_parameter, needs_token
from .middleware import BodyLimit, PageCache, RequestLog
from .routes import calibrations, cells, records, results, sessions, system, web, workbench

log = logging.getLogger("recal.api")


def _operation_id(route: APIRoute) -> str:
    return f"{route.tags[0]}-{route.name}" if route.tags else route.name


def _declares_int(annotation) -> bool:
    return annotation is int or int in typing.get_args(annotation)


async def bounded_numbers(request: Request) -> None:
    """Every route's integer parameters, before anything reads them: an id (``*_id`` or
    ``previous``, in the path or the query: ``docs.is_id_parameter``) is 1 to 2**63 - 1, any other
    integer (``limit``, ``offset``) fits 64 bits, as the database stores them (every id column is
    64-bit since schema version 8; beyond, SQLite and PostgreSQL raise instead of finding nothing).
    422 naming the parameter. An app-wide dependency: it covers the routes added later too (async:
    no thread hop on every request)."""
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None:
        return
    if needs_token(route):  # who is asking comes first: no token is a 401 whatever else is wrong
        await current_token(request)
    errors = []
    for where, declared, given in (
        ("path", dependant.path_params, request.path_params),
        ("query", dependant.query_params, request.query_params),
    ):
        for param in declared:
            value = given.get(param.alias or param.name)
            fault = parameter_fault(param.name, value) if isinstance(value, str) else None
            if fault:  # no database stores NUL or a lone surrogate in text (PostgreSQL: a 500)
                errors.append({"loc": (where, param.name), "msg": fault, "type": "value_error"})
                continue
            if value is None or not _declares_int(param.field_info.annotation):
                continue
            try:
                v = int(value)
            except ValueError:
                continue  # not an integer: the route's own validation answers
            if is_id_parameter(param.name) and not 1 <= v <= MAX_ID:
                errors.append(
                    {
                        "loc": (where, param.name),
                        "msg": f"expected an id from 1 to {MAX_ID}, got {value}",
                        "type": "value_error",
                    }
                )
            elif not -MAX_ID - 1 <= v <= MAX_ID:
                errors.append(
                    {
                        "loc": (where, param.name),
                        "msg": f"expected a 64-bit integer, got {value}",
                        "type": "value_error",
                    }
                )
    errors += await _body_text_faults(request)
    if errors:
        raise RequestValidationError(errors)


async def _body_text_faults(request: Request) -> list[dict]:
    """Every string of a JSON body (keys too) that could not be stored as text, before any route
    reads it: a refused request stores nothing (a PATCH whose model name held a lone surrogate
    answered 500 and kept the model, after which GET /cells answered 500 for every role)."""
    if request.method not in ("POST", "PUT", "PATCH"):
        return []
    if not (request.headers.get("content-type") or "").startswith("application/json"):
        return []
    body = await request.body()  # Starlette keeps it for the route
    try:
        doc = json.loads(body)
    except ValueError:
        return []  # not JSON: the route's own validation answers
    return [{"loc": ("body", *loc), "msg": msg, "type": "value_error"} for loc, msg in document_faults(doc)[:20]]


def _field(loc) -> str:
    """``("body", "allowed_region", 0, 1)`` -> ``body.allowed_region[0][1]``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _lifespan(settings: Settings, runner_factory):
    """Start-up and shut-down: the store migrated and checked, unfinished sessions marked
    interrupted, the session loop and the heavy-work pool."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        engine = make_engine(settings.effective_database_url)
        migrate(engine)
        with Session(engine) as db:  # what a store kept before the API refused it
            unreadable = unreadable_text(db)
        if unreadable:
            log.error(
                "%d stored value(s) hold text that cannot be read (%s); every answer that includes them "
                "fails until `recal repair-text` repairs them",
                len(unreadable),
                ", ".join(f"{f['table']} {f['id']} {f['field']}" for f in unreadable[:5]),
            )
        factory = runner_factory or runner_class(settings)
        if not factory.distributed:  # a fleet's sessions run on, in its workers
            with Session(engine) as db:
                stopped = interrupt_unfinished(db)
            if stopped:
                log.warning("sessions interrupted by the last stop: %s (resume them to continue)", stopped)
        app.state.engine = engine
        app.state.settings = settings
        app.state.runner = factory(engine, settings)
        app.state.heavy = HeavyPool(settings.heavy_workers)
        try:
            yield
        finally:
            app.state.heavy.shutdown()
            app.state.runner.shutdown()
            with Session(engine) as db:
                interrupt_unfinished(db, owner=app.state.runner.owner)
            engine.dispose()

    return lifespan


def _install_error_handlers(app: FastAPI) -> None:
    """Every error a request can meet answered as JSON naming what is at fault; never a traceback."""

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        allowed = allowed_methods(app, request.url.path)
        if allowed and request.method not in allowed:  # /cells/1/tasks/compensate read as task "compensate"
            return JSONResponse(
                {"detail": "Method Not Allowed"}, status_code=405, headers={"Allow": ", ".join(allowed)}
            )
        # 422 naming each field at fault ("body.count: ...") instead of a nested structure only.
        errors = [{"field": _field(e["loc"]), "message": e["msg"]} for e in exc.errors()]
        return JSONResponse(
            {"detail": "; ".join(f"{e['field']}: {e['message']}" for e in errors), "errors": errors}, status_code=422
        )

    def _internal_error(request: Request, exc: Exception) -> JSONResponse:
        log.error("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
        return JSONResponse(
            {"detail": f"internal error ({type(exc).__name__}); the service log has the details"}, status_code=500
        )

    # The store's errors get a handler of their own (not only the catch-all below, after which
    # Starlette re-raises, and the server logs a traceback for what is only a busy database).
    @app.exception_handler(DBAPIError)
    @app.exception_handler(PoolTimeout)
    async def _database(request: Request, exc: Exception):
        if not database_unavailable(exc):
            return _internal_error(request, exc)
        # Nothing wrong with the request: the database is away or out of connections.
        log.warning(
            "database unavailable on %s %s: %s", request.method, request.url.path, getattr(exc, "orig", None) or exc
        )
        return JSONResponse(
            {"detail": "the database is unavailable or overloaded: try again shortly"},
            status_code=503,
            headers={"Retry-After": "2"},
        )

    @app.exception_handler(NotFound)
    @app.exception_handler(Conflict)
    @app.exception_handler(Invalid)
    async def _problem(request: Request, exc: NotFound | Conflict | Invalid):
        # a use case's refusal (service/problems.py): the same body an HTTPException would give
        return JSONResponse({"detail": detail_of(exc)}, status_code=STATUS[type(exc)])

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        headers = dict(exc.headers or {})
        if exc.status_code == 405:  # Allow: every method of the path (Starlette names only one route's)
            headers["Allow"] = ", ".join(allowed_methods(app, request.url.path)) or headers.get("Allow", "")
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        return _internal_error(request, exc)


def create_app(settings: Settings | None = None, *, runner_factory=None) -> FastAPI:
    settings = settings or Settings.from_env()
    app = FastAPI(
        title="Recal",
        version="0.1.0",
        lifespan=_lifespan(settings, runner_factory),
        generate_unique_id_function=_operation_id,
        dependencies=[Depends(bounded_numbers)],
        docs_url=None,
        redoc_url=None,
        swagger_ui_oauth2_redirect_url=None,
        description="Robot calibration service: cells, measurement sessions, calibrations, compensation.",
    )
    # Outermost last: every request is logged and timed (413s included), then its body limited.
    app.add_middleware(BodyLimit, settings=settings)
    app.add_middleware(PageCache)
    app.add_middleware(RequestLog, observe=metrics.install(app))

    _install_error_handlers(app)
    for module in (system, cells, sessions, calibrations, results, workbench, records):
        app.include_router(module.router, prefix="/api/v1")
    app.include_router(web.router)  # the technician's web page at / (service/web)
    app.include_router(metrics.router)
    docs.install(app)
    document_errors(app)
    return app
