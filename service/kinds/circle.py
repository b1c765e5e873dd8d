"""``circle``: each joint swept over as much of its allowed range as it has (up to 300 deg), the
others held at a signature configuration (book §4.6.3, sequence A), measured by the tracker;
circle-point analysis of the sweeps (book §4.6), stored as a calibration of kind ``cpa``."""

from __future__ import annotations

import dataclasses

import numpy as np

from calibration.model import model_from_dict

from ..analysis import AnalysisError, session_measurements, session_sigma, store_calibration
from ..models import KindRules
from ..plans import Plan, PlanRequest, joint_sweeps
from .positions import PositionKind

# Calibration.kind of what a circle session stores (named once: its rules and its store)
CALIBRATION_KIND = "cpa"


class Circle(PositionKind):
    name = "circle"
    order = 30
    title = "Circle points"
    summary = "sweep each joint alone to locate its axis"
    heading = "Circle-point session"
    default_count = 12
    count_help = "points per swept joint"
    # the session kind names the motion (circles), the calibration kind the method (circle-point
    # analysis, as `recal cpa`); both are contracts (the API's session and calibration kinds)
    rules = KindRules(max_count=120, calibration_kind=CALIBRATION_KIND)

    def plan(self, req: PlanRequest) -> Plan:
        return joint_sweeps(req, "circle sweeps")

    def finish(self, db, run, cell, settings) -> None:
        run.calibration_id = circle_point_calibration(db, run, cell, self.instrument(run)).id


def circle_point_calibration(db, run, cell, role: str):
    """Circle-point analysis of the session's sweeps (book §4.6), with the noise the session's
    ``role``'s instrument declares; the report is the one ``recal cpa`` writes."""
    from calibration.cpa import SweepError, Sweeps, circle_point_analysis
    from calibration.report import cpa_report

    data, rows = session_measurements(db, run)
    nominal = model_from_dict(cell.model)
    sweeps = Sweeps(
        q=data.q,
        p_world=data.p_world,
        joint=np.array([(r.joint or 1) - 1 for r in rows]),
        target=data.target,
        row=data.row,
    )
    try:
        res = circle_point_analysis(nominal, sweeps, sigma_m=session_sigma(run, cell, role).sigma_m)
    except (SweepError, ValueError) as exc:
        raise AnalysisError(f"circle-point analysis failed: {exc}") from None
    report = cpa_report(res, nominal, sweeps)
    model = dataclasses.replace(res.model, units=nominal.units, name=f"{cell.name}-cpa")
    return store_calibration(db, cell, run, CALIBRATION_KIND, model, report, None)


KIND = Circle()
