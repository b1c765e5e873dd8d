"""A cell's registered task files (the programs it runs, compensated again after every
calibration): register, list, read, and what compensating all of them needs. The compensation
itself is :func:`service.stored_compensation.compensate_and_store`, run in the heavy-work pool."""

from __future__ import annotations

from sqlmodel import Session, select

from . import programs
from .files import InputError, check_csv_text
from .models import Calibration, Cell, TaskFile
from .problems import Invalid, NotFound
from .store import audit, current_calibration

# What a file's ``content`` may be in: ``content.encode(encoding)`` is the file's bytes. These are
# the compensation route's (service.stored_compensation.decode_upload): UTF-8, or ISO-8859-1, a character
# per byte, for a program that is not UTF-8 (a KRL or RAPID file in Windows-1252).
ENCODINGS = ("utf-8", "iso-8859-1")


def _check_bytes(field: str, name: str, content: str, encoding: str) -> None:
    """The file can be stored as the bytes it was: a known encoding that holds every character."""
    if encoding not in ENCODINGS:
        raise Invalid(f"{field}encoding", f"{name}: expected utf-8 or iso-8859-1, got {encoding!r}")
    try:
        content.encode(encoding)
    except UnicodeEncodeError as exc:
        what = "UTF-8" if encoding == "utf-8" else "ISO-8859-1 (a character per byte)"
        raise Invalid(
            f"{field}content", f"{name}: character {exc.object[exc.start]!r} at {exc.start} is not {what}"
        ) from None


def register_task(
    db: Session,
    cell: Cell,
    *,
    name: str,
    content: str,
    mode: str,
    actor: str,
    encoding: str = "utf-8",
    files: list[dict] | None = None,
) -> dict:
    """Register a task file (a task CSV or a robot program) with ``cell``: ``content.encode(encoding)``
    is its bytes, kept and compensated as they are; ``files`` (``[{"name", "content", "encoding"}]``)
    a KRL ``.src``'s other files, its ``.dat`` (and a ``$config.dat``), as the compensation route
    takes them. :class:`Invalid` names the field when the bytes could not be kept or a file is missing."""
    files = [{"encoding": "utf-8", **f} for f in files or []]
    lower = name.lower()
    if lower.endswith(".dat"):
        raise Invalid("body.name", f"{name}: a KRL program is registered by its .src, with its .dat in files")
    _check_bytes("body.", name, content, encoding)
    if encoding != "utf-8" and programs.format_of(name) == "csv":
        raise Invalid("body.encoding", f"{name}: a task CSV is UTF-8 (contracts §5); got {encoding}")
    if programs.format_of(name) == "csv":
        try:  # the reader the compensation will use, now: a file it cannot read is not kept
            check_csv_text(name, content)
        except InputError as exc:
            raise Invalid("body.content", str(exc)) from None
    if files and not lower.endswith(".src"):
        raise Invalid("body.files", f"{name}: only a KRL .src has other files (its .dat, and $config.dat)")
    for i, f in enumerate(files):
        _check_bytes(f"body.files[{i}].", f["name"], f["content"], f["encoding"])
        if not f["name"].lower().endswith(".dat"):
            raise Invalid(f"body.files[{i}].name", f"{f['name']}: expected the .src's .dat, or $config.dat")
    # a .src alone is taken, as `recal compensate` and the compensation route take it (targets
    # declared in a .dat it lacks are then reported as not compensated); two .dat files are not
    dats = [f for f in files if f["name"].lower().lstrip("$") != "config.dat"]
    if len(dats) > 1:
        raise Invalid("body.files", f"{name} has one .dat (its targets' declarations), got {len(dats)}")
    t = TaskFile(cell_id=cell.id, name=name, content=content, mode=mode, encoding=encoding, files=files or None)
    db.add(t)
    db.commit()
    db.refresh(t)
    audit(db, actor=actor, action="register task file", subject=f"cell {cell.id}", detail={"name": name})
    return {"id": t.id, "name": t.name, "mode": t.mode}


def list_tasks(db: Session, cell_id: int) -> list[dict]:
    rows = db.exec(select(TaskFile).where(TaskFile.cell_id == cell_id).order_by(TaskFile.id)).all()
    return [{"id": t.id, "name": t.name, "mode": t.mode, "created_at": t.created_at} for t in rows]


def read_task(db: Session, cell_id: int, task_id: int) -> dict:
    t = db.get(TaskFile, task_id)
    if t is None or t.cell_id != cell_id:
        raise NotFound(f"no task file {task_id} in cell {cell_id}")
    return {
        "id": t.id,
        "name": t.name,
        "mode": t.mode,
        "content": t.content,
        "encoding": t.encoding,
        "files": t.files or [],
        "created_at": t.created_at,
    }


def tasks_to_compensate(db: Session, cell: Cell, calibration_id: int | None) -> tuple[int, list[tuple]]:
    """The calibration to compensate with (``calibration_id``, default the cell's current one)
    and the cell's task files ``(id, name, mode)``; :class:`NotFound` without a calibration."""
    cal = db.get(Calibration, calibration_id) if calibration_id is not None else current_calibration(db, cell)
    if cal is None or cal.cell_id != cell.id:
        raise NotFound(
            "no calibration to compensate with"
            if calibration_id is None
            else f"no calibration {calibration_id} in cell {cell.id}"
        )
    tasks = db.exec(
        select(TaskFile.id, TaskFile.name, TaskFile.mode).where(TaskFile.cell_id == cell.id).order_by(TaskFile.id)
    ).all()
    return cal.id, [tuple(t) for t in tasks]


def task_input(db: Session, task_id: int) -> dict:
    """What compensating task file ``task_id`` takes (:func:`service.stored_compensation.compensate_and_store`'s
    arguments): ``text``, ``companions`` (file name -> text; ``None`` for a single file) and
    ``encodings`` (file name -> encoding), so that each file is compensated as its bytes."""
    t = db.get(TaskFile, task_id)
    files = t.files or []
    return {
        "text": t.content,
        "companions": {f["name"]: f["content"] for f in files} or None,
        "encodings": {t.name: t.encoding, **{f["name"]: f["encoding"] for f in files}},
    }
