"""How a cell's robot changed over time: its pose calibrations' figures and parameters, each
parameter's change from the previous calibration against their combined uncertainty
(``calibration.report.change_in_sigmas``, the figure the comparison of two calibrations shows
too), and its verify sessions' measured accuracy. Columns only: never whole reports."""

from __future__ import annotations

from typing import Any

from sqlmodel import Session, col, select

from calibration.report import change_in_sigmas, comparable_parameter

from .models import Calibration, identified_calibration_kinds
from .store import verifications


def cell_drift(db: Session, cell_id: int) -> dict:
    """``calibrations``, ``parameters`` and ``verify`` of the cell, oldest first (the API's
    ``GET /cells/{id}/drift`` documents each)."""
    # SQLModel's select() is typed for up to four columns: six, as a tuple
    columns: tuple[Any, ...] = (
        Calibration.id,
        Calibration.created_at,
        Calibration.rms,
        Calibration.predicted,
        Calibration.nominal_version,
        Calibration.report["parameters"],
    )  # not whole reports
    cals = db.exec(
        select(*columns)
        .where(col(Calibration.cell_id) == cell_id, col(Calibration.kind).in_(identified_calibration_kinds()))
        .order_by(col(Calibration.id))
    ).all()
    series: dict[str, list] = {}
    history = []
    prev: dict[str, dict] = {}
    prev_version = None
    for cid, at, rms, predicted, version, parameters in cals:
        history.append({"id": cid, "created_at": at, "rms": rms, "predicted": predicted, "nominal_version": version})
        params = {p["name"]: p for p in parameters or []}
        for name, p in params.items():
            entry = {"calibration_id": cid, "value": p["value"], "std_error": p["std_error"], "unit": p["unit"]}
            if name in prev and version == prev_version and comparable_parameter(name):
                a, b = prev[name], p
                if a.get("value") is not None and b.get("value") is not None:
                    change = b["value"] - a["value"]
                    moved = change_in_sigmas(change, a.get("std_error") or 0.0, b.get("std_error") or 0.0)
                    entry.update({"change": change, "change_sigmas": moved["change_sigmas"]})
            series.setdefault(name, []).append(entry)
        prev, prev_version = params, version
    verify = []
    for sid, at, v in reversed(verifications(db, cell_id)):
        iso = v.iso9283
        verify.append(
            {
                "session_id": sid,
                "at": at,
                "calibration_id": v.calibration_id,
                "n": v.n,
                "rms": v.rms,
                "max": v.max,
                "p95": v.p95,
                "unit": v.unit,
                "iso9283": None
                if not iso
                else {
                    "repeats": iso["repeats"],
                    "AP_mean": iso["accuracy"]["mean"],
                    "AP_max": iso["accuracy"]["max"],
                    "RP_mean": iso["repeatability"]["mean"],
                    "RP_max": iso["repeatability"]["max"],
                },
            }
        )
    return {"calibrations": history, "parameters": series, "verify": verify}
