"""The technician's web page: static files from ``service/web`` served by the service itself
(same origin, same tokens), ``/`` the page and ``/web/...`` its scripts and styles."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse

router = APIRouter(include_in_schema=False)

WEB = Path(__file__).resolve().parent.parent.parent / "web"
TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".ico": "image/x-icon",
    ".json": "application/json",
}


def _file(path: Path) -> FileResponse:
    return FileResponse(
        path,
        media_type=TYPES.get(path.suffix, "application/octet-stream"),
        headers={"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"},
    )


@router.get("/")
def page() -> FileResponse:
    return _file(WEB / "index.html")


@router.get("/web/{path:path}")
def static(path: str) -> FileResponse:
    target = (WEB / path).resolve()
    if WEB not in target.parents or not target.is_file():
        raise HTTPException(404, f"no file {path!r}")
    return _file(target)
