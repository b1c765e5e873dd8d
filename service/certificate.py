"""The calibration certificate: what a metrology lab files about one calibration.

:func:`certificate_data` gathers it (cell, robot, instrument, date, operator, poses, accuracy
before and after in the manner of ISO 9283 — :mod:`calibration.metrics` — the parameters with
their uncertainties, the checks that were run and passed and those not run); the web page
prints it as HTML and :func:`certificate_pdf` renders the same content as a PDF (reportlab).

Accuracy after calibration comes in two kinds: in-sample (the identified model's residuals on
the measurements it was fitted to: optimistic) and hold-out (a verify session that followed
the calibration on the same cell and used it: fresh configurations, the accuracy to quote).
"""

from __future__ import annotations

import io
import math
from datetime import UTC, datetime

import numpy as np
from sqlmodel import Session, select

from calibration.metrics import error_statistics
from calibration.model import model_from_dict

from .device_config import DeviceConfigError, stored_devices
from .models import AuditEntry, Calibration, Cell, RunSession
from .records import corrected_errors, registered_errors, session_measurements
from .results import _r, calibration_result
from .store import as_utc, verifications

INSTRUMENTS = {"tracker": "laser tracker", "cmm": "coordinate measuring machine (I++ DME)"}


def _iso_figures(xyz: list | None, unit: str) -> dict | None:
    """ISO 9283-style figures of single measurements per pose (calibration.metrics)."""
    if not xyz:
        return None
    e = np.asarray(xyz, dtype=float)
    e = e[np.all(np.isfinite(e), axis=1)]
    if len(e) == 0:
        return None
    s = error_statistics(np.zeros_like(e), e)
    out = {
        "n": s.n,
        "mean": s.mean_m,
        "std": s.std_m,
        "mean_plus_3sigma": s.mean_plus_3sigma_m,
        "rms": s.rms_m,
        "p95": s.p95_m,
        "max": s.max_m,
        "bias_xyz": [float(v) for v in s.bias_xyz_m],
    }
    return {k: ([_r(x) for x in v] if isinstance(v, list) else _r(v) if k != "n" else v) for k, v in out.items()} | {
        "unit": unit
    }


def _verify_sessions(db: Session, cell_id: int, cal: Calibration) -> tuple[dict | None, dict | None]:
    """The hold-out checks around ``cal``: the last verify session before it and the first one
    after it that used it (their results, model units)."""
    before = after = None
    for sid, _, v in verifications(db, cell_id, limit=200):
        if sid < (cal.session_id or 0) and before is None:
            before = {"session_id": sid, **v.to_json()}
        if v.calibration_id == cal.id and sid > (cal.session_id or 0):
            after = {"session_id": sid, **v.to_json()}  # keeps the earliest (rows go newest first)
    return before, after


def _holdout(db: Session, cal: Calibration, verify_after: dict | None, unit: str) -> dict | None:
    """ISO 9283-style figures of the identified model on a verify session's measurements (the
    configurations it was not fitted to), with the session's id and what it measured."""
    if verify_after is None:
        return None
    run = db.get(RunSession, verify_after["session_id"])
    try:
        data, _ = session_measurements(db, run)
    except Exception:  # noqa: BLE001 - without its measurements the verify summary still stands
        return None
    model = model_from_dict(cal.model)
    e, inside = corrected_errors(model, data)  # the model with its residual correction, as it is used
    figures = _iso_figures((e / model.units.length_m).tolist(), unit)
    if figures is None:
        return None
    if inside is not None:  # there the geometric model alone was judged: counted, so the figure is read as such
        figures["outside_mapped_region"] = int(np.count_nonzero(~inside))
    return {
        **figures,
        "session_id": run.id,
        "operator": run.created_by,
        "date": as_utc(run.created_at).isoformat(),
        "target": run.target,
    }


def _holdout_model(holdout: dict, model) -> str:
    """What the hold-out figures are of: the model as it stands, with its residual correction
    where it applies (the geometric model alone elsewhere, counted)."""
    text = (
        f"the identified model as it stands on the {holdout['n']} fresh configurations of verify session "
        f"{holdout['session_id']}, measured after the calibration"
    )
    if "outside_mapped_region" not in holdout:
        return text
    family = (model.metadata.get("residual_map") or {}).get("family", "map")
    return (
        f"{text}, with its residual correction ({family}) applied; {holdout['outside_mapped_region']} of them "
        "lie outside the region the correction was fitted in, where the geometric model alone was judged"
    )


def _placed_verify_before(db: Session, verify_before: dict | None, nominal, unit: str) -> dict | None:
    """The verify session before the calibration, as the certificate states it. When the model
    then in use was the nominal one (no calibration yet), its placement in the instrument's frame
    was unknown: the figures that mean "the robot's accuracy before" are the nominal model placed
    where it fits that session best (``registered_errors``, the one definition of "before" the
    page and the CLI use); the unplaced figure (metres off on the demo: the instrument stands
    elsewhere) is kept only as ``unplaced_rms``, a labelled secondary figure."""
    if verify_before is None or verify_before.get("calibration_id") is not None:
        return verify_before
    run = db.get(RunSession, verify_before["session_id"])
    try:
        data, _ = session_measurements(db, run)
        if len(data) < 3:
            raise ValueError("too few rows to place the model")
        e = registered_errors(nominal, data) / nominal.units.length_m
    except Exception:  # noqa: BLE001 - without its measurements the verify summary stands, labelled unplaced
        return {**verify_before, "placed": False}
    figures = _iso_figures(e.tolist(), unit)
    if figures is None:
        return {**verify_before, "placed": False}
    return {**verify_before, **figures, "placed": True, "unplaced_rms": verify_before.get("rms")}


def _instrument_address(cell: Cell, device: str) -> str:
    """Where the session's instrument is (the Leica on emScon for a tracker, when the cell has
    one: sessions measure with it); empty when the stored devices cannot be read."""
    try:
        return stored_devices(cell.devices).instrument_address(device)
    except DeviceConfigError:
        return ""


def last_device_test(db: Session, cell_id: int, until: datetime | None = None) -> dict | None:
    """The last connection test of the cell's devices (stored in the audit log)."""
    q = select(AuditEntry).where(AuditEntry.action == "test devices", AuditEntry.subject == f"cell {cell_id}")
    if until is not None:
        q = q.where(AuditEntry.at <= until)
    a = db.exec(q.order_by(AuditEntry.id.desc())).first()
    if a is None:
        return None
    return {"at": as_utc(a.at).isoformat(), "by": a.actor, "results": (a.detail or {}).get("results", [])}


def certificate_data(db: Session, cal: Calibration) -> dict:
    res = calibration_result(db, cal)
    cell = db.get(Cell, cal.cell_id)
    run = db.get(RunSession, cal.session_id) if cal.session_id is not None else None
    nominal = model_from_dict(cell.model)
    report = res["report"]
    unit = res["units"]["length"]
    device = run.device if run is not None else "tracker"
    test = last_device_test(db, cell.id, cal.created_at) or last_device_test(db, cell.id)
    accuracy = _accuracy(db, cal, cell, res, nominal, unit)
    settings = report.get("settings") or {}
    resid = report.get("residuals") or {}
    checks = _checks(res, run, report, resid, settings, accuracy["verify_after"], cell, unit)
    not_run = [c["name"] for c in checks if c["passed"] is None]
    issued = datetime.now(UTC)
    return {
        "title": "Robot calibration certificate",
        "number": f"RECAL-{cell.id:04d}-{cal.id:06d}",
        "issued_at": issued.isoformat(),
        "calibration": {
            "id": cal.id,
            "kind": cal.kind,
            "date": as_utc(cal.created_at).isoformat(),
            "session_id": cal.session_id,
            "method": "kinematic identification by weighted least squares "
            "(Levenberg-Marquardt), identifiable parameters only",
        },
        "cell": {"id": cell.id, "name": cell.name, "site": cell.site},
        "robot": {
            "model": nominal.name,
            "joints": nominal.n_joints,
            "convention": nominal.convention,
            "identified_convention": (cal.model or {}).get("convention"),
        },
        "instrument": {
            "kind": INSTRUMENTS.get(device, device),
            "device": device,
            "address": _instrument_address(cell, device),
            "identity": _instrument_identity(test, device),
            "identity_checked_at": test["at"] if test else None,
            "noise": settings.get("sigma"),
            "target": run.target if run is not None else None,
        },
        "operator": run.created_by if run is not None else None,
        "poses": {
            "planned": run.planned if run is not None else None,
            "measured": report.get("rows"),
            "outliers": len(report.get("outliers") or []),
            "plan_method": run.session_plan().method if run is not None else None,
        },
        "units": res["units"],
        "accuracy": accuracy,
        "parameters": _parameters(report),
        "unidentifiable": report.get("unidentifiable") or [],
        "notes": report.get("notes") or [],
        "checks": checks,
        "passed": all(c["passed"] for c in checks if c["passed"] is not None),
        "not_run": not_run,
        "verdict": _verdict(checks, not_run),
    }


def _instrument_identity(test: dict | None, device: str) -> str | None:
    """What the instrument said it is at the cell's last connection test (a tracker's identity,
    a CMM's I++ DME server version), or None."""
    identity = None
    if test:
        for r in test["results"]:
            det = r.get("details") or {}
            if device == "tracker" and r.get("device") == "laser tracker" and det.get("identity"):
                identity = det["identity"]
            if device == "cmm" and r.get("device", "").startswith("CMM") and det.get("dme_version"):
                identity = f"I++ DME server {det['dme_version']}"
    return identity


def _parameters(report: dict) -> list[dict]:
    """The identified parameters, each with its expanded uncertainty (k = 2)."""
    params = []
    for p in report.get("parameters") or []:
        se = p.get("std_error")
        params.append({**p, "expanded_uncertainty": _r(2 * se) if se is not None else None})
    return params


def _accuracy(db: Session, cal: Calibration, cell: Cell, res: dict, nominal, unit: str) -> dict:
    """The certificate's accuracy section: ISO 9283-style figures before and after (in-sample),
    on hold-out configurations, of the verify sessions around the calibration, and predicted."""
    errors = res.get("errors") or {}
    before = _iso_figures((errors.get("before") or {}).get("xyz"), unit)
    after = _iso_figures((errors.get("after") or {}).get("xyz"), unit)
    verify_before, verify_after = _verify_sessions(db, cell.id, cal)
    verify_before = _placed_verify_before(db, verify_before, nominal, unit)
    holdout = _holdout(db, cal, verify_after, unit)
    accuracy = {
        "before": before,
        "before_model": (errors.get("before") or {}).get("model"),
        "after": after,
        "after_model": (errors.get("after") or {}).get("model"),
        "after_kind": "in-sample: the identified model's residuals on the measurements it was fitted to "
        "(optimistic; the hold-out figures are the accuracy to quote)",
        "holdout": holdout,
        "holdout_model": None if holdout is None else _holdout_model(holdout, model_from_dict(cal.model)),
        "verify_before": verify_before,
        "verify_after": verify_after,
        "predicted_workspace": _predicted(res.get("workspace") or {}),
        "note": "ISO 9283-style figures from one measurement per pose: mean position error, its standard "
        "deviation, mean + 3 S, RMS, 95th percentile and maximum; the bias is the mean error vector",
    }
    accuracy["rows"] = [{"label": label, **f} for label, f in _accuracy_rows(accuracy)]
    return accuracy


def _verdict(checks: list[dict], not_run: list[str]) -> str:
    failed = [c["name"] for c in checks if c["passed"] is False]
    if failed:
        return f"{len(failed)} check(s) failed: {', '.join(failed)}"
    text = "All checks that were run passed"
    return text + (f"; not run: {', '.join(not_run)}" if not_run else "")


def _predicted(ws: dict) -> dict | None:
    """The predicted position error of the calibrated model (from its parameters' uncertainty)
    at random configurations inside the allowed region: the same quantity the session's plan
    predicted before anything moved (RMS over the configurations, 95th percentile, maximum)."""
    if not ws.get("available"):
        return None
    st = ws.get("stats_rms") or {}
    return {
        "n": ws.get("samples"),
        "rms": st.get("rms"),
        "p95": st.get("p95"),
        "max": st.get("max"),
        "what": "predicted position error of the calibrated model from its parameters' uncertainty (1 sigma, "
        f"3-D) at {ws.get('samples')} random configurations inside the allowed joint ranges; the "
        "instrument's own noise not included",
    }


def _checks(res, run, report, resid, settings, verify_after, cell, unit) -> list[dict]:
    out = []
    ws = res.get("workspace") or {}

    def add(name, passed, detail):
        out.append({"name": name, "passed": passed, "detail": detail})

    add("identification converged", bool(report.get("success")), report.get("message") or "")
    if run is not None:
        measured = report.get("rows") or 0
        add(
            "every planned configuration measured",
            measured >= (run.planned or 0),
            f"{measured} of {run.planned} configurations",
        )
        add(
            "every configuration inside the joint limits and allowed region",
            run.session_plan().limits_checked,
            "checked before each move",
        )
    sigma = settings.get("sigma")
    rms = resid.get("rms")
    if sigma and rms is not None and resid.get("dof"):
        chi = (resid.get("chi2") or 0) / max(resid["dof"], 1)
        add(
            "residuals consistent with the instrument's noise",
            0.3 <= chi <= 3.0,
            f"residual RMS {rms:.4g} {unit} for {sigma:.3g} {unit} per axis (chi2/dof = {chi:.2f})",
        )
    outliers = len(report.get("outliers") or [])
    add("no outlying measurement", outliers == 0, f"{outliers} measurement(s) down-weighted as outliers")
    _check_predicted_accuracy(add, ws, report, sigma, unit)
    if verify_after is not None:
        ok = rms is None or verify_after["rms"] <= max(3 * rms, 1e-12)
        add(
            "hold-out verification on fresh configurations",
            ok,
            f"session {verify_after['session_id']}: RMS {verify_after['rms']:.4g} {unit}, max "
            f"{verify_after['max']:.4g} {unit} on {verify_after['n']} configurations"
            + (
                f", {verify_after['outside_calibrated_region']} of them outside the joint ranges the calibration "
                "measured (extrapolated)"
                if verify_after.get("outside_calibrated_region")
                else ""
            ),
        )
    else:
        add("hold-out verification on fresh configurations", None, "not run yet (start a verify session)")
    if cell.drift_threshold and verify_after is not None:
        add(
            "within the cell's drift threshold",
            verify_after["max"] <= cell.drift_threshold,
            f"max {verify_after['max']:.4g} {unit} against {cell.drift_threshold:.4g} {unit}",
        )
    return out


# The identification is precise enough where the parameters' uncertainty, propagated to positions
# over the workspace (1 sigma, 3-D, at the 95th percentile of the configurations), stays within
# this multiple of the instrument's own 3-D noise (sqrt(3) sigma): the model then predicts
# positions about as well as the instrument measures them, whatever the condition number. With
# 27 parameters from 30 poses the propagated error is itself near sqrt(3) sigma (about
# sqrt(P/N) of it), so a multiple of one would fail sound short sessions.
PRECISE_MULTIPLE = 2.0


def _check_predicted_accuracy(add, ws: dict, report: dict, sigma: float | None, unit: str) -> None:
    """The conditioning check, judged by what it is for: the positions the identified parameters
    predict. A large condition number (weakly separated parameter combinations) is no defect when
    those combinations move no position the cell reaches (the demo's 1.1e3 passed every other
    check and its predicted error is a fraction of the tracker's); the raw number stays in the
    detail, and a failure says what to do."""
    cond = report.get("condition_number")
    rms = (ws.get("stats_rms") or {}) if ws.get("available") else {}
    name = "identified parameters predict positions precisely over the workspace"
    if not sigma or rms.get("p95") is None:
        if cond is not None:
            add(name, None, f"no predicted accuracy to judge (condition number {cond:.3g})")
        return
    floor = PRECISE_MULTIPLE * math.sqrt(3.0) * sigma
    passed = rms["p95"] <= floor
    detail = (
        f"predicted position error (1 sigma, 3-D) {rms['p95']:.3g} {unit} at 95 % of the workspace, max "
        f"{rms.get('max', float('nan')):.3g} {unit}, against a limit of {floor:.3g} {unit} (twice the instrument's own 3-D noise)"
        + (f"; condition number {cond:.3g}" if cond is not None else "")
    )
    if not passed:
        detail += (
            ". Measure more, and more varied, configurations (a longer pose session over the whole allowed "
            "region) and calibrate again: the parameters these poses leave uncertain move positions more "
            "than the instrument's noise"
        )
    add(name, passed, detail)


def _accuracy_rows(acc: dict) -> list[tuple[str, dict]]:
    """(label, ISO 9283-style figures) of each accuracy row of the certificate, in order."""
    rows = []
    if acc.get("verify_before"):
        v = acc["verify_before"]
        if v.get("placed"):
            label = (
                f"Before: verify session {v['session_id']} (the nominal model then in use, placed where it fits "
                f"the instrument best; unplaced RMS {_num(v.get('unplaced_rms'), 4)})"
            )
        elif v.get("placed") is False:
            label = f"Before: verify session {v['session_id']} (the nominal model then in use, not placed: RMS includes where the instrument stands)"
        else:
            label = f"Before: verify session {v['session_id']} (the calibrated model then in use)"
        rows.append((label, v))
    if acc.get("before"):
        rows.append(("Before calibration (starting model, base fitted)", acc["before"]))
    if acc.get("after"):
        rows.append(("After calibration, in-sample (fitted poses)", acc["after"]))
    if acc.get("holdout"):
        rows.append((f"After calibration, hold-out (verify session {acc['holdout']['session_id']})", acc["holdout"]))
    return rows


# --------------------------------------------------------------------------- PDF


def _num(v, digits: int = 6) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}g}"


def certificate_pdf(cert: dict) -> bytes:
    """The certificate as an A4 PDF: the identification of the cell, robot and instrument, the
    accuracy before and after, the checks, the parameters, and the signatures."""
    from reportlab.lib.pagesizes import A4
    from reportlab.lib.units import mm
    from reportlab.platypus import SimpleDocTemplate, Spacer

    buf = io.BytesIO()
    doc = SimpleDocTemplate(
        buf,
        pagesize=A4,
        leftMargin=18 * mm,
        rightMargin=18 * mm,
        topMargin=16 * mm,
        bottomMargin=16 * mm,
        title=f"{cert['title']} {cert['number']}",
        author="Recal",
    )
    pdf = _PdfStyles()
    s = _pdf_identity(pdf, cert)
    s += _pdf_accuracy(pdf, cert)
    s += _pdf_checks(pdf, cert)
    s += _pdf_parameters(pdf, cert)
    s.append(Spacer(1, 8 * mm))
    s.append(pdf.P(f"Overall: {cert['verdict']}."))
    s.append(Spacer(1, 14 * mm))
    s.append(_pdf_signatures())

    def footer(canvas, doc_):
        canvas.saveState()
        canvas.setFont("Helvetica", 7.5)
        canvas.drawString(18 * mm, 9 * mm, f"Recal — {cert['number']}")
        canvas.drawRightString(A4[0] - 18 * mm, 9 * mm, f"page {doc_.page}")
        canvas.restoreState()

    doc.build(s, onFirstPage=footer, onLaterPages=footer)
    return buf.getvalue()


class _PdfStyles:
    """The certificate's paragraph and table styles (reportlab, imported when a PDF is made)."""

    def __init__(self):
        from reportlab.lib import colors
        from reportlab.lib.styles import getSampleStyleSheet
        from reportlab.platypus import TableStyle

        ss = getSampleStyleSheet()
        self.h1, self.h2, self.body = ss["Title"], ss["Heading2"], ss["BodyText"]
        self.small = ss["BodyText"].clone("small", fontSize=8, leading=10)
        self.grid = TableStyle(
            [
                ("GRID", (0, 0), (-1, -1), 0.4, colors.grey),
                ("FONTSIZE", (0, 0), (-1, -1), 8.5),
                ("BACKGROUND", (0, 0), (-1, 0), colors.HexColor("#e8eef5")),
                ("VALIGN", (0, 0), (-1, -1), "TOP"),
            ]
        )
        self.kv = TableStyle(
            [
                ("FONTSIZE", (0, 0), (-1, -1), 9),
                ("TEXTCOLOR", (0, 0), (0, -1), colors.HexColor("#445")),
                ("VALIGN", (0, 0), (-1, -1), "TOP"),
                ("LINEBELOW", (0, 0), (-1, -1), 0.25, colors.lightgrey),
            ]
        )

    def P(self, text, style=None):
        """A paragraph of plain text (reportlab reads markup: & and < are escaped)."""
        from reportlab.platypus import Paragraph

        return Paragraph(str(text).replace("&", "&amp;").replace("<", "&lt;"), style or self.body)

    def grid_with(self, *commands):
        from reportlab.platypus import TableStyle

        return TableStyle(self.grid.getCommands() + list(commands))


def _pdf_identity(pdf: _PdfStyles, cert: dict) -> list:
    """Title, number, and what was calibrated with what, when, by whom."""
    from reportlab.lib.units import mm
    from reportlab.platypus import Paragraph, Spacer, Table

    unit = cert["units"]["length"]
    inst = cert["instrument"]
    rows = [
        ["Cell", f"{cert['cell']['name']} (site {cert['cell']['site']}, id {cert['cell']['id']})"],
        [
            "Robot",
            f"{cert['robot']['model']}, {cert['robot']['joints']} joints, nominal convention "
            f"{cert['robot']['convention']}",
        ],
        [
            "Instrument",
            f"{inst['kind']} at {inst['address'] or '–'}"
            + (f"; identity {inst['identity']}" if inst.get("identity") else "")
            + (f"; noise {inst['noise']:.3g} {unit} per axis" if inst.get("noise") else ""),
        ],
        ["Date of calibration", cert["calibration"]["date"][:19].replace("T", " ") + " UTC"],
        ["Operator", cert.get("operator") or "–"],
        [
            "Poses",
            f"{cert['poses']['measured']} measured of {cert['poses']['planned']} planned "
            f"({cert['poses']['plan_method'] or '–'}); {cert['poses']['outliers']} outlier(s)",
        ],
        ["Method", cert["calibration"]["method"]],
    ]
    return [
        Paragraph(cert["title"], pdf.h1),
        pdf.P(f"Certificate {cert['number']} — issued {cert['issued_at'][:19].replace('T', ' ')} UTC"),
        Spacer(1, 4 * mm),
        Table([[pdf.P(a), pdf.P(b)] for a, b in rows], colWidths=[38 * mm, 136 * mm], style=pdf.kv, hAlign="LEFT"),
    ]


def _pdf_accuracy(pdf: _PdfStyles, cert: dict) -> list:
    """The accuracy table (before, after, hold-out) and what each row means."""
    from reportlab.lib.units import mm
    from reportlab.platypus import Paragraph, Table

    unit = cert["units"]["length"]
    acc = cert["accuracy"]
    figs = [
        ("n", "poses"),
        ("mean", "mean error"),
        ("std", "std dev S"),
        ("mean_plus_3sigma", "mean + 3 S"),
        ("rms", "RMS"),
        ("p95", "95th pct"),
        ("max", "max"),
    ]
    small = pdf.small
    data = [[pdf.P("", small), *[pdf.P(f"{label} ({unit})" if k != "n" else label, small) for k, label in figs]]]
    for label, f in _accuracy_rows(acc):
        data.append([pdf.P(label, small), *[str(f[k]) if k == "n" else _num(f.get(k), 4) for k, _ in figs]])
    out = [
        Paragraph("Accuracy before and after calibration", pdf.h2),
        Table(
            data,
            colWidths=[41 * mm] + [19 * mm] * 7,
            style=pdf.grid_with(("ALIGN", (1, 1), (-1, -1), "RIGHT")),
            repeatRows=1,
            hAlign="LEFT",
        ),
        pdf.P(
            f"Before: {acc.get('before_model') or '–'}. After, {acc['after_kind']}. "
            + (
                f"Hold-out: {acc['holdout_model']}. "
                if acc.get("holdout")
                else "No hold-out check yet: run a verify session on the cell to measure fresh configurations. "
            )
            + f"{acc['note']}.",
            small,
        ),
    ]
    if acc.get("predicted_workspace"):
        w = acc["predicted_workspace"]
        out.append(
            pdf.P(
                f"Predicted: {w['what']}: RMS {_num(w['rms'], 3)} {unit}, 95th percentile {_num(w['p95'], 3)} "
                f"{unit}, max {_num(w['max'], 3)} {unit}.",
                small,
            )
        )
    return out


def _pdf_checks(pdf: _PdfStyles, cert: dict) -> list:
    from reportlab.lib.units import mm
    from reportlab.platypus import Paragraph, Table

    data = [["Check", "Result", "Detail"]]
    for c in cert["checks"]:
        res = "passed" if c["passed"] else ("not run" if c["passed"] is None else "FAILED")
        data.append([pdf.P(c["name"], pdf.small), res, pdf.P(c["detail"], pdf.small)])
    return [
        Paragraph("Checks", pdf.h2),
        Table(data, colWidths=[62 * mm, 18 * mm, 94 * mm], style=pdf.grid, repeatRows=1, hAlign="LEFT"),
    ]


def _pdf_parameters(pdf: _PdfStyles, cert: dict) -> list:
    """The identified parameters with their uncertainties, and those the data could not determine."""
    from reportlab.lib.units import mm
    from reportlab.platypus import Paragraph, Table

    data = [["Parameter", "Unit", "Value", "Change", "Std. unc. u", "U (k=2)"]]
    for p in cert["parameters"]:
        name = p["name"] + (" (from the prior)" if p.get("source") == "prior" else "")
        data.append(
            [
                name,
                p["unit"],
                _num(p["value"], 9),
                _num(p["change"], 4),
                _num(p["std_error"], 3),
                _num(p["expanded_uncertainty"], 3),
            ]
        )
    out = [
        Paragraph("Identified parameters", pdf.h2),
        Table(
            data,
            colWidths=[34 * mm, 14 * mm, 34 * mm, 28 * mm, 28 * mm, 28 * mm],
            style=pdf.grid_with(("ALIGN", (2, 1), (-1, -1), "RIGHT")),
            repeatRows=1,
            hAlign="LEFT",
        ),
        pdf.P(
            "base.*, tool.* (and home.*) are small displacements of those frames about the calibrated model: "
            "their value is 0 by definition, the change is what the calibration moved.",
            pdf.small,
        ),
    ]
    if cert["unidentifiable"]:
        rows = [[u["name"], pdf.P(u["reason"], pdf.small)] for u in cert["unidentifiable"]]
        out.append(Paragraph("Parameters the data could not determine", pdf.h2))
        out.append(
            Table(
                [["Parameter", "Reason"], *rows],
                colWidths=[30 * mm, 144 * mm],
                style=pdf.grid,
                repeatRows=1,
                hAlign="LEFT",
            )
        )
    return out


def _pdf_signatures():
    from reportlab.lib import colors
    from reportlab.lib.units import mm
    from reportlab.platypus import Table, TableStyle

    return Table(
        [["Operator signature", "", "Reviewed by", ""]],
        colWidths=[35 * mm, 52 * mm, 30 * mm, 57 * mm],
        style=TableStyle(
            [
                ("LINEBELOW", (1, 0), (1, 0), 0.5, colors.black),
                ("LINEBELOW", (3, 0), (3, 0), 0.5, colors.black),
                ("FONTSIZE", (0, 0), (-1, -1), 9),
            ]
        ),
    )
