"""Circle-point analysis (book §4.6): joint axes from single-joint sweeps, then a model.

One joint moves at a time while a target on the tool is measured (book §4.6.3). A revolute
joint carries the target round a circle whose plane normal through its centre is the joint
axis; a prismatic joint carries it along a line parallel to the axis. From the N axis lines the
link parameters follow by pure geometry (§4.6.5): directly as a ``poe`` model (axis and point
per joint), or as ``dh`` through the common normals (:func:`calibration.conventions.poe_to_dh`,
Sklar's method).

Fitting (what the field does now, not the book's 1991 regressions; see ``docs/cpa.md``):

- plane: total least squares (SVD). Stone's re-framed z-on-xy regression (§4.6.4, eq.
  4.288-4.295) converges to the same plane; :func:`plane_regression` is the book's regression
  (with eq. 4.252 corrected) for reference;
- circle: the algebraic (Kåsa) fit of eq. 4.263-4.271 as the start, refined by geometric least
  squares in 3D (distance of each point to the circle: out of the plane and radially). The Kåsa
  fit shrinks the radius on short arcs, and the book's "re-centring iteration" (eq. 4.296-4.297)
  cannot help: the algebraic fit is translation invariant (ch4b §4);
- line (prismatic joints): the principal axis (SVD), not the two projected regressions of eq.
  4.273-4.280, which break down for lines perpendicular to x;
- the sign of each axis: the positive joint sense. The rows of a sweep are in the order the
  joint moved (contracts §4); where the swept joint's readings change, they decide the sense.

What CPA cannot give (book §4.6 limitation 1, §4.1): the world -> base and last link -> tool
transforms. :func:`circle_point_analysis` takes them from the nominal model — the base from a
rigid registration of the nominal predictions onto the measurements, the tool relative to a
frame on the last axis — and references the joint offsets to the signature configuration
through the joint readings the sweeps carry.

Also here: Stone's S-model (§4.6.5.1, with the corrected eq. 4.304 and 4.320-4.325), and a
simulator of CPA sweeps (:func:`simulate_sweeps`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .conventions import mdh_to_dh, poe_to_dh
from .errors import RecalError
from .geometry import (  # noqa: F401 (the generic fits live in geometry; these names stay importable here)
    METHODS,
    Circle,
    _points,
    fit_circle,
    fit_line,
    fit_plane,
    kasa_circle,
    plane_regression,
)
from .identification import INSTRUMENT_SIGMA_M
from .kinematics import check_q, fk, joint_variables, target_positions, walk
from .model import KinematicModel
from .registration import register_points
from .transforms import homogeneous, invert, matrix_to_pose, pose_to_matrix, rot, rotvec_to_matrix

# Below this distance of the target from the last axis (in the measured or the nominal robot)
# the target's direction is too uncertain to orient the tool about the last axis.
_MIN_TARGET_RADIUS_M = 1e-3


class SweepError(RecalError, ValueError):
    """Sweeps that circle-point analysis cannot use. ``row`` (1-based data row) and ``column``
    say where, when one place is at fault."""

    def __init__(self, message: str, *, row: int | None = None, column: str | None = None):
        self.row, self.column = row, column
        super().__init__(message)


# --------------------------------------------------------------------------- one joint axis


@dataclass(frozen=True, eq=False)
class AxisFit:
    """One joint axis from one sweep, in the measurement (world) frame, SI.

    ``direction`` (3,): unit, in the joint's positive sense. ``point`` (3,): the centre of
    rotation (revolute) or the centroid of the points (prismatic; its lateral position is
    arbitrary, only the direction of a prismatic axis is physical).

    Diagnostics: ``radius_m`` and ``arc_rad`` (revolute; NaN for prismatic), ``travel_m``
    (prismatic; NaN for revolute), ``out_of_plane_rms_m`` (revolute: distance from the plane of
    rotation, the joint's wobble; prismatic: distance from the line), ``circle_rms_m`` (radial
    residuals in the plane; NaN for prismatic), ``noise_m`` (per-axis noise estimated from the
    residuals), ``direction_std_rad`` and ``point_std_m`` (standard uncertainty of the angle
    between the fitted and the true axis, and of the distance between them across the axis: the
    RMS of those two-dimensional errors, from the residual scatter), ``scale``
    (fitted motion per unit of joint variable: 1 when the joint's gain is right; NaN without
    varying readings), ``n_points``, ``method`` and ``warnings``.
    """

    prismatic: bool
    direction: np.ndarray
    point: np.ndarray
    radius_m: float
    arc_rad: float
    travel_m: float
    out_of_plane_rms_m: float
    circle_rms_m: float
    noise_m: float
    direction_std_rad: float
    point_std_m: float
    scale: float
    n_points: int
    method: str
    warnings: tuple[str, ...] = ()


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _sense(progress: np.ndarray, v: np.ndarray | None) -> tuple[float, float]:
    """(+1 or −1, slope of progress per unit joint variable) for a motion ``progress`` (angle
    or distance along the provisional direction, in row order): the readings decide where they
    change, else the order of the rows."""
    if v is not None and np.ptp(v) > 0:
        slope = float(np.polyfit(v, progress, 1)[0])
        if slope != 0:
            return (1.0 if slope > 0 else -1.0), abs(slope)
    total = progress[-1] - progress[0]
    return (1.0 if total >= 0 else -1.0), float("nan")


def fit_axis(
    points: np.ndarray,
    *,
    prismatic: bool = False,
    v: np.ndarray | None = None,
    method: str = "geometric",
    sigma_m: float | None = None,
    min_arc_rad: float = np.pi,
    min_radius_to_noise: float = 1000.0,
) -> AxisFit:
    """The axis of one joint from the target points of its sweep, ``points`` (m, 3) in the order
    the joint moved (book §4.6.4; the sign rule of ch4b §7.5).

    ``v`` (m,): the swept joint's variable at each point (optional): where it changes, the axis
    points in the sense of increasing ``v``; otherwise the joint is taken to have moved in its
    positive sense (book §4.6.3: q_1 ... q_m run from q_min to q_max). ``method``: ``geometric``
    or ``kasa`` (:func:`fit_circle`). ``sigma_m``: the instrument's noise, for the warnings (the
    residuals' own estimate is used when larger).

    Warnings: an arc under ``min_arc_rad`` (book: "at least half a circle", §4.6.3), a radius
    (or a prismatic travel) under ``min_radius_to_noise`` times the noise (Stone's first
    assumption: the noise orders of magnitude below the radius, §4.6.4).
    """
    P = _points(points, 2 if prismatic else 3)
    if v is not None:
        v = np.asarray(v, dtype=float).reshape(len(P))
    floor = float(sigma_m) if sigma_m is not None else 0.0
    if prismatic:
        return _fit_prismatic_axis(P, v, floor, min_radius_to_noise)
    return _fit_revolute_axis(P, v, method, floor, min_arc_rad, min_radius_to_noise)


def _fit_revolute_axis(
    P: np.ndarray, v: np.ndarray | None, method: str, floor: float, min_arc_rad: float, min_radius_to_noise: float
) -> AxisFit:
    """:func:`fit_axis` of a revolute joint: the normal through the centre of the circle fitted
    to the sweep's points ``P`` (m, 3) (book §4.6.4), signed by the joint's positive sense, with
    the noise from the 2m − 6 degrees of freedom left by the circle's six parameters."""
    warnings: list[str] = []
    m = len(P)
    circ = fit_circle(P, method=method)
    n = circ.normal
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    d = P - circ.centre
    angle = np.unwrap(np.arctan2(d @ w, d @ u))
    sign, slope = _sense(angle, v)
    n, angle = sign * n, sign * angle
    arc = float(min(np.ptp(angle), 2 * np.pi))
    dof = 2 * m - 6
    sq = circ.out_of_plane @ circ.out_of_plane + circ.radial @ circ.radial
    noise = float(np.sqrt(sq / dof)) if dof > 0 else 0.0
    point_std, direction_std = _circle_axis_std(circ.covariance, n)
    if arc < min_arc_rad:
        warnings.append(
            f"arc of {np.rad2deg(arc):.0f} deg is under {np.rad2deg(min_arc_rad):.0f} deg: the axis is "
            f"poorly determined (the book asks for at least half a circle, §4.6.3)"
        )
    ref = max(noise, floor)
    if ref > 0 and circ.radius < min_radius_to_noise * ref:
        warnings.append(
            f"radius is only {circ.radius / ref:.0f} times the noise (at least {min_radius_to_noise:.0f} "
            f"wanted): move the other joints so that the target swings wider"
        )
    return AxisFit(
        False,
        n,
        circ.centre,
        circ.radius,
        arc,
        float("nan"),
        _rms(circ.out_of_plane),
        _rms(circ.radial),
        noise,
        direction_std,
        point_std,
        slope,
        m,
        circ.method,
        tuple(warnings),
    )


def _circle_axis_std(cov: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """(point_std_m, direction_std_rad) of a circle's axis from the fit's covariance ``cov``
    (centre (3) then the normal's two tilts first): the RMS of the distance across the axis
    ``sqrt(tr(P_n Σ_c P_n))``, ``P_n = I − n nᵀ``, and of the angle ``sqrt(tr Σ_tilt)``; NaN
    when the covariance is not finite."""
    if np.all(np.isfinite(cov)):
        Pn = np.eye(3) - np.outer(n, n)
        # the RMS of the angle (and of the distance across the axis) between the fitted and the
        # true axis: both errors are two-dimensional, so the trace, not the largest principal
        # variance, which made the angle's standard uncertainty up to √2 too small (issue 14)
        point_std = float(np.sqrt(max(np.trace(Pn @ cov[:3, :3] @ Pn), 0.0)))
        direction_std = float(np.sqrt(max(np.trace(cov[3:5, 3:5]), 0.0)))
    else:
        point_std = direction_std = float("nan")
    return point_std, direction_std


def _fit_prismatic_axis(P: np.ndarray, v: np.ndarray | None, floor: float, min_radius_to_noise: float) -> AxisFit:
    """:func:`fit_axis` of a prismatic joint: a line through the sweep's points ``P`` (m, 3)."""
    warnings: list[str] = []
    m = len(P)
    c, s, rms = fit_line(P)
    t = (P - c) @ s
    sign, slope = _sense(t, v)
    s, t = sign * s, sign * t
    off = (P - c) - np.outer(t, s)
    dof = max(2 * m - 4, 1)
    noise = float(np.sqrt(np.sum(off**2) / dof))
    spread = float(np.sqrt(np.sum((t - t.mean()) ** 2)))
    travel = float(np.ptp(t))
    ref = max(noise, floor)
    if ref > 0 and travel < min_radius_to_noise * ref:
        warnings.append(
            f"travel is only {travel / ref:.0f} times the noise (at least {min_radius_to_noise:.0f} "
            f"wanted): the axis direction is poorly determined"
        )
    return AxisFit(
        True,
        s,
        c,
        float("nan"),
        float("nan"),
        travel,
        rms,
        float("nan"),
        noise,
        noise / spread if spread > 0 else float("inf"),
        noise / np.sqrt(m),
        slope,
        m,
        "line",
        tuple(warnings),
    )


def combine_axes(fits: list[AxisFit]) -> AxisFit:
    """One axis from several fits of the same joint (several targets measured in one sweep):
    directions and points averaged with weights from their uncertainties; diagnostics the
    worst (largest residuals, smallest radius and arc) of the parts."""
    if len(fits) == 1:
        return fits[0]

    def weights(std):
        s = np.array(std, dtype=float)
        ok = np.isfinite(s) & (s > 0)
        return np.where(ok, 1.0 / np.where(ok, s, 1.0) ** 2, 1.0) if np.any(ok) else np.ones(len(s))

    wd = weights([f.direction_std_rad for f in fits])
    wp = weights([f.point_std_m for f in fits])
    ref = fits[0].direction
    dirs = np.array([f.direction if f.direction @ ref >= 0 else -f.direction for f in fits])
    s = (wd[:, None] * dirs).sum(axis=0)
    s /= np.linalg.norm(s)
    point = (wp[:, None] * np.array([f.point for f in fits])).sum(axis=0) / wp.sum()

    def comb(std):
        std = np.array(std, dtype=float)
        return float(1.0 / np.sqrt(np.sum(1.0 / std**2))) if np.all(np.isfinite(std) & (std > 0)) else float("nan")

    return AxisFit(
        fits[0].prismatic,
        s,
        point,
        min(f.radius_m for f in fits),
        min(f.arc_rad for f in fits),
        min(f.travel_m for f in fits),
        max(f.out_of_plane_rms_m for f in fits),
        max(f.circle_rms_m for f in fits),
        max(f.noise_m for f in fits),
        comb([f.direction_std_rad for f in fits]),
        comb([f.point_std_m for f in fits]),
        float(np.nanmean([f.scale for f in fits])) if any(np.isfinite(f.scale) for f in fits) else float("nan"),
        sum(f.n_points for f in fits),
        fits[0].method,
        tuple(dict.fromkeys(w for f in fits for w in f.warnings)),
    )


# --------------------------------------------------------------------------- axis lines of a model


def _unit_readings(model: KinematicModel) -> KinematicModel:
    """The same robot with readings equal to joint variables (no coupling, gains, harmonics)."""
    return dataclasses.replace(
        model, coupling=None, joints=tuple(dataclasses.replace(j, gain=1.0, harmonic=None) for j in model.joints)
    )


def _axis_key(j) -> str:
    return f"{j.name}.theta" if j.revolute else f"{j.name}.d"


def axis_lines(model: KinematicModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint axes of ``model`` at readings ``q`` (N, n) in its world frame: unit directions
    (N, n, 3) in each joint's positive sense and a point on each (N, n, 3), m."""
    keys = [_axis_key(j) for j in model.joints]
    w = walk(model, check_q(model, q), set(keys))
    return (
        np.stack([np.array(w.axes[k][0]) for k in keys], axis=1),
        np.stack([np.array(w.axes[k][1]) for k in keys], axis=1),
    )


def _screw(s: np.ndarray, r: np.ndarray, amount: float, prismatic: bool) -> np.ndarray:
    """The motion (4, 4) of a joint: rotation by ``amount`` about the line (``r``, ``s``), or a
    translation by ``amount`` along ``s``."""
    if prismatic:
        return homogeneous(np.eye(3), amount * s)
    R = rotvec_to_matrix(amount * s)
    return homogeneous(R, r - R @ r)


def _move_line(T: np.ndarray, s: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, :3] @ s, T[:3, :3] @ r + T[:3, 3]


# --------------------------------------------------------------------------- Stone's S-model


def s_model_transform(beta: float, d: float, a: float, alpha: float, b: float, gamma: float) -> np.ndarray:
    """Stone's S-model link transform (book eq. 4.304, corrected): ``Rz(β)·Tz(d)·Tx(a)·Rx(α)·
    Tz(b)·Rz(γ)``. The printed 4.304 lacks ``Tz(b)`` and writes ``R(z, y_i)`` for ``Rz(γ)``."""
    T = homogeneous(rot(2, beta), np.array([0.0, 0.0, d]))
    T = T @ homogeneous(rot(0, alpha), np.array([a, 0.0, 0.0]))
    return T @ homogeneous(rot(2, gamma), np.array([0.0, 0.0, b]))


def s_model_parameters(B: np.ndarray, *, eps: float = 1e-12) -> tuple[float, float, float, float, float, float]:
    """``(β, d, a, α, b, γ)`` of an S-model link transform ``B`` (4, 4): book eq. 4.320-4.325,
    corrected (ch4b §9.3): ``β = atan2(a_x, −a_y)``, ``α = atan2(sqrt(a_x² + a_y²), a_z)``,
    ``γ = atan2(n_z, a_x n_y − a_y n_x)``, ``b = (p_x sβ − p_y cβ)/sα`` (the printed 4.321 lacks
    the square root, 4.322 loses the sign of γ, 4.324 has the wrong sign), ``a = p_x cβ + p_y sβ``,
    ``d = p_z − b cα``; α in [0, π]. Parallel consecutive axes (sα = 0) leave β, γ and b, d
    coupled: β = b = 0 is taken."""
    B = np.asarray(B, dtype=float)
    n, a_, p = B[:3, 0], B[:3, 2], B[:3, 3]
    s_alpha = float(np.hypot(a_[0], a_[1]))
    if s_alpha > eps:
        beta = float(np.arctan2(a_[0], -a_[1]))
        alpha = float(np.arctan2(s_alpha, a_[2]))
        gamma = float(np.arctan2(n[2], a_[0] * n[1] - a_[1] * n[0]))
        b = float((p[0] * np.sin(beta) - p[1] * np.cos(beta)) / s_alpha)
    else:
        beta, b = 0.0, 0.0
        alpha = 0.0 if a_[2] > 0 else float(np.pi)
        gamma = float(np.arctan2(n[1], n[0]) if a_[2] > 0 else -np.arctan2(n[1], n[0]))
    a = float(p[0] * np.cos(beta) + p[1] * np.sin(beta))
    d = float(p[2] - b * np.cos(alpha))
    return beta, d, a, alpha, b, gamma


def stone_frames(directions: np.ndarray, points: np.ndarray, first_points: np.ndarray) -> np.ndarray:
    """Stone's frames on the identified axes (book eq. 4.299-4.300): frame j (4, 4) has z along
    axis j, its origin at the axis point (the centre of rotation), and x towards the first
    target point of joint j's sweep projected onto the plane of rotation. (n, 4, 4)."""
    out = []
    for s, r, p in zip(np.asarray(directions, float), np.asarray(points, float), np.asarray(first_points, float)):
        s = s / np.linalg.norm(s)
        x = (p - r) - s * (s @ (p - r))
        nx = np.linalg.norm(x)
        if not nx > 0:
            raise ValueError("a first point lies on its axis: the x direction of Stone's frame is undefined")
        x /= nx
        out.append(homogeneous(np.column_stack([x, np.cross(s, x), s]), r))
    return np.array(out)


def s_model_chain(frames: np.ndarray) -> list[tuple[float, float, float, float, float, float]]:
    """S-model parameters of each link between consecutive frames: ``B_j = S_(j-1)⁻¹ S_j``
    (book eq. 4.302) through :func:`s_model_parameters`."""
    F = np.asarray(frames, dtype=float)
    return [s_model_parameters(invert(F[k - 1]) @ F[k]) for k in range(1, len(F))]


# --------------------------------------------------------------------------- sweeps and the model


@dataclass(frozen=True, eq=False, init=False)
class Sweeps:
    """Circle-point data (contracts §4), SI. ``q`` (M, n) joint readings; ``p_world`` (M, 3)
    measured target positions; ``joint`` (M,) the swept joint of each row, 0-based; ``target``
    (M,) target names (``None``: the tool origin); ``row`` (M,) row numbers in the source file.
    Rows of one sweep are in the order the joint moved.

    ``target`` and ``row`` may be left out when built (no names: the tool origin; rows 1..M),
    so once built they are always arrays: the constructor is written out for that."""

    q: np.ndarray
    p_world: np.ndarray
    joint: np.ndarray
    target: np.ndarray
    row: np.ndarray

    def __init__(
        self,
        q: np.ndarray,
        p_world: np.ndarray,
        joint: np.ndarray,
        target: np.ndarray | None = None,
        row: np.ndarray | None = None,
    ):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        M = q.shape[0]
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "p_world", np.asarray(p_world, dtype=float).reshape(M, 3))
        object.__setattr__(self, "joint", np.asarray(joint).reshape(M).astype(int))
        t = np.full(M, None, dtype=object) if target is None else np.asarray(target, dtype=object).reshape(M)
        names = [None if (x is None or x == "") else str(x) for x in t]
        object.__setattr__(self, "target", np.array(names, dtype=object))
        object.__setattr__(self, "row", np.arange(1, M + 1) if row is None else np.asarray(row).reshape(M))

    def __len__(self) -> int:
        return self.q.shape[0]


@dataclass(frozen=True, eq=False)
class CPAResult:
    """Everything :func:`circle_point_analysis` did. Lines and frames in the measurement (world)
    frame, SI.

    ``model``: the model in the requested convention; ``model_poe``: the same robot in ``poe``
    form. ``axes``: per joint the combined :class:`AxisFit` (``None``: not swept, the
    registered nominal axis was used); ``fits``: per joint, per target (name -> fit).
    ``directions``, ``points`` (n, 3): the axes at the signature configuration, whose joint
    variables are ``signature_v`` (n,) and readings ``signature_q`` (n,). ``T_world_base``
    (4, 4): the rigid registration of the nominal model onto the data, ``registration_rms_m``
    its residual. ``nominal_tilt_rad``, ``nominal_offset_m`` (n,): how far each axis lies from
    the registered nominal one (angle; distance at the fitted point). ``target_changes``: target
    name (``None``: the tool origin) -> change (3,) m in the tool frame made to match the target
    measured at the signature.
    """

    model: KinematicModel
    model_poe: KinematicModel
    axes: tuple[AxisFit | None, ...]
    fits: tuple[dict, ...]
    directions: np.ndarray
    points: np.ndarray
    signature_v: np.ndarray
    signature_q: np.ndarray
    T_world_base: np.ndarray
    registration_rms_m: float
    nominal_tilt_rad: np.ndarray
    nominal_offset_m: np.ndarray
    target_changes: dict
    warnings: tuple[str, ...]
    notes: tuple[str, ...]
    success: bool
    message: str
    settings: dict = field(default_factory=dict)


def _rows_text(rows: np.ndarray) -> str:
    return f"rows {int(rows[0])}-{int(rows[-1])}" if len(rows) > 1 else f"row {int(rows[0])}"


def _check_sweeps(model: KinematicModel, sw: Sweeps, v: np.ndarray, tol: np.ndarray, min_points: int):
    """Per swept joint: its row indices and the (median) joint variables held during the sweep."""
    n = model.n_joints
    bad = np.nonzero((sw.joint < 0) | (sw.joint >= n))[0]
    if len(bad):
        k = int(bad[0])
        raise SweepError(
            f"joint {int(sw.joint[k]) + 1} does not exist: the model has joints 1..{n}",
            row=int(sw.row[k]),
            column="joint",
        )
    groups: dict[int, np.ndarray] = {}
    held: dict[int, np.ndarray] = {}
    for j in sorted(set(sw.joint.tolist())):
        idx = np.nonzero(sw.joint == j)[0]
        rows = sw.row[idx]
        for t in dict.fromkeys(sw.target[idx].tolist()):
            sub = idx[np.array([x == t for x in sw.target[idx]])]
            need = 2 if not model.joints[j].revolute else min_points
            if len(sub) < need:
                what = f" of target {t!r}" if t is not None else ""
                raise SweepError(
                    f"the sweep of joint {j + 1} has {len(sub)} points{what} ({_rows_text(sw.row[sub])}); "
                    f"at least {need} are needed",
                    row=int(sw.row[sub[0]]),
                    column="joint",
                )
        med = np.median(v[idx], axis=0)
        for k in range(n):
            if k == j:
                continue
            dev = np.abs(v[idx, k] - med[k])
            if np.any(dev > tol[k]):
                r = int(rows[int(np.argmax(dev > tol[k]))])
                raise SweepError(
                    f"joint {k + 1} moves during the sweep of joint {j + 1} ({_rows_text(rows)}): "
                    f"only the swept joint may move",
                    row=r,
                    column=f"q{k + 1}",
                )
        if not np.ptp(v[idx, j]) > tol[j]:
            raise SweepError(
                f"the reading of joint {j + 1} does not change during its sweep ({_rows_text(rows)}): "
                f"the swept joint's readings are needed (contracts §4)",
                row=int(rows[0]),
                column=f"q{j + 1}",
            )
        groups[j], held[j] = idx, med
    return groups, held


def _signature(n: int, held: dict[int, np.ndarray], groups: dict[int, np.ndarray], v: np.ndarray) -> np.ndarray:
    """The signature configuration (joint variables): joint k at the median of the values it
    was held at during the sweeps of the joints after it (which its value moves), else of the
    joints before it, else the middle of its own sweep."""
    vs = np.zeros(n)
    for k in range(n):
        later = [held[j][k] for j in held if j > k]
        earlier = [held[j][k] for j in held if j < k]
        if later or earlier:
            vs[k] = float(np.median(later or earlier))
        elif k in groups:
            vs[k] = float(np.median(v[groups[k], k]))
    return vs


def _frame_on_line(s: np.ndarray, r: np.ndarray, p: np.ndarray, x_hint: np.ndarray, use_target: bool) -> np.ndarray:
    """A frame (4, 4): z along ``s``, origin the point of the line nearest ``p``, x towards
    ``p`` (``use_target``) or along ``x_hint`` made perpendicular to ``s``."""
    o = r + s * (s @ (p - r))
    x = (p - o) if use_target else np.asarray(x_hint, dtype=float)
    x = x - s * (s @ x)
    if not np.linalg.norm(x) > 1e-12:
        x = np.eye(3)[int(np.argmin(np.abs(s)))]
        x = x - s * (s @ x)
    x /= np.linalg.norm(x)
    return homogeneous(np.column_stack([x, np.cross(s, x), s]), o)


def _rows_of(sweeps: Sweeps, idx: np.ndarray, target) -> np.ndarray:
    """The indices among ``idx`` of the rows that measured ``target``."""
    return idx[np.array([x == target for x in sweeps.target[idx]])]


def _fit_sweeps(nominal: KinematicModel, sweeps: Sweeps, groups: dict, v: np.ndarray, **fit_kw):
    """Step 1: each swept joint's axis where it was measured (one fit per target, combined),
    the fits per joint and target, and the fits' warnings."""
    measured: dict[int, AxisFit] = {}
    fits: list[dict] = [dict() for _ in range(nominal.n_joints)]
    warnings: list[str] = []
    for j, idx in groups.items():
        name = nominal.joints[j].name
        for t in dict.fromkeys(sweeps.target[idx].tolist()):
            sub = _rows_of(sweeps, idx, t)
            try:
                f = fit_axis(sweeps.p_world[sub], prismatic=not nominal.joints[j].revolute, v=v[sub, j], **fit_kw)
            except ValueError as exc:
                raise SweepError(
                    f"the sweep of joint {j + 1} ({_rows_text(sweeps.row[sub])}): {exc}", row=int(sweeps.row[sub[0]])
                ) from None
            fits[j][t] = f
            warnings += [f"joint {j + 1} ({name}){'' if t is None else f', target {t}'}: {w}" for w in f.warnings]
        measured[j] = combine_axes(list(fits[j].values()))
    return measured, fits, warnings


def _axes_at_signature(
    nominal: KinematicModel, sweeps: Sweeps, groups: dict, held: dict, measured: dict, vs: np.ndarray, tol: np.ndarray
):
    """Step 2: the measured axes (n, 3) directions and points at the signature, and per joint
    the transform that took its sweep there. Axis j measured with earlier joints away from the
    signature by Δ is moved back by ``[E_1(Δ_1)···E_(j−1)(Δ_(j−1))]⁻¹``, ``E_k`` the motion
    about the (already moved back) axis k (book §4.6.3, sequence B)."""
    n = nominal.n_joints
    S, R = np.zeros((n, 3)), np.zeros((n, 3))
    moved: dict[int, np.ndarray] = {}
    notes: list[str] = []
    for j in sorted(measured):
        T = np.eye(4)
        for k in range(j):
            delta = held[j][k] - vs[k]
            if abs(delta) <= tol[k]:
                continue
            if k not in measured:
                raise SweepError(
                    f"joint {k + 1} was held away from the signature during the sweep of joint {j + 1}, "
                    f"and joint {k + 1} was not swept, so that axis cannot be moved back",
                    row=int(sweeps.row[groups[j][0]]),
                    column=f"q{k + 1}",
                )
            T = T @ _screw(S[k], R[k], delta, not nominal.joints[k].revolute)
        if not np.array_equal(T, np.eye(4)):
            notes.append(
                f"joint {j + 1}: measured with earlier joints away from the signature; its axis was moved back"
            )
        moved[j] = invert(T)
        S[j], R[j] = _move_line(moved[j], measured[j].direction, measured[j].point)
    return S, R, moved, notes


def _registration(nominal: KinematicModel, sweeps: Sweeps) -> tuple[np.ndarray, float]:
    """Step 3: ``T_world_base`` (4, 4) by rigid registration of the nominal model's predictions
    of every sweep row onto the measurements (with a common reflector-offset correction), and
    the RMS of what is left, m."""
    wk = walk(dataclasses.replace(nominal, base=np.zeros(6)), sweeps.q)
    p_tool = np.array([nominal.target(t) for t in sweeps.target])
    T_wb, _ = register_points(wk.R, wk.p, sweeps.p_world, p_tool)
    pred = (wk.p + np.einsum("nij,nj->ni", wk.R, p_tool)) @ T_wb[:3, :3].T + T_wb[:3, 3]
    return T_wb, float(np.sqrt(np.mean(np.sum((pred - sweeps.p_world) ** 2, axis=1))))


def _target_at_signature(
    sweeps: Sweeps, rows: np.ndarray, fit: AxisFit, v: np.ndarray, j: int, vs_j: float, moved: np.ndarray
) -> np.ndarray:
    """Where the target of joint ``j``'s sweep ``rows`` is at the signature: every point taken
    along the fitted axis by ``vs_j − v_i`` (the readings), averaged, then moved with the
    axis to the signature."""
    pts = [
        _screw(fit.direction, fit.point, vs_j - v[i, j], fit.prismatic) @ np.append(sweeps.p_world[i], 1.0)
        for i in rows
    ]
    p = np.mean(pts, axis=0)[:3]
    return moved[:3, :3] @ p + moved[:3, 3]


def _flange_at_signature(
    nominal: KinematicModel,
    sweeps: Sweeps,
    groups: dict[int, np.ndarray],
    fits: list[dict],
    moved: dict[int, np.ndarray],
    v: np.ndarray,
    vs: np.ndarray,
    S: np.ndarray,
    R: np.ndarray,
    T_wb: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, dict, dict, list[str], list[str]]:
    """Step 4: the flange ``T_world_flange`` (4, 4) at the signature, the tool (4, 4), the
    targets (tool frame) and their changes, notes and warnings.

    The nominal flange is placed relative to a frame on the measured last axis (origin at the
    target's foot, x towards the target; or along the registered nominal flange x when the
    target is within ``_MIN_TARGET_RADIUS_M`` of the axis). Then each target measured in the
    last sweep gets the offset that puts it where it was measured (the tool origin first:
    named targets ride on it)."""
    last = nominal.n_joints - 1
    unit_local = dataclasses.replace(_unit_readings(nominal), base=np.zeros(6))
    S_nom, R_nom = (a[0] for a in axis_lines(unit_local, vs))
    T_fl_nom = fk(dataclasses.replace(unit_local, tool=np.zeros(6)), vs)[0]  # in the nominal base frame
    tool = pose_to_matrix(nominal.tool)
    targets = {k: np.array(p) for k, p in nominal.targets.items()}
    if last not in groups:
        return (
            T_wb @ T_fl_nom,
            tool,
            targets,
            {},
            [],
            ["the last joint was not swept: the flange is the registered nominal one"],
        )
    seen = {
        t: _target_at_signature(sweeps, _rows_of(sweeps, groups[last], t), f, v, last, vs[last], moved[last])
        for t, f in fits[last].items()
    }
    revolute = nominal.joints[last].revolute
    primary = max(seen, key=lambda t: fits[last][t].radius_m if revolute else 0.0)
    p_nom = T_fl_nom[:3, :3] @ (tool[:3, :3] @ nominal.target(primary) + tool[:3, 3]) + T_fl_nom[:3, 3]
    radii = (
        np.linalg.norm(np.cross(p_nom - R_nom[last], S_nom[last])),
        np.linalg.norm(np.cross(seen[primary] - R[last], S[last])),
    )
    use_target = bool(revolute and min(radii) > _MIN_TARGET_RADIUS_M)
    F_nom = _frame_on_line(S_nom[last], R_nom[last], p_nom, T_fl_nom[:3, 0], use_target)
    F_cpa = _frame_on_line(S[last], R[last], seen[primary], T_wb[:3, :3] @ T_fl_nom[:3, 0], use_target)
    T_fl = F_cpa @ invert(F_nom) @ T_fl_nom
    notes = [] if use_target else ["the tool's orientation about the last axis comes from the registered nominal model"]
    changes: dict = {}
    for t in sorted(seen, key=lambda x: x is not None):
        T_tool = T_fl @ tool
        p_t = nominal.target(t)
        changes[t] = T_tool[:3, :3].T @ (seen[t] - (T_tool[:3, :3] @ p_t + T_tool[:3, 3]))
        if t is None:
            tool = tool @ homogeneous(np.eye(3), changes[t])
        else:
            targets[t] = p_t + changes[t]
    return T_fl, tool, targets, changes, notes, []


def _zero_reference_model(nominal, S, R, vs, T_wb, T_fl, tool, targets) -> KinematicModel:
    """Step 5: the ``poe`` model. Axes at the zero of ``offset + v`` (the nominal ``poe``
    offsets, else 0) are the signature axes moved by ``E_1(δ_1)···E_(k−1)(δ_(k−1))``,
    ``δ_i = −offset_i − v_i^sig``; ``home = base⁻¹ · E_1(δ_1)···E_n(δ_n) · T_flange^sig``."""
    offsets = [(j.theta if j.revolute else j.d) if nominal.convention == "poe" else 0.0 for j in nominal.joints]
    T_bw = invert(T_wb)
    G = np.eye(4)
    joints = []
    for k, j in enumerate(nominal.joints):
        s_b, r_b = _move_line(T_bw @ G, S[k], R[k])
        offset = dict(theta=offsets[k]) if j.revolute else dict(theta=0.0, d=offsets[k])
        joints.append(
            dataclasses.replace(j, axis=s_b / np.linalg.norm(s_b), point=r_b, a=0.0, alpha=0.0, beta=None, **offset)
        )
        G = G @ _screw(S[k], R[k], -offsets[k] - vs[k], not j.revolute)
    return dataclasses.replace(
        nominal,
        name=f"{nominal.name}-cpa",
        convention="poe",
        joints=tuple(joints),
        base=matrix_to_pose(T_wb),
        home=matrix_to_pose(T_bw @ G @ T_fl),
        tool=matrix_to_pose(tool),
        targets=targets,
        metadata={},
    )


def circle_point_analysis(
    nominal: KinematicModel,
    sweeps: Sweeps,
    *,
    method: str = "geometric",
    convention: str | None = None,
    sigma_m: float | None = None,
    min_arc_rad: float = np.pi,
    min_radius_to_noise: float = 1000.0,
    min_points: int = 4,
    held_tol_rad: float = 1e-4,
    held_tol_m: float = 1e-5,
    parallel_tol_rad: float = np.deg2rad(5.0),
) -> CPAResult:
    """Joint axes from circle-point sweeps, then a model (book §4.6).

    1. Each joint's sweep (the rows naming it, every other joint variable held within
       ``held_tol_rad`` / ``held_tol_m``) gives its axis (:func:`fit_axis` with ``method``,
       ``sigma_m``, ``min_arc_rad``, ``min_radius_to_noise``; several targets in one sweep
       are fitted apart and combined).
    2. The signature configuration is where the joints were held (joint k: the median of its
       values during the sweeps of later joints). An axis measured with earlier joints
       elsewhere is moved back to the signature by the already identified earlier axes and
       the joint readings (book §4.6.3, sequence B).
    3. The nominal model is registered rigidly onto the measured points (base = instrument ->
       robot base). CPA cannot see the base (§4.6 limitation 1), so this only decides where the
       model's base frame sits; the axes are what was measured.
    4. The flange: the nominal flange relative to a frame on the last axis, placed on the
       measured last axis; the offsets of the targets measured in the last sweep are corrected
       to put them where they were measured (their distance from the last axis is measured;
       the tool's orientation about a point is not, and stays nominal).
    5. ``poe`` model: each axis (direction, point) at the zero of the joint variables, found by
       moving the signature axes back with the readings; the nominal ``poe`` offsets are kept.
    6. ``dh`` model (``convention``; default unless the nominal is ``poe``): :func:`poe_to_dh`
       with the nominal as reference (common normals, Hayati's form for axes parallel within
       ``parallel_tol_rad``). Joint offsets are thereby referenced to the signature readings:
       determined for joints 2..n-1; joints 1 and n share theirs with the base and tool.

    Joints not swept keep their registered nominal axes (with a warning, and ``success``
    False). Raises :class:`SweepError` for sweeps that cannot be used (a joint that does not
    exist, too few points, another joint moving, the swept joint's reading not changing,
    collinear points), ``ValueError`` for other bad input.
    """
    convention, q = _check_cpa_input(nominal, sweeps, method, convention)
    settings = dict(
        method=method,
        convention=convention,
        sigma_m=sigma_m,
        min_arc_rad=min_arc_rad,
        min_radius_to_noise=min_radius_to_noise,
        min_points=min_points,
        held_tol_rad=held_tol_rad,
        held_tol_m=held_tol_m,
        parallel_tol_rad=parallel_tol_rad,
    )
    axes = _signature_axes(nominal, sweeps, q, settings)
    return _model_from_axes(nominal, sweeps, axes, settings)


@dataclass(frozen=True, eq=False)
class _SignatureAxes:
    """Steps 1-2 of :func:`circle_point_analysis`: ``v`` (M, n) the joint variables of the rows,
    ``vs`` (n,) the signature's; ``groups``/``held`` per swept joint its rows and the variables
    held; ``measured``/``fits`` the axis fits; ``S``, ``R`` (n, 3) the axes at the signature
    (zero rows for joints not swept) and ``moved`` per joint the transform that took them there."""

    v: np.ndarray
    vs: np.ndarray
    groups: dict[int, np.ndarray]
    measured: dict[int, AxisFit]
    fits: list[dict]
    S: np.ndarray
    R: np.ndarray
    moved: dict[int, np.ndarray]
    warnings: list[str]
    notes: list[str]


def _signature_axes(nominal: KinematicModel, sweeps: Sweeps, q: np.ndarray, settings: dict) -> _SignatureAxes:
    """Steps 1-2 of :func:`circle_point_analysis`: the sweeps checked, each swept joint's axis
    fitted (:func:`_fit_sweeps`) and moved to the signature configuration
    (:func:`_axes_at_signature`)."""
    n = nominal.n_joints
    v = joint_variables(nominal, q)
    tol = np.array([settings["held_tol_rad"] if j.revolute else settings["held_tol_m"] for j in nominal.joints])
    groups, held = _check_sweeps(nominal, sweeps, v, tol, settings["min_points"])
    vs = _signature(n, held, groups, v)

    measured, fits, warnings = _fit_sweeps(
        nominal,
        sweeps,
        groups,
        v,
        method=settings["method"],
        sigma_m=settings["sigma_m"],
        min_arc_rad=settings["min_arc_rad"],
        min_radius_to_noise=settings["min_radius_to_noise"],
    )
    S, R, moved, notes = _axes_at_signature(nominal, sweeps, groups, held, measured, vs, tol)
    return _SignatureAxes(v, vs, groups, measured, fits, S, R, moved, warnings, notes)


def _model_from_axes(nominal: KinematicModel, sweeps: Sweeps, axes: _SignatureAxes, settings: dict) -> CPAResult:
    """Steps 3-6 of :func:`circle_point_analysis`: the base registered, the axes compared with
    the nominal's, the flange placed, the model at the zero of the joint variables and in the
    requested convention."""
    n = nominal.n_joints
    measured, S, R, vs = axes.measured, axes.S, axes.R, axes.vs
    warnings, notes = axes.warnings, axes.notes
    T_wb, reg_rms = _registration(nominal, sweeps)
    S_nom, R_nom = (
        a[0] for a in axis_lines(dataclasses.replace(_unit_readings(nominal), base=matrix_to_pose(T_wb)), vs)
    )
    tilt, offset = _against_nominal(nominal, measured, S, R, S_nom, R_nom, warnings)
    T_fl, tool, targets, changes, flange_notes, flange_warnings = _flange_at_signature(
        nominal, sweeps, axes.groups, axes.fits, axes.moved, axes.v, vs, S, R, T_wb
    )
    notes += flange_notes
    warnings += flange_warnings
    model_poe = _zero_reference_model(nominal, S, R, vs, T_wb, T_fl, tool, targets)
    model = _in_convention(model_poe, nominal, settings["convention"], settings["parallel_tol_rad"], notes)
    message = f"{len(measured)} of {n} axes identified from {len(sweeps)} points" + (
        f"; {len(warnings)} warnings" if warnings else ""
    )
    return CPAResult(
        model=model,
        model_poe=model_poe,
        axes=tuple(measured.get(j) for j in range(n)),
        fits=tuple(axes.fits),
        directions=S,
        points=R,
        signature_v=vs,
        signature_q=np.linalg.solve(nominal.coupling_matrix, vs),
        T_world_base=T_wb,
        registration_rms_m=reg_rms,
        nominal_tilt_rad=tilt,
        nominal_offset_m=offset,
        target_changes=changes,
        warnings=tuple(warnings),
        notes=tuple(notes),
        success=len(measured) == n,
        message=message,
        settings=settings,
    )


def _check_cpa_input(nominal: KinematicModel, sweeps: Sweeps, method: str, convention: str | None):
    """:func:`circle_point_analysis`'s arguments checked: the convention to write (default: ``poe``
    for a ``poe`` nominal, else ``dh``) and the joint readings."""
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {', '.join(METHODS)}; got {method!r}")
    convention = convention or ("poe" if nominal.convention == "poe" else "dh")
    if convention not in ("poe", "dh"):
        raise ValueError(f"`convention` must be poe or dh; got {convention!r}")
    q = check_q(nominal, sweeps.q)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(sweeps.p_world))):
        raise ValueError("joint readings and positions must be finite")
    for t in set(sweeps.target.tolist()) - {None}:
        try:
            nominal.target(t)
        except KeyError as exc:
            raise ValueError(str(exc).strip("'\"")) from None
    return convention, q


def _against_nominal(nominal, measured, S, R, S_nom, R_nom, warnings: list[str]):
    """The joints not swept take their registered nominal axes (in place, with a warning); then
    each axis's tilt (rad) and offset (m, revolute joints) from the nominal's."""
    n = nominal.n_joints
    for j in sorted(set(range(n)) - set(measured)):
        S[j], R[j] = S_nom[j], R_nom[j]
        warnings.append(
            f"joint {j + 1} ({nominal.joints[j].name}) was not swept: its axis is the registered nominal one"
        )
    tilt = np.arctan2(np.linalg.norm(np.cross(S, S_nom), axis=1), np.sum(S * S_nom, axis=1))
    offset = np.array(
        [
            np.linalg.norm(np.cross(R[j] - R_nom[j], S_nom[j])) if j_.revolute else 0.0
            for j, j_ in enumerate(nominal.joints)
        ]
    )
    return tilt, offset


def _in_convention(model_poe, nominal, convention: str, parallel_tol_rad: float, notes: list[str]):
    """The ``poe`` model of :func:`circle_point_analysis` in ``convention`` (``dh``:
    :func:`poe_to_dh` with the nominal as reference)."""
    if convention != "dh":
        return model_poe
    reference = nominal
    if nominal.convention == "mdh" and not any(j.hayati for j in nominal.joints):
        reference = mdh_to_dh(nominal)
    model = poe_to_dh(model_poe, reference=reference, parallel_tol_rad=parallel_tol_rad)
    if nominal.convention != "dh":
        notes.append(f"written in dh (the nominal model is {nominal.convention})")
    return model


# --------------------------------------------------------------------------- simulation


def simulate_sweeps(
    truth: KinematicModel,
    signature_q: np.ndarray,
    rng: np.random.Generator,
    *,
    span_rad: float = np.deg2rad(200.0),
    travel_m: float = 0.2,
    points: int = 24,
    sigma_m: float = INSTRUMENT_SIGMA_M,
    target: str | None = None,
    joints: tuple[int, ...] | None = None,
    descending: bool = False,
) -> Sweeps:
    """Simulated circle-point sweeps of ``truth`` (book §4.6.3): joint by joint (0-based
    ``joints``, default all, in that order), ``points`` evenly spaced joint values over
    ``span_rad`` (revolute) or ``travel_m`` (prismatic) centred on the signature reading
    (shifted inside the joint limits where needed), every other joint held at ``signature_q``
    (readings, (n,)), the ``target`` measured with normal noise ``sigma_m`` per axis. Rows of a
    sweep run from the lowest to the highest reading (``descending``: the other way). With a
    coupling matrix the joint *variable* is swept and the readings follow."""
    qs = np.asarray(signature_q, dtype=float).reshape(truth.n_joints)
    C = truth.coupling_matrix
    vs = C @ qs
    lim = truth.joint_limits
    rows_q, rows_j = [], []
    for j in range(truth.n_joints) if joints is None else joints:
        half = (span_rad if truth.joints[j].revolute else travel_m) / 2.0
        lo, hi = vs[j] - half, vs[j] + half
        if C[j, j] != 0 and np.count_nonzero(C[j]) == 1:  # the swept reading alone: keep it in its limits
            g = C[j, j]
            qlo, qhi = sorted((lo / g, hi / g))
            shift = max(lim[j, 0] - qlo, 0.0) - max(qhi - lim[j, 1], 0.0)
            lo, hi = lo + shift * g, hi + shift * g
        vals = np.linspace(lo, hi, points)
        V = np.tile(vs, (points, 1))
        V[:, j] = vals
        Q = np.linalg.solve(C, V.T).T
        order = np.argsort(Q[:, j], kind="stable")
        Q = Q[order[::-1] if descending else order]
        rows_q.append(Q)
        rows_j.append(np.full(points, j))
    q = np.concatenate(rows_q)
    p = target_positions(truth, q, target)
    return Sweeps(
        q=q,
        p_world=p + rng.normal(0.0, sigma_m, p.shape),
        joint=np.concatenate(rows_j),
        target=np.array([target] * len(q), dtype=object),
    )
