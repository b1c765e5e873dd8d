"""Analytic identification Jacobians, for every convention (book §2.5, eq. 2.53-2.58).

A parameter acts on the chain as a unit rotation about, or translation along, a world axis
``u`` through a world point ``o`` (recorded while walking the program, see
:mod:`calibration.kinematics`). For a point ``p`` carried by the tool, its effect is
``dp = u × (p − o)`` and ``dω = u`` for a rotation, ``dp = u`` and ``dω = 0`` for a translation:
the screw form of the book's differential-transform Jacobian, which needs no per-convention
formulas.

Rows: position rows ``dp`` (N, 3, P) of the measured point; orientation rows ``dω`` (N, 3, P),
the small rotation of the tool frame expressed in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .kinematics import Walk, walk
from .model import KinematicModel
from .parameters import Parameter


@dataclass(frozen=True, slots=True)
class Prediction:
    """Predicted measurements and, when asked, their derivatives.

    ``p_world`` (N, 3) m: the measured point; ``R_world_tool`` (N, 3, 3); ``Jp`` (N, 3, P)
    d p_world / d params; ``Jr`` (N, 3, P) world-frame rotation per unit parameter.
    """

    p_world: np.ndarray
    R_world_tool: np.ndarray
    Jp: np.ndarray | None = None
    Jr: np.ndarray | None = None


def world_points(w: Walk, p_tool: np.ndarray) -> np.ndarray:
    """World positions (N, 3) of tool-frame points ``p_tool`` (3,) or (N, 3) on a walk's tool frames."""
    p_tool = np.broadcast_to(np.asarray(p_tool, dtype=float), w.p.shape)
    if not np.any(p_tool):  # the tool origin itself (adding zeros would change nothing)
        return w.p.copy()
    return w.p + np.einsum("nij,nj->ni", w.R, p_tool)


def predict(
    model: KinematicModel,
    q: np.ndarray,
    p_tool: np.ndarray,
    params: list[Parameter] | None = None,
    target_names: np.ndarray | None = None,
    payload: np.ndarray | None = None,
) -> Prediction:
    """Predict the world position of tool-frame points ``p_tool`` (N, 3) at readings ``q`` (N, n);
    with ``params``, also the identification Jacobian. ``target_names`` (N,) names the target each
    row measures (``None`` entries: the tool origin); it selects the rows a ``target.*``
    parameter moves. ``payload`` (N, 4): kg and centre of gravity in the tool frame (m) per row,
    for a compliant model (:func:`calibration.kinematics.walk`)."""
    w = walk(model, q, record_keys(params), payload=payload)
    pt = world_points(w, p_tool)
    if not params:
        return Prediction(pt, w.R)
    Jp, Jr = jacobian_from_walk(w, pt, params, q, target_names)
    return Prediction(pt, w.R, Jp, Jr)


def record_keys(params: list[Parameter] | None) -> set[str]:
    """The keys a walk must record for the Jacobian columns of ``params``."""
    return set().union(*(p.record_keys for p in params)) if params else set()


def jacobian_from_walk(
    w: Walk,
    p_world: np.ndarray,
    params: list[Parameter],
    q: np.ndarray,
    target_names: np.ndarray | None = None,
    *,
    orientation: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The Jacobian columns ``(Jp, Jr)``, each (N, 3, P), of ``params`` from a walk that recorded
    :func:`record_keys` (``p_world`` (N, 3): the measured points on that walk). Without
    ``orientation`` (position-only data) ``Jr`` is not computed (``None``).

    The columns are computed component-major, one contiguous (3, N) block per parameter, and
    returned as (N, 3, P) views of those (P, 3, N) buffers: ``Jp.transpose(2, 1, 0)`` is
    contiguous, which the identification stacks without a transposing copy.
    """
    N, P = p_world.shape[0], len(params)
    q = np.asarray(q, dtype=float).reshape(N, -1)
    ptT = p_world.T
    Jp = np.empty((P, 3, N))
    Jr = np.zeros((P, 3, N)) if orientation else None
    lever: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # p − o per origin (keys may share one)
    tmp = np.empty(N)
    for k, par in enumerate(params):
        cp, cr = Jp[k], (Jr[k] if Jr is not None else None)
        first = True
        for key, gen, axis, sign in par.terms:
            if key in w.axes:  # an op: recorded along its own axis
                u, o = w.axes[key]
            else:  # a mark: the frame, any of its axes
                Rf, o = w.frames[key]
                u = Rf[:, :, axis]
            uT = u.T
            if gen == "rot":  # dp = u × (p − o), dω = u
                where = (o.__array_interface__["data"][0], o.strides)
                d = lever.get(where, (None, None))[1]
                if d is None:
                    d = ptT - o.T
                    lever[where] = (o, d)  # keeps o alive, so its memory is not reused
                if first and sign == 1.0:
                    np.multiply(uT[1], d[2], out=cp[0])
                    cp[0] -= np.multiply(uT[2], d[1], out=tmp)
                    np.multiply(uT[2], d[0], out=cp[1])
                    cp[1] -= np.multiply(uT[0], d[2], out=tmp)
                    np.multiply(uT[0], d[1], out=cp[2])
                    cp[2] -= np.multiply(uT[1], d[0], out=tmp)
                    if cr is not None:
                        cr[...] = uT
                else:
                    c = np.cross(uT, d, axis=0)
                    if first:
                        np.multiply(c, sign, out=cp)
                    else:
                        cp += sign * c
                    if cr is not None:
                        cr += sign * uT
            elif first:  # translation: dp = u, dω = 0
                np.multiply(uT, sign, out=cp)
            else:
                cp += sign * uT
            first = False
        if par.q_joint is not None:
            cp *= q[:, par.q_joint]
            if cr is not None:
                cr *= q[:, par.q_joint]
        if par.regressor is not None:  # a compliance term: its joint's offset column times its regressor
            cp *= w.regressors[par.regressor]
            if cr is not None:
                cr *= w.regressors[par.regressor]
        if par.target is not None:
            cp *= (target_names == par.target) if target_names is not None else 0.0
            if cr is not None:
                cr[...] = 0.0
    return Jp.transpose(2, 1, 0), (Jr.transpose(2, 1, 0) if Jr is not None else None)
