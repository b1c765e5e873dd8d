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

from .kinematics import walk
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


def predict(
    model: KinematicModel,
    q: np.ndarray,
    p_tool: np.ndarray,
    params: list[Parameter] | None = None,
    target_names: np.ndarray | None = None,
) -> Prediction:
    """Predict the world position of tool-frame points ``p_tool`` (N, 3) at readings ``q`` (N, n);
    with ``params``, also the identification Jacobian. ``target_names`` (N,) names the target each
    row measures (``None`` entries: the tool origin); it selects the rows a ``target.*``
    parameter moves."""
    record = set().union(*(p.record_keys for p in params)) if params else set()
    w = walk(model, q, record)
    p_tool = np.broadcast_to(np.asarray(p_tool, dtype=float), w.p.shape)
    pt = w.p + np.einsum("nij,nj->ni", w.R, p_tool)
    if not params:
        return Prediction(pt, w.R)
    N, P = pt.shape[0], len(params)
    Jp = np.zeros((N, 3, P))
    Jr = np.zeros((N, 3, P))
    q = np.asarray(q, dtype=float).reshape(N, -1)
    for k, par in enumerate(params):
        colp = np.zeros((N, 3))
        colr = np.zeros((N, 3))
        for key, gen, axis, sign in par.terms:
            if key in w.axes:  # an op: recorded along its own axis
                u, o = w.axes[key]
            else:  # a mark: the frame, any of its axes
                Rf, pf = w.frames[key]
                u, o = Rf[:, :, axis], pf
            if gen == "rot":
                colp += sign * np.cross(u, pt - o)
                colr += sign * u
            else:
                colp += sign * u
        if par.q_joint is not None:
            colp *= q[:, par.q_joint, None]
            colr *= q[:, par.q_joint, None]
        if par.target is not None:
            mask = (target_names == par.target)[:, None] if target_names is not None else np.zeros((N, 1), bool)
            colp *= mask
            colr = np.zeros((N, 3))
        Jp[:, :, k] = colp
        Jr[:, :, k] = colr
    return Prediction(pt, w.R, Jp, Jr)
