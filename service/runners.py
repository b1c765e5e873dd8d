"""Which runner runs a service's sessions, from the settings.

- ``embedded`` (the default): :class:`service.orchestrator.Orchestrator`, sessions in threads of
  the API process;
- ``procrastinate``: :class:`service.fleet.orchestrator.FleetOrchestrator`, sessions queued for
  ``recal worker`` processes (docs/fleet.md).

``create_app`` asks here once; nothing else chooses.
"""

from __future__ import annotations

from .settings import Settings


def runner_class(settings: Settings):
    """The runner class the settings ask for (``RECAL_ENGINE``)."""
    if settings.engine == "embedded":
        from .orchestrator import Orchestrator

        return Orchestrator
    from .fleet.orchestrator import FleetOrchestrator  # needs the fleet extra (procrastinate)

    return FleetOrchestrator
