"""Compensations the service makes and stores: a task file held in memory (the API's compensation
routes, the nightly job) is laid in a temporary folder (the parsers read a KRL program's .dat beside its .src)
and compensated by the same library function as ``recal compensate``
(:func:`service.task_compensation.compensate_task`); messages name the user's files."""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from calibration.compliance import with_payload
from calibration.model import ModelFormatError, model_from_dict

from . import programs
from .files import InputError, parse_payload
from .packed import pack_output, pack_report
from .programs.frames import Frames
from .task_compensation import CompensationInputError, CompensationRequest, calibrated_range_of, compensate_task

__all__ = ["CompensationInputError", "compensate_and_store", "compensate_text", "decode_upload", "read_multipart"]


def decode_upload(name: str, data: bytes) -> tuple[str, str]:
    """An uploaded file's text and the encoding that gives its bytes back: UTF-8 where the bytes
    are UTF-8; else, for a robot program, ISO-8859-1 (Latin-1), one character per byte (a KUKA or ABB program
    written in Windows-1252 comes back byte for byte, comments and all). A task CSV that is not
    UTF-8 is read as before (undecodable bytes replaced): its columns are rewritten anyway."""
    try:
        return data.decode("utf-8"), "utf-8"
    except UnicodeDecodeError:
        if programs.format_of(name) == "csv" and not name.lower().endswith(".dat"):  # KRL's .dat is a program's
            return data.decode("utf-8", errors="replace"), "utf-8"
        return data.decode("iso-8859-1"), "iso-8859-1"


def compensate_text(
    text: str,
    *,
    name: str,
    model_doc: dict,
    nominal_doc: dict,
    mode: str = "joints",
    companions: dict[str, str] | None = None,
    payload: str | None = None,
    encodings: dict[str, str] | None = None,
) -> tuple[str, dict]:
    """Compensate ``text`` (a task CSV or a robot program: URScript, RAPID, KRL, TP, told apart
    by ``name``) with the identified model ``model_doc``; ``nominal_doc`` is what the controller
    knows (targets mode, programs). ``companions``: the program's other files by name (a KRL
    ``.src``'s ``.dat``; a ``$config.dat`` is read for its ``TOOL_DATA``/``BASE_DATA``). Returns
    the compensated text and the per-point report (``recal.compensation-report/1``: ``summary``,
    ``points``, ``uninterpreted``; with companions, ``files``: their compensated texts,
    ``[{"name", "text", "encoding"}]``). ``payload``: the task's payload ``KG[,X,Y,Z]`` for a
    compliant model (``recal compensate --payload``). ``encodings``: file name -> the encoding
    its text was decoded with (:func:`decode_upload`; default UTF-8): each file is compensated
    as those bytes, and its compensated text is given in the same encoding."""
    model, nominal = _models(model_doc, nominal_doc)
    if payload is not None:
        try:
            model = with_payload(model, parse_payload(payload, model))
        except ValueError as exc:
            raise CompensationInputError(str(exc)) from None
    if nominal.n_joints != model.n_joints:
        raise CompensationInputError(
            f"the cell's nominal model has {nominal.n_joints} joints, the calibration {model.n_joints}"
        )
    suffix, fmt_named = _suffix_and_format(name, text)
    encodings = dict(encodings or {})
    companions = dict(companions or {})
    config = {k: companions.pop(k) for k in list(companions) if k.lower().lstrip("$") == "config.dat"}
    # RAPID: the task's other modules (a SYSMOD, a data module), read for their tooldata/wobjdata
    modules = (
        {k: companions.pop(k) for k in list(companions) if programs.format_of(k) == "rapid"}
        if fmt_named == "rapid"
        else {}
    )
    with tempfile.TemporaryDirectory() as tmp:
        laid = _lay_out(Path(tmp), suffix, name, text, companions, config, modules, encodings)
        result = _compensate_laid(laid, model, nominal, mode)
        doc = result.report()
        doc["task"] = name
        for point in doc.get("points", []) + doc.get("uninterpreted", []):
            if "file" in point:
                point["file"] = laid.names.get(str(laid.folder / Path(point["file"]).name), name)
        encs = [encodings.get(name, "utf-8")] + [encodings.get(o, "utf-8") for o in companions]
        texts = [
            data if isinstance(data, str) else data.decode(enc, errors="replace")
            for (_, data), enc in zip(result.outputs, encs)
        ]
        if companions:
            doc["files"] = [{"name": o, "text": t, "encoding": e} for o, t, e in zip(companions, texts[1:], encs[1:])]
        return texts[0], doc


def _models(model_doc: dict, nominal_doc: dict):
    """The calibration's identified model and its cell's nominal model, read from their documents."""
    try:
        return model_from_dict(model_doc), model_from_dict(nominal_doc)
    except ModelFormatError as exc:
        raise CompensationInputError(f"the calibration's model: {exc}") from None


def _suffix_and_format(name: str, text: str) -> tuple[str, str]:
    """The file suffix the task is laid out under, and its format: from ``name``'s extension, or
    from the content when the extension says nothing (refused when neither does)."""
    try:
        fmt_named = programs.format_of(name, None, text=None if name.lower().endswith(".dat") else text)
    except InputError as exc:
        raise CompensationInputError(str(exc).replace("--format", "a file name with its extension (?name=)")) from None
    suffix = Path(name).suffix if programs.format_of(name) == fmt_named else programs.FORMATS[fmt_named][0]
    return suffix, fmt_named


@dataclass
class _Laid:
    """A task and its companions written in a temporary folder, as the parsers read them."""

    folder: Path
    src: Path  # the task, ``task{suffix}``
    out: Path  # where its compensated text goes
    config_path: Path | None  # KUKA's $config.dat
    module_paths: list[Path]  # RAPID's other modules
    names: dict[str, str]  # temporary path -> the user's file name

    def ours(self, message: str) -> str:
        """``message`` with the user's file names, not our temporary ones."""
        for path, user in self.names.items():
            message = message.replace(path, user)
        return message


def _lay_out(d: Path, suffix: str, name: str, text: str, companions, config, modules, encodings) -> _Laid:
    """Write the task ``name``, its companions, $config.dat and RAPID modules in ``d``, each as
    the bytes uploaded: the text back in the encoding it was decoded with."""
    src, out = d / f"task{suffix}", d / f"compensated{suffix}"
    src.write_bytes(text.encode(encodings.get(name, "utf-8")))
    for other, content in companions.items():  # beside the program, under its stem (KRL's .dat)
        (d / f"task{Path(other).suffix}").write_bytes(content.encode(encodings.get(other, "utf-8")))
    config_path = None
    for other, content in config.items():  # KUKA's $config.dat: the TOOL_DATA and BASE_DATA the program selects
        config_path = d / "config.dat"
        config_path.write_bytes(content.encode(encodings.get(other, "utf-8")))
    module_paths = []
    for k, (other, content) in enumerate(modules.items()):  # under their own names, kept apart
        (d / f"m{k}").mkdir()
        module_paths.append(d / f"m{k}" / Path(other).name)  # its name: the report's frames say it
        module_paths[-1].write_bytes(content.encode(encodings.get(other, "utf-8")))
    names = {str(src): name, **{str(d / f"task{Path(o).suffix}"): o for o in companions}}
    names.update({str(p): o for p, o in zip(module_paths, modules)})
    if config_path is not None:
        names[str(config_path)] = "$config.dat"
    return _Laid(d, src, out, config_path, module_paths, names)


def _compensate_laid(laid: _Laid, model, nominal, mode: str):
    """Compensate the laid-out task (``compensate_task``); bad input refused in the user's names."""
    try:
        fmt = programs.format_of(str(laid.src), None)
        frames = (
            Frames.from_options(
                [], [], str(laid.config_path) if laid.config_path else None, modules=[str(p) for p in laid.module_paths]
            )
            if fmt not in ("csv", "urscript")
            else None
        )
        req = CompensationRequest(
            task=str(laid.src),
            out=str(laid.out),
            model_label="the calibration's model",
            fmt=fmt,
            mode=mode,
            nominal=nominal,
            calibrated=calibrated_range_of(model),
            frames=frames,
            report=True,
        )
        return compensate_task(model, req)
    except (InputError, CompensationInputError, ValueError) as exc:
        message = laid.ours(str(exc)).replace("(--module SYSMOD.sys)", "(post it with the program)")
        raise CompensationInputError(message) from None


def read_multipart(content_type: str, body: bytes) -> list[tuple[str, str, str]]:
    """The files of a ``multipart/form-data`` body, ``(file name, text, encoding)`` in order
    (:func:`decode_upload`; the standard library's MIME parser: no extra dependency). A part
    without a file name is ignored."""
    from email.parser import BytesParser
    from email.policy import HTTP

    msg = BytesParser(policy=HTTP).parsebytes(b"Content-Type: " + content_type.encode("latin-1") + b"\r\n\r\n" + body)
    if not msg.is_multipart():
        raise CompensationInputError("expected a multipart/form-data body with the program's files")
    files = []
    for part in msg.iter_parts():
        filename = part.get_filename()
        if filename:
            files.append((Path(filename).name, *decode_upload(filename, part.get_payload(decode=True) or b"")))
    if not files:
        raise CompensationInputError("expected at least one file in the multipart body")
    return files


# Engines of a worker process (service.heavy), one per database URL, opened on its first job and
# kept for the next: a worker serves one service, so this holds one engine.
_ENGINES: dict = {}


def compensate_and_store(
    database_url: str,
    calibration_id: int,
    text: str,
    *,
    name: str,
    mode: str,
    actor: str,
    companions: dict[str, str] | None = None,
    payload: str | None = None,
    audited: bool = True,
    encodings: dict[str, str] | None = None,
) -> tuple[int, str, dict | None, list]:
    """In a worker process: compensate ``text`` (``compensate_text``'s arguments) with calibration
    ``calibration_id``, against the nominal its cell's controller computes with (a UR's own
    kinematics where the cell keeps them, service.controller), and store the result (and,
    ``audited``, its audit entry). Returns (the compensation's id, the compensated text, the
    report's summary, the companions' compensated texts). The models are read and the per-point
    report written here, not in the API process: the report of the largest allowed file is
    megabytes of JSON, and encoding it in the API process held the GIL for a fifth of a second
    (bench/heavy.py)."""
    from sqlmodel import Session

    from .controller import controller_nominal
    from .models import Cell, Compensation
    from .store import audit

    with Session(_engine(database_url)) as db:
        cal = _calibration(db, calibration_id)
        nominal_doc = controller_nominal(db, db.get(Cell, cal.cell_id))
        output, report = compensate_text(
            text,
            name=name,
            model_doc=cal.model,
            nominal_doc=nominal_doc,
            mode=mode,
            companions=companions,
            payload=payload,
            encodings=encodings,
        )
        # stored compressed (service.packed): at most about the input's size, not six times it
        stored_output, stored_encoding = pack_output(output, (encodings or {}).get(name, "utf-8"))
        rec = Compensation(
            calibration_id=calibration_id,
            name=name,
            mode=mode,
            output=stored_output,
            encoding=stored_encoding,  # served again as the bytes it was answered as
            report=pack_report(report),
            created_by=actor,
        )
        db.add(rec)
        db.commit()
        if audited:
            audit(
                db,
                actor=actor,
                action="compensate",
                subject=f"calibration {calibration_id}",
                detail={"name": name, "mode": mode, **({"payload": payload} if payload else {})},
            )
        return rec.id, output, (report or {}).get("summary"), (report or {}).get("files", [])


def compensate_backup_and_audit(
    database_url: str, calibration_id: int, data: bytes, *, actor: str, name: str, limit: int
) -> tuple[bytes, int, dict]:
    """In a worker process: the zipped controller backup ``data`` (a KUKA archive, an ABB backup, a
    folder of Fanuc ``.ls`` programs) compensated with calibration ``calibration_id`` against the
    nominal its cell's controller computes with (service.backups), as ``recal compensate --task
    DIR`` does; audited. Returns (the zip of the same layout with the report,
    ``service.backups.REPORT_NAME``, beside its entries; the targets not compensated; a summary).
    ``limit``: the input bound on the uncompressed size. Bad input raises
    :class:`CompensationInputError` naming the zip entry (never a temporary path)."""
    from sqlmodel import Session

    from .backups import REPORT_NAME, pack_zip, report_bytes, unpack_zip
    from .controller import controller_nominal
    from .models import Cell

    with Session(_engine(database_url)) as db:
        cal = _calibration(db, calibration_id)
        model_doc, nominal_doc = cal.model, controller_nominal(db, db.get(Cell, cal.cell_id))
    model, nominal = _models(model_doc, nominal_doc)
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "in", Path(tmp) / "out"
        src.mkdir()
        names = unpack_zip(data, src, limit)  # UnsafeZip (a ValueError): the route's 413 or 422
        if REPORT_NAME in names:
            raise CompensationInputError(f"the zip already holds {REPORT_NAME}: expected a controller backup")
        result = _compensate_unpacked(src, out, model, nominal)
        result.report["task"] = name
        answer = pack_zip(out, names, {REPORT_NAME: report_bytes(result)})
    summary = {
        "layout": result.layout,
        "programs": result.programs,
        "points": result.points,
        "not_compensated": result.not_compensated,
        "shortfalls": result.short,
    }
    _audit_backup(database_url, actor, calibration_id, name, summary)
    return answer, result.not_compensated, summary


def _compensate_unpacked(src: Path, out: Path, model, nominal):
    """Compensate the backup unpacked in ``src`` into ``out`` (service.backups.compensate_folder);
    bad input refused naming the zip's entries, not our temporary folder nor CLI flags."""
    from .backups import NotABackup, compensate_folder, with_frame_data

    def request(job, out_path):
        frames = Frames.from_options([], [], job.config_dat, modules=list(job.modules), rapid=job.fmt == "rapid")
        frames = with_frame_data(frames, job, src)  # a Fanuc backup's SYSFRAME.VA
        return CompensationRequest(
            task=str(job.path),
            out=str(out_path),
            model_label="the calibration's model",
            fmt=job.fmt,
            nominal=nominal,
            calibrated=calibrated_range_of(model),
            frames=frames,
            report=True,
        )

    def ours(message: str) -> str:  # the zip's entry names, not our temporary folder nor CLI flags
        message = message.replace(str(src) + "/", "").replace(str(src), "the zip")
        return re.sub(
            r"pass --(?:base|tool)-frame \d+=X,Y,Z,W,P,R",
            "not set (or Uninitialized) in the backup's frame data (SYSFRAME.VA)",
            message,
        )

    try:
        return compensate_folder(src, out, model, request)
    except NotABackup as exc:
        raise CompensationInputError(f"the zip: {exc}") from None
    except (InputError, CompensationInputError, ValueError) as exc:
        raise CompensationInputError(ours(str(exc)).replace(" (--module SYSMOD.sys)", "")) from None


def _audit_backup(database_url: str, actor: str, calibration_id: int, name: str, summary: dict) -> None:
    from sqlmodel import Session

    from .store import audit

    with Session(_engine(database_url)) as db:
        audit(
            db,
            actor=actor,
            action="compensate backup",
            subject=f"calibration {calibration_id}",
            detail={"name": name, **{k: v for k, v in summary.items() if k != "shortfalls"}},
        )


def _engine(database_url: str):
    """The worker process's engine for ``database_url`` (made once, kept for the next job)."""
    from .store import make_engine

    engine = _ENGINES.get(database_url)
    if engine is None:
        engine = _ENGINES[database_url] = make_engine(database_url)
    return engine


def _calibration(db, calibration_id: int):
    from .models import Calibration

    cal = db.get(Calibration, calibration_id)
    if cal is None:
        raise CompensationInputError(f"no calibration {calibration_id}")
    return cal
