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

import numpy as np

from .kinematics import check_q, deflections, payload_rows, regressors, walk  # noqa: F401 - re-exported
from .model import STANDARD_GRAVITY, GravityCompliance, KinematicModel


def gravity_torques(
    model: KinematicModel,
    q: np.ndarray,
    masses: Mapping[str, tuple[float, tuple]],
    payload=None,
    gravity=(0.0, 0.0, -1.0),
) -> np.ndarray:
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
        term = name[len("compliance.") :]
        j = term.partition(".")[0]
        if term.endswith(".k"):
            out[:, names.index(j)] += phi  # the payload's torque (its regressor is m_p g · lever)
        elif term in unit:
            out[:, names.index(j)] += unit[term] * phi
    return out


def physical_section(
    model: KinematicModel,
    compliance: Mapping[str, float],
    masses: Mapping[str, tuple[float, tuple]],
    *,
    gravity=(0.0, 0.0, -1.0),
    payload=None,
) -> GravityCompliance:
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


def default_section(
    model: KinematicModel,
    *,
    gravity=(0.0, 0.0, -1.0),
    joints: tuple[str, ...] | None = None,
    lumps: tuple[str, ...] | None = None,
) -> GravityCompliance:
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
        joints = tuple(
            j.name
            for j in model.joints[:3]
            if j.revolute
            and f"{j.name}.theta" in w.axes
            and np.max(np.linalg.norm(np.cross(w.axes[f"{j.name}.theta"][0], g), axis=1)) > 1e-6
        )
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
    return dataclasses.replace(
        model, compliance=dataclasses.replace(model.compliance, payload=None if p is None else tuple(p[0]))
    )


def describe_term(name: str) -> str:
    """A compliance term in words, for the identification report."""
    parts = name.split(".")[1:]
    if parts[1] == "k":
        return f"compliance of joint {parts[0]} ({name})"
    what = "mass" if parts[2] == "m" else f"mass moment {parts[2]}"
    return f"joint {parts[0]} compliance x link {parts[1]} {what} ({name})"


def lumps_in_frames_of(
    masses: Mapping[str, tuple[float, tuple]], source: KinematicModel, target: KinematicModel
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
