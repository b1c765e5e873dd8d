"""Forward kinematics, batched over N configurations.

``T_world_tool(q) = B · A_1(q_1) ··· A_n(q_n) · F`` (contracts §2; book eq. 2.15, 2.75).

A model is compiled into a short *program* of elementary operations (a rotation or translation
about one local axis, or a fixed transform). Walking the program over N configurations at once
updates a stack of frames ``R (N, 3, 3)``, ``p (N, 3)`` with a few vector operations per step,
which is far cheaper than multiplying N 4x4 matrices per step. The same walk records, for the
identification Jacobian (:mod:`calibration.jacobian`), the world axis and origin at which each
parameter acts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .model import STANDARD_GRAVITY, KinematicModel
from .transforms import homogeneous, invert, pose_to_matrix


@dataclass(frozen=True, slots=True)
class Op:
    """One step of a kinematic program.

    ``kind``: ``"rot"`` / ``"trans"`` about / along local ``axis`` by ``const`` (+ the joint
    variable of joint index ``joint`` when given); ``"fixed"`` applies the constant transform
    ``T`` (4, 4); ``"mark"`` only records the frame under ``key``. A ``rot``/``trans`` op with a
    ``key`` records its world axis and origin under that key.
    """

    kind: str
    axis: int = 2
    const: float = 0.0
    joint: int | None = None
    T: np.ndarray | None = None
    key: str | None = None


def joint_variables(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """The joint displacements produced by readings ``q`` (N, n): ``C·q`` plus the gear-eccentricity
    harmonic ``A·sin(k·q_i + phi)`` (book eq. 2.4), before each joint's constant ``theta`` (or
    ``d``) is added. Returns (N, n) rad (m for prismatic joints)."""
    q = check_q(model, q)
    v = q @ model.coupling_matrix.T
    for i, j in enumerate(model.joints):
        if j.harmonic is not None:
            amp, freq, phase = j.harmonic
            v[:, i] += amp * np.sin(freq * q[:, i] + phase)
    return v


def check_q(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """Validate joint readings: (N, n) float (a single (n,) vector becomes N = 1)."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != model.n_joints:
        raise ValueError(f"`q` must have shape (N, {model.n_joints}); got {q.shape}")
    return q


def frame_from_axis(axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """A frame (4, 4) whose z axis is ``axis`` and origin ``point``; x is the unit vector
    perpendicular to z closest to the world axis least aligned with z (deterministic)."""
    z = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    ref = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return homogeneous(np.stack([x, y, z], axis=1), np.asarray(point, dtype=float))


def program(model: KinematicModel) -> list[Op]:
    """Compile ``model`` into its program of elementary operations (see :class:`Op`).

    Keys recorded: ``base``, ``tool``, ``home`` (frames, for their local 6-DOF perturbations);
    ``<joint>.<field>`` for ``dh``/``mdh`` link parameters; ``<joint>.pre``/``<joint>.post``
    (frames before and after a ``poe`` joint's motion); ``<joint>.link`` the frame of the link the
    joint moves (``dh``: Denavit–Hartenberg frame i; ``mdh``: Craig's frame i; ``poe``: the base
    frame carried by joints 1..i), where a lumped mass of :mod:`calibration.compliance` sits.
    """
    ops: list[Op] = [Op("fixed", T=pose_to_matrix(model.base)), Op("mark", key="base")]
    for i, j in enumerate(model.joints):
        n = j.name
        rev = j.revolute
        if model.convention == "dh":
            ops.append(Op("rot", 2, j.theta, i if rev else None, key=f"{n}.theta"))
            if not (j.hayati and rev):
                ops.append(Op("trans", 2, j.d, None if rev else i, key=f"{n}.d"))
            ops.append(Op("trans", 0, j.a, key=f"{n}.a"))
            ops.append(Op("rot", 0, j.alpha, key=f"{n}.alpha"))
            if j.hayati:
                ops.append(Op("rot", 1, j.beta or 0.0, key=f"{n}.beta"))
        elif model.convention == "mdh":
            ops.append(Op("rot", 0, j.alpha, key=f"{n}.alpha"))
            ops.append(Op("trans", 0, j.a, key=f"{n}.a"))
            ops.append(Op("rot", 2, j.theta, i if rev else None, key=f"{n}.theta"))
            ops.append(Op("trans", 2, j.d, None if rev else i, key=f"{n}.d"))
        else:  # poe: F · Rz(theta + v) · F^-1 (or Tz(d + v) for a prismatic joint)
            F = frame_from_axis(*j.axis_point())
            ops.append(Op("fixed", T=F))
            ops.append(Op("mark", key=f"{n}.pre"))
            if rev:
                ops.append(Op("rot", 2, j.theta, i, key=f"{n}.theta"))
            else:
                ops.append(Op("trans", 2, j.d, i, key=f"{n}.d"))
            ops.append(Op("mark", key=f"{n}.post"))
            ops.append(Op("fixed", T=invert(F)))
        ops.append(Op("mark", key=f"{n}.link"))
    if model.convention == "poe":
        ops += [Op("fixed", T=pose_to_matrix(model.poe_home())), Op("mark", key="home")]
    ops += [Op("fixed", T=pose_to_matrix(model.tool)), Op("mark", key="tool")]
    return ops


@dataclass(frozen=True, slots=True)
class Walk:
    """Result of walking a program: the tool frames and what was recorded.

    ``R`` (N, 3, 3), ``p`` (N, 3): ``T_world_tool``. ``axes[key]`` = (u (N, 3) world unit axis,
    o (N, 3) world origin) of an op; ``frames[key]`` = (R, p) of a mark.
    """

    R: np.ndarray
    p: np.ndarray
    axes: dict
    frames: dict
    regressors: dict = field(default_factory=dict)  # compliance term -> (N,) (calibration.compliance)


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _matrices(cols: list[np.ndarray]) -> np.ndarray:
    """(N, 3, 3) rotation matrices from the three world axes, each (3, N) component-major."""
    return np.ascontiguousarray(np.stack(cols, axis=-1).transpose(1, 0, 2))


def _cos_sin(trig: dict, joint: int, v: np.ndarray, const: float) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of ``const + v`` by the angle-sum formulas, from cos v and sin v kept in
    ``trig`` for ``joint`` (computed again only when that joint's variables ``v`` changed)."""
    hit = trig.get(joint)
    if hit is None or not np.array_equal(hit[0], v):
        hit = trig[joint] = (v.copy(), np.cos(v), np.sin(v))
    ck, sk = np.cos(const), np.sin(const)
    return hit[1] * ck - hit[2] * sk, hit[2] * ck + hit[1] * sk


def walk(
    model: KinematicModel,
    q: np.ndarray,
    record: frozenset[str] | set[str] = frozenset(),
    trig: dict | None = None,
    payload: np.ndarray | None = None,
    ops: list[Op] | None = None,
) -> Walk:
    """Run ``model``'s program over readings ``q`` (N, n), recording the keys in ``record``.

    ``trig``: a dict kept by a caller that walks models of one structure over the same readings
    many times (identification): the joints' cos and sin are computed once and reused. ``ops``:
    ``program(model)``, when the caller walks the same model over many chunks of readings.

    A model with a ``compliance`` section is walked at its deflected configuration
    (:func:`deflections`; ``payload`` (N, 4) or (4,): kg and the centre of
    gravity in the tool frame, m; ``None``: the section's own payload), and the walk keeps the
    compliance terms' regressors for the Jacobian.

    Inside, the frame is held as its three world axes and its origin, each (3, N)
    component-major, so every step is a few operations on contiguous length-N rows. A rotation
    about local axis ``a`` replaces the other two axes with new arrays and keeps the third: no
    step mutates an array, so what is recorded needs no copy. Recorded arrays are read-only
    (N, 3) views and may be shared between keys.
    """
    q = check_q(model, q)
    v = joint_variables(model, q)
    regressors: dict = {}
    if model.compliance is not None:
        dv, regressors = deflections(model, q, payload, trig)
        v = v + dv
    N = q.shape[0]
    eye = np.eye(3)
    cols = [np.broadcast_to(eye[:, j : j + 1], (3, N)) for j in range(3)]  # world axes x, y, z
    p = np.zeros((3, N))
    axes: dict = {}
    frames: dict = {}
    for op in program(model) if ops is None else ops:
        if op.kind == "fixed":
            assert op.T is not None  # a fixed op carries its transform
            M, t = op.T[:3, :3], op.T[:3, 3]
            if np.any(t):
                p = p + sum(t[i] * cols[i] for i in range(3) if t[i] != 0.0)
            if not np.array_equal(M, eye):
                C = np.tensordot(M.T, np.stack(cols), axes=1)  # new axis j = Σ_i M[i, j] · axis i
                cols = [C[0], C[1], C[2]]
        elif op.kind == "mark":
            if op.key in record:
                # (N, 3, 3) view of a (3, 3, N) stack: each axis stays a contiguous (3, N) block
                frames[op.key] = (_readonly(np.stack(cols).transpose(2, 1, 0)), _readonly(p.T))
        else:
            value = op.const if op.joint is None else op.const + v[:, op.joint]
            a = op.axis
            if np.ndim(value) == 0 and value == 0.0:
                pass
            elif op.kind == "rot":
                if trig is not None and op.joint is not None:
                    c, s = _cos_sin(trig, op.joint, v[:, op.joint], op.const)
                else:
                    c, s = np.cos(value), np.sin(value)
                i, k = [(1, 2), (2, 0), (0, 1)][a]
                ci, ck = cols[i], cols[k]
                cols[i] = c * ci + s * ck
                cols[k] = c * ck - s * ci
            else:
                p = p + value * cols[a]
            if op.key in record:
                axes[op.key] = (_readonly(cols[a].T), _readonly(p.T))
    return Walk(_matrices(cols), np.ascontiguousarray(p.T), axes, frames, regressors)


def fk(model: KinematicModel, q: np.ndarray, payload: np.ndarray | None = None) -> np.ndarray:
    """``T_world_tool`` (N, 4, 4) for joint readings ``q`` (N, n) (rad; m for prismatic joints);
    ``payload`` as in :func:`walk` (a compliant model only)."""
    w = walk(model, q, payload=payload)
    return homogeneous(w.R, w.p)


def points_world(
    model: KinematicModel, q: np.ndarray, p_tool: np.ndarray, payload: np.ndarray | None = None
) -> np.ndarray:
    """World positions (N, 3) of points given in the tool frame: ``p_tool`` (3,) or (N, 3)."""
    w = walk(model, q, payload=payload)
    return w.p + np.einsum("nij,nj->ni", w.R, np.broadcast_to(np.asarray(p_tool, float), w.p.shape))


def target_positions(
    model: KinematicModel, q: np.ndarray, target: str | None = None, payload: np.ndarray | None = None
) -> np.ndarray:
    """World positions (N, 3) of the named target (``None``: the tool origin)."""
    return points_world(model, q, model.target(target), payload)


# --------------------------------------------------------------------------- joint compliance under gravity
# (book level 3; the model is calibration.model.GravityCompliance, its use calibration.compliance).
# Here because walk() applies the deflections and the deflections walk the rigid chain.


def payload_rows(payload, n_rows: int) -> np.ndarray | None:
    """Payloads (N, 4) (kg, then the centre of gravity x, y, z in the tool frame, m) from ``None``,
    one (4,) payload for every row, or (N, 4); NaN entries mean no payload (0 kg)."""
    if payload is None:
        return None
    p = np.asarray(payload, dtype=float)
    if p.ndim == 1:
        p = np.broadcast_to(p.reshape(4), (n_rows, 4))
    if p.shape != (n_rows, 4):
        raise ValueError(f"`payload` must have shape (4,) or ({n_rows}, 4); got {p.shape}")
    if np.any(p[:, 0] < 0):
        raise ValueError("a payload mass must be >= 0 kg")
    return np.nan_to_num(p, nan=0.0)


def _triple(u: np.ndarray, a: np.ndarray, g: np.ndarray) -> np.ndarray:
    """u · (a × g) per row, (N,)."""
    return np.einsum("ni,ni->n", u, np.cross(a, g))


def regressors(model: KinematicModel, q: np.ndarray, payload=None, trig: dict | None = None) -> dict[str, np.ndarray]:
    """The regressor (N,) of every term of the model's compliance section (eq. 1), keyed by the
    parameter name ``compliance.<term>``, at the rigid configuration of readings ``q`` (N, n).
    ``payload``: see :func:`payload_rows` (``None``: the section's own payload, if any)."""
    c = model.compliance
    if c is None:
        raise ValueError("the model has no compliance section: no regressors")
    q = check_q(model, q)
    N = q.shape[0]
    pay = payload_rows(payload if payload is not None else c.payload, N)
    names = [j.name for j in model.joints]
    pos = {n: i for i, n in enumerate(names)}
    # the base frame is where gravity is given: walk the rigid chain from there
    rigid = dataclasses.replace(model, compliance=None, base=np.zeros(6))
    keys = {f"{j}.theta" for j in c.joints} | {f"{lump}.link" for lump in c.lumps}
    w = walk(rigid, q, keys, trig)
    g = np.broadcast_to(c.gravity, (N, 3))
    out: dict[str, np.ndarray] = {}
    for j in c.joints:
        u, o = w.axes[f"{j}.theta"]
        if pay is None:
            out[f"compliance.{j}.k"] = np.zeros(N)
        else:
            p_cog = w.p + np.einsum("nij,nj->ni", w.R, pay[:, 1:])
            out[f"compliance.{j}.k"] = pay[:, 0] * STANDARD_GRAVITY * _triple(u, p_cog - o, g)
        for lump in c.lumps:
            if pos[lump] < pos[j]:
                continue
            R, p = w.frames[f"{lump}.link"]
            out[f"compliance.{j}.{lump}.m"] = _triple(u, p - o, g)
            for a, s in enumerate("xyz"):
                out[f"compliance.{j}.{lump}.{s}"] = _triple(u, R[:, :, a], g)
    return out


def deflections(
    model: KinematicModel, q: np.ndarray, payload=None, trig: dict | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The joint deflections (N, n) rad under gravity (eq. 1; zero for joints that do not deflect)
    and the terms' regressors (:func:`regressors`)."""
    reg = regressors(model, q, payload, trig)
    c = model.compliance
    assert c is not None  # regressors() refused a rigid model
    dv = np.zeros((len(reg[next(iter(reg))]) if reg else check_q(model, q).shape[0], model.n_joints))
    index = {j.name: i for i, j in enumerate(model.joints)}
    for name, phi in reg.items():
        term = name[len("compliance.") :]
        value = c.values.get(term, 0.0)
        if value:
            dv[:, index[term.partition(".")[0]]] += value * phi
    return dv, reg
