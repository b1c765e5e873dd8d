"""Calibrations: read one, compare two, compensate a task file with one."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse
from sqlmodel import Session
from starlette.concurrency import run_in_threadpool

from ...models import Calibration, CalibrationPublic, Cell, Compensation
from ...results import compare_calibrations
from ...store import audit
from ..deps import Compensator, DbSession, Reader

router = APIRouter(tags=["calibrations"])


def get_calibration(db, calibration_id: int) -> Calibration:
    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise HTTPException(404, f"no calibration {calibration_id}")
    return cal


@router.get("/calibrations/{calibration_id}", response_model=CalibrationPublic)
def read_calibration(calibration_id: int, db: DbSession, tok: Reader):
    return CalibrationPublic(**get_calibration(db, calibration_id).model_dump())


@router.get("/calibrations/{calibration_id}/compare/{other_id}")
def compare(calibration_id: int, other_id: int, db: DbSession, tok: Reader) -> dict:
    """Which parameters moved between two calibrations, in units of their combined standard
    uncertainty: every parameter, the base and tool frames included (the page's comparison,
    :func:`service.results.compare_calibrations`), with the predicted accuracy of both."""
    a, b = get_calibration(db, calibration_id), get_calibration(db, other_id)
    return {**compare_calibrations(a, b), "predicted_from": a.predicted, "predicted_to": b.predicted,
            "nominal_versions": [a.nominal_version, b.nominal_version]}


def _load_for_compensation(engine, calibration_id: int) -> tuple[dict, dict]:
    """The calibration's model and the nominal its cell's controller computes with (a UR's own
    kinematics where the cell keeps them, service.controller)."""
    from ...controller import controller_nominal

    with Session(engine) as db:
        cal = get_calibration(db, calibration_id)
        return cal.model, controller_nominal(db, db.get(Cell, cal.cell_id))


def _store_compensation(engine, calibration_id: int, name: str, mode: str, output: str, report: dict,
                        actor: str, payload: str | None = None) -> int:
    with Session(engine) as db:
        rec = Compensation(calibration_id=calibration_id, name=name, mode=mode, output=output, report=report,
                           created_by=actor)
        db.add(rec)
        db.commit()
        audit(db, actor=actor, action="compensate", subject=f"calibration {calibration_id}",
              detail={"name": name, "mode": mode, **({"payload": payload} if payload else {})})
        return rec.id


@router.post("/calibrations/{calibration_id}/compensate", response_class=PlainTextResponse)
async def compensate(calibration_id: int, request: Request, tok: Compensator,
                     mode: str = "joints", name: str = "task.csv", payload: str | None = None) -> PlainTextResponse:
    """A task CSV or a robot program (URScript, RAPID, TP; ``name`` tells which) in the request
    body, the compensated file out (contracts §5). ``mode``: ``joints`` or ``targets``;
    ``payload``: the task's payload ``KG[,X,Y,Z]`` (kg, centre of gravity in the tool frame in the
    model's length unit), which a calibration with joint compliance sags under. A program of
    several files (KRL: the ``.src`` and its ``.dat``) comes as ``multipart/form-data``, one part
    per file; the answer is then JSON ``{"files": [{"name", "text"}, ...]}``, the program first.
    The compensation runs in a worker process (service.heavy): the service answers every other
    request meanwhile; the database in the thread pool (a networked database may stall)."""
    if mode not in ("joints", "targets"):
        raise HTTPException(422, {"field": "query.mode", "message": "expected joints or targets"})
    from ...compensate import CompensationInputError, compensate_text, read_multipart

    engine = request.app.state.engine
    model_doc, cell_model = await run_in_threadpool(_load_for_compensation, engine, calibration_id)
    raw = await request.body()
    content_type = request.headers.get("content-type", "")
    companions = None
    try:
        if content_type.lower().startswith("multipart/form-data"):
            files = read_multipart(content_type, raw)
            main = next((f for f in files if not f[0].lower().endswith(".dat")), files[0])
            name, body = main
            companions = {n: t for n, t in files if (n, t) != main}
        else:
            body = raw.decode("utf-8", errors="replace")
    except CompensationInputError as exc:
        raise HTTPException(422, {"field": "body", "message": str(exc)}) from None
    if not body.strip():
        raise HTTPException(422, {"field": "body", "message": "expected a task CSV or robot program, got nothing"})
    if any("\x00" in text for text in [body, *(companions or {}).values()]):
        raise HTTPException(422, {"field": "body", "message": "expected a text file, got NUL characters (binary data?)"})

    try:
        output, report = await request.app.state.heavy.run(compensate_text, body, name=name, model_doc=model_doc,
                                                           nominal_doc=cell_model, mode=mode, companions=companions,
                                                           payload=payload)
    except CompensationInputError as exc:
        field = "query.payload" if str(exc).startswith("--payload") else "body"
        raise HTTPException(422, {"field": field, "message": str(exc)}) from None
    rec_id = await run_in_threadpool(_store_compensation, engine, calibration_id, name, mode, output, report, tok.name,
                                     payload)
    if companions is not None:
        from fastapi.responses import JSONResponse

        return JSONResponse({"files": [{"name": name, "text": output}] + report.get("files", [])},
                            headers={"X-Recal-Compensation": str(rec_id)})
    media = "text/csv" if name.lower().endswith(".csv") else "text/plain"
    return PlainTextResponse(output, media_type=media, headers={"X-Recal-Compensation": str(rec_id)})


@router.get("/compensations/{compensation_id}", response_class=PlainTextResponse)
def read_compensation(compensation_id: int, db: DbSession, tok: Reader) -> PlainTextResponse:
    rec = db.get(Compensation, compensation_id)
    if rec is None:
        raise HTTPException(404, f"no compensation {compensation_id}")
    return PlainTextResponse(rec.output, headers={"X-Recal-Calibration": str(rec.calibration_id)})
