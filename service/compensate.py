"""Compensating a task file held in memory (the API's compensate endpoint, the nightly job):
a thin wrapper over ``recal compensate`` (``service.commands.compensate``: task CSV and
URScript, ``service.taskfiles`` and ``calibration.compensation``), run on temporary files so
that the service gives exactly what the command gives, with its per-point report."""

from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path


class CompensationInputError(ValueError):
    """The task file cannot be compensated; the message names the line and field."""


def compensate_text(text: str, *, name: str, model_doc: dict, nominal_doc: dict, mode: str = "joints") -> tuple[str, dict]:
    """Compensate ``text`` (a task CSV or a URScript program, told apart by ``name``) with the
    identified model ``model_doc``; ``nominal_doc`` is what the controller knows (targets mode,
    URScript). Returns the compensated text and the per-point report
    (``recal.compensation-report/1``: ``summary``, ``points``, ``uninterpreted``)."""
    try:
        from service import taskfiles
        from service.commands import compensate as command
    except ImportError:
        raise CompensationInputError("compensation is not available in this build") from None
    if hasattr(taskfiles, "compensate_file"):  # a library entry point, when there is one
        return _with_library(taskfiles, text, name=name, model_doc=model_doc, nominal_doc=nominal_doc, mode=mode)
    import argparse

    from service.cli import Fail
    from service.files import InputError

    suffix = Path(name).suffix or ".csv"
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        src, out, report = d / f"task{suffix}", d / f"compensated{suffix}", d / "report.json"
        src.write_text(text, encoding="utf-8")
        (d / "model.json").write_text(json.dumps(model_doc), encoding="utf-8")
        (d / "nominal.json").write_text(json.dumps(nominal_doc), encoding="utf-8")
        parser = argparse.ArgumentParser(prog="recal compensate")
        command.add_parser(parser)
        args = parser.parse_args(["--model", str(d / "model.json"), "--nominal", str(d / "nominal.json"),
                                  "--task", str(src), "--out", str(out), "--mode", mode, "--report", str(report)])
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # its one-line summary names our temporary files
                command.run(args)
        except (Fail, InputError, ValueError) as exc:
            raise CompensationInputError(str(exc).replace(str(src), name)) from None
        doc = json.loads(report.read_text(encoding="utf-8"))
        doc["task"] = name
        return out.read_bytes().decode("utf-8", errors="replace"), doc


def _with_library(taskfiles, text: str, *, name: str, model_doc: dict, nominal_doc: dict, mode: str):
    from calibration.model import model_from_dict

    model = model_from_dict(model_doc)
    nominal = model_from_dict(nominal_doc)
    suffix = Path(name).suffix or ".csv"
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / f"task{suffix}"
        src.write_text(text, encoding="utf-8")
        try:
            return taskfiles.compensate_file(src, model=model, nominal=nominal, mode=mode)
        except ValueError as exc:
            raise CompensationInputError(str(exc).replace(str(src), name)) from None


# Engines of a worker process (service.heavy), one per database URL, opened on its first job and
# kept for the next: a worker serves one service, so this holds one engine.
_ENGINES: dict = {}


def compensate_and_store(database_url: str, calibration_id: int, text: str, *, name: str, mode: str,
                         actor: str, audited: bool = True) -> tuple[int, str, dict | None]:
    """In a worker process: compensate ``text`` with calibration ``calibration_id`` and store the
    result (and, ``audited``, its audit entry). Returns (the compensation's id, the compensated
    text, the report's summary). The
    models are read and the per-point report written here, not in the API process: the report of
    the largest allowed file is megabytes of JSON, and encoding it in the API process held the
    GIL for a fifth of a second (bench/heavy.py)."""
    from sqlmodel import Session

    from .models import Calibration, Cell, Compensation
    from .store import audit, make_engine

    engine = _ENGINES.get(database_url)
    if engine is None:
        engine = _ENGINES[database_url] = make_engine(database_url)
    with Session(engine) as db:
        cal = db.get(Calibration, calibration_id)
        if cal is None:
            raise CompensationInputError(f"no calibration {calibration_id}")
        nominal_doc = db.get(Cell, cal.cell_id).model
        output, report = compensate_text(text, name=name, model_doc=cal.model, nominal_doc=nominal_doc, mode=mode)
        rec = Compensation(calibration_id=calibration_id, name=name, mode=mode, output=output, report=report,
                           created_by=actor)
        db.add(rec)
        db.commit()
        if audited:
            audit(db, actor=actor, action="compensate", subject=f"calibration {calibration_id}",
                  detail={"name": name, "mode": mode})
        return rec.id, output, (report or {}).get("summary")
