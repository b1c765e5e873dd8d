"""Identification: the kinematic parameters that best explain measured positions (and poses).

One call, one frozen result (after scipy's ``least_squares``): :func:`identify` returns an
:class:`IdentificationResult` that says everything that happened — the identified model, the
parameters freed with their standard errors and correlations, the ones the data cannot
determine and why, conditioning and observability indices, residual statistics, rows
down-weighted as outliers, and how the solver ended.

Method (book §4.4.2, §4.3.3, §4.5.3), in named steps (:func:`identify` calls them in order):

1. Validation (:func:`_check_input`).
2. Convention rewrite (:func:`complete_form`): a complete, proportional parameterisation (book
   §2.7): ``mdh`` -> ``dh`` (exact); parallel consecutive axes in Hayati links (§2.6,
   §2.8.1.1), prismatic joints too; ``poe`` (§2.8.2) where ``dh`` cannot be complete (collinear
   axes: the rank at generic configurations falls short of the ``poe`` form's) or
   proportional. :func:`completeness` counts N = 4R + 2P + 6 (eq. 2.63) and what the
   measurement can see.
3. The candidates (:func:`_candidates`: THE place where the parameter list is assembled; their
   Jacobian columns in :func:`_linearise`), a rigid registration of the nominal predictions onto
   the measurements when the base is unknown or far off (full-pose data: base and tool, the
   robot-world/hand-eye problem), and the identifiable set (:func:`_choose`): a Gram–Schmidt
   selection on the column-scaled, weighted normal equations, in a fixed order of preference
   (:func:`preference_order`); a column that adds (numerically) nothing to those before it is
   not freed, keeps the model's value, and the report names what it duplicates
   (:func:`select_identifiable`); with a :class:`Prior`, its share (§4.3.2). Too few equations
   to check the fit: :class:`NotEnoughData`.
4. Levenberg–Marquardt (:func:`_levenberg_marquardt`) with Marquardt's scaling, the analytic
   Jacobian (:mod:`calibration.jacobian`), an optional robust loss by iteratively reweighted
   rows (a bumped reflector does not ruin the fit; the rows it down-weights are named). Then the
   selection again at the answer (:func:`_reselect`: parameters redundant only at the nominal
   geometry, a target on an axis, are freed where the data determine them), until the freed
   set is stable.
5. Statistics (:func:`_statistics`): covariance ``s²(JᵀWJ)⁻¹`` (book eq. 4.54/4.70 with W =
   Σ⁻¹), ``s² = χ²/dof`` when the residuals are significantly larger than the stated uncertainty
   (:func:`excess_scale`), else 1: the covariance grows when the data show the instrument, the
   fixturing or the model worse than stated, never for a chance excess of χ², and it never
   shrinks below what the instrument states. With a
   :class:`Prior`: ``s²(JᵀWJ + MᵀΣp⁻¹M)⁻¹`` (``M`` the combinations the prior describes,
   :meth:`Prior.combinations`), the prior's term counted in χ². A linearised k-fold
   cross-validation (:func:`_cross_validation`) says whether the covariance predicts the
   hold-out error (``model_error_scale``), and a χ² test (:func:`_consistency`) whether the
   model explains the data at all.
6. Merging (:func:`_merge_prior`): the parameters only the prior determines join the result.

Rows are processed in chunks (:data:`CHUNK_ROWS`): the normal equations are accumulated per
cross-validation fold, and no array of the size of the whole Jacobian is ever made.

Each step's code has a module of its own (this one keeps :func:`identify`, the loop of fit and
selection, and every name it had): :mod:`calibration.identify_start` (steps 1-2 and the
registration), :mod:`calibration.identify_selection` (step 3, the selection at the answer, step
6), :mod:`calibration.identify_solver` (step 4), :mod:`calibration.identify_statistics` (step 5),
and :mod:`calibration.identify_problem`, the rows, residuals and normal equations they share.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .conventions import to_poe
from .identification import (  # noqa: F401 (re-exported)
    INSTRUMENT_SIGMA_M,
    IdentificationResult,
    Measurements,
    Prior,
    Unidentifiable,
)
from .identify_problem import (  # noqa: F401 (re-exported: calibration.identify keeps every name it had)
    CHUNK_ROWS,
    CV_FOLDS,
    LOSSES,
    _Chunk,
    _evaluate,
    _Linearisation,
    _linearise,
    _p_tool,
    _Problem,
    _problem,
    _residuals,
    _robust_weights,
    _sample,
    _stack,
    _target_rows,
)
from .identify_selection import (  # noqa: F401 (re-exported: calibration.identify keeps every name it had)
    CATEGORIES,
    DETERMINED_M,
    DETERMINED_RAD,
    RESELECT_ROWS,
    SAME_MOTION_SINE,
    SEEN_BY_DATA,
    _candidates,
    _category,
    _choose,
    _gram_root,
    _hold_weak,
    _is_joint_parameter,
    _last_joint_offset,
    _matches,
    _merge_prior,
    _offset_duplicates,
    _r_factor,
    _reselect,
    _seen_by_data,
    _select,
    _Selection,
    _sqrt_psd,
    _weak_bound,
    preference_order,
    select_identifiable,
)
from .identify_solver import (
    TERMINATION_MESSAGES,
    _levenberg_marquardt,
    _Solution,
)
from .identify_start import (  # noqa: F401 (re-exported: calibration.identify keeps every name it had)
    ON_AXIS_M,
    REDUNDANCY_MIN,
    NotEnoughData,
    _check_input,
    _check_redundancy,
    _generic_configurations,
    _jacobian_rank,
    _rank,
    _register,
    _targets_on_last_axis,
    complete_form,
    completeness,
    redundancy_margin,
)
from .identify_statistics import (  # noqa: F401 (re-exported: calibration.identify keeps every name it had)
    CONSISTENCY_LEVEL,
    CONSISTENCY_MIN_SCALE,
    GRAM_FACTOR_MAX_CONDITION,
    HELD_SD_M,
    HELD_SD_RAD,
    SCALE_LEVEL,
    _conditioning,
    _consistency,
    _cross_validation,
    _gram_factor,
    _held_sd,
    _reach,
    _statistics,
    chi2_upper_tail,
    drift_scale,
    excess_scale,
    held_covariance,
    held_relations,
    observability_indices,
)
from .model import KinematicModel
from .parameters import Parameter, parameter_values
from .report import describe, explain, relation_coefficients, relation_text, unit_name  # noqa: F401 (re-exported)

# Rounds of "select at the answer, solve again" before the freed set is taken as it stands.
MAX_SELECTION_ROUNDS = 4


# --------------------------------------------------------------------------- steps 4 and 5: fit, select again, judge


@dataclasses.dataclass(frozen=True)
class _Fit:
    """What :func:`_fit_and_reselect` ends with: the model, the final selection, the last
    Levenberg–Marquardt solution, each freed parameter's total step, and the counts."""

    model: KinematicModel
    selection: _Selection
    solution: _Solution
    moved: dict
    iterations: int
    nfev: int
    history: list
    settled: bool = True


def _fit_and_reselect(
    st: _Start,
    prior: Prior | None,
    *,
    loss: str,
    f_scale: float,
    max_iter: int,
    ftol: float,
    xtol: float,
    gtol: float,
    rank_rtol: float,
    reselect: bool,
) -> _Fit:
    """Levenberg–Marquardt on the selected parameters from the start ``st`` (its ``first_lin``:
    [their linearisation at the start] when it can be reused, taken out of the list by the first
    fit); then, when ``reselect``, the selection again at the answer (a parameter redundant only
    at the nominal geometry, e.g. on a reflector nominally on the flange axis, is freed where the
    data show it), and again, until the freed set is stable."""
    start, prob, cands, sel, first_lin = st.model, st.prob, st.cands, st.sel, st.first_lin
    position_only = st.position_only
    current = start
    moved: dict[str, float] = {}
    iterations = nfev = 0
    history: list[float] = []
    settled = True
    for _round in range(MAX_SELECTION_ROUNDS):
        params = [cands[k] for k in sel.kept]
        info = prior.information(params) if prior is not None else np.zeros((len(params), len(params)))
        sol = _levenberg_marquardt(
            current,
            prob,
            params,
            first_lin.pop() if first_lin else _linearise(current, prob, params, loss=loss, f_scale=f_scale),
            info,
            loss=loss,
            f_scale=f_scale,
            max_iter=max_iter,
            ftol=ftol,
            xtol=xtol,
            gtol=gtol,
            # after a re-selection the fit starts at the answer: Gauss-Newton's step first. The
            # freed parameters are weakly determined (a reflector near an axis), and a damping
            # of 1e-3 of the diagonal held them back for five passes over the data (at a
            # million rows with the tool on the flange axis, 11 iterations instead of 6)
            damping=1e-3 if _round == 0 else 1e-9,
        )
        current = sol.model
        for p, s in zip(params, sol.steps):
            moved[p.name] = moved.get(p.name, 0.0) + float(s)
        iterations += sol.iterations
        nfev += sol.nfev
        history += list(sol.history)
        if not reselect:
            break
        again = _reselect(current, prob, cands, sel, rank_rtol=rank_rtol, position_only=position_only)
        if again.kept == sel.kept:
            sel = dataclasses.replace(sel, dropped=again.dropped)
            break
        if _round == MAX_SELECTION_ROUNDS - 1:
            # not settled: keep the set the last fit was made with (its solution, linearisation
            # and covariance belong to it), and say so
            settled = False
            break
        sel = again
    return _Fit(current, sel, sol, moved, iterations, nfev, history, settled)


def identify(
    model: KinematicModel,
    data: Measurements,
    *,
    sigma_m: float = INSTRUMENT_SIGMA_M,
    sigma_rad: float | None = None,
    loss: str = "linear",
    f_scale: float = 3.0,
    register: str = "auto",
    fixed: tuple[str, ...] = (),
    gains: bool = False,
    hayati: bool = True,
    rank_rtol: float = 1e-6,
    max_iter: int = 100,
    ftol: float = 1e-10,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    outlier_sigma: float = 5.0,
    prior: Prior | None = None,
) -> IdentificationResult:
    """Identify the parameters of ``model`` that ``data`` determine.

    ``sigma_m``: the instrument's per-axis standard uncertainty for rows without ``sigma``;
    ``sigma_rad``: orientation uncertainty of full-pose rows (default: ``sigma_m`` over 0.1 m,
    the spacing of tooling balls); ``loss``: ``linear``, ``huber``, ``soft_l1`` or ``cauchy``,
    with ``f_scale`` in units of sigma; ``register``: ``auto`` (when it fits better), ``always``,
    ``never``; ``fixed``: parameter names (or prefixes ending in ``*``) not to free; ``gains``:
    also free the joint gains; ``hayati``: rewrite the model in a complete form
    (:func:`complete_form`: Hayati links for parallel axes, ``poe`` where ``dh`` cannot be
    complete); ``prior``: minimum-variance estimation about ``model`` (book eq. 4.69-4.70): the
    cost gains ``½ (Ms)ᵀ Σp⁻¹ (Ms)`` for the step ``s`` away from ``model`` (``M``:
    :meth:`Prior.combinations`, the identity but for the prior's held parameters); parameters
    with a prior that the data see are estimated (source ``data + prior``) even where the data
    alone cannot determine them, those the data cannot see (:data:`SEEN_BY_DATA`) keep the
    prior's value and covariance (source ``prior``) unless a held parameter the data determine
    was confused with them (a reflector's offset and the tool orientation): then they move with
    it (source ``data + prior``); no registration is done (the prior knows the base).

    Raises ``ValueError`` for inconsistent input (shapes, unknown targets, non-finite values) and
    :class:`NotEnoughData` (a ``ValueError``) when the data leave no redundancy to check the fit.
    """
    st = _prepare(
        model,
        data,
        sigma_m=sigma_m,
        sigma_rad=sigma_rad,
        loss=loss,
        f_scale=f_scale,
        register=register,
        fixed=fixed,
        gains=gains,
        hayati=hayati,
        rank_rtol=rank_rtol,
        prior=prior,
    )
    at_nominal = set(st.sel.kept)

    # 4. Levenberg–Marquardt; then the selection again at the answer, until the freed set is stable
    fit = _fit_and_reselect(
        st,
        prior,
        loss=loss,
        f_scale=f_scale,
        max_iter=max_iter,
        ftol=ftol,
        xtol=xtol,
        gtol=gtol,
        rank_rtol=rank_rtol,
        reselect=prior is None and hayati,
    )
    # 5. statistics at the solution; 6. merging the parameters the prior alone determines
    return _judge(model, data, st, fit, prior, at_nominal, loss=loss, f_scale=f_scale, outlier_sigma=outlier_sigma)


def _judge(
    model: KinematicModel,
    data: Measurements,
    st: _Start,
    fit: _Fit,
    prior: Prior | None,
    at_nominal: set[int],
    *,
    loss: str,
    f_scale: float,
    outlier_sigma: float,
) -> IdentificationResult:
    """Steps 5-6 of :func:`identify`: the statistics at the solution (:func:`_answer`), the
    warnings of a target on the last axis (with the standard errors ``sqrt(diag Σ)`` of the
    parameters freed only at the answer, not in ``at_nominal``), and the result with the
    prior's parameters merged (:func:`_result`)."""
    if not fit.settled:
        st.notes.append(
            f"the freed set did not settle in {MAX_SELECTION_ROUNDS} selections at the identified model: "
            f"the last fit's set is kept"
        )
    ans = _answer(st, fit, prior, loss=loss, f_scale=f_scale, n_poses=len(data))
    params = [st.cands[k] for k in fit.selection.kept]
    answer_sd = np.sqrt(np.maximum(np.diag(ans.stats["covariance"]), 0.0))
    answer_only = [(params[i], float(answer_sd[i])) for i, k in enumerate(fit.selection.kept) if k not in at_nominal]
    warnings = _on_axis_warnings(st.on_axis, answer_only, fit.selection.dropped)
    return _result(model, data, st, fit, ans, prior, warnings, st.settings, outlier_sigma=outlier_sigma)


@dataclasses.dataclass(frozen=True, eq=False)
class _Start:
    """What steps 1-3 end with: the model the fit starts from (complete form, registered), the
    problem, the candidates and their selection, the freed ones' first linearisation (None: to
    be made), and what the report says of the start."""

    model: KinematicModel
    prob: _Problem
    cands: list[Parameter]
    sel: _Selection
    # [the candidates' linearisation at the start, for the first fit] or []: a list the fit
    # empties, so that nothing keeps its per-row arrays alive while the fit makes new ones (a
    # million rows: 38 MB a linearisation)
    first_lin: list
    notes: list[str]
    complete: dict
    on_axis: list
    registration: dict | None
    targets: tuple
    position_only: bool
    settings: dict  # what the result records of the options


def _prepare(
    model: KinematicModel,
    data: Measurements,
    *,
    sigma_m: float,
    sigma_rad: float | None,
    loss: str,
    f_scale: float,
    register: str,
    fixed: tuple[str, ...],
    gains: bool,
    hayati: bool,
    rank_rtol: float,
    prior: Prior | None,
) -> _Start:
    """Steps 1-3 of :func:`identify`: validation, the complete form, the candidates, the
    registration and what the data determine (and the prior's share)."""
    # 1. validation
    _check_input(model, data, loss, register)
    position_only = not np.any(data.has_orientation)
    targets = tuple(sorted(set(data.target) - {None}, key=str)) + ((None,) if None in set(data.target) else ())

    # 2. convention rewrite: a complete, proportional parameterisation
    start, notes = complete_form(model, hayati=hayati)
    complete = completeness(start, targets, orientation=not position_only)
    on_axis = _targets_on_last_axis(start, targets)
    prob = _problem(data, sigma_m, sigma_rad)

    # 3. the parameters, the registration, what the data determine (and the prior's share)
    cands = _candidates(start, data, prior, gains, fixed)
    registration = None
    if register != "never" and prior is None:
        cand, registration = _register(start, prob)
        if register == "always" or registration["applied"]:
            start = cand
            registration["applied"] = True
    lin_all = _linearise(start, prob, cands)
    sel = _choose(cands, lin_all.gram, prior, rank_rtol=rank_rtol, position_only=position_only)
    if prior is None:
        # what the data cannot determine is held before the solver starts, not left to wander
        # (the instrument's sigma: at the nominal the residuals are the robot's errors, not noise)
        sel = _hold_weak(cands, lin_all.gram, sel, 1.0)
        _check_redundancy(prob, len(sel.kept), complete)
    # the candidates' linearisation at the start serves the freed ones' first step when the
    # weights are the same (no robust loss): no second pass over the data
    first_lin = [lin_all.restricted(sel.kept)] if loss == "linear" else []
    del lin_all
    settings = dict(
        sigma_m=sigma_m,
        sigma_rad=prob.sigma_rot,
        loss=loss,
        f_scale=f_scale,
        gains=gains,
        rank_rtol=rank_rtol,
        fixed=list(fixed),
    )
    return _Start(
        start, prob, cands, sel, first_lin, notes, complete, on_axis, registration, targets, position_only, settings
    )


@dataclasses.dataclass(frozen=True, eq=False)
class _Answer:
    """What step 5 says of the answer: :func:`_statistics` (its ``cross_validation`` taken out as
    ``cv``), the χ² test, the prediction growth ``mes`` (``model_error_scale``), the held
    parameters' covariance, and the residuals in the data's order."""

    stats: dict
    cv: dict | None
    mes: float
    consistency: dict
    held_cov: dict | None
    rp: np.ndarray
    rr: np.ndarray
    rms_m: float
    max_m: float


def _answer(st: _Start, fit: _Fit, prior: Prior | None, *, loss: str, f_scale: float, n_poses: int) -> _Answer:
    """Step 5 of :func:`identify`: the statistics at the solution, the cross-validation's growth of
    the predictions, the χ² test, the held parameters' covariance; and (in ``st.complete``) what
    the measurement sees at the identified geometry."""
    current, sel, lin, prob = fit.model, fit.selection, fit.solution.lin, st.prob
    params = [st.cands[k] for k in sel.kept]
    steps = np.array([fit.moved.get(p.name, 0.0) for p in params])
    stats = _statistics(
        current,
        prob,
        params,
        lin,
        steps,
        prior,
        sel,
        loss=loss,
        f_scale=f_scale,
        reach_m=_reach(st.model),
        n_poses=n_poses,
    )
    cv = stats.pop("cross_validation")
    chi2_data = float(lin.c.sum())
    rp = prob.original(lin.rp)
    rr = prob.original(lin.rr)
    rn2 = np.einsum("ni,ni->n", rp, rp)  # squared norms without an (N, 3) temporary
    rms_m = float(np.sqrt(np.mean(rn2))) if len(rn2) else 0.0
    max_m = float(np.sqrt(rn2.max(initial=0.0)))
    del rn2
    mes = 1.0
    if cv is not None:
        cv["rms_m"] = rms_m * math.sqrt(max(cv["chi2"], 0.0) / chi2_data) if chi2_data > 0 else 0.0
        # the cross-validated χ² against what the covariance (already grown by sigma_scale) predicts
        mes = excess_scale(cv["chi2"] / stats["sigma_scale"] ** 2, cv["expected_chi2"])
        cv["model_error_scale"] = mes
    consistency = _consistency(stats["chi2"], stats["dof"])
    held_cov = held_covariance(current, prob, st.cands, sel, stats["sigma_scale"] * mes) if prior is None else None
    # what the measurement can see, at the identified geometry as the selection is: a target
    # nominally on an axis hides parameters the real one shows
    complete = st.complete
    seen = _jacobian_rank(to_poe(current), st.targets or (None,), orientation=not st.position_only)
    if seen != complete["measurable"]:
        complete["measurable_at_nominal"] = complete["measurable"]
        complete["measurable"] = seen
    complete["identified"] = len(sel.by_data)
    return _Answer(stats, cv, mes, consistency, held_cov, rp, rr, rms_m, max_m)


def _result(
    model: KinematicModel,
    data: Measurements,
    st: _Start,
    fit: _Fit,
    ans: _Answer,
    prior: Prior | None,
    warnings: list[str],
    settings: dict,
    *,
    outlier_sigma: float,
) -> IdentificationResult:
    """Step 6 of :func:`identify` (the parameters the prior alone determines join the estimated
    ones) and the result."""
    current, sel, sol, lin, stats = fit.model, fit.selection, fit.solution, fit.solution.lin, ans.stats
    P = len(sel.kept)
    steps = np.array([fit.moved.get(st.cands[k].name, 0.0) for k in sel.kept])
    params, steps, cov, sources, prior_sd = _merge_prior(st.cands, sel, stats["covariance"], steps, prior)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.nan_to_num(corr)
    z = st.prob.original(np.sqrt(lin.z2))
    w_row = st.prob.original(lin.w_row)
    # a row is an outlier against the noise the residuals show, not the instrument's alone: when
    # the model structure cannot explain the data (sigma_scale > 1, the consistency test failed)
    # every row is many instrument sigmas off, and flagging 293 of 300 rows as outliers hides
    # the few that are (issue 25); a gross error still stands out of the scaled noise
    outliers = tuple(int(i) for i in np.nonzero((z > outlier_sigma * stats["sigma_scale"]) | (w_row < 0.5))[0])
    has_rot = data.has_orientation
    rr = ans.rr
    return IdentificationResult(
        model=dataclasses.replace(current, metadata={}, name=identified_name(model.name)),
        start_model=st.model,
        params=tuple(params),
        values=parameter_values(current, params),
        steps=steps,
        std_errors=std,
        covariance=cov,
        correlation=corr,
        unidentifiable=tuple(sel.dropped),
        singular_values=stats["singular_values"],
        condition_number=stats["condition_number"],
        observability=stats["observability"],
        residuals_m=ans.rp,
        residuals_rad=rr,
        rms_m=ans.rms_m,
        max_m=ans.max_m,
        rms_rad=float(np.sqrt(np.mean(np.sum(rr[has_rot] ** 2, axis=1)))) if np.any(has_rot) else 0.0,
        chi2=stats["chi2"],
        dof=stats["dof"],
        sigma_scale=stats["sigma_scale"],
        row_weights=w_row,
        outliers=outliers,
        success=sol.status > 0 if P else False,
        status=sol.status if P else -1,
        message=TERMINATION_MESSAGES[sol.status if P else -1],
        iterations=fit.iterations,
        nfev=fit.nfev,
        cost_history=tuple(fit.history),
        registration=st.registration,
        notes=tuple(st.notes),
        settings=settings,
        sources=tuple(sources),
        prior_std_errors=prior_sd,
        chi2_prior=stats["chi2_prior"],
        data_only=stats["data_only"],
        completeness=st.complete,
        cross_validation=ans.cv,
        consistency=ans.consistency,
        model_error_scale=ans.mes,
        warnings=tuple(warnings),
        held_covariance=ans.held_cov,
    )


def _on_axis_warnings(on_axis: list, answer_only: list[tuple[Parameter, float]], dropped: list) -> list[str]:
    """What a target nominally on the last axis cost: the parameters only the identified
    geometry determined, with their standard errors (``answer_only``: (parameter, SI)), and
    those the data could not determine at all (category ``weak``)."""
    held = [u.name for u in dropped if u.category == "weak"]
    freed = ", ".join(f"{p.name} ±{_sd_text(p, sd)}" for p, sd in answer_only)
    out = []
    for t, dist in on_axis:
        what = "the tool origin" if t is None else f"target {t}"
        out.append(
            f"{what} is nominally on the last joint's axis ({dist * 1e3:.2f} mm from it): what the last axes do "
            f"there is seen only through the real offset from the axis"
            + (
                f"; determined only at the identified geometry, to standard errors of {freed} (the predicted "
                f"accuracy includes them; a target 20 mm or more off the axis determines them better)"
                if answer_only
                else ""
            )
            + (
                f"; not determined, kept at the model's value: {', '.join(held)} (the model may be biased "
                f"by them; put the target 20 mm or more off the axis)"
                if held
                else ""
            )
        )
    return out


def _sd_text(p: Parameter, sd_si: float) -> str:
    """A standard error for a warning, in mm or deg (the warnings' fixed units)."""
    if p.kind == "length":
        return f"{sd_si * 1e3:.2g} mm"
    if p.kind == "angle":
        return f"{math.degrees(sd_si):.2g} deg"
    return f"{sd_si:.2g}"


def identified_name(name: str) -> str:
    """The name of a model identified from the model ``name``: ``ur10e-nominal`` ->
    ``ur10e-identified`` (a model identified again keeps its name)."""
    stripped = True
    while stripped:
        stripped = False
        for suffix in ("-nominal", "-identified", "-true"):
            if name.endswith(suffix):
                name, stripped = name[: -len(suffix)], True
    return f"{name or 'robot'}-identified"
