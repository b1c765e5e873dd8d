"""Joint compliance under gravity: level-3 calibration (book §2.1, §7.7).

A joint is a torsional spring (book §7.7: Whitney et al. found joint stiffness dominant and
modelled it as a linear torsional spring): joint i deflects by ``Δθ_i = c_i · τ_i``, its
compliance times the gravity torque about its axis. The torque comes from lumped masses on the
links after it and from the payload:

    τ_i = Σ_lumps u_i · ((p_lump − o_i) × m g ĝ)  +  u_i · ((p_payload − o_i) × m_p g ĝ)

with ``u_i``, ``o_i`` the joint's axis and a point on it, ``ĝ`` the direction of gravity and
``g`` its magnitude, all in the robot base frame, from the model's own kinematics. With a lump's
centre of gravity ``p = o_L + R_L r`` (``o_L``, ``R_L`` its link's frame, ``r`` in that frame):

    Δθ_i = Σ_L [ μ_iL · u_i·((o_L − o_i) × ĝ) + Σ_a ν_iLa · u_i·((R_L e_a) × ĝ) ]
           + c_i · m_p g · u_i·((p_payload − o_i) × ĝ)                                    (1)

Positions never show a compliance and a mass apart, only their products: the model's terms
are ``μ_iL = c_i m_L g`` (rad per m), ``ν_iLa = c_i m_L g r_a`` (rad) and, where the payload is
known, ``c_i`` itself (rad per N·m). Each is a coefficient of a known function of the
configuration (its *regressor*), so the deflection is linear in the terms and a term's Jacobian
column is its joint's offset column times its regressor (:func:`regressors`). A session measured
with two payloads separates the arm's own weight (μ, ν) from the payload's (c).

Small deflection: the torques are computed at the rigid configuration. A deflection δ changes
the torques by a relative O(δ), so the error this makes is O(δ²) per joint: for a sag of
1e-3 rad, 1e-6 rad, a micrometre at a metre's reach, far below a tracker's noise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .kinematics import check_q, walk
from .model import STANDARD_GRAVITY, GravityCompliance, KinematicModel


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


def deflections(model: KinematicModel, q: np.ndarray, payload=None, trig: dict | None = None
                ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The joint deflections (N, n) rad under gravity (eq. 1; zero for joints that do not deflect)
    and the terms' regressors (:func:`regressors`)."""
    reg = regressors(model, q, payload, trig)
    c = model.compliance
    dv = np.zeros((len(reg[next(iter(reg))]) if reg else check_q(model, q).shape[0], model.n_joints))
    index = {j.name: i for i, j in enumerate(model.joints)}
    for name, phi in reg.items():
        term = name[len("compliance."):]
        value = c.values.get(term, 0.0)
        if value:
            dv[:, index[term.partition(".")[0]]] += value * phi
    return dv, reg


def gravity_torques(model: KinematicModel, q: np.ndarray, masses: Mapping[str, tuple[float, tuple]],
                    payload=None, gravity=(0.0, 0.0, -1.0)) -> np.ndarray:
    """The gravity torque (N, n) N·m about every revolute joint's axis of lumped ``masses``
    (``{link joint: (kg, centre of gravity (3,) m in that link's frame)}``) and the payload, at
    the rigid configuration: the physical quantity the terms of eq. 1 are built from (for
    checks and for sizing a simulated arm)."""
    names = [j.name for j in model.joints]
    rev = [j.name for j in model.joints if j.revolute]
    unit = {}
    for lump, (m, r) in masses.items():
        unit.update({f"{j}.{lump}.m": m * STANDARD_GRAVITY for j in rev})
        unit.update({f"{j}.{lump}.{s}": m * STANDARD_GRAVITY * float(r[a]) for j in rev for a, s in enumerate("xyz")})
    section = GravityCompliance(tuple(rev), tuple(masses), gravity, {})
    probe = dataclasses.replace(model, compliance=section)
    reg = regressors(probe, q, payload)
    out = np.zeros((check_q(model, q).shape[0], len(names)))
    for name, phi in reg.items():
        term = name[len("compliance."):]
        j = term.partition(".")[0]
        if term.endswith(".k"):
            out[:, names.index(j)] += phi  # the payload's torque (its regressor is m_p g · lever)
        elif term in unit:
            out[:, names.index(j)] += unit[term] * phi
    return out


def physical_section(model: KinematicModel, compliance: Mapping[str, float], masses: Mapping[str, tuple[float, tuple]],
                     *, gravity=(0.0, 0.0, -1.0), payload=None) -> GravityCompliance:
    """A compliance section from physical figures: ``compliance`` per deflecting joint (rad per
    N·m, the inverse of its stiffness), lumped ``masses`` ``{link joint: (kg, centre of gravity
    (3,) m in the link's frame)}``: the identifiable products of eq. 1."""
    joints = tuple(compliance)
    section = GravityCompliance(joints, tuple(masses), gravity, {}, payload)
    pos = {j.name: i for i, j in enumerate(model.joints)}
    values = {}
    for term in section.term_names(tuple(pos)):
        parts = term.split(".")
        c = float(compliance[parts[0]])
        if parts[1] == "k":
            values[term] = c
            continue
        m, r = masses[parts[1]]
        values[term] = c * m * STANDARD_GRAVITY * (1.0 if parts[2] == "m" else float(r["xyz".index(parts[2])]))
    return dataclasses.replace(section, values=values)


def default_section(model: KinematicModel, *, gravity=(0.0, 0.0, -1.0), joints: tuple[str, ...] | None = None,
                    lumps: tuple[str, ...] | None = None) -> GravityCompliance:
    """The section ``recal identify --compliance`` starts from (every term 0): by default the
    joints that carry the arm, the revolute ones among the first three whose axis is not along
    gravity (a vertical first axis feels no gravity torque), and lumps on their links and on the
    last link (wrist, tool). Which terms the data determine, the identification decides."""
    g = np.asarray(gravity, dtype=float)
    g = g / np.linalg.norm(g)
    if joints is None:
        rigid = dataclasses.replace(model, compliance=None, base=np.zeros(6))
        rng = np.random.default_rng(0)
        lim = np.clip(model.joint_limits, -np.pi, np.pi)
        q = rng.uniform(lim[:, 0], lim[:, 1], size=(16, model.n_joints))
        keys = {f"{j.name}.theta" for j in model.joints[:3] if j.revolute}
        w = walk(rigid, q, keys)
        joints = tuple(j.name for j in model.joints[:3] if j.revolute and f"{j.name}.theta" in w.axes
                       and np.max(np.linalg.norm(np.cross(w.axes[f"{j.name}.theta"][0], g), axis=1)) > 1e-6)
    if lumps is None:
        last = model.joints[-1].name
        lumps = tuple(dict.fromkeys([*joints, last]))
    return GravityCompliance(tuple(joints), tuple(lumps), g, {})


def with_section(model: KinematicModel, section: GravityCompliance | None) -> KinematicModel:
    """The model with ``section`` as its compliance (``None``: the rigid model)."""
    return dataclasses.replace(model, compliance=section)


def with_payload(model: KinematicModel, payload) -> KinematicModel:
    """A compliant model whose configurations given without a payload carry ``payload`` (kg, x, y,
    z m in the tool frame): the task's payload for prediction and compensation. A rigid model is
    returned unchanged (it has no use for a payload)."""
    if model.compliance is None:
        return model
    p = payload_rows(payload, 1)
    return dataclasses.replace(model, compliance=dataclasses.replace(model.compliance, payload=tuple(p[0])))


def describe_term(name: str) -> str:
    """A compliance term in words, for the identification report."""
    parts = name.split(".")[1:]
    if parts[1] == "k":
        return f"compliance of joint {parts[0]} ({name})"
    what = "mass" if parts[2] == "m" else f"mass moment {parts[2]}"
    return f"joint {parts[0]} compliance x link {parts[1]} {what} ({name})"


def lumps_in_frames_of(masses: Mapping[str, tuple[float, tuple]], source: KinematicModel, target: KinematicModel
                       ) -> dict[str, tuple[float, tuple]]:
    """Lumped ``masses`` whose centres of gravity are given in ``source``'s link frames, expressed
    in ``target``'s (the same robot in another convention: both frames are fixed on the same link,
    so one configuration, q = 0, relates them)."""
    keys = {f"{lump}.link" for lump in masses}
    q0 = np.zeros((1, source.n_joints))
    ws = walk(dataclasses.replace(source, compliance=None, base=np.zeros(6)), q0, keys)
    wt = walk(dataclasses.replace(target, compliance=None, base=np.zeros(6)), q0, keys)
    out = {}
    for lump, (m, r) in masses.items():
        Rs, ps = ws.frames[f"{lump}.link"]
        Rt, pt = wt.frames[f"{lump}.link"]
        p_base = ps[0] + Rs[0] @ np.asarray(r, dtype=float)
        out[lump] = (m, tuple(Rt[0].T @ (p_base - pt[0])))
    return out


# ------------------------------------------------------------------ is compliance worth it here?

# ``--compliance auto`` adds a joint's compliance only when it lowers the cross-validated RMS by
# at least this fraction: extra parameters always fit the training data a little better, and a
# gain this small would not be worth the terms (a rigid arm's data give a few tenths of a percent).
MIN_CV_GAIN = 0.05


@dataclass(frozen=True, eq=False)
class CrossValidation:
    """What k-fold cross-validation said about compliance (m). ``tried`` lists every set of
    deflecting joints evaluated, as ``(joints, cv_rms_m)`` (``()``: rigid), in the order tried;
    ``joints`` the set chosen (``()``: the model stays rigid); ``rms_rigid_m`` and
    ``rms_compliant_m`` the cross-validated RMS of the rigid model and of the model with every
    candidate joint's compliance; ``folds`` the number of folds; ``section`` the compliance
    section chosen (every term 0, for identification to start from), or None."""

    folds: int
    tried: tuple[tuple[tuple[str, ...], float], ...]
    joints: tuple[str, ...]
    rms_rigid_m: float
    rms_compliant_m: float
    section: GravityCompliance | None

    @property
    def rms_chosen_m(self) -> float:
        return dict(self.tried)[self.joints]

    @property
    def gain(self) -> float:
        """Relative reduction of the cross-validated RMS, compliant (every candidate joint)
        against rigid."""
        return 1.0 - self.rms_compliant_m / self.rms_rigid_m if self.rms_rigid_m > 0 else 0.0


def fold_indices(data, folds: int, seed: int = 0) -> list[np.ndarray]:
    """Row indices of each held-out fold: rows of one configuration (``pose_id``) stay together,
    so a fold never tests a configuration the training saw."""
    N = len(data)
    groups = np.asarray(data.pose_id, dtype=object) if data.pose_id is not None else np.arange(N)
    keys = list(dict.fromkeys(groups.tolist()))
    order = np.random.default_rng(seed).permutation(len(keys))
    fold_of = {keys[k]: i % folds for i, k in enumerate(order)}
    labels = np.array([fold_of[g] for g in groups.tolist()])
    return [np.nonzero(labels == f)[0] for f in range(folds)]


def cv_rms(model: KinematicModel, data, folds: list[np.ndarray], identify_kw: dict) -> float:
    """Cross-validated RMS (m) of the position error of ``model`` identified on all folds but one
    and tested on that one, over every row."""
    from .identify import identify  # here: identify imports the kinematics this module extends
    from .jacobian import predict

    sq = 0.0
    n = 0
    for test in folds:
        train = np.setdiff1d(np.arange(len(data)), test)
        result = identify(model, data.subset(train), **identify_kw)
        held = data.subset(test)
        p_tool = np.array([result.model.target(t) for t in held.target])
        p = predict(result.model, held.q, p_tool, payload=held.payload).p_world
        sq += float(np.sum((held.p_world - p) ** 2))
        n += len(test)
    return float(np.sqrt(sq / max(n, 1)))


def choose_compliance(model: KinematicModel, data, *, candidates: GravityCompliance | None = None,
                      folds: int = 5, min_gain: float = MIN_CV_GAIN, seed: int = 0,
                      identify_kw: dict | None = None) -> CrossValidation:
    """Which joints' compliance the data support (``recal identify --compliance auto``): forward
    selection by k-fold cross-validation over :func:`calibration.identify.identify`. Starting
    rigid, add the candidate joint whose compliance lowers the cross-validated RMS most, while it
    lowers it by at least ``min_gain`` (relative). ``candidates``: the section whose joints are
    tried (default :func:`default_section`); the chosen section keeps its gravity and lumps."""
    kw = dict(identify_kw or {})
    cand = candidates if candidates is not None else default_section(model)
    rigid = dataclasses.replace(model, compliance=None)
    fidx = fold_indices(data, folds, seed)
    last = model.joints[-1].name

    def section(joints):
        if not joints:
            return None
        lumps = tuple(lump for lump in cand.lumps if lump in joints or lump == last or lump not in cand.joints)
        return GravityCompliance(tuple(j for j in cand.joints if j in joints), lumps, cand.gravity, {}, cand.payload)

    tried: dict[tuple[str, ...], float] = {}

    def score(joints):
        key = tuple(j for j in cand.joints if j in joints)
        if key not in tried:
            tried[key] = cv_rms(with_section(rigid, section(key)), data, fidx, kw)
        return tried[key]

    chosen: tuple[str, ...] = ()
    best = score(chosen)
    while True:
        options = [j for j in cand.joints if j not in chosen]
        if not options:
            break
        scored = sorted((score(chosen + (j,)), j) for j in options)
        rms, j = scored[0]
        if rms > (1.0 - min_gain) * best:
            break
        chosen = tuple(x for x in cand.joints if x in chosen + (j,))
        best = rms
    full = score(cand.joints)
    return CrossValidation(folds, tuple(tried.items()), chosen, tried[()], full, section(chosen))


def compare(model: KinematicModel, data, *, folds: int = 5, seed: int = 0, identify_kw: dict | None = None) -> dict:
    """Rigid against compliant for a model with a compliance section: the k-fold
    cross-validated RMS (m) of the model identified without its section and with it (every term
    from 0), with the section's joints; what a result page shows side by side."""
    if model.compliance is None:
        raise ValueError("the model has no compliance section to compare with")
    kw = dict(identify_kw or {})
    fidx = fold_indices(data, folds, seed)
    fresh = dataclasses.replace(model.compliance, values={})
    rigid = cv_rms(with_section(model, None), data, fidx, kw)
    compliant = cv_rms(with_section(model, fresh), data, fidx, kw)
    return {"folds": folds, "joints": list(fresh.joints), "lumps": list(fresh.lumps),
            "cv_rms_rigid_m": rigid, "cv_rms_compliant_m": compliant,
            "gain": 1.0 - compliant / rigid if rigid > 0 else 0.0}


def reexpress(model: KinematicModel, source: KinematicModel) -> KinematicModel:
    """``model`` (the same robot as ``source`` in another convention or form, e.g. after
    ``mdh_to_dh``, Hayati links or ``to_poe``) with ``source``'s compliance section re-expressed
    in its own link frames and base frame, so that both sag alike. A lump's terms are its first
    moment: with ``(R, p)`` its link's frames in the two models, ``ν' = R'ᵀ((p − p') μ + R ν)``
    and ``μ' = μ`` (both frames are fixed on the same link, so q = 0 relates them); gravity's
    direction moves with the base frame."""
    c = source.compliance
    if c is None:
        return dataclasses.replace(model, compliance=None)
    keys = {f"{lump}.link" for lump in c.lumps}
    q0 = np.zeros((1, source.n_joints))
    ws = walk(dataclasses.replace(source, compliance=None), q0, keys | {"base"})
    wt = walk(dataclasses.replace(model, compliance=None), q0, keys | {"base"})
    Rbs, Rbt = ws.frames["base"][0][0], wt.frames["base"][0][0]
    values = dict(c.values)
    pos = {j.name: i for i, j in enumerate(source.joints)}
    for j in c.joints:
        for lump in c.lumps:
            if pos[lump] < pos[j]:
                continue
            Rs, ps = (a[0] for a in ws.frames[f"{lump}.link"])
            Rt, pt = (a[0] for a in wt.frames[f"{lump}.link"])
            mu = c.values.get(f"{j}.{lump}.m", 0.0)
            nu = np.array([c.values.get(f"{j}.{lump}.{s}", 0.0) for s in "xyz"])
            nu_t = Rt.T @ ((ps - pt) * mu + Rs @ nu)
            for s, v in zip("xyz", nu_t):
                if v != 0.0 or f"{j}.{lump}.{s}" in values:
                    values[f"{j}.{lump}.{s}"] = float(v)
    gravity = Rbt.T @ (Rbs @ c.gravity)
    return dataclasses.replace(model, compliance=dataclasses.replace(c, gravity=gravity, values=values))
