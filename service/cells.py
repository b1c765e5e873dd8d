"""Cells as records: register one (its nominal model, allowed region and devices checked, each
refusal naming the field), list them, edit one (a new nominal model counted and the old one kept
in the audit log)."""

from __future__ import annotations

from sqlmodel import Session, col, select

from calibration.model import ModelFormatError, model_from_dict

from .device_config import DeviceConfigError, parse_devices
from .models import Cell, CellCreate, CellPublic, CellUpdate, Token
from .plans import RegionError, check_region
from .problems import Conflict, Invalid
from .sessions import driving_session
from .store import audit, current_calibration


def public_cell(db, cell: Cell) -> CellPublic:
    last = current_calibration(db, cell)
    return CellPublic(**cell.model_dump(), last_calibration_id=None if last is None else last.id)


def _check_model(doc: dict):
    """The parsed model, or :class:`Invalid` naming the field of ``body.model`` at fault."""
    try:
        return model_from_dict(doc)
    except ModelFormatError as exc:
        field = f"body.model.{exc.field}" if exc.field else "body.model"
        raise Invalid(field, str(exc).split(": ", 1)[-1]) from None


def _check_region(model, region: list | None, *, sent: bool = True) -> None:
    """:class:`Invalid` naming the row of ``body.allowed_region`` at fault (``sent``: the region came with
    this request; else it is the cell's, checked against a new model)."""
    try:
        check_region(model, region)
    except RegionError as exc:
        field = "body.allowed_region" + (f"[{exc.row}]" if exc.row is not None else "")
        message = (
            str(exc)
            if sent
            else f"the cell's allowed region does not fit the new model: {exc}; send an "
            f"allowed_region for it with the model"
        )
        raise Invalid(field, message) from None


def _check_devices(devices: dict | None) -> None:
    """:class:`Invalid` naming the field of ``body.devices`` at fault (an unknown key with the nearest known
    one); the document is stored as it was sent."""
    if devices is None:
        return
    try:
        parse_devices(devices)
    except DeviceConfigError as exc:
        raise Invalid(f"body.{exc.field}", exc.message) from None


def _name_free(db, name: str, cell_id: int | None = None) -> None:
    other = db.exec(select(Cell.id).where(Cell.name == name)).first()
    if other is not None and other != cell_id:
        raise Conflict(f"a cell named {name!r} exists already")


def register_cell(db: Session, body: CellCreate, tok: Token) -> CellPublic:
    _check_region(_check_model(body.model), body.allowed_region)
    _check_devices(body.devices)
    _name_free(db, body.name)
    cell = Cell(**body.model_dump())
    db.add(cell)
    db.commit()
    db.refresh(cell)
    audit(db, actor=tok.name, action="register cell", subject=f"cell {cell.id}", detail={"name": cell.name})
    return public_cell(db, cell)


def list_cells(db: Session, site: str | None) -> list[CellPublic]:
    q = select(Cell).order_by(col(Cell.id))
    if site is not None:
        q = q.where(Cell.site == site)
    return [public_cell(db, c) for c in db.exec(q).all()]


def edit_cell(db: Session, cell: Cell, body: CellUpdate, tok: Token) -> CellPublic:
    """Change some of a cell's fields. A new ``model`` (the nominal model) is validated as at
    registration, refused while a session drives the cell, and counted (``model_version``; each
    calibration says which it was identified from); the old one is kept in the audit log.
    Calibrations of an earlier nominal no longer serve as the cell's current model or prior."""
    assert cell.id is not None  # a stored cell
    changes = body.model_dump(exclude_unset=True)
    if "name" in changes:
        _name_free(db, changes["name"], cell.id)
    _check_devices(changes.get("devices"))
    detail: dict = {"fields": sorted(changes)}
    if "model" in changes and changes["model"] == cell.model:
        del changes["model"]
    if "model" in changes:
        model = _check_model(changes["model"])
        _check_region(model, changes.get("allowed_region", cell.allowed_region), sent="allowed_region" in changes)
        busy = driving_session(db, cell.id, dry_runs=True)
        if busy is not None:
            raise Conflict(
                f"session {busy.id} is driving this cell ({busy.state}); replace the model when it has stopped"
            )
        detail.update(
            {"old_model": cell.model, "old_model_version": cell.model_version, "model_version": cell.model_version + 1}
        )
        cell.model_version += 1
    elif changes.get("allowed_region") is not None:
        _check_region(model_from_dict(cell.model), changes["allowed_region"])
    for k, v in changes.items():
        setattr(cell, k, v)
    db.add(cell)
    db.commit()
    db.refresh(cell)
    audit(db, actor=tok.name, action="edit cell", subject=f"cell {cell.id}", detail=detail)
    return public_cell(db, cell)
