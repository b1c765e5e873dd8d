"""A calibration's result for people: per-pose errors before and after, predicted accuracy over
the workspace, the comparison with the previous calibration, downloads (model, URDF, DH
table), the certificate (JSON for the printable page, and PDF), and the per-point report of a
compensation."""

from __future__ import annotations

import json
import re

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ...certificate import certificate_data, certificate_pdf
from ...models import Calibration, Compensation
from ...packed import unpack_report
from ...results import calibration_result, compare_calibrations, previous_calibration_id
from ..deps import DbSession, Reader
from ..schemas import CalibrationResult, Certificate, Comparison, CompensationReport

router = APIRouter(tags=["results"])

DOWNLOADS = {
    "model": ("application/json", "json"),
    "urdf": ("application/xml", "urdf"),
    "ur-calibration": ("application/yaml", "ur-calibration.yaml"),
    "dh-csv": ("text/csv", "dh.csv"),
    "dh-md": ("text/markdown", "dh.md"),
}


def _get(db, calibration_id: int) -> Calibration:
    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise HTTPException(404, f"no calibration {calibration_id}")
    return cal


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-") or "robot"


@router.get("/calibrations/{calibration_id}/result", response_model=CalibrationResult)
def result(calibration_id: int, db: DbSession, tok: Reader) -> dict:
    """The result page's data: the report's parameters (with standard errors) and the
    parameters the data could not determine (with the reason), per-pose position errors
    before (the starting model with its base placed where it fits best) and after (the
    identified model), and the predicted 95 % position uncertainty at random configurations
    inside the cell's allowed region; ``previous_id``: the cell's calibration before this one."""
    return calibration_result(db, _get(db, calibration_id))


@router.get("/calibrations/{calibration_id}/comparison", response_model=Comparison)
def comparison(calibration_id: int, db: DbSession, tok: Reader, previous: int | None = None) -> dict:
    """This calibration against ``previous`` (default: the cell's calibration of the same kind
    before it): every parameter, including those estimated in only one of them and the base
    and tool frames (see :func:`service.results.compare_calibrations`). ``null`` parameters when there is none."""
    cal = _get(db, calibration_id)
    prev_id = previous if previous is not None else previous_calibration_id(db, cal)
    if prev_id is None:
        return {"from": None, "to": cal.id, "parameters": None}
    return compare_calibrations(_get(db, prev_id), cal)


@router.get("/calibrations/{calibration_id}/download/{fmt}")
def download(calibration_id: int, fmt: str, db: DbSession, tok: Reader) -> Response:
    """The identified model as a file: ``model`` (recal.model/1 JSON), ``urdf``, ``ur-calibration``
    (UR's calibration YAML), ``dh-csv`` or ``dh-md`` (DH table, CSV or Markdown)."""
    if fmt not in DOWNLOADS:
        raise HTTPException(404, f"unknown format {fmt!r}; one of: {', '.join(DOWNLOADS)}")
    cal = _get(db, calibration_id)
    media, ext = DOWNLOADS[fmt]
    stem = _slug(f"{cal.model.get('name') or 'model'}-cal{cal.id}")
    headers = {"Content-Disposition": f'attachment; filename="{stem}.{ext}"'}
    if fmt == "model":
        return Response(json.dumps(cal.model, indent=2) + "\n", media_type=media, headers=headers)
    from calibration.model import model_from_dict

    try:
        from calibration import export
    except ImportError:  # pragma: no cover - export ships with the package
        raise HTTPException(501, "exports are not available in this build") from None
    model = model_from_dict(cal.model)
    try:
        text = export.export(model, fmt)
    except ValueError as exc:
        raise HTTPException(422, f"cannot export this model as {fmt}: {exc}") from None
    warnings = export.export_warnings(model, fmt) if hasattr(export, "export_warnings") else []
    if warnings:
        headers["X-Recal-Export-Warnings"] = "; ".join(warnings)[:1000]
    return Response(text, media_type=media, headers=headers)


@router.get("/calibrations/{calibration_id}/certificate", response_model=Certificate)
def certificate(calibration_id: int, db: DbSession, tok: Reader) -> dict:
    """The calibration certificate's content (the web page prints it)."""
    return certificate_data(db, _get(db, calibration_id))


def _certificate(engine, calibration_id: int) -> dict:
    with Session(engine) as db:
        return certificate_data(db, _get(db, calibration_id))


@router.get("/calibrations/{calibration_id}/certificate.pdf")
async def certificate_as_pdf(calibration_id: int, request: Request, tok: Reader) -> Response:
    """The calibration certificate as a PDF (A4), rendered in a worker process (service.heavy),
    awaited: no request thread is held meanwhile (abort and pause need them)."""
    cert = await run_in_threadpool(_certificate, request.app.state.engine, calibration_id)
    try:
        pdf = await request.app.state.heavy.run(certificate_pdf, cert)
    except ImportError:
        raise HTTPException(
            501,
            "PDF output needs the reportlab package (pip install reportlab); print the certificate page to PDF instead",
        ) from None
    return Response(
        pdf,
        media_type="application/pdf",
        headers={"Content-Disposition": f'attachment; filename="{cert["number"]}.pdf"'},
    )


@router.get("/compensations/{compensation_id}/report", response_model=CompensationReport)
def compensation_report(compensation_id: int, db: DbSession, tok: Reader) -> dict:
    """What the compensation reported per task point (flags, residuals, convergence)."""
    rec = db.get(Compensation, compensation_id)
    if rec is None:
        raise HTTPException(404, f"no compensation {compensation_id}")
    return {
        "id": rec.id,
        "calibration_id": rec.calibration_id,
        "name": rec.name,
        "mode": rec.mode,
        "created_by": rec.created_by,
        "created_at": rec.created_at,
        "report": unpack_report(rec.report) or {},
    }
