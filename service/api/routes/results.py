"""A calibration's result for people: per-pose errors before and after, predicted accuracy over
the workspace, the comparison with the previous calibration, downloads (model, URDF, DH
table), the certificate (JSON for the printable page, and PDF), and the per-point report of a
compensation."""

from __future__ import annotations

import json
import re

import numpy as np
from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from calibration.model import KinematicModel, model_from_dict
from calibration.parameters import LOCAL_6, parameter_values
from calibration.transforms import invert, matrix_to_rotvec, pose_to_matrix

from ...certificate import certificate_data, certificate_pdf
from ...models import Calibration, Compensation
from ...results import _parameters_for, calibration_result, previous_calibration_id
from ..deps import DbSession, Reader
from ..schemas import CalibrationResult, Certificate, Comparison, CompensationReport

router = APIRouter(tags=["results"])

DOWNLOADS = {
    "model": ("application/json", "json"),
    "urdf": ("application/xml", "urdf"),
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


FRAMES = ("base", "tool", "home")


def _frame_step(a: KinematicModel, b: KinematicModel, frame: str) -> np.ndarray | None:
    """(6,) SI: how ``frame`` moved from model ``a`` to model ``b``, as the local step the
    ``frame.*`` parameters describe (``T_b = T_a · exp(step)``, calibration.parameters)."""
    pa, pb = getattr(a, frame), getattr(b, frame)
    if pa is None or pb is None:
        return None
    D = invert(pose_to_matrix(pa)) @ pose_to_matrix(pb)
    return np.concatenate([D[:3, 3], matrix_to_rotvec(D[:3, :3])])


def _model_values(model: KinematicModel, names: list[str]) -> dict[str, float]:
    """SI values of the named (non-local) parameters in ``model`` (those it has)."""
    params, _ = _parameters_for(model, names)
    return dict(zip((p.name for p in params), parameter_values(model, params).tolist()))


def compare_calibrations(a: Calibration, b: Calibration) -> dict:
    """Every parameter of two calibrations of a cell, from ``a`` to ``b``: those estimated in
    both, in only one (``new``: estimated in ``b`` only; ``not estimated``: in ``a`` only, ``b``
    kept its starting value; ``from the prior``: ``b`` kept it from ``a``, its data could not
    determine it) and the base and tool frames (how far each moved, along and about its own
    axes). ``moved``: the change exceeds twice its standard uncertainty (both
    calibrations' combined, or the one that estimated it)."""
    ma, mb = model_from_dict(a.model), model_from_dict(b.model)
    units = mb.units
    ra = {p["name"]: p for p in (a.report or {}).get("parameters") or []}
    rb = {p["name"]: p for p in (b.report or {}).get("parameters") or []}
    names = list(dict.fromkeys([*ra, *rb]))
    plain = [n for n in names if n.split(".")[0] not in FRAMES and ".tilt_" not in n and ".shift_" not in n]
    va, vb = _model_values(ma, plain), _model_values(mb, plain)
    rows = []

    def add(name, unit, x_from, x_to, group, change=None):
        pa, pb = ra.get(name), rb.get(name)
        sa = pa.get("std_error") if pa else None
        sb = pb.get("std_error") if pb else None
        sig = [s for s in (sa, sb) if s is not None]
        sigma = float(np.sqrt(sum(s * s for s in sig))) if sig else None
        if change is None and x_from is not None and x_to is not None:
            change = x_to - x_from
        if pb and pb.get("source") == "prior":
            status = "from the prior"  # in b, but kept from a: these measurements did not determine it
        else:
            status = "both" if pa and pb else "new" if pb else "not estimated" if pa else "fixed"
        moved = bool(sigma and change is not None and abs(change) > 2 * sigma)
        rows.append({"name": name, "unit": unit, "group": group, "from": x_from, "to": x_to, "change": change,
                     "sigma": sigma, "change_sigmas": abs(change) / sigma if sigma and change is not None else None,
                     "moved": moved, "status": status})

    for n in names:
        if n not in plain:
            continue
        unit = (rb.get(n) or ra.get(n))["unit"]
        scale = units.length_m if unit == units.length else units.angle_rad if unit == units.angle else 1.0
        fa = va[n] / scale if n in va else (ra[n]["value"] if n in ra else None)
        fb = vb[n] / scale if n in vb else (rb[n]["value"] if n in rb else None)
        add(n, unit, fa, fb, "target" if n.startswith("target.") else "joint")
    for frame in FRAMES:
        step = _frame_step(ma, mb, frame)
        if step is None:
            continue
        for k, axis in enumerate(LOCAL_6):
            name = f"{frame}.{axis}"
            translation = k < 3
            value = step[k] / (units.length_m if translation else units.angle_rad)
            if name in ra or name in rb or abs(value) > 1e-9:
                add(name, units.length if translation else units.angle, None, None, frame, float(value))
    rows.sort(key=lambda r: (not r["moved"], -(r["change_sigmas"] or 0), r["name"]))
    return {"from": a.id, "to": b.id, "rms_from": a.rms, "rms_to": b.rms, "parameters": rows,
            "counts": {k: sum(r["status"] == k for r in rows)
                       for k in ("both", "new", "not estimated", "from the prior", "fixed")}
            | {"moved": sum(r["moved"] for r in rows)}}


@router.get("/calibrations/{calibration_id}/comparison", response_model=Comparison)
def comparison(calibration_id: int, db: DbSession, tok: Reader, previous: int | None = None) -> dict:
    """This calibration against ``previous`` (default: the cell's calibration of the same kind
    before it): every parameter, including those estimated in only one of them and the base
    and tool frames (see :func:`compare_calibrations`). ``null`` parameters when there is none."""
    cal = _get(db, calibration_id)
    prev_id = previous if previous is not None else previous_calibration_id(db, cal)
    if prev_id is None:
        return {"from": None, "to": cal.id, "parameters": None}
    return compare_calibrations(_get(db, prev_id), cal)


@router.get("/calibrations/{calibration_id}/download/{fmt}")
def download(calibration_id: int, fmt: str, db: DbSession, tok: Reader) -> Response:
    """The identified model as a file: ``model`` (recal.model/1 JSON), ``urdf``, ``dh-csv`` or
    ``dh-md`` (DH table, CSV or Markdown)."""
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
        raise HTTPException(501, "PDF output needs the reportlab package (pip install reportlab); print the "
                                 "certificate page to PDF instead") from None
    return Response(pdf, media_type="application/pdf",
                    headers={"Content-Disposition": f'attachment; filename="{cert["number"]}.pdf"'})


@router.get("/compensations/{compensation_id}/report", response_model=CompensationReport)
def compensation_report(compensation_id: int, db: DbSession, tok: Reader) -> dict:
    """What the compensation reported per task point (flags, residuals, convergence)."""
    rec = db.get(Compensation, compensation_id)
    if rec is None:
        raise HTTPException(404, f"no compensation {compensation_id}")
    return {"id": rec.id, "calibration_id": rec.calibration_id, "name": rec.name, "mode": rec.mode,
            "created_by": rec.created_by, "created_at": rec.created_at, "report": rec.report or {}}
