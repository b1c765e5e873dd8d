"""Compensating a task file held in memory (the API's compensate endpoint, the nightly job):
a thin wrapper over ``recal compensate`` (``service.commands.compensate``: task CSV, URScript,
RAPID, KRL and TP, ``service.taskfiles``, ``service.programs`` and ``calibration.compensation``), run on temporary files so
that the service gives exactly what the command gives, with its per-point report."""

from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path
from calibration.errors import RecalError


class CompensationInputError(RecalError, ValueError):
    """The task file cannot be compensated; the message names the line and field."""


def compensate_text(text: str, *, name: str, model_doc: dict, nominal_doc: dict, mode: str = "joints",
                    companions: dict[str, str] | None = None) -> tuple[str, dict]:
    """Compensate ``text`` (a task CSV or a robot program: URScript, RAPID, KRL, TP, told apart
    by ``name``) with the identified model ``model_doc``; ``nominal_doc`` is what the controller
    knows (targets mode, programs). ``companions``: the program's other files by name (a KRL
    ``.src``'s ``.dat``; a ``$config.dat`` is read for its ``TOOL_DATA``/``BASE_DATA``). Returns
    the compensated text and the per-point report (``recal.compensation-report/1``: ``summary``, ``points``, ``uninterpreted``; with companions,
    ``files``: their compensated texts, ``[{"name", "text"}]``)."""
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
        companions = dict(companions or {})
        config = {k: companions.pop(k) for k in list(companions) if k.lower().lstrip("$") == "config.dat"}
        for other, content in companions.items():  # beside the program, under its stem (KRL's .dat)
            (d / f"task{Path(other).suffix}").write_text(content, encoding="utf-8")
        extra = []
        for content in config.values():  # KUKA's $config.dat: the TOOL_DATA and BASE_DATA the program selects
            (d / "config.dat").write_text(content, encoding="utf-8")
            extra = ["--config-dat", str(d / "config.dat")]
        (d / "model.json").write_text(json.dumps(model_doc), encoding="utf-8")
        (d / "nominal.json").write_text(json.dumps(nominal_doc), encoding="utf-8")
        parser = argparse.ArgumentParser(prog="recal compensate")
        command.add_parser(parser)
        args = parser.parse_args(["--model", str(d / "model.json"), "--nominal", str(d / "nominal.json"),
                                  "--task", str(src), "--out", str(out), "--mode", mode, "--report", str(report),
                                  *extra])
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # its one-line summary names our temporary files
                command.run(args)
        except (Fail, InputError, ValueError) as exc:
            message = str(exc).replace(str(src), name).replace(str(d / "config.dat"), "$config.dat")
            for other in companions:
                message = message.replace(str(d / f"task{Path(other).suffix}"), other)
            raise CompensationInputError(message) from None
        doc = json.loads(report.read_text(encoding="utf-8"))
        doc["task"] = name
        names = {f"task{Path(o).suffix}": o for o in companions or {}}
        for point in doc.get("points", []) + doc.get("uninterpreted", []):
            if "file" in point:  # the user's file names, not our temporary ones
                point["file"] = names.get(Path(point["file"]).name, name)
        if companions:
            doc["files"] = [{"name": o, "text": (d / f"compensated{Path(o).suffix}").read_bytes().decode(
                "utf-8", errors="replace")} for o in companions if (d / f"compensated{Path(o).suffix}").exists()]
        return out.read_bytes().decode("utf-8", errors="replace"), doc


def read_multipart(content_type: str, body: bytes) -> list[tuple[str, str]]:
    """The files of a ``multipart/form-data`` body, ``(file name, text)`` in order (the standard
    library's MIME parser: no extra dependency). A part without a file name is ignored."""
    from email.parser import BytesParser
    from email.policy import HTTP

    msg = BytesParser(policy=HTTP).parsebytes(b"Content-Type: " + content_type.encode("latin-1") + b"\r\n\r\n" + body)
    if not msg.is_multipart():
        raise CompensationInputError("expected a multipart/form-data body with the program's files")
    files = []
    for part in msg.iter_parts():
        filename = part.get_filename()
        if filename:
            files.append((Path(filename).name, (part.get_payload(decode=True) or b"").decode("utf-8", errors="replace")))
    if not files:
        raise CompensationInputError("expected at least one file in the multipart body")
    return files


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
