"""Predicted accuracy of an identified model, and hold-out validation (book §4.3, eq. 4.70).

The parameters' covariance ``Σx`` propagates to any configuration through the identification
Jacobian: the predicted position of a target has covariance ``J Σx Jᵀ`` (N, 3, 3). When the
residuals show more than the instrument's noise (the model does not explain the data: a sag, a
deflection the model lacks), the model's error at any configuration also has that excess, the
model-structure error ``σ_s² I`` (:func:`structure_sigma`), which no parameter covariance
describes. A fresh measurement differs from the prediction by both plus the instrument's noise,
so the actual error ``e`` should satisfy ``eᵀ (J Σx Jᵀ + σ_s² I + σ² I)⁻¹ e ≤ χ²₃(0.95)`` in 95 %
of cases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import RecalError
from .identification import IdentificationResult, Measurements, expected_rms_m
from .jacobian import predict
from .metrics import registered_errors
from .model import KinematicModel
from .parameters import Parameter, candidate_parameters


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of the χ² distribution with ``dof`` degrees of freedom."""
    from scipy.special import gammaincinv  # here, not at the top: scipy.special costs ~0.2 s to import

    return float(2.0 * gammaincinv(dof / 2.0, p))


def _p_tool(model, names) -> np.ndarray:
    return np.array([model.target(t) for t in names]) if len(names) else np.zeros((0, 3))


def propagate(
    model: KinematicModel,
    params: list[Parameter],
    covariance: np.ndarray,
    q: np.ndarray,
    targets: np.ndarray,
    payload: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance (N, 3, 3) m² of the positions of per-row ``targets`` (N,) (``None``: the tool
    origin) at readings ``q`` (N, n), from the covariance (P, P) SI of ``params`` of ``model``:
    ``J Σx Jᵀ`` (book eq. 4.70). ``payload`` (N, 4): per row, for a compliant model."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if not params:
        return np.zeros((len(q), 3, 3))
    Jp = predict(model, q, _p_tool(model, targets), list(params), targets, payload).Jp
    assert Jp is not None  # asked with params
    return np.einsum("nip,pq,njq->nij", Jp, covariance, Jp)


def prediction_covariance(result: IdentificationResult) -> np.ndarray:
    """The parameters' covariance (P, P) SI for predictions: the identification's covariance
    (already scaled by ``sigma_scale``) grown by ``model_error_scale`` squared, when the
    cross-validated error exceeded what the covariance predicts (the model's structure misses
    something the in-sample residuals hide)."""
    return result.covariance * result.model_error_scale**2


def structure_sigma(result: IdentificationResult) -> float:
    """The model-structure error per axis (m) that the residuals show beyond the stated noise:
    ``σ √(s²m² − 1)``, ``σ`` the per-axis noise the stated uncertainties expect in these residuals
    (``expected_rms / √3``), ``s`` = ``sigma_scale``, ``m`` = ``model_error_scale``; 0 when both are
    1 (no significant excess: the model explains the data). The data cannot tell an unmodelled
    effect (a sag: the same error at the same configuration, in the model's predictions too) from
    an instrument noisier than stated (not in the model's predictions); the bound takes the
    excess for the former, so that it covers the model's error in both cases (with a noisier
    instrument, more than 95 %), and the χ² test says the model does not explain the data."""
    grow = result.sigma_scale * result.model_error_scale
    if not grow > 1.0:
        return 0.0
    return expected_rms_m(result) / math.sqrt(3.0) * math.sqrt(grow**2 - 1.0)


def position_covariance(
    result: IdentificationResult,
    q: np.ndarray,
    target: str | None = None,
    targets: np.ndarray | None = None,
    payload: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance (N, 3, 3) m² of the error of the predicted position of ``target`` (or per-row
    ``targets``) at readings ``q`` (N, n): the identified parameters' covariance propagated
    (:func:`prediction_covariance`), plus the model-structure error's (:func:`structure_sigma`)."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    names = np.array([target] * len(q), dtype=object) if targets is None else np.asarray(targets, dtype=object)
    C = propagate(result.model, list(result.params), prediction_covariance(result), q, names, payload)
    return C + structure_sigma(result) ** 2 * np.eye(3)


def radius_95(C: np.ndarray, level: float = 0.95) -> np.ndarray:
    """A radius (N,) that an error of covariance ``C`` (N, 3, 3) stays within with probability
    ``level`` (conservative: the largest principal axis, scaled by the χ²₃ quantile)."""
    lam = np.linalg.eigvalsh(C)[:, -1]
    return np.sqrt(chi2_quantile(level, 3) * np.maximum(lam, 0.0))


def predicted_uncertainty(
    result: IdentificationResult, q: np.ndarray, target: str | None = None, *, level: float = 0.95
) -> np.ndarray:
    """A radius (N,) m that the model's position error at ``q`` stays within with probability
    ``level`` (conservative: the largest principal axis of the covariance, scaled by the χ²₃
    quantile). The measurement noise is not included."""
    return radius_95(position_covariance(result, q, target), level)


class CovarianceError(RecalError, ValueError):
    """A model's stored covariance is missing or does not fit the model; ``field`` is the JSON
    path at fault (``identification.covariance.names[3]``)."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(message)


def covariance_from_block(model: KinematicModel) -> tuple[list[Parameter], np.ndarray]:
    """The parameters and their covariance (P, P) SI stored in an identified model's
    ``identification`` block (:func:`calibration.report.identification_block`)."""
    block = model.metadata.get("identification")
    cov = block.get("covariance") if isinstance(block, dict) else None
    if not isinstance(cov, dict):
        raise CovarianceError(
            "identification.covariance",
            "this model stores no parameter covariance (a model written by `recal identify` does)",
        )
    names = cov.get("names")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise CovarianceError("identification.covariance.names", "expected a list of parameter names")
    try:
        matrix = np.array(cov.get("matrix"), dtype=float)
    except (TypeError, ValueError):
        matrix = np.zeros(0)
    if matrix.shape != (len(names), len(names)) or not np.all(np.isfinite(matrix)):
        raise CovarianceError(
            "identification.covariance.matrix", f"expected a {len(names)} x {len(names)} matrix of numbers"
        )
    grow = cov.get("model_error_scale", 1.0)
    if isinstance(grow, bool) or not isinstance(grow, (int, float)) or not grow >= 1.0:
        raise CovarianceError("identification.covariance.model_error_scale", f"expected a number >= 1, got {grow!r}")
    matrix = matrix * float(grow) ** 2  # the bound grows as the cross-validation said (prediction_covariance)
    gains = any(n.endswith(".gain") for n in names)
    known = {p.name: p for p in candidate_parameters(model, targets=tuple(model.targets), gains=gains)}
    for i, n in enumerate(names):
        if n not in known:
            raise CovarianceError(f"identification.covariance.names[{i}]", f"no parameter {n!r} in this model")
    return [known[n] for n in names], matrix


def structure_sigma_from_block(model: KinematicModel) -> float:
    """The model-structure error per axis (m) stored in an identified model's ``identification``
    block (:func:`structure_sigma` when it was identified; 0 in files written before it was
    stored): added to every predicted position's covariance, ``σ_s² I``."""
    block = model.metadata.get("identification")
    cov = block.get("covariance") if isinstance(block, dict) else None
    value = cov.get("structure_sigma_m", 0.0) if isinstance(cov, dict) else 0.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0.0:
        raise CovarianceError(
            "identification.covariance.structure_sigma_m", f"expected a number >= 0 (metres), got {value!r}"
        )
    return float(value)


def stored_position_covariance(
    model: KinematicModel, q: np.ndarray, target: str | None = None, payload: np.ndarray | None = None
) -> np.ndarray:
    """Covariance (N, 3, 3) m² of the error of an identified model's predicted position of
    ``target`` at readings ``q`` (N, n): :func:`stored_position_bound`'s, the one bound every verb
    (predict, the result page, the certificate) uses. Raises :class:`CovarianceError` naming the
    field at fault."""
    return stored_position_bound(model, q, target, payload)[0]


def stored_position_bound(
    model: KinematicModel, q: np.ndarray, target: str | None = None, payload: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Covariance (N, 3, 3) m² of the error of a stored model's predicted position of ``target``
    at readings ``q`` (N, n), and (N,) whether its residual correction applies there (None: the
    model carries none).

    Where the correction applies (inside the region it was fitted in), the position is the
    geometric model's plus the correction, and its error is what the nested cross-validation
    measured on held-out poses of the region, the instrument's noise taken out, sized so that the
    95 % radius is their 95 % quantile (``residual_map.cross_validation.model_sigma_95_m``,
    :func:`correction_sigma_from_model`): that
    error is of the whole procedure (the geometric model identified on the training folds, the
    correction fitted to them), so the parameters' covariance is in it already. Elsewhere, and
    for a model without a correction: what the ``identification`` block stores, the parameters'
    covariance grown by ``model_error_scale`` (:func:`covariance_from_block`), propagated, plus
    the model-structure error (:func:`structure_sigma_from_block`), what :func:`position_covariance`
    gives for the identification's result."""
    from .residual_map import from_model

    params, Sigma = covariance_from_block(model)
    structure_m = structure_sigma_from_block(model)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    names = np.array([target] * len(q), dtype=object)
    C = propagate(model, params, Sigma, q, names, payload) + structure_m**2 * np.eye(3)
    correction = from_model(model)
    if correction is None:
        return C, None
    p_tool = model.targets[target] if target is not None else None
    inside = np.asarray(correction.evaluate(q, p_tool)[1], dtype=bool)
    sigma_c = correction_sigma_from_model(model)
    C[inside] = sigma_c**2 * np.eye(3)
    return C, inside


def correction_sigma_from_model(model: KinematicModel) -> float:
    """The per-axis σ (m) of a model's corrected position inside its residual correction's region,
    from the cross-validation its ``residual_map`` section stores (model length unit):
    ``model_sigma_95_m``, the σ whose Gaussian 95 % radius is the held-out errors' own 95 %
    quantile, never below the RMS's (:func:`calibration.residual_base.quantile_model_sigma`: the
    errors left are longer-tailed than a Gaussian, and the RMS's σ alone covered 92 %, not 95 %).
    A file written before it was stored: ``model_sigma_m``, the RMS's σ
    (:func:`calibration.residual_base.corrected_model_sigma`); before that, the cross-validated RMS
    with the correction over √3 (``rms_with_m``; the instrument's noise left in)."""
    section = model.metadata.get("residual_map")
    cv = section.get("cross_validation") if isinstance(section, dict) else None
    cv = cv if isinstance(cv, dict) else {}
    for key, scale in (("model_sigma_95_m", 1.0), ("model_sigma_m", 1.0), ("rms_with_m", 1.0 / math.sqrt(3.0))):
        value = cv.get(key)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0.0:
            raise CovarianceError(
                f"residual_map.cross_validation.{key}", f"expected a number >= 0 (model length unit), got {value!r}"
            )
        return float(value) * scale * model.units.length_m
    raise CovarianceError(
        "residual_map.cross_validation.model_sigma_m",
        "this model's residual correction stores no cross-validated error (a model written by "
        "`recal identify --residual-map auto` does)",
    )


def rotation_covariance(
    model: KinematicModel, params: list[Parameter], covariance: np.ndarray, q: np.ndarray, payload=None
) -> np.ndarray:
    """Covariance (N, 3, 3) rad² of the tool frame's orientation (a world-frame rotation vector)
    at readings ``q`` (N, n), from the covariance (P, P) SI of ``params`` of ``model``: ``Jr Σx Jrᵀ``."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if not params:
        return np.zeros((len(q), 3, 3))
    pred = predict(model, q, np.zeros((len(q), 3)), list(params), np.full(len(q), None, dtype=object), payload)
    assert pred.Jr is not None  # asked for (params)
    return np.einsum("nip,pq,njq->nij", pred.Jr, covariance, pred.Jr)


def _held_params(model: KinematicModel, names: list[str], field: str) -> list[Parameter]:
    gains = any(n.endswith(".gain") for n in names)
    known = {p.name: p for p in candidate_parameters(model, targets=tuple(model.targets), gains=gains)}
    for i, n in enumerate(names):
        if n not in known:
            raise CovarianceError(f"{field}.names[{i}]", f"no parameter {n!r} in this model")
    return [known[n] for n in names]


def orientation_covariance(result: IdentificationResult, q: np.ndarray, payload=None) -> np.ndarray:
    """Covariance (N, 3, 3) rad² of the error of the tool frame's predicted orientation at readings
    ``q`` (N, n): the freed parameters' covariance and, where parameters were held, their prior
    width (:attr:`IdentificationResult.held_covariance`). A position-only fit does not measure the
    orientation: there the held parameters (the tool's rotation, the last joint's offset, whatever
    the data could not determine) decide it, and a bound from the freed ones alone claimed to know
    them to zero. The model-structure error of the positions is not an orientation's and is not
    added."""
    held = result.held_covariance
    if held is None:
        return rotation_covariance(result.model, list(result.params), prediction_covariance(result), q, payload)
    params = _held_params(result.model, held["names"], "held_covariance")
    return rotation_covariance(result.model, params, np.asarray(held["matrix"]), q, payload)


def orientation_from_block(model: KinematicModel) -> tuple[list[Parameter], np.ndarray]:
    """The parameters and the covariance (P, P) SI that an identified model's ``identification``
    block stores for its orientation: ``covariance.held`` (the freed and held parameters, the held
    ones at their prior width: :func:`calibration.identify.held_covariance`) where it was written,
    else the freed parameters' (:func:`covariance_from_block`: nothing held, or a file written
    before the held ones were stored). Raises :class:`CovarianceError` naming the field at fault."""
    params, matrix = covariance_from_block(model)
    held = model.metadata["identification"]["covariance"].get("held")
    if held is None:
        return params, matrix
    field = "identification.covariance.held"
    names = held.get("names") if isinstance(held, dict) else None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise CovarianceError(f"{field}.names", "expected a list of parameter names")
    try:
        matrix = np.array(held.get("matrix"), dtype=float)
    except (TypeError, ValueError):
        matrix = np.zeros(0)
    if matrix.shape != (len(names), len(names)) or not np.all(np.isfinite(matrix)):
        raise CovarianceError(f"{field}.matrix", f"expected a {len(names)} x {len(names)} matrix of numbers")
    return _held_params(model, names, field), matrix


def stored_orientation_covariance(model: KinematicModel, q: np.ndarray, payload=None) -> np.ndarray:
    """Covariance (N, 3, 3) rad² of the error of an identified model's predicted tool orientation
    at readings ``q`` (N, n), from what its ``identification`` block stores
    (:func:`orientation_from_block`): what :func:`orientation_covariance` gives for the
    identification's result, for a model read from a file or a store."""
    params, Sigma = orientation_from_block(model)
    return rotation_covariance(model, params, Sigma, q, payload)


@dataclass(frozen=True, slots=True)
class Validation:
    """Hold-out errors of a model on measurements it was not fitted to (m).

    ``coverage_95``: the fraction of rows whose error lies inside the predicted 95 % region
    (the model's error, :func:`position_covariance`: the parameters' covariance for predictions
    and the model-structure error the residuals showed, plus the instrument's stated noise);
    close to 0.95 when the uncertainty is honest.
    ``before_*``: the same errors of the starting model placed where it fits ``holdout`` best
    (base and one common target offset registered: :func:`calibration.metrics.registered_errors`).
    """

    n: int
    errors_m: np.ndarray
    rms_m: float
    max_m: float
    p95_m: float
    mean_m: float
    coverage_95: float
    before_rms_m: float
    before_max_m: float
    before_p95_m: float


def _stats(e: np.ndarray) -> tuple[float, float, float, float]:
    if len(e) == 0:
        return 0.0, 0.0, 0.0, 0.0
    return float(np.sqrt(np.mean(e**2))), float(e.max()), float(np.percentile(e, 95)), float(e.mean())


def validate(result: IdentificationResult, holdout: Measurements) -> Validation:
    """Errors of ``result.model`` (and of the starting model) on ``holdout``."""
    names, row_sigma = holdout.target, holdout.sigma
    assert row_sigma is not None  # Measurements.__post_init__ fills it (NaN: the instrument's)
    sigma = np.where(np.isfinite(row_sigma) & (row_sigma > 0), row_sigma, result.settings["sigma_m"])
    p = predict(result.model, holdout.q, _p_tool(result.model, names), payload=holdout.payload).p_world
    e_vec = holdout.p_world - p
    e = np.linalg.norm(e_vec, axis=1)
    # the model's error (parameters and structure) plus the instrument's stated noise
    C = position_covariance(result, holdout.q, targets=names, payload=holdout.payload) + (sigma**2)[
        :, None, None
    ] * np.eye(3)
    d2 = np.einsum("ni,ni->n", e_vec, np.linalg.solve(C, e_vec[:, :, None])[:, :, 0])
    coverage = float(np.mean(d2 <= chi2_quantile(0.95, 3))) if len(e) else 0.0
    # "before": the starting model placed where it fits these data best, its base and one common
    # reflector offset registered (calibration.metrics.registered_errors, the one definition the
    # page, the certificate and the nightly job use). The start's own base, registered without the
    # offset, made a UR10 with a T-Mac read 15 mm "before" where it was 1 mm off (issue 25), and a
    # reflector 50 mm from the nominal's target read 50.7 mm (tests/calibration/test_before_figure.py).
    start = result.start_model
    e0 = np.linalg.norm(
        registered_errors(start, holdout.q, holdout.p_world, _p_tool(start, names), holdout.payload)[0], axis=1
    )
    rms, mx, p95, mean = _stats(e)
    b_rms, b_max, b_p95, _ = _stats(e0)
    return Validation(len(e), e, rms, mx, p95, mean, coverage, b_rms, b_max, b_p95)
