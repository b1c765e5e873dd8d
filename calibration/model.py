"""The kinematic model: an immutable description of one robot (contracts §2).

A ``KinematicModel`` is frozen; a changed model is a new model (``dataclasses.replace`` or the
functions in :mod:`calibration.parameters`). Everything inside is SI (metres, radians); the
``units`` only say how the model is read from and written to a ``recal.model/1`` document.

Conventions, per joint (contracts §2): ``dh`` ``Rz(theta+q)·Tz(d)·Tx(a)·Rx(alpha)``; ``dh`` with
``beta`` (Hayati, book eq. 2.64) ``Rz(theta+q)·Tx(a)·Rx(alpha)·Ry(beta)``; ``mdh`` (Craig)
``Rx(alpha)·Tx(a)·Rz(theta+q)·Tz(d)``; ``poe`` rotation by ``theta+q`` about the unit ``axis``
through ``point`` (both in the base frame at q = 0; book eq. 2.72-2.75), the chain ending with
``home``. The joint variable is ``(C·q)_i`` with the coupling matrix ``C`` (default
``diag(gain)``), plus an optional gear-eccentricity harmonic ``A·sin(k·q_i + phi)`` (book eq. 2.4).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, overload

import numpy as np

from .errors import RecalError

FORMAT = "recal.model/1"
CONVENTIONS = ("dh", "mdh", "poe")
JOINT_TYPES = ("revolute", "prismatic")
# The fields this format defines. A joint field outside JOINT_FIELDS is refused (a misspelt
# "alpah" would otherwise silently default to 0 and give a wrong model); top-level sections
# beyond MODEL_FIELDS are kept (an identified model's "identification", a library file's
# "source", a compliant model's "compliance", ...) unless they look like a misspelt known one.
MODEL_FIELDS = (
    "format",
    "name",
    "units",
    "convention",
    "base",
    "joints",
    "tool",
    "targets",
    "coupling",
    "home",
    "compliance",
)
JOINT_FIELDS = (
    "name",
    "type",
    "theta",
    "d",
    "a",
    "alpha",
    "beta",
    "gain",
    "lower",
    "upper",
    "axis",
    "point",
    "harmonic",
    "velocity",
    "effort",
)
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "in": 0.0254}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}


class ModelFormatError(RecalError, ValueError):
    """A model document is malformed. ``field`` is the JSON path at fault (``joints[2].alpha``)."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}" if field else message)


@dataclass(frozen=True, slots=True)
class Units:
    """How lengths and angles are written in the model file and the CSVs used with it."""

    length: str = "m"
    angle: str = "rad"

    @property
    def length_m(self) -> float:
        """Metres per file length unit."""
        return LENGTH_UNITS[self.length]

    @property
    def angle_rad(self) -> float:
        """Radians per file angle unit."""
        return ANGLE_UNITS[self.angle]


def _frozen(a, shape=None) -> np.ndarray:
    arr = np.array(a, dtype=float)
    if shape is not None:
        arr = arr.reshape(shape)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Joint:
    """One joint and the link after it. Lengths in m, angles in rad.

    ``dh``/``mdh`` use ``theta, d, a, alpha`` (and ``beta`` for a Hayati link in ``dh``);
    ``poe`` uses ``axis``, ``point`` and ``theta`` (revolute offset) or ``d`` (prismatic offset).
    ``harmonic`` is ``(amplitude, frequency, phase)`` of gear eccentricity (book eq. 2.4), in rad
    (or m), per rad of reading (or per m) and rad. ``velocity`` (rad/s or m/s) and ``effort`` (N·m
    or N) are the joint's published limits where known (``None``: unknown); the kinematics do not
    use them, exports (URDF) do.
    """

    name: str
    type: str = "revolute"
    theta: float = 0.0
    d: float = 0.0
    a: float = 0.0
    alpha: float = 0.0
    beta: float | None = None
    axis: np.ndarray | None = None
    point: np.ndarray | None = None
    gain: float = 1.0
    lower: float = -2 * math.pi
    upper: float = 2 * math.pi
    harmonic: tuple[float, float, float] | None = None
    velocity: float | None = None
    effort: float | None = None

    @property
    def revolute(self) -> bool:
        return self.type == "revolute"

    @property
    def hayati(self) -> bool:
        return self.beta is not None

    def axis_point(self) -> tuple[np.ndarray, np.ndarray]:
        """A ``poe`` joint's unit axis and a point on it (m): both set for every ``poe`` joint
        (:func:`model_from_dict` requires them); a joint of another convention has none."""
        if self.axis is None or self.point is None:
            raise ValueError(f"joint {self.name!r} has no axis and point (not a poe joint)")
        return self.axis, self.point


@dataclass(frozen=True, eq=False)
class KinematicModel:
    """A robot: base, joints, tool, named targets. Immutable; SI inside.

    ``base`` and ``tool`` are 6-vector poses (contracts §1), ``home`` (``poe`` only) the flange
    pose at q = 0 in the base frame; ``targets`` map names to points (3,) in the tool frame;
    ``coupling`` (n, n) maps readings to joint variables (``None``: ``diag(gain)``).
    ``metadata`` keeps the document's other top-level fields (e.g. an ``identification`` block).
    """

    name: str
    convention: str
    joints: tuple[Joint, ...]
    base: np.ndarray = field(default_factory=lambda: _frozen(np.zeros(6)))
    tool: np.ndarray = field(default_factory=lambda: _frozen(np.zeros(6)))
    home: np.ndarray | None = None
    targets: Mapping[str, np.ndarray] = field(default_factory=lambda: MappingProxyType({}))
    coupling: np.ndarray | None = None
    units: Units = Units()
    metadata: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    compliance: GravityCompliance | None = None  # joint compliance under gravity (level 3), see below

    def __post_init__(self):
        if self.convention not in CONVENTIONS:
            raise ModelFormatError("convention", f"expected one of {', '.join(CONVENTIONS)}, got {self.convention!r}")
        object.__setattr__(self, "base", _frozen(self.base, (6,)))
        object.__setattr__(self, "tool", _frozen(self.tool, (6,)))
        if self.home is not None:
            object.__setattr__(self, "home", _frozen(self.home, (6,)))
        elif self.convention == "poe":
            object.__setattr__(self, "home", _frozen(np.zeros(6)))
        object.__setattr__(
            self, "targets", MappingProxyType({k: _frozen(v, (3,)) for k, v in dict(self.targets).items()})
        )
        if self.coupling is not None:
            C = _frozen(self.coupling)
            n = len(self.joints)
            if C.shape != (n, n):
                raise ModelFormatError("coupling", f"expected a {n} x {n} matrix, got shape {C.shape}")
            object.__setattr__(self, "coupling", C)
        object.__setattr__(self, "joints", tuple(self.joints))
        object.__setattr__(self, "metadata", MappingProxyType(dict(self.metadata)))
        if self.compliance is not None:
            _check_compliance(self.compliance, self.joints)

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def joint_limits(self) -> np.ndarray:
        """(n, 2) lower and upper limit of each joint reading (rad or m)."""
        return np.array([[j.lower, j.upper] for j in self.joints], dtype=float)

    @property
    def coupling_matrix(self) -> np.ndarray:
        """The (n, n) matrix C mapping readings to joint variables (``diag(gain)`` without coupling)."""
        if self.coupling is not None:
            return np.array(self.coupling)
        return np.diag([j.gain for j in self.joints])

    def poe_home(self) -> np.ndarray:
        """A ``poe`` model's home pose (6,) of the flange at zero readings; every ``poe`` model has
        one (:func:`model_from_dict`), the other conventions none."""
        if self.home is None:
            raise ValueError(f"model {self.name!r} has no home pose (not a poe model)")
        return self.home

    def target(self, name: str | None) -> np.ndarray:
        """A target point (3,) in the tool frame; ``None`` is the tool origin."""
        if name is None or name == "":
            return np.zeros(3)
        try:
            return np.array(self.targets[name])
        except KeyError:
            known = ", ".join(sorted(self.targets)) or "none"
            raise KeyError(f"unknown target {name!r} (the model has: {known})") from None


# ------------------------------------------------------------------------- reading documents


@overload
def _number(d: Mapping, key: str, where: str, default: float, *, required: bool = False) -> float: ...
@overload
def _number(d: Mapping, key: str, where: str, default: None = None, *, required: bool = False) -> float | None: ...
def _number(d: Mapping, key: str, where: str, default: float | None = None, *, required: bool = False) -> float | None:
    if key not in d or d[key] is None:
        if required:
            raise ModelFormatError(f"{where}.{key}" if where else key, "is required (a number)")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ModelFormatError(f"{where}.{key}" if where else key, f"expected a finite number, got {v!r}")
    return float(v)


def _vector(v, n: int, where: str) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ModelFormatError(where, f"expected a list of {n} numbers, got {v!r}")
    out = []
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ModelFormatError(f"{where}[{i}]", f"expected a finite number, got {x!r}")
        out.append(float(x))
    return np.array(out)


def _pose(v, where: str, units: Units) -> np.ndarray:
    p = _vector(v, 6, where)
    return np.concatenate([p[:3] * units.length_m, p[3:] * units.angle_rad])


def _did_you_mean(key: str, known: tuple[str, ...], cutoff: float) -> str | None:
    """The known field ``key`` is probably a misspelling of (case aside, or by difflib's ratio)."""
    for k in known:
        if key.lower() == k.lower():
            return k
    close = difflib.get_close_matches(key, known, n=1, cutoff=cutoff)
    return close[0] if close else None


def _check_fields(doc: Mapping[str, Any], raw_joints) -> None:
    """Refuse unknown joint fields and top-level near-misses of known fields (``MODEL_FIELDS``)."""
    for key in doc:
        if key not in MODEL_FIELDS:
            guess = _did_you_mean(str(key), MODEL_FIELDS, 0.8)
            if guess is not None:
                raise ModelFormatError(str(key), f"unknown field; did you mean {guess!r}?")
    for i, jd in enumerate(raw_joints):
        if not isinstance(jd, Mapping):
            continue
        for key in jd:
            if key not in JOINT_FIELDS:
                guess = _did_you_mean(str(key), JOINT_FIELDS, 0.6)
                hint = f"did you mean {guess!r}?" if guess else f"expected one of {', '.join(JOINT_FIELDS)}"
                raise ModelFormatError(f"joints[{i}].{key}", f"unknown field; {hint}")


def model_from_dict(doc: Mapping[str, Any]) -> KinematicModel:
    """Read a ``recal.model/1`` document (already parsed JSON) into a model in SI units.

    Raises ``ModelFormatError`` naming the JSON field at fault and what was expected.
    """
    if not isinstance(doc, Mapping):
        raise ModelFormatError("", "expected a JSON object")
    _check_fields(doc, doc.get("joints") if isinstance(doc.get("joints"), list) else [])
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise ModelFormatError("format", f"expected {FORMAT!r}, got {fmt!r}")
    units = _units_of(doc)
    L = units.length_m
    convention = doc.get("convention")
    if convention not in CONVENTIONS:
        raise ModelFormatError("convention", f"expected one of {', '.join(CONVENTIONS)}, got {convention!r}")
    raw_joints = doc.get("joints")
    if not isinstance(raw_joints, list) or not raw_joints:
        raise ModelFormatError("joints", "expected a non-empty list of joints")
    coupling = None
    if doc.get("coupling") is not None:
        c = doc["coupling"]
        n = len(raw_joints)
        if not isinstance(c, list) or len(c) != n:
            raise ModelFormatError("coupling", f"expected {n} rows of {n} numbers")
        coupling = np.array([_vector(row, n, f"coupling[{i}]") for i, row in enumerate(c)])
    joints: list[Joint] = []
    names: set[str] = set()
    for i, jd in enumerate(raw_joints):
        joints.append(_joint_from_dict(jd, i, convention, units, coupling, names))
    targets = {}
    raw_targets = doc.get("targets") or {}
    if not isinstance(raw_targets, Mapping):
        raise ModelFormatError("targets", "expected an object mapping names to [x, y, z]")
    for tname, tv in raw_targets.items():
        targets[str(tname)] = _vector(tv, 3, f"targets.{tname}") * L
    home = None
    if convention == "poe":
        if "home" not in doc:
            raise ModelFormatError("home", "is required for convention poe (the flange pose at q = 0)")
        home = _pose(doc["home"], "home", units)
    known = set(MODEL_FIELDS)
    return KinematicModel(
        name=str(doc.get("name", "")),
        convention=convention,
        joints=tuple(joints),
        base=_pose(doc.get("base", [0] * 6), "base", units),
        tool=_pose(doc.get("tool", [0] * 6), "tool", units),
        home=home,
        targets=targets,
        coupling=coupling,
        units=units,
        metadata={k: v for k, v in doc.items() if k not in known},
        compliance=None if doc.get("compliance") is None else compliance_from_dict(doc["compliance"], joints, units),
    )


def _joint_from_dict(
    jd: Any, i: int, convention: str, units: Units, coupling: np.ndarray | None, names: set[str]
) -> Joint:
    """Joint ``i`` of a model document (``jd``), in SI; ``names``: the joint names read so far
    (this one is added)."""
    L, A = units.length_m, units.angle_rad
    where = f"joints[{i}]"
    if not isinstance(jd, Mapping):
        raise ModelFormatError(where, "expected an object")
    jtype = jd.get("type", "revolute")
    if jtype not in JOINT_TYPES:
        raise ModelFormatError(f"{where}.type", f"expected revolute or prismatic, got {jtype!r}")
    name = str(jd.get("name", f"j{i + 1}"))
    if name in names:
        raise ModelFormatError(f"{where}.name", f"duplicate joint name {name!r}")
    names.add(name)
    var_scale = A if jtype == "revolute" else L  # unit of this joint's reading
    if "gain" in jd and coupling is not None:
        raise ModelFormatError(f"{where}.gain", "a model may give `coupling` or `gain`, not both")
    kw: dict[str, Any] = dict(
        name=name,
        type=jtype,
        theta=_number(jd, "theta", where, 0.0) * A,
        d=_number(jd, "d", where, 0.0) * L,
        gain=_number(jd, "gain", where, 1.0),
    )
    # Without limits: a full turn either way for revolute joints, 10 m for prismatic ones.
    default_limit = 2 * math.pi if jtype == "revolute" else 10.0
    lower, upper = _number(jd, "lower", where), _number(jd, "upper", where)
    kw["lower"] = -default_limit if lower is None else lower * var_scale
    kw["upper"] = default_limit if upper is None else upper * var_scale
    if kw["lower"] >= kw["upper"]:
        raise ModelFormatError(f"{where}.lower", "must be below `upper`")
    if convention == "poe":
        if "axis" not in jd:
            raise ModelFormatError(f"{where}.axis", "is required for convention poe (a unit 3-vector)")
        axis = _vector(jd["axis"], 3, f"{where}.axis")
        norm = np.linalg.norm(axis)
        if not norm > 0:
            raise ModelFormatError(f"{where}.axis", "must not be zero")
        kw["axis"] = axis / norm
        kw["point"] = _vector(jd.get("point", [0, 0, 0]), 3, f"{where}.point") * L
    else:
        kw["a"] = _number(jd, "a", where, 0.0) * L
        kw["alpha"] = _number(jd, "alpha", where, 0.0) * A
        if jd.get("beta") is not None:
            if convention != "dh":
                raise ModelFormatError(f"{where}.beta", "Hayati's beta is defined for convention dh only")
            kw["beta"] = _number(jd, "beta", where, 0.0) * A  # present: checked just above
            if kw["d"] != 0.0 and jtype == "revolute":
                raise ModelFormatError(f"{where}.d", "must be 0 or absent in a Hayati (beta) link")
    # Published speed and torque (force) limits, for exports; SI inside (rad/s or m/s, N·m or N).
    for key, scale in (("velocity", var_scale), ("effort", 1.0)):
        v = _number(jd, key, where)
        if v is not None:
            if not v > 0:
                raise ModelFormatError(f"{where}.{key}", f"expected a positive number, got {v!r}")
            kw[key] = v * scale
    if jd.get("harmonic") is not None:
        h = _vector(jd["harmonic"], 3, f"{where}.harmonic")
        # k multiplies the reading: per radian (dimensionless) or per file length unit
        freq_scale = 1.0 if jtype == "revolute" else 1.0 / L
        kw["harmonic"] = (h[0] * var_scale, h[1] * freq_scale, h[2] * A)
    return Joint(**kw)


def _units_of(doc: Mapping[str, Any]) -> Units:
    """A model document's ``units``."""
    u = doc.get("units")
    if not isinstance(u, Mapping):
        raise ModelFormatError("units", 'expected {"length": "mm"|"m"|"in", "angle": "deg"|"rad"}')
    if u.get("length") not in LENGTH_UNITS:
        raise ModelFormatError("units.length", f"expected one of mm, m, in; got {u.get('length')!r}")
    if u.get("angle") not in ANGLE_UNITS:
        raise ModelFormatError("units.angle", f"expected deg or rad; got {u.get('angle')!r}")
    return Units(u["length"], u["angle"])


def _r(x: float, digits: int = 12) -> float:
    """Round for writing: keeps files readable without losing meaningful precision."""
    v = round(float(x), digits)
    return 0.0 if v == 0 else v


def model_to_dict(model: KinematicModel, *, units: Units | None = None) -> dict[str, Any]:
    """Write a model as a ``recal.model/1`` document in ``units`` (default: the model's own)."""
    units = units or model.units
    L, A = units.length_m, units.angle_rad

    def pose(p):
        p = np.asarray(p)
        return [_r(v / L) for v in p[:3]] + [_r(v / A) for v in p[3:]]

    joints = []
    for j in model.joints:
        var_scale = A if j.revolute else L
        jd: dict[str, Any] = {"name": j.name, "type": j.type}
        if model.convention == "poe":
            axis, point = j.axis_point()
            jd["axis"] = [_r(v) for v in axis]
            jd["point"] = [_r(v / L) for v in point]
            if j.revolute:
                jd["theta"] = _r(j.theta / A)
            else:
                jd["d"] = _r(j.d / L)
        else:
            jd["theta"] = _r(j.theta / A)
            if not (j.hayati and j.revolute):
                jd["d"] = _r(j.d / L)
            jd["a"] = _r(j.a / L)
            jd["alpha"] = _r(j.alpha / A)
            if j.hayati:
                jd["beta"] = _r((j.beta or 0.0) / A)
        if model.coupling is None and j.gain != 1.0:
            jd["gain"] = _r(j.gain, 15)
        if j.harmonic is not None:
            freq_scale = 1.0 if j.revolute else 1.0 / L
            jd["harmonic"] = [_r(j.harmonic[0] / var_scale), _r(j.harmonic[1] / freq_scale), _r(j.harmonic[2] / A)]
        jd["lower"] = _r(j.lower / var_scale)
        jd["upper"] = _r(j.upper / var_scale)
        if j.velocity is not None:
            jd["velocity"] = _r(j.velocity / var_scale)
        if j.effort is not None:
            jd["effort"] = _r(j.effort)
        joints.append(jd)
    doc: dict[str, Any] = {
        "format": FORMAT,
        "name": model.name,
        "units": {"length": units.length, "angle": units.angle},
        "convention": model.convention,
        "base": pose(model.base),
        "joints": joints,
    }
    if model.convention == "poe":
        doc["home"] = pose(model.home)
    doc["tool"] = pose(model.tool)
    doc["targets"] = {k: [_r(v / L) for v in p] for k, p in model.targets.items()}
    if model.coupling is not None:
        doc["coupling"] = [[_r(v) for v in row] for row in model.coupling]
    if model.compliance is not None:
        doc["compliance"] = compliance_to_dict(model.compliance, units)
    for k, v in model.metadata.items():
        doc[k] = v
    return doc


# ------------------------------------------------------------- joint compliance under gravity

STANDARD_GRAVITY = 9.80665  # m/s²; gravity's magnitude (the section gives only its direction)
COMPLIANCE_TERMS = ("k", "m", "x", "y", "z")


@dataclass(frozen=True, eq=False)
class GravityCompliance:
    """Joint compliance under gravity, the model's optional level-3 section (book §2.1, §7.7;
    :mod:`calibration.compliance` computes with it). SI inside.

    ``gravity`` (3,) the unit direction of gravity in the robot base frame (default ``-z``);
    ``joints`` the revolute joints that deflect; ``lumps`` the joints whose moving link carries a
    lumped mass. ``values`` maps term names to SI values; a term not given is 0:

    - ``<joint>.k``: the joint's compliance c (rad per N·m), which multiplies the (known) payload's
      gravity torque;
    - ``<joint>.<lump>.m``: c·m·g of the lump (rad per m of lever of the lump's link-frame origin);
    - ``<joint>.<lump>.x|y|z``: c·m·g·r of the lump (rad), ``r`` its centre of gravity in that
      link's frame.

    Only these products are identifiable from positions (a compliance and a mass appear only
    multiplied). ``payload`` (kg, x, y, z m in the tool frame) is the payload applied to
    configurations given without one (the task's payload; ``None``: no payload).
    """

    joints: tuple[str, ...]
    lumps: tuple[str, ...]
    gravity: np.ndarray = field(default_factory=lambda: _frozen([0.0, 0.0, -1.0]))
    values: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    payload: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        g = np.array(self.gravity, dtype=float).reshape(3)
        n = float(np.linalg.norm(g))
        if not n > 0:
            raise ModelFormatError("compliance.gravity", "must not be zero")
        object.__setattr__(self, "gravity", _frozen(g / n))
        object.__setattr__(self, "joints", tuple(self.joints))
        object.__setattr__(self, "lumps", tuple(self.lumps))
        object.__setattr__(self, "values", MappingProxyType({k: float(v) for k, v in dict(self.values).items()}))
        if self.payload is not None:
            object.__setattr__(self, "payload", tuple(float(v) for v in self.payload))

    def term_names(self, joint_order: tuple[str, ...]) -> list[str]:
        """Every term of this section (``j2.j3.m``, ..., ``j2.k``): per deflecting joint each lump
        on a link at or after it, then its compliance. In that order the identifiability selection
        prefers them: with one payload throughout, the payload's torque is a heavier last link and
        the lumps keep it; only a second payload determines the compliance itself."""
        pos = {n: i for i, n in enumerate(joint_order)}
        out = []
        for j in self.joints:
            for lump in self.lumps:
                if pos[lump] >= pos[j]:
                    out += [f"{j}.{lump}.{t}" for t in COMPLIANCE_TERMS[1:]]
            out.append(f"{j}.k")
        return out


def compliance_term_kind(term: str) -> str:
    """The unit kind of a term: ``angle_per_torque`` (rad/N·m), ``angle_per_length`` (rad/m) or
    ``angle`` (rad)."""
    t = term.rpartition(".")[2]
    return {"k": "angle_per_torque", "m": "angle_per_length"}.get(t, "angle")


def _compliance_scale(term: str, units: Units) -> float:
    """SI per file unit of a term (torque stays N·m: the units block has no force unit)."""
    kind = compliance_term_kind(term)
    if kind == "angle_per_length":
        return units.angle_rad / units.length_m
    return units.angle_rad


def _check_compliance(c: GravityCompliance, joints) -> None:
    by_name = {j.name: j for j in joints}
    for i, n in enumerate(c.joints):
        if n not in by_name:
            raise ModelFormatError(f"compliance.joints[{i}]", f"no joint {n!r} in this model")
        if not by_name[n].revolute:
            raise ModelFormatError(f"compliance.joints[{i}]", f"joint {n!r} is prismatic; expected a revolute joint")
    for i, n in enumerate(c.lumps):
        if n not in by_name:
            raise ModelFormatError(f"compliance.lumps[{i}]", f"no joint {n!r} in this model")
    allowed = set(c.term_names(tuple(by_name)))
    for k in c.values:
        if k not in allowed:
            raise ModelFormatError(
                f"compliance.terms.{k}",
                "not a term of these joints and lumps (expected "
                "<joint>.k or <joint>.<lump>.m|x|y|z with the lump's link at or after the joint)",
            )


def compliance_from_dict(d: Any, joints, units: Units) -> GravityCompliance:
    """Read the ``compliance`` section (docs/formats.md) in the model's ``units``."""
    if not isinstance(d, Mapping):
        raise ModelFormatError("compliance", "expected an object with joints, lumps, gravity and terms")
    names = [j.name for j in joints]

    def name_list(key):
        v = d.get(key, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise ModelFormatError(f"compliance.{key}", "expected a list of joint names")
        return tuple(v)

    jl, ll = name_list("joints"), name_list("lumps")
    for key, lst in (("joints", jl), ("lumps", ll)):
        for i, n in enumerate(lst):
            if n not in names:
                raise ModelFormatError(f"compliance.{key}[{i}]", f"no joint {n!r}; expected one of {', '.join(names)}")
    gravity = _vector(d.get("gravity", [0, 0, -1]), 3, "compliance.gravity")
    terms = d.get("terms", {})
    if not isinstance(terms, Mapping):
        raise ModelFormatError("compliance.terms", "expected an object mapping term names to numbers")
    values = {}
    for k, v in terms.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ModelFormatError(f"compliance.terms.{k}", f"expected a finite number, got {v!r}")
        values[str(k)] = float(v) * _compliance_scale(str(k), units)
    payload = None
    if d.get("payload") is not None:
        p = _vector(d["payload"], 4, "compliance.payload")
        if p[0] < 0:
            raise ModelFormatError("compliance.payload[0]", "expected a mass >= 0 kg")
        payload = (p[0], *(p[1:] * units.length_m))
    c = GravityCompliance(jl, ll, gravity, values, payload)
    _check_compliance(c, joints)
    return c


def compliance_to_dict(c: GravityCompliance, units: Units) -> dict[str, Any]:
    """The ``compliance`` section in ``units``."""
    A, L = units.angle, units.length
    out: dict[str, Any] = {
        "gravity": [_r(v) for v in c.gravity],
        "joints": list(c.joints),
        "lumps": list(c.lumps),
        "terms": {k: float(f"{v / _compliance_scale(k, units):.12g}") for k, v in c.values.items()},
        "term_units": {"k": f"{A}/(N·m)", "m": f"{A}/{L}", "x|y|z": A},
    }
    if c.payload is not None:
        out["payload"] = [_r(c.payload[0])] + [_r(v / units.length_m) for v in c.payload[1:]]
    return out
