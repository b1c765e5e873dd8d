"""Nominal models of ABB-, KUKA- and Fanuc-like six-axis arms, built here for the program tests
(mm and degrees, standard DH), each with its brand's zero pose and joint directions:

- ABB-like: zero = upper arm vertical, forearm horizontal forward; J2 and J3 positive tilt
  forward and down;
- KUKA-like: A2 = 0 upper arm horizontal, A2 = -90 vertical, A3 = 0 stretched, A1, A4 and A6
  turning the other way (gain -1);
- Fanuc-like: the ABB-like chain read through the coupling of contracts §2 (J3 from the horizon,
  C = [[1,..],[0,1,..],[0,-1,-1,..],[..,-1,..],[..,-1,..],[..,-1]]).

And a "true robot" for each: the nominal with sub-millimetre and sub-0.1° errors in every link.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from calibration.conventions import hayati_for_parallel_axes
from calibration.model import model_from_dict
from calibration.parameters import apply_step, candidate_parameters

DEG = math.pi / 180


def _joint(name, theta, d, a, alpha, lo, hi, **kw):
    return {
        "name": name,
        "type": "revolute",
        "theta": theta,
        "d": d,
        "a": a,
        "alpha": alpha,
        "lower": lo,
        "upper": hi,
        **kw,
    }


def arm(brand: str):
    if brand == "abb":
        joints = [
            _joint("j1", 0, 495, 175, -90, -180, 180),
            _joint("j2", -90, 0, 900, 0, -90, 150),
            _joint("j3", 0, 0, 175, -90, -180, 75),
            _joint("j4", 0, 960, 0, 90, -400, 400),
            _joint("j5", 0, 0, 0, -90, -125, 125),
            _joint("j6", 0, 135, 0, 0, -400, 400),
        ]
        extra = {}
    elif brand == "kuka":
        joints = [
            _joint("a1", 0, 675, 260, -90, -185, 185, gain=-1),
            _joint("a2", 0, 0, 680, 0, -140, -5),
            _joint("a3", -90, 0, 35, -90, -120, 158),
            _joint("a4", 0, 670, 0, 90, -350, 350, gain=-1),
            _joint("a5", 0, 0, 0, -90, -122.5, 122.5),
            _joint("a6", 0, 115, 0, 0, -350, 350, gain=-1),
        ]
        extra = {}
    elif brand == "fanuc":
        joints = [
            _joint("j1", 0, 525, 150, -90, -170, 170),
            _joint("j2", -90, 0, 790, 0, -100, 160),
            _joint("j3", 0, 0, 150, -90, -170, 270),
            _joint("j4", 0, 860, 0, 90, -200, 200),
            _joint("j5", 0, 0, 0, -90, -140, 140),
            _joint("j6", 0, 100, 0, 0, -450, 450),
        ]
        extra = {
            "coupling": [
                [1, 0, 0, 0, 0, 0],
                [0, 1, 0, 0, 0, 0],
                [0, -1, -1, 0, 0, 0],
                [0, 0, 0, -1, 0, 0],
                [0, 0, 0, 0, -1, 0],
                [0, 0, 0, 0, 0, -1],
            ]
        }
    else:
        raise ValueError(brand)
    return model_from_dict(
        {
            "format": "recal.model/1",
            "name": f"{brand}-like",
            "units": {"length": "mm", "angle": "deg"},
            "convention": "dh",
            "base": [0, 0, 0, 0, 0, 0],
            "tool": [0, 0, 0, 0, 0, 0],
            "joints": joints,
            **extra,
        }
    )


def true_robot(nominal, seed: int, base=(2000.0, -500.0, 150.0, 0.2, -0.1, 25.0)):
    """The nominal with errors in every link (0.5 mm, 0.1° offsets, 0.05° twists) and where the
    instrument sees its base: what `recal identify` would hand back for a well calibrated arm."""
    rng = np.random.default_rng(seed)
    m, _ = hayati_for_parallel_axes(nominal)
    params = candidate_parameters(m, base=False, tool=False)
    sig = [0.5e-3 if p.kind == "length" else 0.1 * DEG if p.name.endswith(".theta") else 0.05 * DEG for p in params]
    m = apply_step(m, params, rng.normal(0.0, sig))
    b = np.array(base, dtype=float)
    return dataclasses.replace(m, base=np.concatenate([b[:3] * 1e-3, b[3:] * DEG]), name=f"{nominal.name}-true-{seed}")
