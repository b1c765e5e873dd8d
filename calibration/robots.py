"""A library of nominal robot models, by name (``nominal("ur10e")``).

- Universal Robots e-Series (UR3e, UR5e, UR10e, UR16e): the DH tables Universal Robots
  publishes for its robots (standard DH, mm and degrees).
- PUMA 560 of the book's case study (Mooring, Roth & Driels, ch. 6), in inches and degrees as
  printed: ``puma560`` is the modified-DH model of Table 6.1 (standard DH links, Hayati's form
  for the parallel joints 2-3, the base transform B->0 and the 6-parameter tool transform folded
  exactly into ``base`` and joint 6), and ``puma560-zrp`` the zero-reference-position model of
  Table 6.2 with T0 of eq. 6.11 as ``home``.
- Industrial arms (KUKA KR 16, KR 210, LBR iiwa 14; ABB IRB 4600, IRB 6700; Fanuc M-20iA,
  R-2000iC with the J2/J3 coupling; Yaskawa GP25; Staubli TX2-90; Franka FR3): the serial chains
  of their public ROS descriptions, in mm and degrees.

Every document names the source of its figures in a top-level ``"source"`` and says what the
robot is in ``"description"``; joints carry ``velocity`` and ``effort`` limits where published.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .model import KinematicModel, Units, model_from_dict, model_to_dict
from .urdf import ChainJoint, chain_to_model, origin

_UR_SOURCE = (
    "Universal Robots, DH parameters for calculations of kinematics and dynamics (published table, "
    "standard DH); speed and torque limits from Universal Robots' ur_description "
    "(github.com/UniversalRobots/Universal_Robots_ROS2_Description, config/<type>/joint_limits.yaml)"
)

# (deg/s, N·m) per joint, from ur_description's joint_limits.yaml of each type.
_UR_LIMITS = {
    "ur3e": ((180, 180, 180, 360, 360, 360), (54, 54, 28, 9, 9, 9)),
    "ur5e": ((180,) * 6, (150, 150, 150, 28, 28, 28)),
    "ur10e": ((120, 120, 180, 180, 180, 180), (330, 330, 150, 54, 54, 54)),
    "ur16e": ((120, 120, 180, 180, 180, 180), (330, 330, 150, 54, 54, 54)),
}

_UR_DH = {
    # name: (d1, a2, a3, d4, d5, d6) in mm, from Universal Robots' published DH parameters.
    "ur3e": (151.85, -243.55, -213.2, 131.05, 85.35, 92.1),
    "ur5e": (162.5, -425.0, -392.2, 133.3, 99.7, 99.6),
    "ur10e": (180.7, -612.7, -571.55, 174.15, 119.85, 116.55),
    "ur16e": (180.7, -478.4, -360.0, 174.15, 119.85, 116.55),
}


def _ur(name: str) -> dict[str, Any]:
    d1, a2, a3, d4, d5, d6 = _UR_DH[name]
    rows = [(d1, 0.0, 90.0), (0.0, a2, 0.0), (0.0, a3, 0.0), (d4, 0.0, 90.0), (d5, 0.0, -90.0), (d6, 0.0, 0.0)]
    velocity, effort = _UR_LIMITS[name]
    return {
        "format": "recal.model/1",
        "name": f"{name}-nominal",
        "source": _UR_SOURCE,
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": [
            {
                "name": f"j{i + 1}",
                "type": "revolute",
                "theta": 0.0,
                "d": d,
                "a": a,
                "alpha": alpha,
                "lower": -360.0,
                "upper": 360.0,
                "velocity": float(velocity[i]),
                "effort": float(effort[i]),
            }
            for i, (d, a, alpha) in enumerate(rows)
        ],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


# Joint ranges of the PUMA 560 (degrees), as commonly published for the arm.
_PUMA_LIMITS = [(-160, 160), (-225, 45), (-45, 225), (-110, 170), (-100, 100), (-266, 266)]


def _puma_dh() -> dict[str, Any]:
    """Table 6.1 (inches, degrees). B->0 (Type 1, no joint variable):
    Rz(0)·Tz(32.878)·Tx(-15.591)·Rx(-90) = pose [-15.591, 0, 32.878, -90, 0, 0].
    1->2 is Hayati's Type 2 (``beta``). 5->6 (Type 3, eq. 6.4):
    Rz(Θ6 + 90)·Ry(0)·Rx(0)·T(0, 0, 2.213) = a DH link with theta = 90, d = 2.213 and an
    identity tool."""
    links = [
        {"theta": 0.0, "d": 14.681, "a": 0.0, "alpha": -90.0},
        {"theta": 0.0, "a": 17.000, "alpha": 0.0, "beta": 0.0},
        {"theta": 0.0, "d": 5.870, "a": -0.800, "alpha": 90.0},
        {"theta": 0.0, "d": 17.050, "a": 0.0, "alpha": -90.0},
        {"theta": 0.0, "d": 0.0, "a": 0.0, "alpha": 90.0},
        {"theta": 90.0, "d": 2.213, "a": 0.0, "alpha": 0.0},
    ]
    return {
        "format": "recal.model/1",
        "name": "puma560-nominal",
        "source": "Mooring, Roth & Driels (1991), Fundamentals of Manipulator Calibration, Table 6.1; joint "
        "ranges as commonly published for the PUMA 560",
        "units": {"length": "in", "angle": "deg"},
        "convention": "dh",
        "base": [-15.591, 0.0, 32.878, -90.0, 0.0, 0.0],
        "joints": [
            {"name": f"j{i + 1}", "type": "revolute", **link, "lower": lo, "upper": hi}
            for i, (link, (lo, hi)) in enumerate(zip(links, _PUMA_LIMITS))
        ],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


def _puma_zrp() -> dict[str, Any]:
    """Table 6.2 (u dimensionless, p in inches) with T0 of eq. 6.11 as ``home``:
    T0 = [[0,-1,0,1.2],[0,0,1,33.96],[-1,0,0,27.73]] = pose [1.2, 33.96, 27.73, 0, 90, 90]."""
    axes = [(0, 1, 0), (0, 0, -1), (0, 0, -1), (0, 1, 0), (0, 0, -1), (0, 1, 0)]
    points = [
        (-15.00, 14.70, 33.60),
        (-15.00, 14.70, 27.73),
        (2.00, 14.70, 27.73),
        (1.20, 31.75, 27.73),
        (1.20, 31.75, 27.73),
        (1.20, 31.75, 27.73),
    ]
    return {
        "format": "recal.model/1",
        "name": "puma560-zrp-nominal",
        "source": "Mooring, Roth & Driels (1991), Fundamentals of Manipulator Calibration, Table 6.2 and eq. 6.11; "
        "joint ranges as commonly published for the PUMA 560",
        "units": {"length": "in", "angle": "deg"},
        "convention": "poe",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": [
            {
                "name": f"j{i + 1}",
                "type": "revolute",
                "axis": list(u),
                "point": list(p),
                "theta": 0.0,
                "lower": lo,
                "upper": hi,
            }
            for i, (u, p, (lo, hi)) in enumerate(zip(axes, points, _PUMA_LIMITS))
        ],
        "home": [1.2, 33.96, 27.73, 0.0, 90.0, 90.0],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


# --------------------------------------------------------------------------- industrial arms
#
# Each arm is the serial chain of its public ROS description (ROS-Industrial support packages,
# franka_description), transcribed joint by joint: (name, origin xyz in m, origin rpy in rad,
# axis, lower, upper in rad, velocity in rad/s, effort in N·m), then the fixed joints to the
# ROS-Industrial ``tool0`` frame (the flange with z pointing out of it). The model's flange is
# ``tool0``, so a reading is the joint position the ROS driver reports (Fanuc: see coupling).
# calibration.urdf builds the model (exact poe, then dh by common normals), the same code that
# reads a URDF file.

_D = math.radians
_PI = math.pi


def _j(name, xyz, axis, lower_deg, upper_deg, vel_deg_s=None, effort=None, rpy=(0.0, 0.0, 0.0)):
    return (name, xyz, rpy, axis, _D(lower_deg), _D(upper_deg), None if vel_deg_s is None else _D(vel_deg_s), effort)


def _jr(name, xyz, axis, lower, upper, vel=None, effort=None, rpy=(0.0, 0.0, 0.0)):
    """As _j, with limits already in rad and rad/s (as the source writes them)."""
    return (name, xyz, rpy, axis, lower, upper, vel, effort)


_ROSI = "ROS-Industrial {repo} ({pkg}/urdf/{file}, commit {commit}): joint origins, axes, limits{extra}"
_ARMS: dict[str, dict[str, Any]] = {
    "kr16": {
        "description": "KUKA KR 16-2, 6-axis, 16 kg, 1.61 m reach",
        "source": _ROSI.format(
            repo="kuka_experimental",
            pkg="kuka_kr16_support",
            file="kr16_2_macro.xacro",
            commit="e78bbd15edb2b39c9053ff3b963ef2947e10a531",
            extra=" and velocities",
        ),
        "joints": [
            _j("joint_a1", (0, 0, 0.675), (0, 0, -1), -185, 185, 156),
            _j("joint_a2", (0.26, 0, 0), (0, 1, 0), -155, 35, 156),
            _j("joint_a3", (0.68, 0, 0), (0, 1, 0), -130, 154, 156),
            _j("joint_a4", (0.67, 0, -0.035), (-1, 0, 0), -350, 350, 330),
            _j("joint_a5", (0, 0, 0), (0, 1, 0), -130, 130, 330),
            _j("joint_a6", (0, 0, 0), (-1, 0, 0), -350, 350, 615),
        ],
        "tail": [((0.158, 0, 0), (0, 0, 0)), ((0, 0, 0), (0, _PI / 2, 0))],
    },
    "kr210": {
        "description": "KUKA KR 210 L150 (KR 210-2 family), 6-axis, 150 kg, 3.1 m reach",
        "source": _ROSI.format(
            repo="kuka_experimental",
            pkg="kuka_kr210_support",
            file="kr210l150_macro.xacro",
            commit="e78bbd15edb2b39c9053ff3b963ef2947e10a531",
            extra=" and velocities (CAD-derived origins, kept as published)",
        ),
        "joints": [
            _j("joint_a1", (-0.00262, 0.00097586, 0.33099), (0, 0, 1), -185, 185, 123),
            _j("joint_a2", (0.35277, -0.037476, 0.4192), (0, 1, 0), -45, 85, 115),
            _j("joint_a3", (-9.8483e-05, -0.1475, 1.2499), (0, 1, 0), -210, 65, 112),
            _j("joint_a4", (0.95795, 0.184, -0.055059), (1, 0, 0), -350, 350, 179),
            _j("joint_a5", (0.542, 0, 0), (0, 1, 0), -125, 125, 172),
            _j("joint_a6", (0.1925, 0, 0), (1, 0, 0), -350, 350, 219),
        ],
        "tail": [((0.0375, 0, -0.00023924), (0, 0, 0)), ((0, 0, 0), (0, _PI / 2, 0))],
    },
    "irb4600": {
        "description": "ABB IRB 4600-60/2.05, 6-axis, 60 kg, 2.05 m reach",
        "source": _ROSI.format(
            repo="abb_experimental",
            pkg="abb_irb4600_support",
            file="irb4600_60_205_macro.xacro",
            commit="20b9cf86ad274e4f98540b9c9efe59f94245d2d1",
            extra=" and velocities",
        ),
        "joints": [
            _jr("joint_1", (0, 0, 0.495), (0, 0, 1), -3.141, 3.141, 3.054),
            _jr("joint_2", (0.175, 0, 0), (0, 1, 0), -1.570, 2.617, 3.054),
            _jr("joint_3", (0, 0, 0.9), (0, 1, 0), -3.141, 1.308, 3.054),
            _jr("joint_4", (0, 0, 0.175), (1, 0, 0), -6.981, 6.981, 4.363),
            _jr("joint_5", (0.960, 0, 0), (0, 1, 0), -2.181, 2.094, 4.363),
            _jr("joint_6", (0.135, 0, 0), (1, 0, 0), -6.981, 6.981, 6.283),
        ],
        "tail": [((0, 0, 0), (0, _PI / 2, 0))],
    },
    "irb6700": {
        "description": "ABB IRB 6700-200/2.60, 6-axis, 200 kg, 2.60 m reach",
        "source": _ROSI.format(
            repo="abb_experimental",
            pkg="abb_irb6700_support",
            file="irb6700_200_260_macro.xacro",
            commit="20b9cf86ad274e4f98540b9c9efe59f94245d2d1",
            extra=" and velocities (the balancing cylinder's joints are not on the chain)",
        ),
        "joints": [
            _j("joint_1", (0, 0, 0.78), (0, 0, 1), -170, 170, 110),
            _j("joint_2", (0.32, 0, 0), (0, 1, 0), -65, 85, 110),
            _j("joint_3", (0, 0, 1.125), (0, 1, 0), -180, 70, 110),
            _j("joint_4", (0, 0, 0.2), (1, 0, 0), -300, 300, 190),
            _j("joint_5", (1.1425, 0, 0), (0, 1, 0), -130, 130, 150),
            _j("joint_6", (0.2, 0, 0), (1, 0, 0), -360, 360, 210),
        ],
        "tail": [((0, 0, 0), (0, _PI / 2, 0))],
    },
    "m20ia": {
        "description": "Fanuc M-20iA, 6-axis, 20 kg, 1.81 m reach; J3 read relative to the horizon (coupling)",
        "source": _ROSI.format(
            repo="fanuc",
            pkg="fanuc_m20ia_support",
            file="m20ia_macro.xacro",
            commit="8fee5e30e535378758ace26dfdffb8ab0403e23c",
            extra=" and velocities; J2/J3 coupling: fanuc_driver's linkage_transform with "
            "J23_factor 1 (robot_interface_streaming_m20ia.launch)",
        ),
        "joints": [
            _jr("joint_1", (0, 0, 0.525), (0, 0, 1), -2.967060, 2.967060, 3.403392),
            _jr("joint_2", (0.150, 0, 0), (0, 1, 0), -1.745329, 2.792527, 3.054326),
            _jr("joint_3", (0, 0, 0.790), (0, -1, 0), -3.228859, 4.766843, 3.141593),
            _jr("joint_4", (0, 0, 0.250), (-1, 0, 0), -3.490658, 3.490658, 6.283185),
            _jr("joint_5", (0.835, 0, 0), (0, -1, 0), -2.443461, 2.443461, 6.283185),
            _jr("joint_6", (0.100, 0, 0), (-1, 0, 0), -4.712389, 4.712389, 9.599311),
        ],
        "tail": [((0, 0, 0), (_PI, -_PI / 2, 0))],
        "j23": True,
    },
    "r2000ic": {
        "description": "Fanuc R-2000iC/165F, 6-axis, 165 kg, 2.66 m reach; J3 read relative to the horizon (coupling)",
        "source": _ROSI.format(
            repo="fanuc_experimental",
            pkg="fanuc_r2000ic_support",
            file="r2000ic165f_macro.xacro",
            commit="39929f69abd6b4a5bdca414d3d9bdb71919011e3",
            extra=" and velocities; J2/J3 coupling: fanuc_driver's linkage_transform with "
            "J23_factor 1 (robot_interface_streaming_r2000ic165f.launch)",
        ),
        "joints": [
            _j("joint_1", (0, 0, 0.670), (0, 0, 1), -185, 185, 130),
            _j("joint_2", (0.312, 0, 0), (0, 1, 0), -60, 76, 115),
            _j("joint_3", (0, 0, 1.075), (0, -1, 0), -132, 180, 125),
            _j("joint_4", (0, 0, 0.225), (-1, 0, 0), -360, 360, 180),
            _j("joint_5", (1.280, 0, 0), (0, -1, 0), -125, 125, 180),
            _j("joint_6", (0.215, 0, 0), (-1, 0, 0), -360, 360, 260),
        ],
        "tail": [((0, 0, 0), (_PI, -_PI / 2, 0))],
        "j23": True,
    },
    "gp25": {
        "description": "Yaskawa Motoman GP25, 6-axis, 25 kg, 1.73 m reach",
        "source": "ROS-Industrial motoman (motoman_gp25_support/urdf/gp25_macro.xacro, commit "
        "433be15f6a27cb9a5715cc3887b1cd15ff33a8cb): joint origins, axes, limits, velocities and efforts "
        "(tool0 rpy 3.1415926 -1.570796 0 read as pi, -pi/2)",
        "joints": [
            _j("joint_1_s", (0, 0, 0.505), (0, 0, 1), -180, 180, 210, 3087.0),
            _j("joint_2_l", (0.150, 0, 0), (0, 1, 0), -105, 155, 210, 3087.0),
            _j("joint_3_u", (0, 0, 0.760), (0, -1, 0), -86, 160, 265, 926.1),
            _j("joint_4_r", (0, 0, 0.200), (-1, 0, 0), -200, 200, 420, 88.2),
            _j("joint_5_b", (0.795, 0, 0), (0, -1, 0), -155, 150, 420, 70.56),
            _j("joint_6_t", (0, 0, 0), (-1, 0, 0), -455, 455, 885, 50.31),
        ],
        "tail": [((0.100, 0, 0), (_PI, -_PI / 2, 0))],
    },
    "tx2-90": {
        "description": "Staubli TX2-90, 6-axis, 14 kg, 1.0 m reach (floor mounted)",
        "source": "ROS-Industrial staubli_experimental (staubli_tx2_90_support/urdf/tx2_90_macro.xacro, commit "
        "256a71acea2161b64e12af1a6b925a7f26695007): joint origins, axes, limits, nominal velocities and "
        "efforts (floor mounted)",
        "joints": [
            _j("joint_1", (0, 0, 0.478), (0, 0, 1), -180, 180, 265, 318.0),
            _j("joint_2", (0.050, 0, 0), (0, 1, 0), -130, 147.5, 210, 166.0),
            _j("joint_3", (0, 0.050, 0.425), (0, 1, 0), -145, 145, 315, 76.0),
            _j("joint_4", (0, 0, 0), (0, 0, 1), -270, 270, 450, 34.0),
            _j("joint_5", (0, 0, 0.425), (0, 1, 0), -115, 140, 370, 29.0),
            _j("joint_6", (0, 0, 0.100), (0, 0, 1), -270, 270, 630, 11.0),
        ],
        "tail": [((0, 0, 0), (0, -_PI / 2, 0)), ((0, 0, 0), (0, _PI / 2, 0))],
    },
    "fr3": {
        "description": "Franka Research 3, 7-axis, 3 kg; flange = fr3_link8 (no hand)",
        "source": "franka_description (frankaemika/franka_description, robots/fr3/kinematics.yaml and "
        "joint_limits.yaml, commit b299b39d9692bfae795184df32a98ce7778d56af): joint origins, limits, "
        "velocities and efforts; every axis is the joint frame's z",
        "joints": [
            _jr("fr3_joint1", (0, 0, 0.333), (0, 0, 1), -2.7437, 2.7437, 2.62, 87.0),
            _jr("fr3_joint2", (0, 0, 0), (0, 0, 1), -1.7837, 1.7837, 2.62, 87.0, rpy=(-_PI / 2, 0, 0)),
            _jr("fr3_joint3", (0, -0.316, 0), (0, 0, 1), -2.9007, 2.9007, 2.62, 87.0, rpy=(_PI / 2, 0, 0)),
            _jr("fr3_joint4", (0.0825, 0, 0), (0, 0, 1), -3.0421, -0.1518, 2.62, 87.0, rpy=(_PI / 2, 0, 0)),
            _jr("fr3_joint5", (-0.0825, 0.384, 0), (0, 0, 1), -2.8065, 2.8065, 5.26, 12.0, rpy=(-_PI / 2, 0, 0)),
            _jr("fr3_joint6", (0, 0, 0), (0, 0, 1), 0.5445, 4.5169, 4.18, 12.0, rpy=(_PI / 2, 0, 0)),
            _jr("fr3_joint7", (0.088, 0, 0), (0, 0, 1), -3.0159, 3.0159, 5.26, 12.0, rpy=(_PI / 2, 0, 0)),
        ],
        "tail": [((0, 0, 0.107), (0, 0, 0))],
    },
    "iiwa14": {
        "description": "KUKA LBR iiwa 14 R820, 7-axis, 14 kg, 0.82 m reach",
        "source": _ROSI.format(
            repo="kuka_experimental",
            pkg="kuka_lbr_iiwa_support",
            file="lbr_iiwa_14_r820_macro.xacro",
            commit="e78bbd15edb2b39c9053ff3b963ef2947e10a531",
            extra=" and velocities; efforts: KUKA LBR iiwa 14 R820 data sheet, maximum torques",
        ),
        "joints": [
            _jr("joint_a1", (0, 0, 0), (0, 0, 1), -2.9668, 2.9668, 1.4834, 320.0),
            _jr("joint_a2", (-0.00043624, 0, 0.36), (0, 1, 0), -2.0942, 2.0942, 1.4834, 320.0),
            _jr("joint_a3", (0, 0, 0), (0, 0, 1), -2.9668, 2.9668, 1.7452, 176.0),
            _jr("joint_a4", (0.00043624, 0, 0.42), (0, -1, 0), -2.0942, 2.0942, 1.3089, 176.0),
            _jr("joint_a5", (0, 0, 0), (0, 0, 1), -2.9668, 2.9668, 2.2688, 110.0),
            _jr("joint_a6", (0, 0, 0.4), (0, 1, 0), -2.0942, 2.0942, 2.356, 40.0),
            _jr("joint_a7", (0, 0, 0), (0, 0, 1), -3.0541, 3.0541, 2.356, 40.0),
        ],
        "tail": [((0, 0, 0.126), (0, 0, 0))],
    },
}


def arm_chain(name: str) -> list[ChainJoint]:
    """The serial chain of a library arm (its ROS description's joints, to ``tool0``)."""
    arm = _ARMS[name]
    chain, parent = [], "base_link"
    for k, (jname, xyz, rpy, axis, lo, hi, vel, eff) in enumerate(arm["joints"]):
        child = f"link_{k + 1}"
        chain.append(
            ChainJoint(
                jname, "revolute", parent, child, origin(xyz, rpy), np.array(axis, dtype=float), lo, hi, vel, eff
            )
        )
        parent = child
    for k, (xyz, rpy) in enumerate(arm["tail"]):
        child = "tool0" if k == len(arm["tail"]) - 1 else f"fixed_{k + 1}"
        chain.append(ChainJoint(f"{parent}-{child}", "fixed", parent, child, origin(xyz, rpy), np.zeros(3)))
        parent = child
    return chain


def _arm(name: str) -> dict[str, Any]:
    arm = _ARMS[name]
    model = chain_to_model(f"{name}-nominal", arm_chain(name), convention="auto", units=Units("mm", "deg"))
    doc = model_to_dict(model)
    if arm.get("j23"):
        # Fanuc reports J3 relative to the horizon; fanuc_driver turns it into the serial angle
        # of the ROS description with J3_ros = J3 + J2 (linkage_transform, J23_factor = 1).
        n = model.n_joints
        C = np.eye(n)
        C[2, 1] = 1.0
        doc["coupling"] = C.tolist()
    return {
        "format": doc.pop("format"),
        "name": doc.pop("name"),
        "source": arm["source"],
        "description": arm["description"],
        **doc,
    }


_DESCRIPTIONS = {
    "ur3e": "Universal Robots UR3e, 6-axis, 3 kg, 0.5 m reach",
    "ur5e": "Universal Robots UR5e, 6-axis, 5 kg, 0.85 m reach",
    "ur10e": "Universal Robots UR10e, 6-axis, 12.5 kg, 1.3 m reach",
    "ur16e": "Universal Robots UR16e, 6-axis, 16 kg, 0.9 m reach",
    "puma560": "Unimation PUMA 560 of the book's case study (modified DH, Table 6.1; inches)",
    "puma560-zrp": "Unimation PUMA 560 of the book's case study (zero-reference position, Table 6.2; inches)",
    **{k: v["description"] for k, v in _ARMS.items()},
}

_LIBRARY: dict[str, Callable[[], dict]] = {
    **{name: functools.partial(_ur, name) for name in _UR_DH},
    "puma560": _puma_dh,
    "puma560-zrp": _puma_zrp,
    **{name: functools.partial(_arm, name) for name in _ARMS},
}


def describe(name: str) -> str:
    """A one-line description of a library robot."""
    return _DESCRIPTIONS[name.lower()]


def is_ur(model_name: str) -> bool:
    """Whether a model name is a Universal Robots arm of the library, as written or identified
    (``ur10e-nominal``, ``ur10e-identified``, ``ur5e-controller``)."""
    head = model_name.lower().split("-")[0]
    return head in _UR_DH


def names() -> tuple[str, ...]:
    """The names ``nominal`` accepts."""
    return tuple(sorted(_LIBRARY))


def nominal_document(name: str) -> dict[str, Any]:
    """The ``recal.model/1`` document of a library robot (its published units)."""
    try:
        doc = _LIBRARY[name.lower()]()
    except KeyError:
        raise KeyError(f"unknown robot {name!r}; known: {', '.join(names())}") from None
    doc.setdefault("description", describe(name))
    return doc


def nominal(name: str) -> KinematicModel:
    """The nominal model of a library robot."""
    return model_from_dict(nominal_document(name))
