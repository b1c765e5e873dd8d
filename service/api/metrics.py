"""Prometheus metrics at ``GET /metrics`` (prometheus-client's text format), for an operator's
monitoring (docs/service.md, "Operations"):

- ``recal_request_duration_seconds{method, route, status}``: every request's latency (a
  histogram; ``route`` is the route's template, never an id);
- ``recal_sessions{state}``: sessions by state; ``recal_measurements``: measurements stored;
- per cell (``cell``: its name): ``recal_cell_verified_rms`` / ``recal_cell_verified_max``, the last
  completed verify session's measured accuracy (the model's length unit, ``unit`` label),
  ``recal_cell_drift_threshold`` and ``recal_cell_drift_ratio`` (that max over the threshold:
  above 1 the cell has drifted, what ``recal nightly`` recalibrates).

Each app has its own registry (tests build many apps in one process); the store's figures are
read when scraped, in one query each. No token: like ``/health``, a scraper on the plant
network reads it, and it names cells and counts only.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from sqlalchemy import func
from sqlmodel import Session, select

from ..kinds import KINDS  # noqa: F401 - registers the kinds' rules kinds_that reads
from ..models import Cell, Measurement, RunSession, VerifyResult, kinds_that

router = APIRouter(include_in_schema=False)

BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class StoreCollector:
    """Figures read from the store at each scrape."""

    def __init__(self, app):
        self.app = app

    def collect(self):
        engine = getattr(self.app.state, "engine", None)
        if engine is None:
            return
        with Session(engine) as db:
            states = db.exec(select(RunSession.state, func.count()).group_by(RunSession.state)).all()
            n_meas = db.exec(select(func.count(Measurement.id))).one()
            cells = db.exec(select(Cell.id, Cell.name, Cell.model["units"], Cell.drift_threshold)).all()
            verifies = db.exec(
                select(RunSession.cell_id, RunSession.verify)
                .where(
                    RunSession.kind.in_(kinds_that(lambda r: r.stores == "verification")),  # type: ignore[attr-defined]
                    RunSession.state == "completed",
                    RunSession.dry_run == False,  # noqa: E712
                )
                .order_by(RunSession.id)
            ).all()
        g = GaugeMetricFamily("recal_sessions", "Sessions by state", labels=["state"])
        for state, n in states:
            g.add_metric([state], n)
        yield g
        yield GaugeMetricFamily("recal_measurements", "Measurements stored", value=n_meas)
        last: dict[int, VerifyResult] = {}
        for cell_id, doc in verifies:  # oldest first: the last one wins
            v = VerifyResult.from_json(doc) if doc else None
            if v is not None and v.max is not None:
                last[cell_id] = v
        rms = GaugeMetricFamily(
            "recal_cell_verified_rms", "Last verify session's measured RMS position error", labels=["cell", "unit"]
        )
        mx = GaugeMetricFamily(
            "recal_cell_verified_max", "Last verify session's measured max position error", labels=["cell", "unit"]
        )
        thr = GaugeMetricFamily("recal_cell_drift_threshold", "The cell's drift threshold", labels=["cell", "unit"])
        ratio = GaugeMetricFamily(
            "recal_cell_drift_ratio",
            "Last verified max error over the drift threshold (above 1: drifted)",
            labels=["cell"],
        )
        for cell_id, name, units, threshold in cells:
            unit = (units or {}).get("length") or "?"
            v = last.get(cell_id)
            if v is not None:
                if v.rms is not None:
                    rms.add_metric([name, unit], float(v.rms))
                mx.add_metric([name, unit], float(v.max or 0.0))
            if threshold:
                thr.add_metric([name, unit], float(threshold))
                if v is not None:
                    ratio.add_metric([name], float(v.max or 0.0) / float(threshold))
        yield from (rms, mx, thr, ratio)


def install(app) -> callable:
    """The app's registry, with its request histogram and the store's figures; returns the
    function :class:`.middleware.RequestLog` calls with each request's latency."""
    registry = CollectorRegistry(auto_describe=True)
    latency = Histogram(
        "recal_request_duration_seconds",
        "Request latency at the service",
        ["method", "route", "status"],
        buckets=BUCKETS_S,
        registry=registry,
    )
    registry.register(StoreCollector(app))
    app.state.metrics_registry = registry

    def observe(method: str, route: str, status: int, elapsed_s: float) -> None:
        latency.labels(method, route, str(status)).observe(elapsed_s)

    return observe


@router.get("/metrics")
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.metrics_registry), media_type=CONTENT_TYPE_LATEST)
