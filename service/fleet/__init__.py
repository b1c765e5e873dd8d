"""The fleet: sessions run by ``recal worker`` processes through a PostgreSQL-backed task queue
(Procrastinate), for plants with many cells on several networks (docs/fleet.md).

- :mod:`.jobs`: the queue (one per site), the schema, deferring and cancelling session jobs.
- :mod:`.runner`: :class:`FleetRunner`, what API processes use instead of the
  embedded :class:`service.session_loop.EmbeddedRunner` when ``RECAL_ENGINE=procrastinate``.
- :mod:`.worker`: the worker process: runs ``run_session`` for the jobs of its sites, renews
  the session's lease, carries pause and abort requests to the running session.
- :mod:`.reaper`: turns sessions whose worker vanished into ``interrupted`` ones.

Nothing here is imported by the embedded default: Procrastinate is the ``fleet`` extra.
"""
