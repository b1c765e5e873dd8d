"""The data and the result of an identification (:func:`calibration.identify.identify`):
:class:`Measurements`, :class:`Prior`, :class:`Unidentifiable` and :class:`IdentificationResult`.

Apart from the algorithm so that what reads a result (the report's words, the uncertainty it
propagates) depends on these types, not on the identification that makes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .model import KinematicModel
from .parameters import Parameter

# The per-axis standard uncertainty (m) assumed where neither the rows nor the caller state the
# instrument's: a laser tracker a few metres from a cobot (a Leica AT960's MPE of ±(15 µm + 6 µm/m)
# read as a 95 % bound at 3-4 m). One name for it, used by every default in calibration/ and
# service/; an instrument that knows its own (the emScon tracker at its range) states it per row.
INSTRUMENT_SIGMA_M = 20e-6


@dataclass(frozen=True, eq=False, init=False)
class Measurements:
    """Measured data, SI. ``q`` (N, n) joint readings; ``p_world`` (N, 3) measured target
    positions; ``quat`` (N, 4) tool orientation ``(qw, qx, qy, qz)`` or NaN where a row has
    none (``None``: position-only data); ``target`` (N,) target names (``None``: tool origin);
    ``sigma`` (N,) m per-axis standard uncertainty or NaN for the instrument's; ``pose_id`` (N,);
    ``row`` (N,) row numbers in the source file, for reports; ``payload`` (N, 4) kg and centre of
    gravity in the tool frame (m) per row, for a compliant model (``None``: the model's own)."""

    q: np.ndarray
    p_world: np.ndarray
    quat: np.ndarray | None
    target: np.ndarray
    sigma: np.ndarray
    pose_id: np.ndarray | None
    row: np.ndarray
    payload: np.ndarray | None

    # written out (not the dataclass's) so that ``target``, ``sigma`` and ``row``, which may be
    # left out, are arrays once built: readers need not test them for None
    def __init__(
        self,
        q: np.ndarray,
        p_world: np.ndarray,
        quat: np.ndarray | None = None,
        target: np.ndarray | None = None,
        sigma: np.ndarray | None = None,
        pose_id: np.ndarray | None = None,
        row: np.ndarray | None = None,
        payload: np.ndarray | None = None,
    ):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        object.__setattr__(self, "q", q)
        p = np.asarray(p_world, dtype=float).reshape(N, 3)
        object.__setattr__(self, "p_world", p)
        if quat is not None:
            quat = np.asarray(quat, dtype=float).reshape(N, 4)
        object.__setattr__(self, "quat", quat)
        t = np.full(N, None, dtype=object) if target is None else np.asarray(target, dtype=object).reshape(N)
        t = np.array([None if (x is None or x == "") else str(x) for x in t], dtype=object)
        object.__setattr__(self, "target", t)
        s = np.full(N, np.nan) if sigma is None else np.asarray(sigma, dtype=float).reshape(N)
        object.__setattr__(self, "sigma", s)
        object.__setattr__(self, "pose_id", pose_id)
        object.__setattr__(self, "row", np.arange(1, N + 1) if row is None else row)
        if payload is not None:
            payload = np.asarray(payload, dtype=float).reshape(N, 4)
        object.__setattr__(self, "payload", payload)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def has_orientation(self) -> np.ndarray:
        """(N,) True where the row carries a measured orientation."""
        if self.quat is None:
            return np.zeros(len(self), bool)
        return np.all(np.isfinite(self.quat), axis=1)

    def subset(self, idx) -> Measurements:
        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]

        return Measurements(
            self.q[idx],
            self.p_world[idx],
            pick(self.quat),
            self.target[idx],
            self.sigma[idx],
            pick(self.pose_id),
            self.row[idx],
            pick(self.payload),
        )


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior knowledge of parameters (book §4.3.2, minimum-variance estimation): the model passed
    to :func:`identify` is the prior mean, and ``covariance`` (P, P) SI the uncertainty of the
    parameters ``names`` about it (typically the previous calibration's covariance, inflated for
    drift). Parameters without a prior are unconstrained.

    ``held``: the parameters the previous calibration kept at the model's value because its data
    could not tell them from a combination of the ones it estimated, each with that relation
    (:attr:`Unidentifiable.relation`, SI: a unit change of it moves the measured points as
    changes ``c`` of those do; :func:`held_relations`). Its data then determined each estimated
    ``p`` only together with them, ``p + Σ c·u``, and that combination is what ``covariance``
    describes: a held parameter that new data determine (a tool orientation measured at last)
    moves the parameters it was confused with instead of being held by their prior."""

    names: tuple[str, ...]
    covariance: np.ndarray
    held: dict = field(default_factory=dict)

    def _block(self, params: list[Parameter]) -> tuple[list[int], np.ndarray]:
        idx = {n: i for i, n in enumerate(self.names)}
        have = [k for k, p in enumerate(params) if p.name in idx]
        rows = [idx[params[k].name] for k in have]
        return have, np.asarray(self.covariance, dtype=float)[np.ix_(rows, rows)]

    def combinations(self, params: list[Parameter]) -> np.ndarray:
        """The matrix M (H, P) of the combinations the prior describes, one row per parameter of
        ``params`` with a prior (in the order of ``params``): ``M·s`` for a step ``s`` (P,) over
        ``params``, the held ones of ``params`` entering by their relation."""
        have, _ = self._block(params)
        row = {params[k].name: i for i, k in enumerate(have)}
        M = np.zeros((len(have), len(params)))
        M[np.arange(len(have)), have] = 1.0
        for k, p in enumerate(params):
            for name, c in self.held.get(p.name, ()):
                if name in row:
                    M[row[name], k] += c
        return M

    def information(self, params: list[Parameter]) -> np.ndarray:
        """The prior information matrix ``Mᵀ Σ⁻¹ M`` over ``params`` (:meth:`combinations`, Σ the
        marginal covariance of the parameters of ``params`` with a prior; zero rows and columns
        for parameters neither with a prior nor held)."""
        have, sub = self._block(params)
        if not have:
            return np.zeros((len(params), len(params)))
        M = self.combinations(params)
        return M.T @ np.linalg.pinv(sub, hermitian=True) @ M

    def covariance_of(self, params: list[Parameter]) -> np.ndarray:
        """The prior covariance (P, P) over ``params`` (NaN rows and columns for parameters without
        a prior)."""
        have, sub = self._block(params)
        cov = np.full((len(params), len(params)), np.nan)
        cov[np.ix_(have, have)] = sub
        return cov


@dataclass(frozen=True, slots=True)
class Unidentifiable:
    """A parameter the data cannot determine; it keeps the model's value.

    ``reason`` in words (SI units); ``category`` one of :data:`CATEGORIES`; ``relation`` the
    freed parameters whose combined motion it duplicates: a unit change of ``name`` moves the
    measured points as changes ``coefficient`` of those do (SI: m or rad of each per m or rad of
    ``name``), largest first in the scaled (dimensionless) parameterisation the selection uses;
    ``kinds`` the kinds (``length``, ``angle``, ``scale``) of ``name`` and of each related
    parameter, for writing the coefficients in other units (:func:`explain`).
    """

    name: str
    reason: str
    relation: tuple[tuple[str, float], ...] = ()
    category: str = "no_effect"
    kinds: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class IdentificationResult:
    """Everything :func:`identify` did. Arrays over the parameters with an estimate are (P,) /
    (P, P), SI.

    ``sources`` (P,) says what determined each: ``"data"``, ``"data + prior"`` (minimum-variance
    estimation with a :class:`Prior`) or ``"prior"`` (the data cannot see it: it keeps the
    prior's value and uncertainty and was not estimated); ``prior_std_errors`` (P,) the prior's
    standard errors (NaN without one). ``singular_values``, ``condition_number`` and
    ``observability`` are those of what was estimated (with a prior: data and prior together);
    ``data_only`` (with a prior) the same statistics for the parameters the data alone determine.
    ``chi2`` is the weighted residuals' (plus, with a prior, the prior term ``chi2_prior``) and
    ``dof`` its degrees of freedom (residuals, plus prior constraints, minus estimated
    parameters).

    Residuals are measured minus predicted: ``residuals_m`` (N, 3) position, ``residuals_rad``
    (N, 3) orientation (zeros for position-only rows).

    ``completeness``: :func:`completeness` of the form identified, with ``identified`` (what the
    data determined); ``cross_validation``: :func:`_cross_validation` (``folds``, ``chi2``,
    ``expected_chi2``, ``scale``, ``rms_m``, ``model_error_scale``; None with fewer than 10
    poses); ``model_error_scale``: how much predictions grow beyond the covariance
    (:func:`calibration.uncertainty.prediction_covariance`); ``consistency``: the χ² test
    (:func:`_consistency`); ``warnings``: what the user should know (a target nominally on the
    last axis); ``held_covariance``: the freed and the held geometric parameters' covariance, the
    held ones with a prior width (:func:`calibration.identify.held_covariance`; None when none is
    held, or with a :class:`Prior`), for what the data did not measure (a position-only fit's
    orientation).
    """

    model: KinematicModel
    start_model: KinematicModel
    params: tuple[Parameter, ...]
    values: np.ndarray
    steps: np.ndarray
    std_errors: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    unidentifiable: tuple[Unidentifiable, ...]
    singular_values: np.ndarray
    condition_number: float
    observability: dict
    residuals_m: np.ndarray
    residuals_rad: np.ndarray
    rms_m: float
    max_m: float
    rms_rad: float
    chi2: float
    dof: int
    sigma_scale: float
    row_weights: np.ndarray
    outliers: tuple[int, ...]
    success: bool
    status: int
    message: str
    iterations: int
    nfev: int
    cost_history: tuple[float, ...]
    registration: dict | None
    notes: tuple[str, ...] = ()
    settings: dict = field(default_factory=dict)
    sources: tuple[str, ...] = ()
    prior_std_errors: np.ndarray | None = None
    chi2_prior: float = 0.0
    data_only: dict | None = None
    completeness: dict | None = None
    cross_validation: dict | None = None
    consistency: dict | None = None
    model_error_scale: float = 1.0
    warnings: tuple[str, ...] = ()
    held_covariance: dict | None = None

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def n_rows(self) -> int:
        return len(self.residuals_m)


# --------------------------------------------------------------------------- residuals

# Rows are processed in chunks of this many: the Jacobian of a chunk (3 rows per measurement, one
# column per parameter) is the largest array identification makes, so memory does not grow with
# the data beyond a few (N, 3) arrays, and each chunk's arrays stay in cache.


def expected_rms_m(result: IdentificationResult) -> float:
    """The residual RMS (m) the stated uncertainty expects: the actual one over √(χ²/dof)."""
    ratio = math.sqrt(result.chi2 / result.dof) if result.dof > 0 and result.chi2 > 0 else 1.0
    return result.rms_m / ratio
