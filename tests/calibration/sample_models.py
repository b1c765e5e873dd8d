"""Model documents (``recal.model/1``) used across the calibration tests, and a reference forward
kinematics written straight from contracts §2 (4x4 products of elementary transforms), independent
of ``calibration.kinematics``.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from calibration.robots import nominal_document

LENGTH = {"m": 1.0, "mm": 1e-3, "in": 0.0254}
ANGLE = {"rad": 1.0, "deg": math.pi / 180}


# --------------------------------------------------------------------------- elementary transforms


def Rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def Ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def Rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def Trans(x, y, z):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def Tx(a):
    return Trans(a, 0, 0)


def Tz(d):
    return Trans(0, 0, d)


def Pose(p):
    """Contracts §1: Trans(x, y, z)·Rz(rz)·Ry(ry)·Rx(rx)."""
    return Trans(*p[:3]) @ Rz(p[5]) @ Ry(p[4]) @ Rx(p[3])


def screw(axis, point, angle):
    """Rotation by ``angle`` about the unit ``axis`` through ``point`` (book eq. 2.72-2.73)."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (np.eye(3) - R) @ np.asarray(point, float)
    return T


# --------------------------------------------------------------------------- reference FK


def reference_fk(doc: dict, q_file: np.ndarray) -> np.ndarray:
    """``T_world_tool`` (4, 4) in metres for one joint reading vector in the document's units,
    straight from contracts §2."""
    L, A = LENGTH[doc["units"]["length"]], ANGLE[doc["units"]["angle"]]
    joints = doc["joints"]
    # readings in SI: revolute in rad, prismatic in m
    q = np.array([q_file[i] * (L if j.get("type", "revolute") == "prismatic" else A) for i, j in enumerate(joints)])
    if doc.get("coupling") is not None:
        v = np.asarray(doc["coupling"], float) @ q
    else:
        v = np.array([j.get("gain", 1.0) for j in joints]) * q
    for i, j in enumerate(joints):
        if j.get("harmonic") is not None:
            amp, k, phase = j["harmonic"]
            prismatic = j.get("type", "revolute") == "prismatic"
            amp_si = amp * (L if prismatic else A)
            k_si = k / L if prismatic else k
            v[i] += amp_si * math.sin(k_si * q[i] + phase * A)

    def pose(key):
        p = np.asarray(doc.get(key, [0] * 6), float)
        return Pose(np.concatenate([p[:3] * L, p[3:] * A]))

    T = pose("base")
    for i, j in enumerate(joints):
        prismatic = j.get("type", "revolute") == "prismatic"
        theta = j.get("theta", 0.0) * A
        d = j.get("d", 0.0) * L
        a = j.get("a", 0.0) * L
        alpha = j.get("alpha", 0.0) * A
        if prismatic:
            d += v[i]
        else:
            theta += v[i]
        if doc["convention"] == "dh" and j.get("beta") is not None:
            beta = j["beta"] * A
            T = T @ Rz(theta) @ Tz(d if prismatic else 0.0) @ Tx(a) @ Rx(alpha) @ Ry(beta)
        elif doc["convention"] == "dh":
            T = T @ Rz(theta) @ Tz(d) @ Tx(a) @ Rx(alpha)
        elif doc["convention"] == "mdh":
            T = T @ Rx(alpha) @ Tx(a) @ Rz(theta) @ Tz(d)
        else:
            u = np.asarray(j["axis"], float)
            u = u / np.linalg.norm(u)
            if prismatic:
                T = T @ Trans(*(u * d))
            else:
                T = T @ screw(u, np.asarray(j.get("point", [0, 0, 0]), float) * L, theta)
    if doc["convention"] == "poe":
        T = T @ pose("home")
    return T @ pose("tool")


# --------------------------------------------------------------------------- documents


def fanuc_r2000ic_doc() -> dict:
    """A Fanuc R-2000iC-like arm with the coupling matrix of contracts §2 (J3 reported relative to
    the horizon: the DH angle of joint 3 is -(J2 + J3); J4-J6 reversed)."""
    rows = [
        (670.0, 312.0, -90.0),
        (0.0, 1075.0, 0.0),
        (0.0, 225.0, -90.0),
        (1280.0, 0.0, 90.0),
        (0.0, 0.0, -90.0),
        (215.0, 0.0, 0.0),
    ]
    theta = [0, -90, 0, 0, 0, 0]
    C = [
        [1, 0, 0, 0, 0, 0],
        [0, 1, 0, 0, 0, 0],
        [0, -1, -1, 0, 0, 0],
        [0, 0, 0, -1, 0, 0],
        [0, 0, 0, 0, -1, 0],
        [0, 0, 0, 0, 0, -1],
    ]
    return {
        "format": "recal.model/1",
        "name": "fanuc-r2000ic",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": [
            {
                "name": f"j{i + 1}",
                "type": "revolute",
                "theta": theta[i],
                "d": d,
                "a": a,
                "alpha": al,
                "lower": -180,
                "upper": 180,
            }
            for i, (d, a, al) in enumerate(rows)
        ],
        "tool": [0, 0, 150, 0, 0, 0],
        "targets": {"smr1": [0, 30, 60]},
        "coupling": C,
    }


def craig_puma_mdh_doc() -> dict:
    """Craig's modified-DH PUMA 560 (alpha, a of the preceding link), mm and degrees."""
    rows = [(0, 0, 0), (-90, 0, 0), (0, 431.8, 149.09), (-90, -20.32, 433.07), (90, 0, 0), (-90, 0, 0)]
    return {
        "format": "recal.model/1",
        "name": "puma-craig",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "mdh",
        "base": [100, -50, 660, 0, 0, 30],
        "joints": [{"name": f"j{i + 1}", "theta": 0, "d": d, "a": a, "alpha": al} for i, (al, a, d) in enumerate(rows)],
        "tool": [0, 0, 56.25, 0, 0, 0],
        "targets": {"ball": [20, 0, 40]},
    }


def prismatic_doc(convention: str) -> dict:
    """A small R-P-R-R arm with one prismatic joint, in ``convention`` (metres, radians); offsets
    and twists not zero, so that every field matters."""
    if convention == "poe":
        joints = [
            {"name": "j1", "axis": [0, 0, 1], "point": [0.01, -0.02, 0], "theta": 0.03},
            {"name": "j2", "type": "prismatic", "axis": [0.1, 0.2, 1.0], "point": [0.3, 0, 0.4], "d": 0.05},
            {"name": "j3", "axis": [0, 1, 0], "point": [0.3, 0.05, 0.9], "theta": -0.2},
            {"name": "j4", "axis": [1, 0, 0.1], "point": [0.5, 0.05, 0.9], "theta": 0.1},
        ]
        extra = {"home": [0.6, 0.05, 0.9, 0.1, -0.2, 0.3]}
    else:
        joints = [
            {"name": "j1", "theta": 0.03, "d": 0.4, "a": 0.1, "alpha": -1.4},
            {"name": "j2", "type": "prismatic", "theta": 0.4, "d": 0.2, "a": 0.05, "alpha": 1.2},
            {"name": "j3", "theta": -0.2, "d": 0.1, "a": 0.3, "alpha": 0.5},
            {"name": "j4", "theta": 0.1, "d": 0.15, "a": 0.02, "alpha": 0.0},
        ]
        extra = {}
    for j in joints:
        if j.get("type") == "prismatic":
            j.update(lower=0.0, upper=0.5)
        else:
            j.update(lower=-3.0, upper=3.0)
    return {
        "format": "recal.model/1",
        "name": f"rprr-{convention}",
        "units": {"length": "m", "angle": "rad"},
        "convention": convention,
        "base": [0.2, -0.1, 0.05, 0.1, 0.2, -0.3],
        "joints": joints,
        "tool": [0.01, 0.02, 0.1, 0.3, -0.1, 0.2],
        "targets": {"t1": [0.0, 0.05, 0.02], "t2": [-0.04, 0.0, 0.06]},
        **extra,
    }


def stanford_5r1p_doc(lever_in: float = 10.0) -> dict:
    """The 5R1P robot of the book's Table 4.1 (Driels & Pathre), inches and degrees, standard DH.
    Link 3 is prismatic (r_3 the variable); l_6 = r_6 = ``lever_in`` (the tool distance from the
    wrist); joint ranges "N" of Table 4.7."""
    rows = [  # alpha, l, r
        (-90.0, 0.0, 6.0),
        (90.0, 0.0, 12.0),
        (30.0, 0.0, 0.0),
        (-90.0, 0.0, 0.0),
        (90.0, 0.0, 0.0),
        (0.0, lever_in, lever_in),
    ]
    ranges = [(0, 300), (-120, 120), (12, 48), (0, 360), (-120, 120), (0, 360)]
    joints = []
    for i, ((alpha, l, r), (lo, hi)) in enumerate(zip(rows, ranges)):
        j = {
            "name": f"j{i + 1}",
            "type": "prismatic" if i == 2 else "revolute",
            "theta": 0.0,
            "d": r,
            "a": l,
            "alpha": alpha,
            "lower": lo,
            "upper": hi,
        }
        joints.append(j)
    return {
        "format": "recal.model/1",
        "name": "5r1p",
        "units": {"length": "in", "angle": "deg"},
        "convention": "dh",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": joints,
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


def all_convention_docs() -> dict[str, dict]:
    """One document per convention and feature, by a short id."""
    ur = nominal_document("ur10e")
    ur["base"] = [1500, -800, 200, 2, -3, 120]
    ur["tool"] = [5, -3, 80, 10, 0, -20]
    ur["targets"] = {"smr1": [0, 0, 50], "ball1": [40, 0, 30]}
    gained = copy.deepcopy(ur)
    gained["name"] = "ur10e-gains"
    for k, g in enumerate([1.001, 0.999, 1.0005, 1.0, 0.998, 1.002]):
        gained["joints"][k]["gain"] = g
    harmonic = copy.deepcopy(ur)
    harmonic["name"] = "ur10e-harmonic"
    harmonic["joints"][1]["harmonic"] = [0.02, 3.0, 40.0]
    harmonic["joints"][4]["harmonic"] = [0.01, 50.0, -10.0]
    pris_harm = prismatic_doc("dh")
    pris_harm["name"] = "rprr-harmonic"
    pris_harm["joints"][1]["harmonic"] = [0.0002, 2 * math.pi / 0.005, 0.3]  # 0.2 mm, 5 mm period
    return {
        "dh": ur,
        "dh_gain": gained,
        "dh_harmonic": harmonic,
        "dh_hayati": nominal_document("puma560"),
        "dh_coupling": fanuc_r2000ic_doc(),
        "mdh": craig_puma_mdh_doc(),
        "poe": nominal_document("puma560-zrp"),
        "dh_prismatic": prismatic_doc("dh"),
        "mdh_prismatic": prismatic_doc("mdh"),
        "poe_prismatic": prismatic_doc("poe"),
        "dh_prismatic_harmonic": pris_harm,
        "5r1p": stanford_5r1p_doc(),
    }


def random_readings(doc: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` joint readings (n, joints) in the document's units, inside the joint limits (revolute
    ones clipped to ±180 deg)."""
    A = ANGLE[doc["units"]["angle"]]
    out = np.empty((n, len(doc["joints"])))
    for i, j in enumerate(doc["joints"]):
        if j.get("type", "revolute") == "prismatic":
            lo, hi = j.get("lower", 0.0), j.get("upper", 0.3 / LENGTH[doc["units"]["length"]])
        else:
            lo = max(j.get("lower", -math.pi / A), -math.pi / A)
            hi = min(j.get("upper", math.pi / A), math.pi / A)
        out[:, i] = rng.uniform(lo, hi, n)
    return out


def si_readings(doc: dict, q_file: np.ndarray) -> np.ndarray:
    """Readings in the document's units -> SI (rad, m)."""
    scale = np.array(
        [
            LENGTH[doc["units"]["length"]] if j.get("type", "revolute") == "prismatic" else ANGLE[doc["units"]["angle"]]
            for j in doc["joints"]
        ]
    )
    return np.asarray(q_file, float) * scale
