"""The identification report: a JSON-ready dict in the model's own units."""

from __future__ import annotations

import math

import numpy as np

from .identify import IdentificationResult, explain, relation_coefficients
from .model import KinematicModel, Units, model_to_dict
from .uncertainty import Validation


def _unit(kind: str, units: Units) -> tuple[str, float]:
    """(unit name, SI per unit) of a parameter kind."""
    if kind == "length":
        return units.length, units.length_m
    if kind == "angle":
        return units.angle, units.angle_rad
    if kind == "angle_per_length":  # compliance x mass terms (calibration.compliance)
        return f"{units.angle}/{units.length}", units.angle_rad / units.length_m
    if kind == "angle_per_torque":  # a joint's compliance; torque stays N·m (the units have no force)
        return f"{units.angle}/(N·m)", units.angle_rad
    return "1", 1.0


def _f(x: float, digits: int = 9) -> float | None:
    x = float(x)
    return None if not math.isfinite(x) else float(f"{x:.{digits}g}")


def identification_report(result: IdentificationResult, units: Units, *, data_rows: np.ndarray | None = None,
                          validation: Validation | None = None) -> dict:
    """Everything a metrologist needs to judge the identification, in ``units``."""
    L = units.length_m
    rows = np.arange(1, result.n_rows + 1) if data_rows is None else np.asarray(data_rows)
    params = []
    for k, p in enumerate(result.params):
        uname, s = _unit(p.kind, units)
        entry = {"name": p.name, "unit": uname, "value": _f(result.values[k] / s),
                 "change": _f(result.steps[k] / s), "std_error": _f(result.std_errors[k] / s),
                 "source": result.sources[k] if result.sources else "data"}
        if result.prior_std_errors is not None and math.isfinite(result.prior_std_errors[k]):
            entry["prior_std_error"] = _f(result.prior_std_errors[k] / s)
        params.append(entry)
    rn = np.linalg.norm(result.residuals_m, axis=1)
    report = {
        "success": result.success,
        "status": result.status,
        "message": result.message,
        "iterations": result.iterations,
        "function_evaluations": result.nfev,
        "units": {"length": units.length, "angle": units.angle},
        "rows": result.n_rows,
        "parameters": params,
        "unidentifiable": [
            {"name": u.name, "reason": explain(u, units), "category": u.category,
             "same_as": [{"name": n, "coefficient": _f(c), "unit": cu} for n, c, cu in relation_coefficients(u, units)]}
            for u in result.unidentifiable
        ],
        "correlation": {"names": list(result.param_names),
                        "matrix": [[_f(v, 4) for v in row] for row in result.correlation]},
        "condition_number": _f(result.condition_number),
        "observability": {k: _f(v) for k, v in result.observability.items()},
        "residuals": {
            "rms": _f(result.rms_m / L), "max": _f(result.max_m / L),
            "p95": _f(np.percentile(rn, 95) / L) if len(rn) else 0.0,
            "rms_per_axis": [_f(v / L) for v in np.sqrt(np.mean(result.residuals_m**2, axis=0))],
            "rms_orientation": _f(result.rms_rad / units.angle_rad),
            "chi2": _f(result.chi2), "dof": result.dof,
            "sigma_scale": _f(result.sigma_scale),
        },
        "data_only": None if result.data_only is None else {
            "parameters": list(result.data_only["parameters"]),
            "condition_number": _f(result.data_only["condition_number"]),
            "observability": {k: _f(v) for k, v in result.data_only["observability"].items()},
        },
        "outliers": [
            {"row": int(rows[i]), "residual": _f(rn[i] / L), "weight": _f(result.row_weights[i], 4)}
            for i in result.outliers
        ],
        "registration": None if result.registration is None else {
            # SI in the result (rms_before_m); here in the length unit, so without the suffix
            (k.removesuffix("_m") if k.startswith("rms") else k): (_f(v / L) if k.startswith("rms") else v)
            for k, v in result.registration.items() if k != "point_offset_correction_m"
        },
        "notes": list(result.notes),
        "settings": {**{k: v for k, v in result.settings.items() if k not in ("sigma_m", "sigma_rad")},
                     "sigma": _f(result.settings["sigma_m"] / L),
                     "sigma_orientation": _f(result.settings["sigma_rad"] / units.angle_rad)},
    }
    if validation is not None:
        report["validation"] = {
            "rows": validation.n, "rms": _f(validation.rms_m / L), "max": _f(validation.max_m / L),
            "p95": _f(validation.p95_m / L), "mean": _f(validation.mean_m / L),
            "inside_predicted_95": _f(validation.coverage_95, 4),
            "before": {"rms": _f(validation.before_rms_m / L), "max": _f(validation.before_max_m / L),
                       "p95": _f(validation.before_p95_m / L)},
        }
    return report


def identification_block(result: IdentificationResult, units: Units, *, nominal: KinematicModel | None = None,
                         q: np.ndarray | None = None) -> dict:
    """The compact ``identification`` block written into an identified model file.

    With ``nominal``, the block also keeps the nominal model (what a controller that was never
    calibrated knows: compensation's ``targets`` mode needs it); with the identification data's
    readings ``q`` (N, n), the joint ranges they covered (the calibrated region), in ``units``.

    ``identified_from`` names the model the identification started from (the nominal's name) and
    ``covariance`` keeps the parameters' covariance, SI whatever ``units`` say (``names``, their
    ``kinds``, ``matrix``): what :func:`calibration.uncertainty.covariance_from_block` needs to
    predict the position uncertainty anywhere (``recal predict --uncertainty``).
    """
    full = identification_report(result, units)
    block = {k: full[k] for k in ("success", "message", "rows", "parameters", "unidentifiable", "condition_number",
                                  "observability", "residuals", "notes")}
    if full["data_only"] is not None:
        block["data_only"] = full["data_only"]
    block["identified_from"] = (nominal or result.start_model).name
    block["covariance"] = {
        "units": "SI (m, rad; gains 1)",
        "names": list(result.param_names),
        "kinds": [p.kind for p in result.params],
        "matrix": [[float(v) for v in row] for row in result.covariance],
    }
    if nominal is not None:
        block["nominal"] = model_to_dict(nominal, units=units)
    if q is not None and len(q):
        model = result.model
        scale = np.array([units.angle_rad if j.revolute else units.length_m for j in model.joints])
        block["joint_ranges"] = [[float(lo), float(hi)] for lo, hi in zip(q.min(axis=0) / scale, q.max(axis=0) / scale)]
    return block
