"""What every session kind says: how it plans, which instrument it opens, how it measures one
configuration, and what it makes of the measurements at the end (:class:`SessionKind`). The
session loop runs any kind the same way; :mod:`service.kinds` holds the table."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from sqlmodel import Session

from calibration.model import KinematicModel

from ..control import Control
from ..devices import CellDevices, DeviceConfigError, DevicesConfig, stored_devices
from ..models import Cell, KindRules, Measurement, RunSession
from ..plans import Plan, PlanRequest
from ..problems import Invalid
from ..settings import Settings


@dataclass(frozen=True)
class Step:
    """What measuring one configuration needs: the session, its open devices, the cell's
    current model (``guide``: where the instrument should look), and the database (for the
    measurements so far)."""

    db: Session
    run: RunSession
    devices: CellDevices
    settings: Settings
    control: Control
    guide: KinematicModel


def cell_devices(cell: Cell, *, field: str) -> DevicesConfig:
    """The cell's devices for a kind's ``check``: a stored document that cannot be used is
    refused naming ``field`` (the request's choice that needs it) and the document's field."""
    try:
        return stored_devices(cell.devices)
    except DeviceConfigError as exc:
        raise Invalid(field, f"the cell's devices: {exc}") from None


class SessionKind(ABC):
    """One kind of session (``pose``, ``verify``, ``circle``, ``joint``): its name, how the page
    offers it (``title``, ``summary``, ``heading``, the count's default and cap and what it
    counts), what it measures with (``instruments``: roles of the device registry; the request's
    ``device`` chooses among them when ``device_choice``), and :attr:`rules`: what the rows, the
    store and the pages need to know of it (registered by :mod:`service.kinds`)."""

    name: str
    order: int  # where the page offers it among the kinds (the first is its proposal)
    title: str
    summary: str
    heading: str
    default_count: int
    count_help: str
    instruments: tuple[str, ...]
    device_choice: bool = True
    rules: KindRules

    def describe(self) -> dict:
        """The kind as the page reads it (``GET /api/v1/kinds``)."""
        return {
            "name": self.name,
            "title": self.title,
            "summary": self.summary,
            "heading": self.heading,
            "default_count": self.default_count,
            "max_count": self.rules.max_count,
            "count_help": self.count_help,
            "instruments": list(self.instruments),
            "device_choice": self.device_choice,
            "payloads": self.rules.carries_payloads,
            "repeats": self.rules.repeats,
            "importable": self.rules.importable,
            "stores": self.rules.stores,
        }

    @abstractmethod
    def check(self, cell: Cell, model: KinematicModel, *, device: str, joints: list[int] | None, payloads) -> None:
        """Refuse a session the cell cannot run (:class:`service.problems.Invalid` naming the
        request field), before anything is stored or moves: a configuration error is never
        found half-way through a session."""

    def default_target(self, model: KinematicModel, device: str) -> str | None:
        """The model target the session measures when the request names none."""
        return None

    @abstractmethod
    def instrument(self, run: RunSession) -> str:
        """The measuring device's key in ``session.device_state``: ``tracker``, ``cmm``, ``encoder``."""

    @abstractmethod
    def plan(self, req: PlanRequest) -> Plan:
        """The session's configurations (checked against the limits by the caller)."""

    @abstractmethod
    def open_instrument(self, devices: CellDevices, cell: Cell, run: RunSession, settings: Settings) -> None:
        """Open the measuring device(s) into ``devices`` (the robot is open already). Raises
        ``DeviceError``, ``DeviceConfigError`` or ``OSError``."""

    @abstractmethod
    def measure_one(self, step: Step, seq: int, q_read: np.ndarray, joint: int) -> list[Measurement]:
        """The measurements at configuration ``seq`` (readings ``q_read``, swept ``joint`` or 0)."""

    @abstractmethod
    def finish(self, db: Session, run: RunSession, cell: Cell, settings: Settings) -> None:
        """What the measured session gives (a calibration, a verification), on ``run`` and in the
        store; the caller commits ``run``. Raises :class:`service.analysis.AnalysisError`."""
