"""The table of session kinds: one module per kind, each saying how it plans, which instrument it
opens, how it measures one configuration and what it makes of the measurements
(:class:`~service.kinds.base.SessionKind`). The session loop, the start of a session and the
import of external measurements look the kind up here and run any kind the same way (the pages
show each kind's result: ``service.results``).

- ``pose`` (:mod:`.pose`): planned poses, identification;
- ``verify`` (:mod:`.verify`): fresh configurations, the current calibration's errors;
- ``circle`` (:mod:`.circle`): joint sweeps, circle-point analysis;
- ``joint`` (:mod:`.joint`): joint sweeps against reference encoders, gains and harmonics.

A new kind is its module alone (with its test and its docs): every module here with a ``KIND``
is in the table, and its rules (:class:`service.models.KindRules`) reach the rows, the store and
the pages through it (``GET /api/v1/kinds``); nothing outside this package names a kind.
"""

from __future__ import annotations

import importlib
import pkgutil

from sqlmodel import Session

from ..models import Cell, RunSession, register_kind_rules
from ..settings import Settings
from .base import SessionKind, Step


def _find_kinds() -> list[SessionKind]:
    """Every module of this package with a ``KIND`` (a new kind is its module alone), in the
    kinds' ``order`` (the page offers them so; the first is the page's proposal)."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        kind = getattr(importlib.import_module(f"{__name__}.{info.name}"), "KIND", None)
        if isinstance(kind, SessionKind):
            found.append(kind)
    return sorted(found, key=lambda k: (k.order, k.name))


KINDS: dict[str, SessionKind] = {k.name: k for k in _find_kinds()}
for _kind in KINDS.values():  # what the rows, the store and the pages read of each kind
    register_kind_rules(_kind.name, _kind.rules)


def describe_kinds() -> list[dict]:
    """Every kind as the page reads it (``GET /api/v1/kinds``), in the table's order."""
    return [k.describe() for k in KINDS.values()]


def kind_of(name: str) -> SessionKind:
    """The session kind called ``name`` (the request's ``kind`` is checked against this table's
    names by ``SessionCreate``; a stored session always names one)."""
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"unknown session kind {name!r}; expected one of {', '.join(KINDS)}") from None


def finish_session(db: Session, run: RunSession, cell: Cell, settings: Settings) -> None:
    """The session's last step (its kind's ``finish``), committed with the session."""
    kind_of(run.kind).finish(db, run, cell, settings)
    db.add(run)
    db.commit()
    db.refresh(run)


__all__ = ["KINDS", "SessionKind", "Step", "describe_kinds", "finish_session", "kind_of"]
