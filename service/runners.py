"""What runs a service's sessions: one :class:`SessionRunner` protocol, two implementations.

- ``embedded`` (the default): :class:`service.session_loop.EmbeddedRunner`, sessions in threads of
  the API process;
- ``procrastinate``: :class:`service.fleet.runner.FleetRunner`, sessions queued for
  ``recal worker`` processes (docs/fleet.md).

``create_app`` asks :func:`runner_class` once; the routes and the use cases see only the
protocol (tests/runners runs one contract suite against both).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from sqlmodel import Session

from .models import RunSession
from .settings import Settings


@runtime_checkable
class SessionRunner(Protocol):
    """Runs sessions. ``owner``: the lease-owner name this runner's sessions are held under
    (what an API process interrupts at its stop); ``distributed``: sessions run in other
    processes and go on when this API process stops (so its start and stop must not interrupt
    them)."""

    owner: str
    distributed: bool

    def queue(self, db: Session, run: RunSession) -> bool:
        """Queue ``run`` (planned, flushed, not committed) in the caller's transaction, so that the
        session and what will run it are stored together. True when queued; False when the caller
        must :meth:`start` it once committed (the embedded runner), or when a process already
        holds it."""

    def start(self, session_id: int) -> None:
        """Run the (committed, planned) session."""

    def pause(self, session_id: int) -> bool:
        """Ask the running session to pause after the pose under way; False when nothing runs it
        (the caller records the state itself)."""

    def abort(self, session_id: int) -> bool:
        """Stop the robot now and end the session; False when nothing runs it."""

    def is_active(self, session_id: int) -> bool:
        """The session is planned or running under this runner."""

    def wait(self, session_id: int, timeout_s: float | None = None) -> None:
        """Return when the session's end is stored (it is no longer active; an aborted session's
        devices may still be closing, its lease keeping the cell), or after ``timeout_s``."""

    def not_ready(self) -> str | None:
        """Why this runner cannot take a session now (``/ready`` says it), or None."""

    def shutdown(self, timeout_s: float = 5.0) -> None:
        """Stop running sessions (embedded: pause them) and release what the runner holds."""


def runner_class(settings: Settings):
    """The runner class the settings ask for (``RECAL_ENGINE``): ``cls(engine, settings)``."""
    if settings.engine == "embedded":
        from .session_loop import EmbeddedRunner

        return EmbeddedRunner
    from .fleet.runner import FleetRunner  # needs the fleet extra (procrastinate)

    return FleetRunner
