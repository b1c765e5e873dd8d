"""Accuracy figures of verification data, in the manner of ISO 9283 (formulas in docs/accuracy.md).

Inputs are what a verification session has: for each measurement row, the commanded position
(the model's prediction of where the target should be for the commanded joints, or the
programmed point) and the measured one, both in the world frame (m); optionally the commanded
and measured orientations (3, 3); and a ``pose_id`` grouping rows that repeat one command.

- :func:`pose_statistics`: per commanded pose measured several times, ISO 9283 §7.2.1 and §7.2.2:
  the barycentre of the measured positions, the pose accuracy ``AP`` (distance of the barycentre
  from the command, and its components), the pose repeatability ``RP = l̄ + 3·S_l`` (l the
  distances of the measurements from their barycentre), and per axis the orientation accuracy
  ``AP_a, AP_b, AP_c`` and repeatability ``±3·S_a`` etc.
- :func:`error_statistics`: one measurement per pose: mean, standard deviation, 3σ, mean + 3σ,
  RMS, 95th percentile and maximum of the position error (and of the orientation error angle).
- :func:`group_configurations`: which rows repeat one commanded configuration, from their joint
  readings (when the data carry no pose label).
- :func:`position_errors` and :func:`registered_errors`: what a model gets wrong on measured
  data, as it stands and with its base placed where it fits best; :func:`norm_statistics` the
  figures of a set of error lengths. These are the one definition of the errors and figures the
  CLI, the API, the web page and the certificate show.

Orientation (where ISO 9283 subtracts the robot's angles a, b, c): each measured orientation's
deviation from its command is taken as the small rotation ``δ = log(R_meas · R_cmdᵀ)`` resolved on
the world (measurement) axes x, y, z. Unlike differences of Euler or RPY angles it does not wrap
at ±180° and does not depend on the angle convention; for the small deviations a robot has it
is what the differences of the angles about the fixed x, y, z axes measure.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .kinematics import points_world, walk
from .model import KinematicModel
from .registration import register_points
from .transforms import matrix_to_rotvec


def _check(p_cmd, p_meas, R_cmd, R_meas) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    p_cmd = np.atleast_2d(np.asarray(p_cmd, float))
    p_meas = np.atleast_2d(np.asarray(p_meas, float))
    if p_meas.ndim != 2 or p_meas.shape[1] != 3 or p_cmd.shape != p_meas.shape:
        raise ValueError(f"`p_cmd` and `p_meas` must both have shape (N, 3); got {p_cmd.shape} and {p_meas.shape}")
    if len(p_meas) == 0:
        raise ValueError("no measurements")
    if not (np.all(np.isfinite(p_cmd)) and np.all(np.isfinite(p_meas))):
        raise ValueError("positions must be finite")
    if (R_cmd is None) != (R_meas is None):
        raise ValueError("give both `R_cmd` and `R_meas`, or neither")
    delta = None
    if R_cmd is not None:
        R_cmd = np.asarray(R_cmd, float).reshape(-1, 3, 3)
        R_meas = np.asarray(R_meas, float).reshape(-1, 3, 3)
        if len(R_cmd) != len(p_meas) or len(R_meas) != len(p_meas):
            raise ValueError(f"`R_cmd` and `R_meas` must have shape ({len(p_meas)}, 3, 3)")
        delta = orientation_deviation(R_cmd, R_meas)
    return p_cmd, p_meas, delta


def orientation_deviation(R_cmd: np.ndarray, R_meas: np.ndarray) -> np.ndarray:
    """The small rotation (N, 3) rad taking each commanded orientation to the measured one,
    resolved on the world axes: ``log(R_meas · R_cmdᵀ)``."""
    return matrix_to_rotvec(np.asarray(R_meas, float) @ np.swapaxes(np.asarray(R_cmd, float), -1, -2))


# --------------------------------------------------------------------------- which rows repeat a pose


def group_configurations(q: np.ndarray, tol: np.ndarray | float) -> np.ndarray:
    """Pose labels (N,) int, 0, 1, ... in order of first appearance, for joint readings ``q``
    (N, n): two rows are the same commanded configuration when every joint differs by at most
    ``tol`` (a number, or (n,) per joint, in the readings' units), and sameness is transitive
    (connected components of that relation: a robot's readings at one commanded configuration
    scatter by its encoder resolution, far less than the distance between two poses of a
    measurement plan)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    q = np.atleast_2d(np.asarray(q, float))
    tol = np.broadcast_to(np.asarray(tol, float), (q.shape[1],))
    if not np.all(tol > 0):
        raise ValueError(f"`tol` must be positive; got {tol}")
    N = len(q)
    pairs = cKDTree(q / tol).query_pairs(r=1.0, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(N, N))
    _, labels = connected_components(graph, directed=False)
    first: dict[int, int] = {}
    return np.array([first.setdefault(k, len(first)) for k in labels.tolist()], dtype=int)


# --------------------------------------------------------------------------- repeated poses


@dataclass(frozen=True, eq=False)
class PoseStatistics:
    """ISO 9283 pose accuracy and repeatability, one entry per commanded pose (m, rad).

    ``pose_ids`` (P,) in order of first appearance; ``n`` (P,) measurements per pose;
    ``command_m`` (P, 3) and ``barycentre_m`` (P, 3); ``AP_xyz_m`` (P, 3) = barycentre − command
    and ``AP_m`` (P,) its length; ``l_mean_m`` (P,) mean distance of the measurements from their
    barycentre, ``S_l_m`` (P,) its standard deviation, ``RP_m`` (P,) = l̄ + 3·S_l (NaN where
    n < 2). With orientations: ``AP_abc_rad`` (P, 3) mean deviation about x, y, z and
    ``RP_abc_rad`` (P, 3) = 3·S about each axis (the ISO's ±3·S_a), else ``None``.
    """

    pose_ids: np.ndarray
    n: np.ndarray
    command_m: np.ndarray
    barycentre_m: np.ndarray
    AP_xyz_m: np.ndarray
    AP_m: np.ndarray
    l_mean_m: np.ndarray
    S_l_m: np.ndarray
    RP_m: np.ndarray
    AP_abc_rad: np.ndarray | None
    RP_abc_rad: np.ndarray | None

    @property
    def max_AP_m(self) -> float:
        """The worst pose accuracy over the poses (what an ISO 9283 report quotes)."""
        return float(np.max(self.AP_m))

    @property
    def max_RP_m(self) -> float:
        """The worst pose repeatability over the poses measured at least twice (NaN if none)."""
        ok = np.isfinite(self.RP_m)
        return float(np.max(self.RP_m[ok])) if np.any(ok) else float("nan")


def _sample_std(x: np.ndarray, axis: int = 0) -> np.ndarray:
    n = x.shape[axis]
    if n < 2:
        return np.full(np.delete(x.shape, axis), np.nan) if x.ndim > 1 else np.array(np.nan)
    return np.std(x, axis=axis, ddof=1)


def pose_statistics(
    p_cmd: np.ndarray,
    p_meas: np.ndarray,
    pose_id: np.ndarray,
    *,
    R_cmd: np.ndarray | None = None,
    R_meas: np.ndarray | None = None,
) -> PoseStatistics:
    """ISO 9283 pose accuracy AP and repeatability RP (§7.2.1-7.2.2) of measurements ``p_meas``
    (N, 3) m of commands ``p_cmd`` (N, 3), grouped by ``pose_id`` (N,); orientations ``R_cmd``,
    ``R_meas`` (N, 3, 3) optional. The command of a pose is the mean of its rows' commands (they
    are equal when the rows repeat one command)."""
    p_cmd, p_meas, delta = _check(p_cmd, p_meas, R_cmd, R_meas)
    pose_id = np.asarray(pose_id, dtype=object).reshape(-1)
    if len(pose_id) != len(p_meas):
        raise ValueError(f"`pose_id` must have {len(p_meas)} entries; got {len(pose_id)}")
    ids = list(dict.fromkeys(pose_id.tolist()))
    rows: dict = {k: [] for k in ids}
    for i, k in enumerate(pose_id.tolist()):
        rows[k].append(i)
    P = len(ids)
    n = np.zeros(P, int)
    cmd, bary, l_mean, S_l = np.zeros((P, 3)), np.zeros((P, 3)), np.zeros(P), np.zeros(P)
    ap_abc = np.zeros((P, 3)) if delta is not None else None
    rp_abc = np.zeros((P, 3)) if delta is not None else None
    for k, key in enumerate(ids):
        idx = np.array(rows[key])
        n[k] = len(idx)
        cmd[k] = p_cmd[idx].mean(axis=0)
        bary[k] = p_meas[idx].mean(axis=0)  # x̄ = (1/n) Σ x_j
        l = np.linalg.norm(p_meas[idx] - bary[k], axis=1)  # l_j = |x_j − x̄|
        l_mean[k] = l.mean()
        S_l[k] = _sample_std(l)
        if delta is not None and ap_abc is not None and rp_abc is not None:
            d = delta[idx]
            ap_abc[k] = d.mean(axis=0)  # ā − a_c (the command's deviation is 0)
            rp_abc[k] = 3.0 * _sample_std(d)
    ap_xyz = bary - cmd
    return PoseStatistics(
        pose_ids=np.array(ids, dtype=object),
        n=n,
        command_m=cmd,
        barycentre_m=bary,
        AP_xyz_m=ap_xyz,
        AP_m=np.linalg.norm(ap_xyz, axis=1),
        l_mean_m=l_mean,
        S_l_m=S_l,
        RP_m=l_mean + 3.0 * S_l,
        AP_abc_rad=ap_abc,
        RP_abc_rad=rp_abc,
    )


# --------------------------------------------------------------------------- one measurement per pose


@dataclass(frozen=True, eq=False)
class ErrorStatistics:
    """Statistics of the position error ``e = |p_meas − p_cmd|`` over N rows (m), and of the
    orientation error angle ``|δ|`` (rad) when orientations were given (else NaN).

    ``mean``, ``std`` (sample, N − 1), ``three_sigma`` = 3·std, ``mean_plus_3sigma`` = mean +
    3·std (the bound ISO 9283 uses for repeatability, applied to the errors), ``rms``, ``p95``
    (95th percentile), ``max``; ``bias_xyz_m`` (3,) the mean error vector and ``std_xyz_m`` (3,)
    its per-axis standard deviation; ``bias_abc_rad`` (3,) the mean orientation deviation."""

    n: int
    errors_m: np.ndarray
    mean_m: float
    std_m: float
    three_sigma_m: float
    mean_plus_3sigma_m: float
    rms_m: float
    p95_m: float
    max_m: float
    bias_xyz_m: np.ndarray
    std_xyz_m: np.ndarray
    errors_rad: np.ndarray | None
    mean_rad: float
    std_rad: float
    three_sigma_rad: float
    mean_plus_3sigma_rad: float
    rms_rad: float
    max_rad: float
    bias_abc_rad: np.ndarray | None


def _scalar_stats(e: np.ndarray) -> tuple[float, float, float, float, float, float, float]:
    mean = float(e.mean())
    std = float(_sample_std(e))
    return (
        mean,
        std,
        3.0 * std,
        mean + 3.0 * std,
        float(np.sqrt(np.mean(e**2))),
        float(np.percentile(e, 95)),
        float(e.max()),
    )


def error_statistics(
    p_cmd: np.ndarray, p_meas: np.ndarray, *, R_cmd: np.ndarray | None = None, R_meas: np.ndarray | None = None
) -> ErrorStatistics:
    """Error statistics of single measurements ``p_meas`` (N, 3) m of commands ``p_cmd`` (N, 3),
    orientations ``R_cmd``, ``R_meas`` (N, 3, 3) optional (std and 3σ are NaN for N = 1)."""
    p_cmd, p_meas, delta = _check(p_cmd, p_meas, R_cmd, R_meas)
    ev = p_meas - p_cmd
    e = np.linalg.norm(ev, axis=1)
    mean, std, s3, bound, rms, p95, mx = _scalar_stats(e)
    nan = float("nan")
    if delta is not None:
        a = np.linalg.norm(delta, axis=1)
        am, asd, a3, ab, arms, _, amx = _scalar_stats(a)
        bias_abc = delta.mean(axis=0)
    else:
        a, am, asd, a3, ab, arms, amx, bias_abc = None, nan, nan, nan, nan, nan, nan, None
    return ErrorStatistics(
        n=len(e),
        errors_m=e,
        mean_m=mean,
        std_m=std,
        three_sigma_m=s3,
        mean_plus_3sigma_m=bound,
        rms_m=rms,
        p95_m=p95,
        max_m=mx,
        bias_xyz_m=ev.mean(axis=0),
        std_xyz_m=_sample_std(ev),
        errors_rad=a,
        mean_rad=am,
        std_rad=asd,
        three_sigma_rad=a3,
        mean_plus_3sigma_rad=ab,
        rms_rad=arms,
        max_rad=amx,
        bias_abc_rad=bias_abc,
    )


# --------------------------------------------------------------------------- a model's errors on data


def outside_joint_ranges(q: np.ndarray, ranges: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(N,) bool: the readings ``q`` (N, n) that lie outside the joint ranges ``ranges`` (n, 2), SI
    (an identified model's calibrated region, ``identification.joint_ranges``): there a
    prediction, a compensation or a bound is an extrapolation of what the identification saw."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    r = np.asarray(ranges, dtype=float).reshape(q.shape[1], 2)
    return np.any((q < r[:, 0] - tol) | (q > r[:, 1] + tol), axis=1)


def position_errors(
    model: KinematicModel, q: np.ndarray, p_world: np.ndarray, p_tool: np.ndarray, payload: np.ndarray | None = None
) -> np.ndarray:
    """(N, 3) measured minus predicted positions, m: ``e = p_world − T_world_tool(q) · p_tool``
    (the book's position error, eq. 4.1 with the model as the estimate), ``p_tool`` (3,) or (N, 3);
    ``payload`` (N, 4) per row, which a compliant model sags under."""
    return np.asarray(p_world, float) - points_world(model, q, p_tool, payload)


def registration(
    model: KinematicModel, q: np.ndarray, p_world: np.ndarray, p_tool: np.ndarray, payload: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Where ``model``'s base fits the measured points best, ``T_world_base`` (4, 4), and one common
    tool-frame offset (3,) m of the measured point (``registration.register_points``, as the
    identification registers): a model placed on data whose instrument placement and reflector
    mounting are unknown. Needs at least three non-collinear points; ``payload`` as in
    :func:`position_errors`."""
    w = walk(dataclasses.replace(model, base=np.zeros(6)), q, payload=payload)
    return register_points(w.R, w.p, p_world, np.broadcast_to(np.asarray(p_tool, float), w.p.shape))


def placed_points(
    model: KinematicModel,
    X: np.ndarray,
    c: np.ndarray,
    q: np.ndarray,
    p_tool: np.ndarray,
    payload: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 3) world positions of the tool-frame points ``p_tool`` (3,) or (N, 3) at readings ``q``
    with ``model``'s base at ``X`` and the common offset ``c`` (:func:`registration`)."""
    w = walk(dataclasses.replace(model, base=np.zeros(6)), np.atleast_2d(q), payload=payload)
    pt = np.broadcast_to(np.asarray(p_tool, float), w.p.shape)
    return (w.p + np.einsum("nij,nj->ni", w.R, pt + c)) @ X[:3, :3].T + X[:3, 3]


def registered_errors(
    model: KinematicModel, q: np.ndarray, p_world: np.ndarray, p_tool: np.ndarray, payload: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) errors, m, of ``model`` with its base placed where it fits the data best and one
    common tool-frame offset of the measured point absorbed (:func:`registration`), and that
    offset (3,), m.

    The robot's own inaccuracy apart from where the instrument stands and how the reflector
    sits: what "before" means for a nominal model whose placement in the instrument frame is
    unknown."""
    X, c = registration(model, q, p_world, p_tool, payload)
    return np.asarray(p_world, float) - placed_points(model, X, c, q, p_tool, payload), c


@dataclass(frozen=True)
class NormStatistics:
    """Figures of N error lengths (any one unit): ``rms``, ``mean``, ``max``, ``p95`` (95th
    percentile), ``std`` (sample, N − 1; 0 for one value). All NaN when N = 0."""

    n: int
    rms: float
    mean: float
    max: float
    p95: float
    std: float


def norm_statistics(e: np.ndarray) -> NormStatistics:
    """:class:`NormStatistics` of the lengths ``e`` (N,)."""
    e = np.asarray(e, dtype=float).ravel()
    if len(e) == 0:
        nan = float("nan")
        return NormStatistics(0, nan, nan, nan, nan, nan)
    return NormStatistics(
        n=len(e),
        rms=float(np.sqrt(np.mean(e**2))),
        mean=float(e.mean()),
        max=float(e.max()),
        p95=float(np.percentile(e, 95)),
        std=float(_sample_std(e)) if len(e) > 1 else 0.0,
    )
