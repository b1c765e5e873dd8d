"""An independent complete model to judge identification by (issue 14), and random arms to judge
it on.

``reference_fit``: every link of the nominal DH chain followed by its own 6-DOF error transform,
fitted with ``scipy.optimize.least_squares`` (over-parameterised on purpose: whatever the real
robot's deviations, this model can follow them), written here from contracts §2 without
``calibration.kinematics``.

``random_arm`` and ``random_case``: a random 6R in dh and a perturbed "true" robot of it, with
the reflector on the last axis or off it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.model import model_from_dict
from calibration.simulate import perturbed


def exp6(x):
    """A 6-DOF transform from (translation, rotation vector)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[3:]).as_matrix()
    T[:3, 3] = x[:3]
    return T


def dh_link(theta, d, a, alpha):
    """``Rz(θ)·Tz(d)·Tx(a)·Rx(α)`` (contracts §2) for arrays θ, d (N,): the product written out."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), math.cos(alpha), math.sin(alpha)
    A = np.zeros((len(theta), 4, 4))
    A[:, 0] = np.stack([ct, -st * ca, st * sa, a * ct], axis=1)
    A[:, 1] = np.stack([st, ct * ca, -ct * sa, a * st], axis=1)
    A[:, 2, 1], A[:, 2, 2], A[:, 2, 3], A[:, 3, 3] = sa, ca, d, 1.0
    return A


def reference_points(model, x, q):
    """``E0 · Π (Aᵢ(qᵢ) · Eᵢ) · target``: the nominal DH links (written from contracts §2) each
    followed by a 6-DOF error Eᵢ, and the target's position; ``x`` = 6 per Eᵢ, then the target."""
    n = model.n_joints
    T = np.broadcast_to(exp6(x[:6]), (len(q), 4, 4))
    for i, j in enumerate(model.joints):
        th = j.theta + (q[:, i] if j.revolute else 0.0)
        d = j.d + (0.0 if j.revolute else q[:, i])
        A = dh_link(np.broadcast_to(th, len(q)), np.broadcast_to(d, len(q)), j.a, j.alpha)
        T = T @ A @ exp6(x[6 * (i + 1) : 6 * (i + 2)])
    p = x[6 * (n + 1) :]
    return T[:, :3, :3] @ p + T[:, :3, 3]


def reference_fit(model, data, target="smr"):
    """The complete model fitted to ``data`` (one target); returns a predictor of positions."""
    n = model.n_joints
    x0 = np.concatenate([np.zeros(6 * (n + 1)), model.targets[target]])
    sol = least_squares(
        lambda x: (reference_points(model, x, data.q) - data.p_world).ravel(), x0, method="lm", xtol=1e-12, ftol=1e-12
    )
    return lambda q: reference_points(model, sol.x, q)


def random_arm(rng, *, on_axis: bool):
    """A random 6R in dh: each link's d and a zero or 0.1-0.5 m, alpha 0 or ±90° (so parallel,
    collinear and intersecting axes all occur); a reflector on the last axis, or 40 mm off it."""
    joints = []
    for i in range(6):
        joints.append(
            {
                "name": f"j{i + 1}",
                "theta": 0.0,
                "lower": -3.0,
                "upper": 3.0,
                "d": float(rng.choice([0.0, rng.uniform(0.1, 0.5)])),
                "a": float(rng.choice([0.0, rng.uniform(0.1, 0.5)])) if i < 5 else 0.0,
                "alpha": float(np.deg2rad(rng.choice([0.0, 90.0, -90.0]))) if i < 5 else 0.0,
            }
        )
    target = [0.0, 0.0, 0.05] if on_axis else [0.04, 0.01, 0.05]
    return model_from_dict(
        {
            "format": "recal.model/1",
            "units": {"length": "m", "angle": "rad"},
            "convention": "dh",
            "joints": joints,
            "targets": {"smr": target},
        }
    )


def random_case(seed: int):
    """Arm ``seed`` of a reproducible series (the even ones with the reflector nominally on the
    last axis), its true robot (links perturbed as calibration.simulate.perturbed does, the real
    reflector about 0.7 mm per axis off its nominal place) and the generator to go on with."""
    rng = np.random.default_rng(seed)
    nom = random_arm(rng, on_axis=seed % 2 == 0)
    truth = perturbed(nom, rng)
    truth = dataclasses.replace(truth, targets={"smr": nom.targets["smr"] + rng.normal(0, 0.7e-3, 3)})
    return nom, truth, rng
