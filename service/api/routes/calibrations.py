"""Calibrations: read one, compare two, activate or retire one, compensate a task file with one."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse, Response
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ...models import Calibration, CalibrationPublic, Cell, Compensation
from ...packed import output_bytes
from ...problems import Conflict
from ...results import compare_calibrations
from ...sessions import driving_session
from ...store import activate_calibration, calibration_status, retire_calibration
from ..deps import CellEditor, Compensator, DbSession, Reader
from ..schemas import Comparison

router = APIRouter(tags=["calibrations"])


def get_calibration(db, calibration_id: int) -> Calibration:
    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise HTTPException(404, f"no calibration {calibration_id}")
    return cal


def public_calibration(db, cal: Calibration) -> CalibrationPublic:
    db.refresh(cal)  # a commit (the audit entry) expired it, and an expired row dumps as {}
    return CalibrationPublic(**cal.model_dump(), status=calibration_status(db, cal))


@router.get("/calibrations/{calibration_id}", response_model=CalibrationPublic)
def read_calibration(calibration_id: int, db: DbSession, tok: Reader):
    return public_calibration(db, get_calibration(db, calibration_id))


def _changeable(db, cal: Calibration, verb: str) -> Cell:
    """The calibration's cell, if its current model may change now: not while a session drives
    it (a session works with the model it started with)."""
    cell = db.get(Cell, cal.cell_id)
    busy = driving_session(db, cal.cell_id, dry_runs=True)
    if busy is not None:
        raise Conflict(
            f"session {busy.id} is driving this cell ({busy.state}); {verb} the calibration when it has stopped"
        )
    return cell


@router.post("/calibrations/{calibration_id}/activate", response_model=CalibrationPublic)
def activate(calibration_id: int, db: DbSession, tok: CellEditor):
    """Make this calibration the cell's current one (the model compensation, verify sessions and
    the next calibration's prior use); a retired one is brought back. Only a pose calibration
    identified from the cell's present nominal model; not while a session drives the cell.
    Audited ("activate calibration", who and which was current before)."""
    cal = get_calibration(db, calibration_id)
    cell = _changeable(db, cal, "activate")
    if cal.kind != "pose":
        raise Conflict(f"calibration {cal.id} is a {cal.kind} calibration; only a pose calibration is a cell's model")
    if cal.nominal_version != cell.model_version:
        raise Conflict(
            f"calibration {cal.id} was identified from nominal model version {cal.nominal_version}; the cell's is "
            f"version {cell.model_version}"
        )
    if calibration_status(db, cal) != "current":
        activate_calibration(db, cal, actor=tok.name, why="activated by hand")
    return public_calibration(db, cal)


@router.post("/calibrations/{calibration_id}/retire", response_model=CalibrationPublic)
def retire(calibration_id: int, db: DbSession, tok: CellEditor):
    """Retire this calibration: kept and readable, but no longer a candidate or the cell's model
    (the calibration activated before it that is not retired becomes current again, else the
    nominal model). Not while a session drives the cell. Audited ("retire calibration")."""
    cal = get_calibration(db, calibration_id)
    _changeable(db, cal, "retire")
    if cal.retired_at is None:
        retire_calibration(db, cal, actor=tok.name)
    return public_calibration(db, cal)


@router.get("/calibrations/{calibration_id}/compare/{other_id}", response_model=Comparison)
def compare(calibration_id: int, other_id: int, db: DbSession, tok: Reader) -> dict:
    """Which parameters moved between two calibrations, in units of their combined standard
    uncertainty: every parameter, the base and tool frames included (the page's comparison,
    :func:`service.results.compare_calibrations`), with the predicted accuracy of both."""
    a, b = get_calibration(db, calibration_id), get_calibration(db, other_id)
    return {
        **compare_calibrations(a, b),
        "predicted_from": a.predicted,
        "predicted_to": b.predicted,
        "nominal_versions": [a.nominal_version, b.nominal_version],
    }


def _exists(engine, calibration_id: int) -> None:
    with Session(engine) as db:
        get_calibration(db, calibration_id)


@router.post("/calibrations/{calibration_id}/compensate", response_class=PlainTextResponse)
async def compensate(
    calibration_id: int,
    request: Request,
    tok: Compensator,
    mode: str = "joints",
    name: str = "task.csv",
    payload: str | None = None,
) -> Response:
    """A task CSV or a robot program (URScript, RAPID, TP; ``name`` tells which) in the request
    body, the compensated file out (contracts §5). ``mode``: ``joints`` or ``targets``;
    ``payload``: the task's payload ``KG[,X,Y,Z]`` (kg, centre of gravity in the tool frame in the
    model's length unit), which a calibration with joint compliance sags under. A program of
    several files (KRL: the ``.src`` and its ``.dat``; RAPID: the module and the task's other
    modules, read for the tooldata and wobjdata they declare) comes as ``multipart/form-data``,
    one part per file; the answer is then JSON ``{"files": [{"name", "text", "encoding"}, ...]}``, the
    program first. A program that is not UTF-8 (a KRL or RAPID file in Windows-1252) is read as
    ISO-8859-1, a character per byte, and answered in it: the body with ``charset=iso-8859-1``, a
    JSON file with ``"encoding": "iso-8859-1"`` (``text.encode("iso-8859-1")`` is the file's bytes).
    The compensation runs in a worker process (service.heavy), which also stores it: the service
    answers every other request meanwhile. ``X-Recal-Not-Compensated`` (and the JSON's
    ``not_compensated``) counts the targets left as written or not converged, as ``recal
    compensate`` exits 3 for them; the stored report's rows name them."""
    if mode not in ("joints", "targets"):
        raise HTTPException(422, {"field": "query.mode", "message": "expected joints or targets"})
    from ...stored_compensation import CompensationInputError, compensate_and_store

    await run_in_threadpool(_exists, request.app.state.engine, calibration_id)  # 404 before any work
    raw = await request.body()
    name, body, companions, encodings = _uploaded(request.headers.get("content-type", ""), raw, name)
    try:
        rec_id, output, summary, files = await request.app.state.heavy.run(
            compensate_and_store,
            request.app.state.settings.effective_database_url,
            calibration_id,
            body,
            name=name,
            mode=mode,
            actor=tok.name,
            companions=companions,
            payload=payload,
            encodings=encodings,
        )
    except CompensationInputError as exc:
        field = "query.payload" if str(exc).startswith("--payload") else "body"
        raise HTTPException(422, {"field": field, "message": str(exc)}) from None
    return _compensated_answer(rec_id, name, output, summary, files, companions, encodings)


def _uploaded(content_type: str, raw: bytes, name: str):
    """The uploaded task or program: (its name, its text, the program's other files by name or
    None, each file's encoding), from a plain body named ``name`` or a multipart one (the program
    first: the part that is not a KRL ``.dat``). Nothing, or binary data, is refused (422)."""
    from ...stored_compensation import CompensationInputError, decode_upload, read_multipart

    companions = None
    try:
        if content_type.lower().startswith("multipart/form-data"):
            files = read_multipart(content_type, raw)
            main = next((f for f in files if not f[0].lower().endswith(".dat")), files[0])
            name, body, _ = main
            companions = {n: t for n, t, _ in files if (n, t) != main[:2]}
            encodings = {n: e for n, _, e in files}
        else:
            body, encoding = decode_upload(name, raw)
            encodings = {name: encoding}
    except CompensationInputError as exc:
        raise HTTPException(422, {"field": "body", "message": str(exc)}) from None
    if not body.strip():
        raise HTTPException(422, {"field": "body", "message": "expected a task CSV or robot program, got nothing"})
    if any("\x00" in text for text in [body, *(companions or {}).values()]):
        raise HTTPException(
            422, {"field": "body", "message": "expected a text file, got NUL characters (binary data?)"}
        )
    return name, body, companions, encodings


def _compensated_answer(rec_id, name: str, output: str, summary, files, companions, encodings) -> Response:
    """The compensated file as the upload came: the text in its encoding, or for a multipart
    upload JSON with every file; with the compensation's id and the count of targets not
    compensated in the headers."""
    # the CLI's exit 3: targets left as written (unreachable) or not converged, counted here and
    # named by the stored report's rows (GET /compensations/{id}/report)
    short = int((summary or {}).get("not_compensated", 0))
    headers = {"X-Recal-Compensation": str(rec_id), "X-Recal-Not-Compensated": str(short)}
    if companions is not None:
        from fastapi.responses import JSONResponse

        return JSONResponse(
            {"files": [{"name": name, "text": output, "encoding": encodings[name]}] + files, "not_compensated": short},
            headers=headers,
        )
    media = "text/csv" if name.lower().endswith(".csv") else "text/plain"
    if encodings[name] != "utf-8":  # a program that is not UTF-8 comes back as the bytes it was
        return Response(
            output.encode(encodings[name]), media_type=f"{media}; charset={encodings[name]}", headers=headers
        )
    return PlainTextResponse(output, media_type=media, headers=headers)


@router.post("/calibrations/{calibration_id}/compensate-backup", response_class=Response)
async def compensate_backup(
    calibration_id: int, request: Request, tok: Compensator, name: str = "backup.zip"
) -> Response:
    """A controller backup folder, zipped (a KUKA archive with ``KRC/R1/System/$config.dat``, an
    ABB backup with ``RAPID/TASK*/PROGMOD`` and ``SYSMOD``, a folder of Fanuc ``.ls`` programs), in
    the request body (``application/zip``); the zip of the same layout back, every program
    compensated as ``recal compensate --task DIR`` compensates it and every other entry byte for
    byte, with the report (``recal-compensation-report.json``: a row per target, a summary per
    file). ``X-Recal-Not-Compensated`` counts the targets left as written or not converged (the
    CLI's exit 3). A zip entry with an absolute path or ``..`` is refused (422), and so is a zip
    whose entries unpack beyond the input bound ``RECAL_MAX_INPUT_BYTES`` (413), before anything
    is written. The work runs in a worker process (service.heavy); it is audited, not stored."""
    from ...backups import UnsafeZip
    from ...files import max_input_bytes
    from ...stored_compensation import CompensationInputError, compensate_backup_and_audit

    await run_in_threadpool(_exists, request.app.state.engine, calibration_id)  # 404 before any work
    raw = await request.body()
    if not raw:
        raise HTTPException(422, {"field": "body", "message": "expected a zip of a controller backup, got nothing"})
    try:
        answer, short, _summary = await request.app.state.heavy.run(
            compensate_backup_and_audit,
            request.app.state.settings.effective_database_url,
            calibration_id,
            raw,
            actor=tok.name,
            name=name,
            limit=max_input_bytes(),
        )
    except UnsafeZip as exc:
        raise HTTPException(413 if exc.too_large else 422, {"field": "body", "message": str(exc)}) from None
    except CompensationInputError as exc:
        raise HTTPException(422, {"field": "body", "message": str(exc)}) from None
    stem = name[:-4] if name.lower().endswith(".zip") else name
    headers = {
        "X-Recal-Not-Compensated": str(short),
        "Content-Disposition": f'attachment; filename="{stem}-compensated.zip"',
    }
    return Response(answer, media_type="application/zip", headers=headers)


@router.get("/compensations/{compensation_id}", response_class=PlainTextResponse)
def read_compensation(compensation_id: int, db: DbSession, tok: Reader) -> Response:
    """The compensated file (a KRL program's ``.src``; the report's ``files`` hold its ``.dat``)
    as the bytes the compensation answered: UTF-8, or a program that was not UTF-8 with
    ``charset=iso-8859-1``, byte for byte."""
    rec = db.get(Compensation, compensation_id)
    if rec is None:
        raise HTTPException(404, f"no compensation {compensation_id}")
    data, charset = output_bytes(rec.output, rec.encoding)
    return Response(
        data,
        media_type=f"text/plain; charset={charset}",
        headers={"X-Recal-Calibration": str(rec.calibration_id)},
    )
