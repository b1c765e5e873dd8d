"""Levenberg-Marquardt on the selected parameters (:func:`calibration.identify.identify`,
step 4): Marquardt's scaling, the analytic Jacobian, a robust loss by iteratively reweighted
rows."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .identify_problem import _Linearisation, _linearise, _Problem
from .model import KinematicModel
from .parameters import Parameter, apply_step

TERMINATION_MESSAGES = {
    -1: "the data cannot determine any parameter",
    0: "the maximum number of iterations was reached before convergence",
    1: "converged: the relative reduction of the cost fell below ftol",
    2: "converged: the parameter step fell below xtol",
    3: "converged: the gradient fell below gtol",
}


@dataclass(frozen=True, eq=False)
class _Solution:
    model: KinematicModel
    lin: _Linearisation
    steps: np.ndarray
    status: int
    iterations: int
    nfev: int
    history: tuple


def _levenberg_marquardt(
    model: KinematicModel,
    prob: _Problem,
    params: list[Parameter],
    lin: _Linearisation,
    info: np.ndarray,
    *,
    loss: str,
    f_scale: float,
    max_iter: int,
    ftol: float,
    xtol: float,
    gtol: float,
    damping: float = 1e-3,
) -> _Solution:
    """Levenberg–Marquardt with Marquardt's scaling (the damping proportional to diag(JᵀWJ + I_p),
    ``I_p`` the prior's information), from ``model`` whose linearisation is ``lin``; robust
    weights recomputed at every trial (IRLS: a trial is compared with the current point under the
    trial's weights). Stops as MINPACK does (``ftol``, ``xtol``, ``gtol``). ``damping``: the
    first step's (grown tenfold at every rejected trial, shrunk tenfold after an accepted one)."""
    P = len(params)
    steps = np.zeros(P)
    if not P:
        return _Solution(model, lin, steps, -1, 0, 1, (lin.cost,))
    lam, nfev, status, it = damping, 1, 0, 0
    cost = lin.cost
    history = [cost]
    for it in range(1, max_iter + 1):  # noqa: B007 (the iterations done, read after the loop)
        A = lin.gram + info
        g = lin.gradient - info @ steps
        D = np.maximum(np.diag(A), 1e-30)
        if np.max(np.abs(g) / np.sqrt(D)) < gtol * max(1.0, math.sqrt(2 * cost)):
            status = 3
            break
        improved = False
        for _ in range(30):
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            predicted = float(delta @ g - 0.5 * delta @ A @ delta)
            if lam <= 1e-3 and predicted <= ftol * cost:
                # the (nearly Gauss-Newton) model predicts no relative reduction beyond ftol:
                # converged, without spending a trial evaluation to confirm it
                break
            trial = apply_step(model, params, delta)
            nfev += 1
            tlin = _linearise(trial, prob, params, loss=loss, f_scale=f_scale)
            tcost = tlin.cost + 0.5 * float((steps + delta) @ info @ (steps + delta))
            # the current point's cost under the trial's weights (IRLS)
            ref = 0.5 * float(tlin.w_row @ lin.z2) + 0.5 * float(steps @ info @ steps)
            if tcost < ref or tcost <= cost:
                improved = True
                break
            # at the rounding floor: neither the actual nor the predicted reduction exceeds
            # ftol (MINPACK's test), so no damping will find a better point
            if abs(cost - tcost) <= ftol * cost and predicted <= ftol * cost:
                break
            lam *= 10
        if not improved:
            status = 1
            break
        step_norm = float(np.linalg.norm(delta * np.sqrt(D)))
        rel = (cost - tcost) / max(cost, 1e-300)
        model, lin, cost = trial, tlin, tcost
        steps = steps + delta
        history.append(cost)
        lam = max(lam / 10, 1e-12)
        if 0 <= rel < ftol:
            status = 1
            break
        if step_norm < xtol * (1.0 + float(np.linalg.norm(steps * np.sqrt(D)))):
            status = 2
            break
    else:
        status = 0
    return _Solution(model, lin, steps, status, it, nfev, tuple(history))
