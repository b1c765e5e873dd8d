"""The identification's words and report: why a parameter is not identified (in any units), and
the JSON-ready report in the model's own units.

The calibration core computes; this module writes. :mod:`calibration.identify` takes its
explanations from here, so it imports neither identify nor what imports identify.
"""

from __future__ import annotations

import math

import numpy as np

from .identification import IdentificationResult, Unidentifiable, expected_rms_m
from .model import KinematicModel, Units, model_to_dict
from .parameters import LOCAL_6, parameter_values, parameters_by_name
from .transforms import invert, matrix_to_pose, matrix_to_rotvec, pose_to_matrix
from .uncertainty import Validation, structure_sigma

# --------------------------------------------------------------------------- words


def describe(name: str) -> str:
    if name.startswith("compliance."):  # joint compliance under gravity (calibration.compliance)
        from .compliance import describe_term  # here: compliance imports identify, which imports this

        return describe_term(name)
    head, _, f = name.rpartition(".")
    words = {
        "theta": "offset",
        "d": "d",
        "a": "a",
        "alpha": "twist alpha",
        "beta": "Hayati beta",
        "gain": "gain",
        "tilt_x": "axis tilt x",
        "tilt_y": "axis tilt y",
        "shift_x": "axis shift x",
        "shift_y": "axis shift y",
    }
    if head in ("base", "tool", "home"):
        kind = "translation" if f.startswith("t") else "rotation"
        return f"{head} {kind} {f[1]} ({name})"
    if head.startswith("target."):
        return f"target {head[7:]} {f} ({name})"
    return f"joint {head} {words.get(f, f)} ({name})"


def unit_name(kind: str, units: Units | None) -> tuple[str, float]:
    """(unit, SI per unit) of a parameter kind (``length``, ``angle``, ``scale``, the compliance
    terms' ``angle_per_length`` and ``angle_per_torque``) in ``units``
    (None: SI). The one place a parameter's unit is named: the reports, the relations and the
    identification's notes all write units through it."""
    if kind == "length":
        return ("m", 1.0) if units is None else (units.length, units.length_m)
    if kind == "angle":
        return ("rad", 1.0) if units is None else (units.angle, units.angle_rad)
    if kind == "angle_per_length":  # compliance x mass terms (calibration.compliance)
        return ("rad/m", 1.0) if units is None else (f"{units.angle}/{units.length}", units.angle_rad / units.length_m)
    if kind == "angle_per_torque":  # a joint's compliance; torque stays N·m (the units have no force)
        return ("rad/(N·m)", 1.0) if units is None else (f"{units.angle}/(N·m)", units.angle_rad)
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
        what = (
            "the target offsets already describe"
            if any(n.startswith("target.") for n, _ in u.relation)
            else "the tool translation already describes"
        )
        return (
            f"{d} only turns the measured points about the axis of joint {joint}, which {what}: "
            f"position-only data cannot tell the two apart, so it keeps the model's value ({rel})"
        )
    if u.category == "weak":
        return (
            f"{d} is redundant only at the nominal geometry (a target on an axis)"
            + (f" where {rel}" if rel else "")
            + "; at the identified geometry the data determine it too "
            "weakly to free it, so it keeps the model's value"
        )
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


def consistency_text(result: IdentificationResult, units: Units) -> str:
    """One line on whether the model explains the data (the χ² test of ``result.consistency``)."""
    c = result.consistency or {}
    L, u = units.length_m, units.length
    level = f"{100 * c.get('level', 0.0):.3g} %"
    if c.get("consistent", True):
        return (
            f"the model explains the data: residual RMS {result.rms_m / L:.3g} {u}, "
            f"{expected_rms_m(result) / L:.3g} {u} expected (chi-squared test at the {level} level)"
        )
    return (
        f"the model does not explain the data: residual RMS {result.rms_m / L:.3g} {u} against "
        f"{expected_rms_m(result) / L:.3g} {u} expected (chi-squared test at the {level} level); see the report"
    )


def summary_line(result: IdentificationResult, units: Units, n_rows: int, validation: Validation | None = None) -> str:
    """The one line ``recal identify`` prints."""
    L, u = units.length_m, units.length
    line = (
        f"identified {len(result.params)} parameters from {n_rows} rows: "
        f"residual RMS {result.rms_m / L:.4g} {u}, max {result.max_m / L:.4g} {u}; "
        f"{len(result.unidentifiable)} not identifiable; {result.message}"
    )
    if result.cross_validation is not None:
        line += f"; cross-validated RMS {result.cross_validation['rms_m'] / L:.4g} {u}"
    if validation is not None:
        line += (
            f"; hold-out RMS {validation.rms_m / L:.4g} {u} (before {validation.before_rms_m / L:.4g}), "
            f"{100 * validation.coverage_95:.1f}% inside the predicted 95% bound"
        )
    return line


def _f(x: float, digits: int = 9) -> float | None:
    x = float(x)
    return None if not math.isfinite(x) else float(f"{x:.{digits}g}")


def identification_report(
    result: IdentificationResult,
    units: Units,
    *,
    data_rows: np.ndarray | None = None,
    validation: Validation | None = None,
) -> dict:
    """Everything a metrologist needs to judge the identification, in ``units``."""
    L = units.length_m
    rows = np.arange(1, result.n_rows + 1) if data_rows is None else np.asarray(data_rows)
    rn = np.linalg.norm(result.residuals_m, axis=1)
    report = {
        "success": result.success,
        "status": result.status,
        "message": result.message,
        "iterations": result.iterations,
        "function_evaluations": result.nfev,
        "units": {"length": units.length, "angle": units.angle},
        "rows": result.n_rows,
        "parameters": _parameters_section(result, units),
        "unidentifiable": [
            {
                "name": u.name,
                "reason": explain(u, units),
                "category": u.category,
                "same_as": [
                    {"name": n, "coefficient": _f(c), "unit": cu} for n, c, cu in relation_coefficients(u, units)
                ],
            }
            for u in result.unidentifiable
        ],
        "correlation": {
            "names": list(result.param_names),
            "matrix": [[_f(v, 4) for v in row] for row in result.correlation],
        },
        "condition_number": _f(result.condition_number),
        "observability": {k: _f(v) for k, v in result.observability.items()},
        "residuals": _residuals_section(result, units, rn),
        "cross_validation": _cross_validation_section(result, L),
        "consistency": None
        if result.consistency is None
        else {
            **{k: (_f(v) if isinstance(v, float) else v) for k, v in result.consistency.items()},
            "expected_rms": _f(expected_rms_m(result) / L),
            "message": consistency_text(result, units),
        },
        "complete": result.completeness,
        "warnings": list(result.warnings),
        "data_only": None
        if result.data_only is None
        else {
            "parameters": list(result.data_only["parameters"]),
            "condition_number": _f(result.data_only["condition_number"]),
            "observability": {k: _f(v) for k, v in result.data_only["observability"].items()},
        },
        "outliers": [
            {"row": int(rows[i]), "residual": _f(rn[i] / L), "weight": _f(result.row_weights[i], 4)}
            for i in result.outliers
        ],
        "registration": _registration_section(result, L),
        "notes": list(result.notes),
        "settings": {
            **{k: v for k, v in result.settings.items() if k not in ("sigma_m", "sigma_rad")},
            "sigma": _f(result.settings["sigma_m"] / L),
            "sigma_orientation": _f(result.settings["sigma_rad"] / units.angle_rad),
        },
    }
    if validation is not None:
        report["validation"] = _validation_section(validation, L)
    return report


def _parameters_section(result: IdentificationResult, units: Units) -> list[dict]:
    """The report's ``parameters``: each estimated one's value, change and standard error in ``units``."""
    params = []
    for k, p in enumerate(result.params):
        uname, s = _unit(p.kind, units)
        entry = {
            "name": p.name,
            "unit": uname,
            "value": _f(result.values[k] / s),
            "change": _f(result.steps[k] / s),
            "std_error": _f(result.std_errors[k] / s),
            "source": result.sources[k] if result.sources else "data",
        }
        if result.prior_std_errors is not None and math.isfinite(result.prior_std_errors[k]):
            entry["prior_std_error"] = _f(result.prior_std_errors[k] / s)
        params.append(entry)
    return params


def _residuals_section(result: IdentificationResult, units: Units, rn: np.ndarray) -> dict:
    """The report's ``residuals`` (``rn``: the position residuals' lengths, m)."""
    L = units.length_m
    return {
        "rms": _f(result.rms_m / L),
        "max": _f(result.max_m / L),
        "p95": _f(np.percentile(rn, 95) / L) if len(rn) else 0.0,
        "rms_per_axis": [_f(v / L) for v in np.sqrt(np.mean(result.residuals_m**2, axis=0))],
        "rms_orientation": _f(result.rms_rad / units.angle_rad),
        "chi2": _f(result.chi2),
        "dof": result.dof,
        "sigma_scale": _f(result.sigma_scale),
        "model_error_scale": _f(result.model_error_scale),
    }


def _cross_validation_section(result: IdentificationResult, L: float) -> dict | None:
    """The report's ``cross_validation`` (``L``: metres per length unit)."""
    cv = result.cross_validation
    if cv is None:
        return None
    return {
        "folds": cv["folds"],
        "method": "linearised k-fold: each fold predicted by the fit without it (one Gauss-Newton step from "
        "the full fit)",
        "rms": _f(cv["rms_m"] / L),
        "in_sample_rms": _f(result.rms_m / L),
        "chi2": _f(cv["chi2"]),
        "expected_chi2": _f(cv["expected_chi2"]),
        "scale": _f(cv["scale"]),
    }


def _registration_section(result: IdentificationResult, L: float) -> dict | None:
    """The report's ``registration``: SI in the result (rms_before_m); here in the length unit,
    so without the suffix."""
    if result.registration is None:
        return None
    return {
        (k.removesuffix("_m") if k.startswith("rms") else k): (_f(v / L) if k.startswith("rms") else v)
        for k, v in result.registration.items()
        if k != "point_offset_correction_m"
    }


def _validation_section(validation: Validation, L: float) -> dict:
    """The report's ``validation``: the hold-out errors, and the start's ("before")."""
    return {
        "rows": validation.n,
        "rms": _f(validation.rms_m / L),
        "max": _f(validation.max_m / L),
        "p95": _f(validation.p95_m / L),
        "mean": _f(validation.mean_m / L),
        "inside_predicted_95": _f(validation.coverage_95, 4),
        "before": {
            "rms": _f(validation.before_rms_m / L),
            "max": _f(validation.before_max_m / L),
            "p95": _f(validation.before_p95_m / L),
        },
    }


def identification_block(
    result: IdentificationResult,
    units: Units,
    *,
    nominal: KinematicModel | None = None,
    q: np.ndarray | None = None,
    report: dict | None = None,
) -> dict:
    """The compact ``identification`` block written into an identified model file.

    ``report``: the :func:`identification_report` of this ``result`` in these ``units`` when the
    caller has made it already (the CLI and the service both print or store one), so that it is
    made once per calibration (issue 23).

    With ``nominal``, the block also keeps the nominal model (what a controller that was never
    calibrated knows: compensation's ``targets`` mode needs it); with the identification data's
    readings ``q`` (N, n), the joint ranges they covered (the calibrated region), in ``units``.

    ``identified_from`` names the model the identification started from (the nominal's name) and
    ``covariance`` keeps the parameters' covariance, SI whatever ``units`` say (``names``, their
    ``kinds``, ``matrix``): what :func:`calibration.uncertainty.covariance_from_block` needs to
    predict the position uncertainty anywhere (``recal predict --uncertainty``).
    """
    full = identification_report(result, units) if report is None else report
    block = {
        k: full[k]
        for k in (
            "success",
            "message",
            "rows",
            "parameters",
            "unidentifiable",
            "condition_number",
            "observability",
            "residuals",
            "notes",
            "complete",
            "cross_validation",
            "consistency",
            "warnings",
        )
    }
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
        # and add the model-structure error the residuals showed, per axis (m; structure_sigma)
        "structure_sigma_m": float(structure_sigma(result)),
    }
    if result.held_covariance is not None:
        # the orientation's uncertainty: freed and held parameters, the held ones at their prior
        # width (calibration.uncertainty.orientation_from_block); already grown as predictions are
        held = result.held_covariance
        block["covariance"]["held"] = {
            "names": list(held["names"]),
            "prior_sd": [None if not np.isfinite(v) else float(v) for v in held["prior_sd"]],
            "matrix": [[float(v) for v in row] for row in held["matrix"]],
        }
    if nominal is not None:
        block["nominal"] = model_to_dict(nominal, units=units)
    if q is not None and len(q):
        model = result.model
        scale = np.array([units.angle_rad if j.revolute else units.length_m for j in model.joints])
        block["joint_ranges"] = [[float(lo), float(hi)] for lo, hi in zip(q.min(axis=0) / scale, q.max(axis=0) / scale)]
    return block


# --------------------------------------------------------------------------- circle-point analysis


def _vec(v, scale: float = 1.0) -> list:
    return [_f(x / scale) for x in np.asarray(v, dtype=float)]


def _plain(key: str) -> str:
    """A setting's name without its SI suffix (the report is in the model's units)."""
    return {"held_tol_rad": "held_tol_angle", "held_tol_m": "held_tol_length"}.get(
        key, key.removesuffix("_rad").removesuffix("_m")
    )


def _setting(key: str, value, L: float, A: float):
    """A setting in the model's units (``*_rad`` angles, ``*_m`` lengths)."""
    if value is None or isinstance(value, (str, int)):
        return value
    return _f(value / A) if key.endswith("_rad") else _f(value / L) if key.endswith("_m") else _f(value)


def cpa_report(result, nominal: KinematicModel, sweeps) -> dict:
    """The circle-point analysis report (``recal cpa --report``, a circle session's result), JSON-ready,
    in the nominal model's units."""
    u = nominal.units
    L, A = u.length_m, u.angle_rad
    joints = []
    for j, jt in enumerate(nominal.joints):
        axis = result.axes[j]
        rows = sweeps.row[sweeps.joint == j]
        entry = {
            "joint": j + 1,
            "name": jt.name,
            "type": jt.type,
            "swept": axis is not None,
            "axis": {"direction": _vec(result.directions[j]), "point": _vec(result.points[j], L)},
            "from_nominal": {
                "tilt": _f(result.nominal_tilt_rad[j] / A),
                "offset": _f(result.nominal_offset_m[j] / L) if jt.revolute else None,
            },
        }
        if axis is not None:
            entry["rows"] = [int(rows[0]), int(rows[-1])]
            entry["targets"] = [t for t in result.fits[j]]
            fits = []
            for t, f in result.fits[j].items():
                fits.append(
                    {
                        "target": t,
                        "points": f.n_points,
                        "method": f.method,
                        "radius": _f(f.radius_m / L),
                        "arc": _f(f.arc_rad / A),
                        "travel": _f(f.travel_m / L),
                        "out_of_plane_rms": _f(f.out_of_plane_rms_m / L),
                        "circle_rms": _f(f.circle_rms_m / L),
                        "noise": _f(f.noise_m / L),
                        "direction_std": _f(f.direction_std_rad / A),
                        "position_std": _f(f.point_std_m / L),
                        "scale": _f(f.scale),
                        "axis": {"direction": _vec(f.direction), "point": _vec(f.point, L)},
                        "warnings": list(f.warnings),
                    }
                )
            entry["fits"] = fits
        joints.append(entry)
    base = matrix_to_pose(result.T_world_base)
    return {
        "success": result.success,
        "message": result.message,
        "units": {"length": u.length, "angle": u.angle},
        "convention": result.model.convention,
        "rows": len(sweeps),
        "signature": {"q": [_f(v / (A if jt.revolute else L)) for v, jt in zip(result.signature_q, nominal.joints)]},
        "joints": joints,
        "registration": {
            "base": _vec(np.concatenate([base[:3] / L, base[3:] / A])),
            "rms": _f(result.registration_rms_m / L),
            "method": "rigid point registration of the nominal model onto the sweeps (Kabsch)",
        },
        "target_changes": {("tool" if t is None else t): _vec(d, L) for t, d in result.target_changes.items()},
        "warnings": list(result.warnings),
        "notes": list(result.notes),
        "settings": {_plain(k): _setting(k, v, L, A) for k, v in result.settings.items()},
    }


# --------------------------------------------------------------------------- two calibrations

FRAMES = ("base", "tool", "home")
COMPARISON_STATUSES = ("both", "new", "not estimated", "from the prior", "fixed")


def frame_step(a: KinematicModel, b: KinematicModel, frame: str) -> np.ndarray | None:
    """(6,) SI: how ``frame`` moved from model ``a`` to model ``b``, as the local step the
    ``frame.*`` parameters describe (``T_b = T_a · exp(step)``, calibration.parameters)."""
    pa, pb = getattr(a, frame), getattr(b, frame)
    if pa is None or pb is None:
        return None
    D = invert(pose_to_matrix(pa)) @ pose_to_matrix(pb)
    return np.concatenate([D[:3, 3], matrix_to_rotvec(D[:3, :3])])


def _model_values(model: KinematicModel, names: list[str]) -> dict[str, float]:
    """SI values of the named (non-local) parameters in ``model`` (those it has)."""
    params, _ = parameters_by_name(model, names)
    return dict(zip((p.name for p in params), parameter_values(model, params).tolist()))


def comparable_parameter(name: str) -> bool:
    """Whether a parameter's value means the same in two calibrations: not the base, tool and
    home frames' local steps, nor a Hayati link's tilt or shift (each is a step from its own
    calibration's model, not a value; :func:`compare_parameters` compares the frames apart)."""
    return name.split(".", maxsplit=1)[0] not in FRAMES and ".tilt_" not in name and ".shift_" not in name


def change_in_sigmas(change: float | None, sd_a: float | None, sd_b: float | None) -> dict:
    """A parameter's ``change`` from one calibration to another against its uncertainty:
    ``sigma``, the two standard uncertainties combined (``sqrt(σa² + σb²)``, or the one that is
    known), ``change_sigmas`` = ``|change| / sigma``, and ``moved``: beyond twice ``sigma``
    (None and False where it cannot be said). The drift page and the comparison of two
    calibrations both show this."""
    known = [s for s in (sd_a, sd_b) if s is not None]
    sigma = float(np.sqrt(sum(s * s for s in known))) if known else None
    if not sigma or change is None:
        return {"sigma": sigma, "change_sigmas": None, "moved": False}
    return {"sigma": sigma, "change_sigmas": abs(change) / sigma, "moved": bool(abs(change) > 2 * sigma)}


def compare_parameters(
    model_a: KinematicModel, params_a: list[dict], model_b: KinematicModel, params_b: list[dict]
) -> list[dict]:
    """Every parameter of two calibrations, from ``a`` to ``b`` (``params_*``: the reports'
    ``parameters`` entries, in ``model_b``'s units): those estimated in both, in only one
    (``new``: estimated in ``b`` only; ``not estimated``: in ``a`` only, ``b`` kept its starting
    value; ``from the prior``: ``b`` kept it from ``a``, its data could not determine it) and the
    base and tool frames (how far each moved, along and about its own axes). ``moved``: the
    change exceeds twice its standard uncertainty (both calibrations' combined, or the one that
    estimated it). Rows sorted with the moved first, by how many sigmas they moved."""
    units = model_b.units
    ra = {p["name"]: p for p in params_a}
    rb = {p["name"]: p for p in params_b}
    names = list(dict.fromkeys([*ra, *rb]))
    plain = [n for n in names if comparable_parameter(n)]
    va, vb = _model_values(model_a, plain), _model_values(model_b, plain)
    rows = []

    def add(name, unit, x_from, x_to, group, change=None):
        pa, pb = ra.get(name), rb.get(name)
        if change is None and x_from is not None and x_to is not None:
            change = x_to - x_from
        if pb and pb.get("source") == "prior":
            status = "from the prior"  # in b, but kept from a: these measurements did not determine it
        else:
            status = "both" if pa and pb else "new" if pb else "not estimated" if pa else "fixed"
        moved = change_in_sigmas(change, pa.get("std_error") if pa else None, pb.get("std_error") if pb else None)
        rows.append(
            {"name": name, "unit": unit, "group": group, "from": x_from, "to": x_to, "change": change}
            | moved
            | {"status": status}
        )

    for n in plain:
        unit = (rb.get(n) or ra[n])["unit"]  # n is a key of one of them
        scale = units.length_m if unit == units.length else units.angle_rad if unit == units.angle else 1.0
        fa = va[n] / scale if n in va else (ra[n]["value"] if n in ra else None)
        fb = vb[n] / scale if n in vb else (rb[n]["value"] if n in rb else None)
        add(n, unit, fa, fb, "target" if n.startswith("target.") else "joint")
    for frame in FRAMES:
        step = frame_step(model_a, model_b, frame)
        if step is None:
            continue
        for k, axis in enumerate(LOCAL_6):
            name = f"{frame}.{axis}"
            translation = k < 3
            value = step[k] / (units.length_m if translation else units.angle_rad)
            if name in ra or name in rb or abs(value) > 1e-9:
                add(name, units.length if translation else units.angle, None, None, frame, float(value))
    rows.sort(key=lambda r: (not r["moved"], -(r["change_sigmas"] or 0), r["name"]))
    return rows
