"""Compensating a task file held in memory (the API's compensate endpoint, the nightly job):
a thin wrapper over ``service.taskfiles`` (task CSV and URScript) and ``calibration.compensation``."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


class CompensationInputError(ValueError):
    """The task file cannot be compensated; the message names the line and field."""


def compensate_text(text: str, *, name: str, model_doc: dict, nominal_doc: dict, mode: str = "joints") -> tuple[str, dict]:
    """Compensate ``text`` (a task CSV or a URScript program, told apart by ``name``) with the
    identified model ``model_doc``; ``nominal_doc`` is what the controller knows (targets mode).
    Returns the compensated text and a per-point report."""
    from calibration.model import model_from_dict

    try:
        from service import taskfiles
    except ImportError:
        raise CompensationInputError("compensation is not available in this build") from None
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
