"""The parameters identification can free, and how a step in them changes a model.

Each parameter acts on the kinematic program (:func:`calibration.kinematics.program`) as one
or more elementary motions (a rotation about, or translation along, a local axis of a recorded
frame). That gives both its Jacobian column (:mod:`calibration.jacobian`) and its update
(:func:`apply_step`): a step is always taken about the current model, so the same machinery
serves ``dh``, ``mdh`` and ``poe``.

Names:

- ``base.tx ... base.rz``: translation along / rotation about the base frame's own axes
  (likewise ``tool.*`` in the tool frame and ``home.*`` in the ``poe`` home frame). Local
  perturbations avoid the gimbal lock of the 6-vector angles.
- ``<joint>.theta``, ``.d``, ``.a``, ``.alpha``, ``.beta``: link parameters of ``dh``/``mdh``;
  ``theta`` is the joint offset of a revolute joint, ``d`` that of a prismatic one.
- ``<joint>.tilt_x``, ``.tilt_y``: ``poe`` axis direction, rotated about the two axes
  perpendicular to it through ``point``; ``.shift_x``, ``.shift_y``: ``point`` moved
  perpendicular to the axis.
- ``<joint>.gain``: the reading scale (level-1 calibration, book eq. 2.2).
- ``target.<name>.x|y|z``: a target's position in the tool frame.
- ``compliance.<joint>.k``, ``compliance.<joint>.<lump>.m|x|y|z``: the terms of a compliant
  model's joint compliance under gravity (:class:`calibration.model.GravityCompliance`); each
  moves the chain like its joint's offset, times its regressor (:mod:`calibration.compliance`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .kinematics import frame_from_axis
from .model import KinematicModel, compliance_term_kind
from .transforms import homogeneous, matrix_to_pose, pose_to_matrix, rotvec_to_matrix

LOCAL_6 = ("tx", "ty", "tz", "rx", "ry", "rz")


@dataclass(frozen=True, slots=True)
class Parameter:
    """One identifiable parameter.

    ``terms``: ``(key, generator, axis, sign)`` — the parameter moves the chain like a unit
    ``generator`` (``"rot"``/``"trans"``) about/along local ``axis`` of the frame recorded
    under ``key``, times ``sign``. ``q_joint``: the column is scaled by that joint's reading
    (gains). ``target``: the parameter moves only rows that measure this target. ``regressor``:
    the column is scaled by the walk's regressor of that name (compliance terms).
    ``kind`` is ``"length"``, ``"angle"``, ``"scale"``, or for compliance terms
    ``"angle_per_torque"`` / ``"angle_per_length"`` (for units and column scaling).
    """

    name: str
    kind: str
    terms: tuple[tuple[str, str, int, float], ...]
    q_joint: int | None = None
    target: str | None = None
    regressor: str | None = None  # the column is scaled by the walk's regressor of this name (compliance)

    @property
    def record_keys(self) -> set[str]:
        return {t[0] for t in self.terms}


def _local6(prefix: str, key: str) -> list[Parameter]:
    out = []
    for k, n in enumerate(LOCAL_6):
        gen = "trans" if k < 3 else "rot"
        out.append(Parameter(f"{prefix}.{n}", "length" if k < 3 else "angle", ((key, gen, k % 3, 1.0),)))
    return out


def _link_fields(j) -> list[Parameter]:
    """A dh/mdh link's parameters, the joint offset first."""
    n, rev = j.name, j.revolute
    theta = Parameter(f"{n}.theta", "angle", ((f"{n}.theta", "rot", 2, 1.0),))
    d = Parameter(f"{n}.d", "length", ((f"{n}.d", "trans", 2, 1.0),))
    fields = [theta] if rev else [d, theta]
    if rev and not j.hayati:
        fields.append(d)
    fields.append(Parameter(f"{n}.a", "length", ((f"{n}.a", "trans", 0, 1.0),)))
    fields.append(Parameter(f"{n}.alpha", "angle", ((f"{n}.alpha", "rot", 0, 1.0),)))
    if j.hayati:
        fields.append(Parameter(f"{n}.beta", "angle", ((f"{n}.beta", "rot", 1, 1.0),)))
    return fields


def candidate_parameters(
    model: KinematicModel, *, targets: tuple[str, ...] = (), gains: bool = False, base: bool = True, tool: bool = True
) -> list[Parameter]:
    """Every parameter identification may free, in the order the identifiability selection
    prefers to keep them (base first, then the joints in order, then targets, then the tool, then
    the last ``dh``/``mdh`` link's fields other than its joint offset)."""
    params: list[Parameter] = _local6("base", "base") if base else []
    last: list[Parameter] = []
    for i, j in enumerate(model.joints):
        n = j.name
        rev = j.revolute
        if model.convention in ("dh", "mdh") and i == model.n_joints - 1:
            # The last link's fields duplicate the tool and target offsets; keep the joint
            # offset here and let the targets (what was really measured) come before the rest.
            fields = _link_fields(j)
            params.append(fields[0])
            last = fields[1:]
        elif model.convention in ("dh", "mdh"):
            params += _link_fields(j)
        else:
            pre, post = f"{n}.pre", f"{n}.post"
            if rev:
                params.append(Parameter(f"{n}.theta", "angle", ((f"{n}.theta", "rot", 2, 1.0),)))
            else:
                params.append(Parameter(f"{n}.d", "length", ((f"{n}.d", "trans", 2, 1.0),)))
            for ax, s in ((0, "x"), (1, "y")):
                params.append(Parameter(f"{n}.tilt_{s}", "angle", ((pre, "rot", ax, 1.0), (post, "rot", ax, -1.0))))
            if rev:
                for ax, s in ((0, "x"), (1, "y")):
                    params.append(
                        Parameter(f"{n}.shift_{s}", "length", ((pre, "trans", ax, 1.0), (post, "trans", ax, -1.0)))
                    )
    if model.convention == "poe":
        params += _local6("home", "home")
    for t in targets:
        for k, s in enumerate("xyz"):
            params.append(Parameter(f"target.{t}.{s}", "length", (("tool", "trans", k, 1.0),), target=t))
    if tool:
        params += _local6("tool", "tool")
    # After the tool: its six local motions span every rigid motion of the last body, so the dh
    # fields (and mdh's d) are then exactly dependent and dropped (mdh's a, alpha place the last
    # axis and stay). Before it, a tool frame nearly (not exactly) aligned with the last link kept
    # both, e.g. j6.a and tool.tx: ill-conditioned, LM drifted them to ±metres and crawled.
    params += last
    if gains and model.coupling is None:
        for i, j in enumerate(model.joints):
            key, gen, ax = (f"{j.name}.theta", "rot", 2) if j.revolute else (f"{j.name}.d", "trans", 2)
            params.append(Parameter(f"{j.name}.gain", "scale", ((key, gen, ax, 1.0),), q_joint=i))
    return params + compliance_parameters(model)


def compliance_parameters(model: KinematicModel) -> list[Parameter]:
    """The terms of the model's compliance section (none for a rigid model), after every
    geometric parameter: the identifiability selection keeps geometry first. A term deflects
    its joint, so it moves the chain like that joint's offset times the term's regressor."""
    c = model.compliance
    if c is None:
        return []
    out = []
    for term in c.term_names(tuple(j.name for j in model.joints)):
        joint = term.partition(".")[0]
        name = f"compliance.{term}"
        out.append(Parameter(name, compliance_term_kind(term), ((f"{joint}.theta", "rot", 2, 1.0),), regressor=name))
    return out


def _compose_local(pose6: np.ndarray, delta6: np.ndarray) -> np.ndarray:
    """``pose · exp(delta)``: a small translation and rotation in the pose's own frame."""
    T = pose_to_matrix(pose6) @ homogeneous(rotvec_to_matrix(delta6[3:]), delta6[:3])
    return matrix_to_pose(T)


def apply_step(model: KinematicModel, params: list[Parameter], delta: np.ndarray) -> KinematicModel:
    """A new model moved by ``delta`` (P,) along ``params`` from ``model``."""
    delta = np.asarray(delta, dtype=float)
    by_name = {p.name: float(d) for p, d in zip(params, delta)}
    changes: dict = {}

    for frame in ("base", "tool", "home"):
        d6 = np.array([by_name.get(f"{frame}.{n}", 0.0) for n in LOCAL_6])
        if np.any(d6):
            changes[frame] = _compose_local(getattr(model, frame), d6)

    joints = []
    for j in model.joints:
        n = j.name
        upd: dict = {}
        for f in ("theta", "d", "a", "alpha", "beta", "gain"):
            if f"{n}.{f}" in by_name:
                upd[f] = getattr(j, f) + by_name[f"{n}.{f}"]
        if model.convention == "poe":
            tilt = np.array([by_name.get(f"{n}.tilt_x", 0.0), by_name.get(f"{n}.tilt_y", 0.0), 0.0])
            shift = np.array([by_name.get(f"{n}.shift_x", 0.0), by_name.get(f"{n}.shift_y", 0.0), 0.0])
            if np.any(tilt) or np.any(shift):
                F = frame_from_axis(*j.axis_point()) @ homogeneous(rotvec_to_matrix(tilt), shift)
                upd["axis"] = F[:3, 2] / np.linalg.norm(F[:3, 2])
                upd["point"] = F[:3, 3]
        joints.append(dataclasses.replace(j, **upd) if upd else j)
    changes["joints"] = tuple(joints)

    moved_targets = {}
    for t, p in model.targets.items():
        d3 = np.array([by_name.get(f"target.{t}.{s}", 0.0) for s in "xyz"])
        moved_targets[t] = p + d3
    changes["targets"] = moved_targets
    if model.compliance is not None:
        terms = {n[len("compliance.") :]: d for n, d in by_name.items() if n.startswith("compliance.")}
        if terms:
            values = dict(model.compliance.values)
            for t, d in terms.items():
                values[t] = values.get(t, 0.0) + d
            changes["compliance"] = dataclasses.replace(model.compliance, values=values)
    return dataclasses.replace(model, **changes)


def parameter_values(model: KinematicModel, params: list[Parameter]) -> np.ndarray:
    """Current values (P,) of the named parameters, SI. Local perturbation parameters
    (``base.*``, ``tool.*``, ``home.*``, ``*.tilt_*``, ``*.shift_*``) are 0 by definition:
    they describe steps about the current model."""
    out = []
    for p in params:
        head, _, field = p.name.rpartition(".")
        if p.name.startswith("compliance."):
            values = model.compliance.values if model.compliance is not None else {}
            out.append(float(values.get(p.name[len("compliance.") :], 0.0)))
        elif p.name.startswith("target."):
            t = p.name.split(".")[1]
            out.append(float(model.targets[t]["xyz".index(field)]))
        elif head in ("base", "tool", "home") or field.startswith(("tilt_", "shift_")):
            out.append(0.0)
        else:
            joint = next(j for j in model.joints if j.name == head)
            out.append(float(getattr(joint, field)))
    return np.array(out)


def parameters_by_name(model: KinematicModel, names: list[str]) -> tuple[list[Parameter], list[str]]:
    """The candidate parameters of ``model`` named in ``names`` (in that order), and the names it
    has no such parameter for (for example a stored covariance's names on a changed model)."""
    gains = any(n.endswith(".gain") for n in names)
    cands = {p.name: p for p in candidate_parameters(model, targets=tuple(model.targets), gains=gains)}
    missing = [n for n in names if n not in cands]
    return [cands[n] for n in names if n in cands], missing
