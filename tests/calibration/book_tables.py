"""The PUMA 560 parameter tables of the book's case study (Mooring, Roth & Driels, *Fundamentals
of Manipulator Calibration*, 1991, ch. 6), as printed (inches and degrees), with the misprints
the extraction found corrected (``/work/shared/reference/ch6_ch7_app.md`` §2, §7), and builders
that turn them into ``recal.model/1`` documents.

DH tables (6.1, 6.5, 6.6, 6.11): one row per transform B->0, 0->1, ..., 5->6.
- Type 1 rows (standard DH, eq. 6.1): ``(r, l, alpha, dtheta)`` = ``Rz(theta)·Tz(r)·Tx(l)·Rx(alpha)``.
  B->0 has no joint variable (its theta is the constant ``dtheta``).
- Type 2 row 1->2 (Hayati, eq. 6.3): ``(l, alpha, beta, dtheta)`` = ``Rz(theta)·Tx(l)·Rx(alpha)·Ry(beta)``.
- Type 3 row 5->6 (eq. 6.4): ``(dx, dy, dz, tx, ty, tz)`` = ``Rz(tz)·Ry(ty)·Rx(tx)·T(dx, dy, dz)``,
  joint 6 entering as ``tz = Θ6 + param 6``.

ZRP tables (6.2, 6.7, 6.8, 6.12): per joint ``(u_x, u_y, u_z, p_x, p_y, p_z)`` in frame B at the
zero position, and the joint offsets (degrees). The book prints u to 3 decimals; the dependent
component is recomputed from the unit norm (Table 6.3: ``u_y`` for joints 1, 4, 6 along +Y,
``u_z`` for joints 2, 3, 5 along -Z). ``T0`` (eq. 6.11) is the end-effector pose at zero.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.transforms import matrix_to_pose

# --------------------------------------------------------------------------- DH tables

TABLE_6_1 = [  # nominal
    (32.878, -15.591, -90.000, 0.000),
    (14.681, -0.000, -90.000, 0.000),
    (17.000, 0.000, 0.000, 0.000),
    (5.870, -0.800, 90.000, 0.000),
    (17.050, 0.000, -90.000, 0.000),
    (0.000, 0.000, 90.000, 0.000),
    (0.000, 0.000, 2.213, 0.000, 0.000, 90.000),
]

TABLE_6_5 = [  # identified from data file 1
    (33.632, -15.022, -90.121, 0.086),
    (14.047, -0.000, -89.981, 1.962),
    (17.038, 0.062, -0.354, -0.109),
    (5.939, -0.807, 90.397, 0.735),
    (17.055, 0.005, -90.025, -0.512),
    (-0.015, -0.004, 89.986, -1.443),
    (-0.001, 0.024, 2.211, -0.019, 0.140, 87.901),
]

TABLE_6_6 = [  # identified from data file 2
    (33.635, -15.021, -90.132, 0.103),
    (14.048, 0.001, -89.974, 1.959),
    (17.034, 0.069, -0.337, -0.098),
    (5.915, -0.796, 90.310, 0.691),
    (17.054, 0.003, -89.978, -0.527),
    (-0.014, -0.005, 89.983, -1.442),
    (-0.009, 0.020, 2.212, -0.006, 0.208, 87.907),
]

TABLE_6_11 = [  # used in the accuracy test: the average of 6.5 and 6.6
    (33.634, -15.022, -90.127, 0.095),
    (14.048, -0.001, -89.978, 1.961),
    (17.036, 0.066, -0.346, -0.104),
    (5.927, -0.802, 90.354, 0.713),
    (17.055, 0.004, -90.002, -0.520),
    (-0.015, -0.005, 89.986, -1.443),
    (-0.005, 0.022, 2.212, -0.013, 0.174, 87.904),
]

# --------------------------------------------------------------------------- ZRP tables

T0 = np.array([[0, -1, 0, 1.2], [0, 0, 1, 33.96], [-1, 0, 0, 27.73], [0, 0, 0, 1.0]])  # eq. 6.11, inches

TABLE_6_2 = {  # nominal
    "axes": [
        (0, 1, 0, -15.00, 14.70, 33.60),
        (0, 0, -1, -15.00, 14.70, 27.73),
        (0, 0, -1, 2.00, 14.70, 27.73),
        (0, 1, 0, 1.20, 31.75, 27.73),
        (0, 0, -1, 1.20, 31.75, 27.73),
        (0, 1, 0, 1.20, 31.75, 27.73),
    ],
    "offsets": (0, 0, 0, 0, 0, 0),
}

TABLE_6_7 = {  # identified from data file 1
    "axes": [
        (-0.001, 1.000, -0.002, -15.044, 14.70, 33.601),
        (-0.003, -0.002, -1.000, -15.063, 14.014, 27.73),
        (-0.010, -0.001, -1.000, 1.926, 14.690, 27.73),
        (0.006, 1.000, 0.006, 1.229, 31.75, 27.716),
        (0.407, 0.002, -0.913, 1.228, 31.752, 27.73),
        (0.000, 1.000, 0.002, 1.224, 31.75, 27.729),
    ],
    "offsets": (1.773, 2.061, -1.889, 24.054, -1.040, -26.122),
}

TABLE_6_8 = {  # identified from data file 2 (u5: the book prints "-0.987j"; it is k)
    "axes": [
        (-0.002, 1.000, -0.002, -15.048, 14.70, 33.601),
        (-0.004, -0.002, -1.000, -15.067, 14.010, 27.73),
        (-0.010, -0.001, -1.000, 1.919, 14.691, 27.73),
        (0.006, 1.000, 0.004, 1.224, 31.75, 27.707),
        (0.158, 0.004, -0.987, 1.224, 31.751, 27.73),
        (0.000, 1.000, 0.004, 1.220, 31.75, 27.721),
    ],
    "offsets": (1.747, 2.073, -1.921, 9.138, -1.104, -11.209),
}

TABLE_6_12 = {  # used in the accuracy test (offset 6 printed with two decimals)
    "axes": [
        (-0.002, 1.000, -0.002, -15.046, 14.70, 33.601),
        (-0.004, -0.002, -1.000, -15.065, 14.012, 27.73),
        (-0.010, -0.001, -1.000, 1.923, 14.691, 27.73),
        (0.006, 1.000, 0.005, 1.227, 31.75, 27.712),
        (0.087, 0.003, -0.996, 1.226, 31.752, 27.73),
        (0.000, 1.000, 0.003, 1.222, 31.75, 27.725),
    ],
    "offsets": (1.760, 2.067, -1.905, 5.000, -1.072, -7.07),
}

# Table 6.3: which u component is dependent (index) and its sign
DEPENDENT_U = [(1, +1.0), (2, -1.0), (2, -1.0), (1, +1.0), (2, -1.0), (1, +1.0)]

# Table 6.4: standard deviations of the pose measurement (mm and radians)
SIGMA_POSITION_MM = 0.05024  # 0.001978 in (Fig. 6.8)
SIGMA_ORIENTATION_RAD = 0.0006

# --------------------------------------------------------------------------- builders


def _harden(r, l, alpha_deg, theta_deg):
    """Type 1 (eq. 6.1): Rz(theta)·Tz(r)·Tx(l)·Rx(alpha)."""
    a, t = math.radians(alpha_deg), math.radians(theta_deg)
    ca, sa, ct, st = math.cos(a), math.sin(a), math.cos(t), math.sin(t)
    return np.array([[ct, -st * ca, st * sa, l * ct], [st, ct * ca, -ct * sa, l * st], [0, sa, ca, r], [0, 0, 0, 1.0]])


def dh_document(table, name: str) -> dict:
    """A ``recal.model/1`` document (inches, degrees, ``dh`` with a Hayati link 2) for a DH table.

    B->0 becomes ``base``; 0->1 .. 4->5 the links of joints 1-5 (joint 2 Hayati); the Type 3
    transform 5->6 becomes joint 6 (``theta`` = param 6, a pure Rz link) and the tool
    ``Ry(ty)·Rx(tx)·T(dx, dy, dz)`` = pose ``[R·d, tx, ty, 0]``."""
    b = table[0]
    base = matrix_to_pose(_harden(b[0], b[1], b[2], b[3]))
    base = [*base[:3], *np.degrees(base[3:])]
    joints = [
        {"name": "j1", "theta": table[1][3], "d": table[1][0], "a": table[1][1], "alpha": table[1][2]},
        {"name": "j2", "theta": table[2][3], "a": table[2][0], "alpha": table[2][1], "beta": table[2][2]},
    ]
    for k in (3, 4, 5):
        r, l, alpha, dtheta = table[k]
        joints.append({"name": f"j{k}", "theta": dtheta, "d": r, "a": l, "alpha": alpha})
    dx, dy, dz, tx, ty, tz = table[6]
    joints.append({"name": "j6", "theta": tz, "d": 0.0, "a": 0.0, "alpha": 0.0})
    ca, sa = math.cos(math.radians(tx)), math.sin(math.radians(tx))
    cb, sb = math.cos(math.radians(ty)), math.sin(math.radians(ty))
    R = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]]) @ np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    t = R @ np.array([dx, dy, dz])
    return {
        "format": "recal.model/1",
        "name": name,
        "units": {"length": "in", "angle": "deg"},
        "convention": "dh",
        "base": [float(v) for v in base],
        "joints": joints,
        "tool": [*t.tolist(), tx, ty, 0.0],
        "targets": {},
    }


def unit_axis(row, joint: int) -> np.ndarray:
    """The axis of a ZRP row with its dependent component recomputed (Table 6.3)."""
    u = np.array(row[:3], dtype=float)
    k, sign = DEPENDENT_U[joint]
    others = [i for i in range(3) if i != k]
    u[k] = sign * math.sqrt(max(0.0, 1.0 - u[others[0]] ** 2 - u[others[1]] ** 2))
    return u


def zrp_document(table, name: str) -> dict:
    """A ``recal.model/1`` ``poe`` document (inches, degrees) for a ZRP table: FK = D1···D6·T0
    with φ_i = Θ_i + offset_i (eq. 2.75, 6.2)."""
    home = matrix_to_pose(T0)
    joints = []
    for i, row in enumerate(table["axes"]):
        joints.append(
            {
                "name": f"j{i + 1}",
                "axis": unit_axis(row, i).tolist(),
                "point": list(row[3:]),
                "theta": table["offsets"][i],
            }
        )
    return {
        "format": "recal.model/1",
        "name": name,
        "units": {"length": "in", "angle": "deg"},
        "convention": "poe",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": joints,
        "home": [*home[:3].tolist(), *np.degrees(home[3:]).tolist()],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }
