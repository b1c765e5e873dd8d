"""The identification's words and report: why a parameter is not identified (in any units), and
the JSON-ready report in the model's own units.

The calibration core computes; this module writes. :mod:`calibration.identify` takes its
explanations from here, so it imports nothing of the core at import time (only for types).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .model import KinematicModel, Units, model_to_dict

if TYPE_CHECKING:  # identify imports this module for its words: no import cycle at run time
    from .identify import IdentificationResult, Unidentifiable
    from .uncertainty import Validation


# --------------------------------------------------------------------------- words

def describe(name: str) -> str:
    head, _, f = name.rpartition(".")
    words = {"theta": "offset", "d": "d", "a": "a", "alpha": "twist alpha", "beta": "Hayati beta",
             "gain": "gain", "tilt_x": "axis tilt x", "tilt_y": "axis tilt y", "shift_x": "axis shift x",
             "shift_y": "axis shift y"}
    if head in ("base", "tool", "home"):
        kind = "translation" if f.startswith("t") else "rotation"
        return f"{head} {kind} {f[1]} ({name})"
    if head.startswith("target."):
        return f"target {head[7:]} {f} ({name})"
    return f"joint {head} {words.get(f, f)} ({name})"


def unit_name(kind: str, units: Units | None) -> tuple[str, float]:
    """(unit, SI per unit) of a parameter kind (``length``, ``angle``, ``scale``) in ``units``
    (None: SI). The one place a parameter's unit is named: the reports, the relations and the
    identification's notes all write units through it."""
    if kind == "length":
        return ("m", 1.0) if units is None else (units.length, units.length_m)
    if kind == "angle":
        return ("rad", 1.0) if units is None else (units.angle, units.angle_rad)
    return ("", 1.0)


def relation_coefficients(u: Unidentifiable, units=None) -> list[tuple[str, float, str]]:
    """``u.relation`` in ``units`` (a :class:`calibration.model.Units`; None: SI): (name,
    coefficient, unit of the coefficient such as ``mm/deg``) per related parameter."""
    out = []
    kinds = u.kinds or ("",) * (len(u.relation) + 1)
    un, sn = unit_name(kinds[0], units)
    for (name, c), kind in zip(u.relation, kinds[1:]):
        uj, sj = unit_name(kind, units)
        unit = uj if not un else (f"{uj}/{un}" if uj else f"1/{un}")
        out.append((name, c * sn / sj, "1" if uj == un else unit))
    return out


def relation_text(u: Unidentifiable, units=None, *, terms: int = 6) -> str:
    """The relation in words: ``1 mm of tool.ty ≡ +1.43 deg of j6.theta +1 mm of target.smr1.x``."""
    kinds = u.kinds or ("",) * (len(u.relation) + 1)
    un, _ = unit_name(kinds[0], units)
    parts = []
    for (name, c, _), kind in zip(relation_coefficients(u, units)[:terms], kinds[1:]):
        uj, _ = unit_name(kind, units)
        parts.append(f"{c:+.3g}{' ' + uj if uj else ''} of {name}")
    more = " + …" if len(u.relation) > terms else ""
    return f"1{' ' + un if un else ''} of {u.name} ≡ {' '.join(parts)}{more}"


def explain(u: Unidentifiable, units=None) -> str:
    """Why ``u`` is not identified, in words, with the relation's coefficients in ``units``
    (a :class:`calibration.model.Units`; None: SI)."""
    d = describe(u.name)
    rel = relation_text(u, units) if u.relation else ""
    if u.category == "tool_orientation":
        return "tool orientation is unobservable from position-only data" + (f" ({rel})" if rel else "")
    if u.category == "target_offsets":
        return f"{d} moves the measured points exactly as the target offsets do ({rel})"
    if u.category == "last_joint_offset":
        joint = u.name.rpartition(".")[0]
        what = ("the target offsets already describe" if any(n.startswith("target.") for n, _ in u.relation)
                else "the tool translation already describes")
        return (f"{d} only turns the measured points about the axis of joint {joint}, which {what}: "
                f"position-only data cannot tell the two apart, so it keeps the model's value ({rel})")
    if u.category == "weak":
        return (f"{d} is redundant only at the nominal geometry (a target on an axis)"
                + (f" where {rel}" if rel else "") + "; at the identified geometry the data determine it too "
                "weakly to free it, so it keeps the model's value")
    if u.category == "same_motion":
        return f"{d} and {describe(u.relation[0][0])} are the same motion ({rel})"
    if u.category == "combination":
        return f"{d} moves the measured points as a combination of freed parameters does: {rel}"
    return f"{d} has no effect on these measurements"



def _unit(kind: str, units: Units) -> tuple[str, float]:
    """(unit name, SI per unit) of a parameter kind in a report (a gain's unit is ``1``)."""
    name, si = unit_name(kind, units)
    return name or "1", si


# --------------------------------------------------------------------------- the report


def expected_rms_m(result: IdentificationResult) -> float:
    """The residual RMS (m) the stated uncertainty expects: the actual one over √(χ²/dof)."""
    ratio = math.sqrt(result.chi2 / result.dof) if result.dof > 0 and result.chi2 > 0 else 1.0
    return result.rms_m / ratio


def consistency_text(result: IdentificationResult, units: Units) -> str:
    """One line on whether the model explains the data (the χ² test of ``result.consistency``)."""
    c = result.consistency or {}
    L, u = units.length_m, units.length
    level = f"{100 * c.get('level', 0.0):.3g} %"
    if c.get("consistent", True):
        return (f"the model explains the data: residual RMS {result.rms_m / L:.3g} {u}, "
                f"{expected_rms_m(result) / L:.3g} {u} expected (chi-squared test at the {level} level)")
    return (f"the model does not explain the data: residual RMS {result.rms_m / L:.3g} {u} against "
            f"{expected_rms_m(result) / L:.3g} {u} expected (chi-squared test at the {level} level); see the report")


def summary_line(result: IdentificationResult, units: Units, n_rows: int, validation: Validation | None = None) -> str:
    """The one line ``recal identify`` prints."""
    L, u = units.length_m, units.length
    line = (f"identified {len(result.params)} parameters from {n_rows} rows: "
            f"residual RMS {result.rms_m / L:.4g} {u}, max {result.max_m / L:.4g} {u}; "
            f"{len(result.unidentifiable)} not identifiable; {result.message}")
    if result.cross_validation is not None:
        line += f"; cross-validated RMS {result.cross_validation['rms_m'] / L:.4g} {u}"
    if validation is not None:
        line += (f"; hold-out RMS {validation.rms_m / L:.4g} {u} (before {validation.before_rms_m / L:.4g}), "
                 f"{100 * validation.coverage_95:.1f}% inside the predicted 95% bound")
    return line


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
            "model_error_scale": _f(result.model_error_scale),
        },
        "cross_validation": None if result.cross_validation is None else {
            "folds": result.cross_validation["folds"],
            "method": "linearised k-fold: each fold predicted by the fit without it (one Gauss-Newton step from "
                      "the full fit)",
            "rms": _f(result.cross_validation["rms_m"] / L), "in_sample_rms": _f(result.rms_m / L),
            "chi2": _f(result.cross_validation["chi2"]), "expected_chi2": _f(result.cross_validation["expected_chi2"]),
            "scale": _f(result.cross_validation["scale"]),
        },
        "consistency": None if result.consistency is None else {
            **{k: (_f(v) if isinstance(v, float) else v) for k, v in result.consistency.items()},
            "expected_rms": _f(expected_rms_m(result) / L),
            "message": consistency_text(result, units),
        },
        "complete": result.completeness,
        "warnings": list(result.warnings),
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
                                  "observability", "residuals", "notes", "complete", "cross_validation",
                                  "consistency", "warnings")}
    if full["data_only"] is not None:
        block["data_only"] = full["data_only"]
    block["identified_from"] = (nominal or result.start_model).name
    block["covariance"] = {
        "units": "SI (m, rad; gains 1)",
        "names": list(result.param_names),
        "kinds": [p.kind for p in result.params],
        "matrix": [[float(v) for v in row] for row in result.covariance],
        # predictions use matrix x model_error_scale² (calibration.uncertainty.prediction_covariance)
        "model_error_scale": float(result.model_error_scale),
    }
    if nominal is not None:
        block["nominal"] = model_to_dict(nominal, units=units)
    if q is not None and len(q):
        model = result.model
        scale = np.array([units.angle_rad if j.revolute else units.length_m for j in model.joints])
        block["joint_ranges"] = [[float(lo), float(hi)] for lo, hi in zip(q.min(axis=0) / scale, q.max(axis=0) / scale)]
    return block
