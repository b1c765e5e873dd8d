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
        return get_swagger_ui_html(openapi_url=app.openapi_url, title="Recal API", swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{ASSETS}/swagger-ui.css",
                                   swagger_favicon_url=f"{ASSETS}/favicon-32x32.png")


ERRORS = {
    401: "no token, or an unknown or revoked one",
    403: "the token's role may not do this",
    404: "no such resource",
    409: "the resource's state does not allow this (a session running, a name taken...)",
    413: "the request body is beyond the route's limit",
    422: "a request field at fault, named",
    503: "the database is unavailable or overloaded: try again shortly (Retry-After)",
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
                codes = [422, 503]
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
                        responses[str(code)] = {"description": ERRORS[code], "content": {"application/json": {
                            "schema": {"$ref": f"#/components/schemas/{model}"}}}}
        app.openapi_schema = doc
        return doc

    app.openapi = openapi
