"""The API's documentation, served from the service's own files (a plant network has no CDN):
Swagger UI at ``/docs`` from the assets the ``swagger-ui-py`` package ships, and the error
statuses of every operation with their real body shapes in the OpenAPI document."""

from __future__ import annotations

from pathlib import Path

from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.staticfiles import StaticFiles

from .schemas import Problem, ValidationProblem

ASSETS = "/docs/assets"


def swagger_assets() -> Path:
    import swagger_ui  # swagger-ui-py: Swagger UI 5's built files, no server of its own used

    return Path(swagger_ui.__file__).resolve().parent / "static"


def install(app) -> None:
    app.mount(ASSETS, StaticFiles(directory=swagger_assets()), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui():
        return get_swagger_ui_html(
            openapi_url=app.openapi_url,
            title="Recal API",
            swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{ASSETS}/favicon-32x32.png",
        )


ERRORS = {
    400: "the body cannot be parsed as its Content-Type says",
    401: "no token, or an unknown or revoked one",
    403: "the token's role may not do this",
    404: "no such resource",
    409: "the resource's state does not allow this (a session running, a name taken...)",
    413: "the request body is beyond the route's limit",
    422: "a request field at fault, named",
    503: "the database is unavailable or overloaded: try again shortly (Retry-After)",
}


# What the routes answering files send (a route's ``response_class`` alone says JSON or nothing).
CONTENT = {
    ("get", "/certificate.pdf"): ("application/pdf",),
    ("get", "/download/{fmt}"): ("application/json", "application/xml", "text/csv", "text/markdown"),
    ("get", "/compensations/{compensation_id}"): ("text/plain",),
    ("post", "/calibrations/{calibration_id}/compensate"): ("text/csv", "text/plain"),
    ("post", "/calibrations/{calibration_id}/compensate-backup"): ("application/zip",),
    ("get", "/measurements.csv"): ("text/csv",),
}


def document_errors(app) -> None:
    """Each operation's error statuses in the OpenAPI document, with the bodies the handlers
    send (``Problem``; 422 ``ValidationProblem``), replacing FastAPI's default 422
    (``HTTPValidationError``, a shape this service never sends): 401 and 403 where a token is
    needed, 404 where a path names a resource, 409 and 413 on what changes something, 422 and
    503 everywhere (every route checks its parameters and reads the database)."""
    from fastapi.openapi.utils import get_openapi

    def openapi():
        if app.openapi_schema is not None:
            return app.openapi_schema
        doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        schemas = doc.setdefault("components", {}).setdefault("schemas", {})
        for model in (Problem, ValidationProblem):
            extra = model.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in extra.pop("$defs", {}).items():
                schemas.setdefault(name, sub)
            schemas[model.__name__] = extra
        schemas.pop("HTTPValidationError", None)
        schemas.pop("ValidationError", None)
        for path, ops in doc.get("paths", {}).items():
            for method, op in ops.items():
                _bound_integers(op)
                if path.endswith("/events"):  # the bearer token, or a ticket (stream_reader)
                    op["security"] = [{"bearer": []}]
                if path.endswith("/compensate") and path.startswith("/api/v1/calibrations/"):
                    op["requestBody"] = {
                        "required": True,
                        "description": "the task CSV or robot program (a KRL "
                        "program's .src and .dat: multipart/form-data, one part per file)",
                        "content": {
                            m: {"schema": {"type": "string", "minLength": 1}} for m in ("text/csv", "text/plain")
                        },
                    }
                if path.endswith("/compensate-backup"):
                    op["requestBody"] = {
                        "required": True,
                        # the zip's bytes whatever the Content-Type says (application/zip is usual):
                        # declared as octet-stream, the binary type OpenAPI tools can send
                        "description": "a controller backup folder, zipped (KUKA archive, ABB backup, Fanuc .ls); "
                        "sent as application/zip or application/octet-stream",
                        "content": {
                            "application/octet-stream": {
                                "schema": {"type": "string", "format": "binary", "minLength": 1}
                            }
                        },
                    }
                if method == "post" and path.endswith("/measurements") and path.startswith("/api/v1/cells/"):
                    op["requestBody"] = {
                        "required": True,
                        "description": "a measurement CSV (contracts §3)",
                        "content": {"text/csv": {"schema": {"type": "string", "minLength": 1}}},
                    }
                for (m, suffix), types in CONTENT.items():
                    if method == m and path.endswith(suffix) and "200" in op.get("responses", {}):
                        op["responses"]["200"]["content"] = {t: {"schema": {"type": "string"}} for t in types}
                codes = [422, 503]
                if "requestBody" in op:
                    codes.append(400)  # a body that is not what its Content-Type says (JSON that does not parse)
                if op.get("security"):
                    codes += [401, 403]
                if "{" in path:
                    codes.append(404)
                if method in ("post", "patch", "put", "delete"):
                    codes += [409, 413]
                responses = op.setdefault("responses", {})
                for code in codes:
                    model = "ValidationProblem" if code == 422 else "Problem"
                    if code == 422 or str(code) not in responses:
                        responses[str(code)] = {
                            "description": ERRORS[code],
                            "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{model}"}}},
                        }
        app.openapi_schema = doc
        return doc

    app.openapi = openapi


# Query parameters that carry an id without being named ``*_id``.
ID_PARAMETERS = ("previous",)


def is_id_parameter(name: str) -> bool:
    """Whether the path or query parameter ``name`` carries an id (1 to 2**63 - 1): the one rule
    ``app.bounded_numbers`` enforces and the OpenAPI document states."""
    return name.endswith("_id") or name in ID_PARAMETERS


def _bound_integers(op: dict) -> None:
    """The bounds ``app.bounded_numbers`` enforces, in the document: an id (``is_id_parameter``)
    is 1 to 2**63 - 1, any other integer parameter a 64-bit integer (what both databases store)."""
    from ..models import MAX_ID

    for param in op.get("parameters", []):
        schema = param.get("schema", {})
        options = schema.get("anyOf", [schema])
        for option in options:
            if option.get("type") != "integer":
                continue
            if is_id_parameter(param["name"]):
                option["minimum"] = max(option.get("minimum", 1), 1)
                option["maximum"] = min(option.get("maximum", MAX_ID), MAX_ID)
            else:
                option["minimum"] = max(option.get("minimum", -MAX_ID - 1), -MAX_ID - 1)
                option["maximum"] = min(option.get("maximum", MAX_ID), MAX_ID)


def needs_token(route) -> bool:
    """Whether ``route`` authenticates its caller with a bearer token (cached on the route)."""
    cached = getattr(route, "_recal_needs_token", None)
    if cached is None:
        from .deps import current_token

        cached, stack = False, [route.dependant]
        while stack and not cached:
            d = stack.pop()
            cached = d.call is current_token
            stack.extend(d.dependencies)
        route._recal_needs_token = cached
    return cached


def allowed_methods(app, path: str) -> list[str]:
    """The methods the OpenAPI document lists for the path template ``path`` matches."""
    import re

    patterns = getattr(app.state, "path_patterns", None)
    if patterns is None:
        patterns = app.state.path_patterns = [
            (
                re.compile("^" + re.sub(r"\\{[^}]+\\}", "[^/]+", re.escape(p)) + "$"),
                p.count("{"),
                sorted(m.upper() for m in ops),
            )
            for p, ops in app.openapi().get("paths", {}).items()
        ]
    # the most specific template first: /cells/{id}/tasks/compensate before /cells/{id}/tasks/{task_id}
    matches = [(wildcards, methods) for pattern, wildcards, methods in patterns if pattern.match(path)]
    return min(matches)[1] if matches else []
