"""The data as the identification's solver sees them (:func:`calibration.identify.identify`,
steps 3-5): the rows in chunks and cross-validation folds (:class:`_Problem`), the residuals of a
model, and the weighted normal equations of a set of parameters (:func:`_linearise`, THE place
where the identification Jacobian's columns are assembled).

Rows are processed in chunks (:data:`CHUNK_ROWS`): the normal equations are accumulated per
cross-validation fold, and no array of the size of the whole Jacobian is ever made.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from .identification import (
    Measurements,
)
from .jacobian import Prediction, jacobian_from_walk, record_keys, world_points
from .kinematics import program, walk
from .model import KinematicModel
from .parameters import Parameter
from .transforms import matrix_to_rotvec, quat_to_matrix

LOSSES = ("linear", "huber", "soft_l1", "cauchy")


CHUNK_ROWS = 8192


# k of the k-fold cross-validation (:func:`_cross_validation`); data with fewer than 2k poses are
# not cross-validated.
CV_FOLDS = 5


@dataclass(frozen=True, slots=True)
class _Chunk:
    a: int  # rows [a, b) of the (fold-ordered) data
    b: int
    fold: int
    targets: dict  # target name -> (b - a,) bool, the rows of the chunk that measure it
    rot: bool  # some row of the chunk carries an orientation


@dataclass(frozen=True, eq=False)
class _Problem:
    """The data with their weights, in fold order: ``data`` is the caller's data with its rows
    reordered by ``order`` (so that each cross-validation fold is a contiguous block of rows,
    processed in ``chunks``)."""

    data: Measurements
    p_tool_names: np.ndarray  # (N,) object
    has_rot: np.ndarray  # (N,) bool
    R_meas: np.ndarray | None  # (N, 3, 3)
    sigma_pos: np.ndarray  # (N,) m
    sigma_rot: float  # rad
    target_rows: dict = field(default_factory=dict)  # target name -> (N,) bool, the rows that measure it
    trig: dict = field(default_factory=dict)  # the joints' cos and sin over the data, for every walk (kinematics.walk)
    order: np.ndarray | None = None  # (N,) the caller's row of each row here
    chunks: tuple = ()
    n_folds: int = 1

    def original(self, a: np.ndarray) -> np.ndarray:
        """Per-row values (N, ...) in this problem's order -> in the caller's order."""
        if self.order is None or (a.ndim and a.strides[0] == 0):  # the same for every row (zeros)
            return a
        out = np.empty_like(a)
        out[self.order] = a
        return out


def _problem(data: Measurements, sigma_m: float, sigma_rad: float | None, *, folds: int = CV_FOLDS) -> _Problem:
    """The data with their weights: ``sigma_m`` for rows without their own ``sigma``, ``sigma_rad``
    for orientations (default ``sigma_m`` over 0.1 m); rows grouped into ``folds`` folds by pose
    (every ``folds``-th pose in one fold), each fold cut into chunks of :data:`CHUNK_ROWS`."""
    N = len(data)
    key = data.pose_id if data.pose_id is not None else np.arange(N)
    pose = np.unique(np.asarray(key), return_inverse=True)[1].reshape(N) if N else np.zeros(0, int)
    k = folds if N and pose.max() + 1 >= 2 * folds else 1
    fold = pose % k
    order = None
    if k > 1:
        order = np.argsort(fold, kind="stable")
        data = data.subset(order)
        fold = fold[order]
    has_rot = data.has_orientation
    R_meas = (
        quat_to_matrix(np.where(np.isfinite(data.quat), data.quat, [1, 0, 0, 0])) if data.quat is not None else None
    )
    sigma_pos = np.where(np.isfinite(data.sigma) & (data.sigma > 0), data.sigma, sigma_m)
    sigma_rot = float(sigma_rad) if sigma_rad is not None else sigma_m / 0.1
    bounds = np.searchsorted(fold, np.arange(k + 1))
    chunks = []
    for f in range(k):
        for a in range(int(bounds[f]), int(bounds[f + 1]), CHUNK_ROWS):
            b = min(a + CHUNK_ROWS, int(bounds[f + 1]))
            chunks.append(_Chunk(a, b, f, _target_rows(data.target[a:b]), bool(np.any(has_rot[a:b]))))
    return _Problem(
        data,
        data.target,
        has_rot,
        R_meas,
        sigma_pos,
        sigma_rot,
        _target_rows(data.target),
        order=order,
        chunks=tuple(chunks),
        n_folds=k,
    )


def _target_rows(names: np.ndarray) -> dict:
    return {name: names == name for name in sorted(set(names) - {None})}


def _p_tool(model: KinematicModel, names: np.ndarray, rows: dict | None = None) -> np.ndarray:
    """Each row's target point in the tool frame (N, 3); ``rows``: :func:`_target_rows` of
    ``names``, when already known."""
    out = np.zeros((len(names), 3))
    for name, mask in (_target_rows(names) if rows is None else rows).items():
        out[mask] = model.targets[name]
    return out


def _residuals(model, prob: _Problem, record=frozenset()):
    """Walk ``model`` over the data (recording ``record``): the walk, the predicted points and the
    residuals, measured minus predicted (position (N, 3), orientation (N, 3))."""
    w = walk(model, prob.data.q, record, prob.trig, prob.data.payload)
    pt = world_points(w, _p_tool(model, prob.p_tool_names, prob.target_rows))
    rp = prob.data.p_world - pt
    rr = np.zeros_like(rp)
    if prob.R_meas is not None and np.any(prob.has_rot):
        m = prob.has_rot
        rr[m] = matrix_to_rotvec(prob.R_meas[m] @ np.swapaxes(w.R[m], 1, 2))
    return w, pt, rp, rr


def _evaluate(model, prob: _Problem, params=None) -> tuple[Prediction, np.ndarray, np.ndarray]:
    w, pt, rp, rr = _residuals(model, prob, record_keys(params))
    if not params:
        return Prediction(pt, w.R), rp, rr
    Jp, Jr = jacobian_from_walk(w, pt, params, prob.data.q, prob.p_tool_names, orientation=bool(np.any(prob.has_rot)))
    return Prediction(pt, w.R, Jp, Jr), rp, rr


def _stack(prob: _Problem, rp, rr, Jp=None, Jr=None):
    """Weighted residual vector (and Jacobian): position rows / sigma_pos, orientation rows /
    sigma_rot (book §4.3.3: scale rows to equal variance).

    Component-major order: the x residuals of all rows, then y, then z, then the orientation
    rows likewise. :func:`calibration.jacobian.predict` computes its columns in that order, so
    the Jacobian (M, P) is a Fortran-ordered array made without a transposing copy: ``Jp`` (from
    :func:`~calibration.jacobian.jacobian_from_walk`, used for nothing else) is weighted in place."""
    wp = 1.0 / prob.sigma_pos
    r = [(rp.T * wp).reshape(-1)]
    cols: list[np.ndarray] | None = None  # the Jacobian's transposed blocks, with Jp
    if Jp is not None:
        JpT = Jp.transpose(2, 1, 0)  # (P, 3, N), contiguous
        JpT = np.multiply(JpT, wp, out=JpT) if JpT.flags.c_contiguous and JpT.flags.writeable else JpT * wp
        cols = [JpT.reshape(Jp.shape[2], -1)]  # (P, 3N)
    if np.any(prob.has_rot):
        m = prob.has_rot
        r.append((rr[m].T / prob.sigma_rot).reshape(-1))
        if cols is not None:
            assert Jr is not None  # rows with an orientation have its Jacobian
            cols.append((Jr.transpose(2, 1, 0)[:, :, m] / prob.sigma_rot).reshape(Jr.shape[2], -1))
    Jt = None if cols is None else cols[0] if len(cols) == 1 else np.concatenate(cols, axis=1)
    return (r[0] if len(r) == 1 else np.concatenate(r)), (None if Jt is None else Jt.T)


def _robust_weights(z: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """IRLS weights rho'(s) for row norms ``z`` (in sigma units); s = (z / f_scale)²."""
    s = (z / f_scale) ** 2
    if loss == "linear":
        return np.ones_like(z)
    if loss == "huber":
        return np.where(s <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(s, 1e-300)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + s)
    if loss == "cauchy":
        return 1.0 / (1.0 + s)
    raise ValueError(f"`loss` must be one of {', '.join(LOSSES)}; got {loss!r}")


@dataclass(frozen=True, eq=False)
class _Linearisation:
    """The weighted least-squares problem at one model, accumulated over the rows chunk by chunk
    (the Jacobian itself is never kept whole). Per fold ``k`` of the cross-validation:
    ``G[k] = JₖᵀWJₖ``, ``g[k] = JₖᵀWrₖ``, ``c[k] = rₖᵀWrₖ`` and ``n[k]`` residuals (W: the rows'
    1/σ² times their robust weights). ``R`` (with ``factor``): a triangular factor of ``ΣG``
    from the rows themselves (better conditioned than a factor of G)."""

    rp: np.ndarray  # (N, 3) m, measured minus predicted
    rr: np.ndarray  # (N, 3) rad, zeros for rows without orientation
    z2: np.ndarray  # (N,) the row's squared residual norm in units of its sigma
    w_row: np.ndarray  # (N,) the robust weight each row carries in G, g, c
    G: np.ndarray  # (K, P, P)
    g: np.ndarray  # (K, P)
    c: np.ndarray  # (K,)
    n: np.ndarray  # (K,)
    R: np.ndarray | None = None

    @property
    def cost(self) -> float:
        return 0.5 * float(self.c.sum())

    def restricted(self, idx: list[int]) -> _Linearisation:
        """The same linearisation for the parameters ``idx`` only (no pass over the data)."""
        return dataclasses.replace(self, G=self.G[:, idx][:, :, idx], g=self.g[:, idx], R=None)

    @property
    def gram(self) -> np.ndarray:
        return self.G.sum(axis=0)

    @property
    def gradient(self) -> np.ndarray:
        return self.g.sum(axis=0)


def _linearise(
    model: KinematicModel,
    prob: _Problem,
    params: list[Parameter],
    *,
    loss: str = "linear",
    f_scale: float = 3.0,
    factor: bool = False,
) -> _Linearisation:
    """Residuals and the normal equations of ``params`` at ``model``, weighted (book §4.3.3: rows
    scaled to equal variance; robust ``loss`` by iteratively reweighted rows), chunk by chunk.

    THE place where the identification's Jacobian columns are assembled: the kinematic
    parameters' columns come from the walk (:func:`calibration.jacobian.jacobian_from_walk`),
    the compliance terms' too (a joint offset's column times the walk's regressor, which a
    compliant model's walk keeps for each chunk's ``payload``); another block of parameters adds
    its columns to ``Jt`` here, and its candidates in :func:`_candidates`.
    """
    N, P, K = len(prob.data), len(params), prob.n_folds
    rp = np.empty((N, 3))
    # rotation residuals: zeros that take no memory when no row has an orientation (24 bytes a
    # row, twice over while the fit holds two linearisations)
    rr = np.zeros((N, 3)) if any(ch.rot for ch in prob.chunks) else np.broadcast_to(np.zeros(3), (N, 3))
    z2, w_row = np.empty(N), np.ones(N)
    G, g, c, n = np.zeros((K, P, P)), np.zeros((K, P)), np.zeros(K), np.zeros(K, dtype=int)
    R: np.ndarray | None = None
    keys = record_keys(params)
    data = prob.data
    ops = program(model)  # compiled once for every chunk
    for ch in prob.chunks:
        a, b, f = ch.a, ch.b, ch.fold
        q = data.q[a:b]
        payload = None if data.payload is None else data.payload[a:b]  # a compliant model's (issue 17)
        w = walk(model, q, keys, payload=payload, ops=ops)
        pt = world_points(w, _p_tool(model, prob.p_tool_names[a:b], ch.targets))
        rpc = data.p_world[a:b] - pt
        rp[a:b] = rpc
        wp = 1.0 / prob.sigma_pos[a:b]
        zp = rpc * wp[:, None]
        zz = np.einsum("ni,ni->n", zp, zp)
        m = None
        if ch.rot:
            assert prob.R_meas is not None  # a chunk with orientation rows has measured orientations
            m = prob.has_rot[a:b]
            rrc = matrix_to_rotvec(prob.R_meas[a:b][m] @ np.swapaxes(w.R[m], 1, 2))
            rr[a:b][m] = rrc
            zr = rrc / prob.sigma_rot
            zz[m] += np.einsum("ni,ni->n", zr, zr)
        z2[a:b] = zz
        wr = _robust_weights(np.sqrt(zz), loss, f_scale)
        w_row[a:b] = wr
        c[f] += float(wr @ zz)
        n[f] += 3 * (b - a) + (3 * int(np.count_nonzero(m)) if m is not None else 0)
        if not P:
            continue
        Jp, Jr = jacobian_from_walk(w, pt, params, q, prob.p_tool_names[a:b], orientation=ch.rot)
        sw = np.sqrt(wr)
        JpT = Jp.transpose(2, 1, 0)  # (P, 3, n), contiguous: weighted in place
        JpT *= wp * sw
        cols, res = [JpT.reshape(P, -1)], [(zp.T * sw).reshape(-1)]
        if m is not None:
            assert Jr is not None  # asked for (orientation=ch.rot)
            cols.append((Jr.transpose(2, 1, 0)[:, :, m] * (sw[m] / prob.sigma_rot)).reshape(P, -1))
            res.append((zr.T * sw[m]).reshape(-1))
        Jt = cols[0] if len(cols) == 1 else np.concatenate(cols, axis=1)  # (P, rows of the chunk)
        rv = res[0] if len(res) == 1 else np.concatenate(res)
        G[f] += Jt @ Jt.T
        g[f] += Jt @ rv
        if factor:
            # numpy's stubs type every mode's answer as the (Q, R) pair; mode "r" returns R alone
            R = cast(np.ndarray, np.linalg.qr(Jt.T if R is None else np.vstack([R, Jt.T]), mode="r"))
    return _Linearisation(rp, rr, z2, w_row, G, g, c, n, R)


def _sample(prob: _Problem, n: int) -> tuple[_Problem, float]:
    """At most ``n`` rows of ``prob`` evenly spread, as one fold, and the share of the rows taken."""
    N = len(prob.data)
    if N <= n:
        return prob, 1.0
    idx = np.linspace(0, N - 1, n).round().astype(int)
    data = prob.data.subset(idx)
    has_rot = prob.has_rot[idx]
    chunks = tuple(
        _Chunk(
            a,
            min(a + CHUNK_ROWS, n),
            0,
            _target_rows(data.target[a : a + CHUNK_ROWS]),
            bool(np.any(has_rot[a : a + CHUNK_ROWS])),
        )
        for a in range(0, n, CHUNK_ROWS)
    )
    sub = _Problem(
        data,
        data.target,
        has_rot,
        None if prob.R_meas is None else prob.R_meas[idx],
        prob.sigma_pos[idx],
        prob.sigma_rot,
        _target_rows(data.target),
        chunks=chunks,
        n_folds=1,
    )
    return sub, n / N
