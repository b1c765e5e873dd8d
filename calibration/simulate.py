"""Synthetic robots and measurements, for tests, benchmarks and the demo (book §4.5: simulate
the identification before measuring).

A "true" robot is the nominal one with every link carrying a small random 6-DOF error: the
nominal model is rewritten exactly in ``poe`` form (where every joint axis may tilt and shift
freely) and each axis, joint offset, the home, base and tool frames are perturbed.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .conventions import to_poe
from .identification import INSTRUMENT_SIGMA_M, Measurements
from .kinematics import fk
from .model import KinematicModel
from .parameters import apply_step, candidate_parameters
from .transforms import matrix_to_quat, rotvec_to_matrix
from .transmission import JointTransmission


def perturbed(
    model: KinematicModel,
    rng: np.random.Generator,
    *,
    length_m: float = 0.5e-3,
    angle_rad: float = np.deg2rad(0.05),
    offset_rad: float = np.deg2rad(0.1),
    base_length_m: float = 0.0,
    base_angle_rad: float = 0.0,
    tool_length_m: float = 0.0,
    tool_angle_rad: float = 0.0,
) -> KinematicModel:
    """A "true" robot near ``model`` (returned in ``poe`` form): normal errors of standard
    deviation ``length_m`` on every axis shift and the home position, ``angle_rad`` on every
    axis tilt and the home orientation, ``offset_rad`` on every joint offset; base and tool
    errors as given."""
    poe = to_poe(model)
    params = candidate_parameters(poe, targets=(), gains=False)
    delta = np.zeros(len(params))
    for k, p in enumerate(params):
        head, _, f = p.name.rpartition(".")
        if head == "base":
            delta[k] = rng.normal(0, base_length_m if f.startswith("t") else base_angle_rad)
        elif head == "tool":
            delta[k] = rng.normal(0, tool_length_m if f.startswith("t") else tool_angle_rad)
        elif head == "home":
            delta[k] = rng.normal(0, length_m if f.startswith("t") else angle_rad)
        elif f == "theta":
            delta[k] = rng.normal(0, offset_rad)
        elif f == "d":
            delta[k] = rng.normal(0, length_m)
        elif f.startswith("tilt"):
            delta[k] = rng.normal(0, angle_rad)
        elif f.startswith("shift"):
            delta[k] = rng.normal(0, length_m)
    return dataclasses.replace(apply_step(poe, params, delta), name=f"{model.name}-true")


def random_configurations(
    model: KinematicModel, n: int, rng: np.random.Generator, *, limits: np.ndarray | None = None
) -> np.ndarray:
    """``n`` joint vectors (n, joints) uniform within ``limits`` (n_joints, 2) (default the
    model's joint limits, clipped to ±pi for revolute joints)."""
    lim = model.joint_limits if limits is None else np.asarray(limits, dtype=float)
    lim = lim.copy()
    for i, j in enumerate(model.joints):
        if j.revolute and limits is None:
            lim[i] = np.clip(lim[i], -np.pi, np.pi)
    return rng.uniform(lim[:, 0], lim[:, 1], size=(n, model.n_joints))


def simulate_measurements(
    truth: KinematicModel,
    q: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma_m: float = INSTRUMENT_SIGMA_M,
    targets: tuple[str | None, ...] = (None,),
    full_pose: bool = False,
    sigma_rad: float = 0.0,
    payload: np.ndarray | None = None,
    transmission: JointTransmission | None = None,
) -> Measurements:
    """Measurements of ``truth`` at readings ``q`` (N, n): every named target (``None``: the tool
    origin) at every configuration, with normal noise ``sigma_m`` per axis; with ``full_pose``,
    the tool orientation too, rotated by normal noise ``sigma_rad`` per axis. ``payload`` (N, 4)
    or (4,): kg and centre of gravity in the tool frame (m) at each configuration (a compliant
    ``truth`` sags under it); the rows carry it. ``transmission``: the truth's joint transmission
    errors (:func:`harmonic_drive_errors`): the joints stand at ``q + δq(q)`` while the rows
    record the readings ``q``."""
    q = np.asarray(q, dtype=float)
    pay = None if payload is None else np.broadcast_to(np.asarray(payload, dtype=float), (len(q), 4))
    T = fk(truth, q if transmission is None else q + transmission.joint_errors(q), pay)
    rows_q, rows_p, rows_t, rows_quat, pose_id, rows_pay = [], [], [], [], [], []
    for t in targets:
        p_tool = truth.target(t)
        p = T[:, :3, 3] + T[:, :3, :3] @ p_tool
        rows_q.append(q)
        rows_p.append(p + rng.normal(0, sigma_m, p.shape))
        rows_t += [t] * len(q)
        rows_pay.append(np.zeros((len(q), 4)) if pay is None else pay)
        pose_id.append(np.arange(len(q)))
        if full_pose:
            R = T[:, :3, :3]
            if sigma_rad > 0:
                R = rotvec_to_matrix(rng.normal(0, sigma_rad, (len(q), 3))) @ R
            rows_quat.append(matrix_to_quat(R))
    order = np.argsort(np.concatenate(pose_id), kind="stable")
    cat = lambda a: np.concatenate(a)[order]  # noqa: E731
    return Measurements(
        q=cat(rows_q),
        p_world=cat(rows_p),
        quat=cat(rows_quat) if full_pose else None,
        target=np.array(rows_t, dtype=object)[order],
        pose_id=cat(pose_id),
        payload=None if pay is None else cat(rows_pay),
    )


# ------------------------------------------------------------- joint transmission errors (issue 28)

# A harmonic drive's transmission error, per joint (rad), by term: (cycles per output turn, amplitude).
# Figures of the size and shape stated for cobot-size drives (a transmission accuracy of the order
# of one arc-minute peak to peak in the makers' catalogues; measured errors, e.g. Tuttle and
# Seering 1996, are dominated by once- and twice-per-output-turn terms, with a ripple at twice the
# wave generator's speed). The amplitudes here are below the catalogue's bound, as on a good arm:
# - once per output turn (circular spline and bearing eccentricity): 0.004-0.010 deg;
# - twice per output turn (flexspline ellipticity): 0.002-0.005 deg;
# - twice per wave-generator turn, i.e. 2N per output turn for gear ratio N: 3-8 arc-seconds, a
#   period of 1.8 deg of joint angle at N = 100: "sharp in the configuration", as issue 28 found on
#   a real UR10 where smooth maps failed.
# At a UR10's reach (1.3 m) 0.01 deg is 0.2 mm: the size of what a complete geometric model left
# on the measured UR10 (0.49 mm) and UR5 (0.11 mm).
HARMONIC_DRIVE_TERMS_DEG = ((1.0, (0.004, 0.010)), (2.0, (0.002, 0.005)), ("2N", (3 / 3600, 8 / 3600)))
HARMONIC_DRIVE_RATIO = 101  # UR-class joints: 100-101:1 harmonic drives


def harmonic_drive_errors(
    model: KinematicModel, rng: np.random.Generator, *, gear_ratios: tuple[float, ...] | None = None
) -> JointTransmission:
    """Joint transmission errors of harmonic drives (:data:`HARMONIC_DRIVE_TERMS_DEG`) for every
    revolute joint of ``model``: each term's amplitude uniform in its range, its phase uniform;
    ``gear_ratios`` per joint (default :data:`HARMONIC_DRIVE_RATIO` for all)."""
    n = model.n_joints
    ratios_n = gear_ratios or (HARMONIC_DRIVE_RATIO,) * n
    ratios, coefs = [], []
    for i, j in enumerate(model.joints):
        if not j.revolute:
            ratios.append(np.zeros(0))
            coefs.append(np.zeros((0, 2)))
            continue
        r, c = [], []
        for k, (lo, hi) in HARMONIC_DRIVE_TERMS_DEG:
            amp, phase = np.deg2rad(rng.uniform(lo, hi)), rng.uniform(0, 2 * np.pi)
            r.append(2.0 * ratios_n[i] if k == "2N" else float(k))
            c.append((amp * np.sin(phase), amp * np.cos(phase)))  # a·sin(r q + φ) = a sinφ cos + a cosφ sin
        ratios.append(np.array(r))
        coefs.append(np.array(c))
    return JointTransmission(tuple(ratios), tuple(coefs))


# ------------------------------------------------------------------ arms that sag under gravity

# A 165 kg-payload industrial arm: R-2000iC/165F-class dimensions (mm), standard DH, the
# shoulder (j2) offset so that q = 0 holds the lower arm upright. Approximate figures for
# simulation; not a vendor's published model.
HEAVY_ARM_DH = (
    (670.0, 312.0, -90.0, 0.0),
    (0.0, 1075.0, 0.0, -90.0),
    (0.0, 225.0, -90.0, 0.0),
    (1280.0, 0.0, 90.0, 0.0),
    (0.0, 0.0, -90.0, 0.0),
    (215.0, 0.0, 0.0, 0.0),
)  # d, a, alpha, theta


def heavy_arm_nominal() -> KinematicModel:
    """The nominal model of a 165 kg-payload arm (:data:`HEAVY_ARM_DH`), in mm and degrees."""
    from .model import model_from_dict

    limits = ((-180, 180), (-60, 75), (-80, 180), (-180, 180), (-125, 125), (-180, 180))
    return model_from_dict(
        {
            "format": "recal.model/1",
            "name": "arm165-nominal",
            "units": {"length": "mm", "angle": "deg"},
            "convention": "dh",
            "base": [0] * 6,
            "tool": [0] * 6,
            "targets": {},
            "joints": [
                {
                    "name": f"j{i + 1}",
                    "type": "revolute",
                    "d": d,
                    "a": a,
                    "alpha": al,
                    "theta": th,
                    "lower": lo,
                    "upper": hi,
                }
                for i, ((d, a, al, th), (lo, hi)) in enumerate(zip(HEAVY_ARM_DH, limits))
            ],
        }
    )


# Physical figures of two sagging arms (SI): joint compliance (rad per N·m = 1 / stiffness), lumped
# masses {link joint: (kg, centre of gravity in that link's DH frame, m)}, rated payload (kg, cog).
#
# - "cobot": a UR10e-class arm (10 kg payload class). Link masses from Universal Robots' published
#   dynamic parameters (upper arm 13 kg, forearm 4 kg, wrists 4.7 kg lumped at the flange);
#   joint stiffness 2e5 N·m/rad (shoulder) and 1e5 N·m/rad (elbow), the order reported for
#   harmonic-drive cobot joints. Sag at full reach and payload: about 2 mm.
# - "arm165": a 165 kg-payload arm. Joint stiffness 5e6 N·m/rad (j2) and 2e6 N·m/rad (j3), the
#   order of magnitude identified on heavy arms of this class (a few 1e6 N·m/rad for the
#   shoulder and elbow, e.g. Dumas et al. 2011 on a KUKA KR 240); the lower arm's net weight after
#   its gravity balancer 60 kg, the upper arm with the wrist housing 180 kg, the wrist 50 kg. Sag
#   at full payload, arm stretched out: 4 to 6 mm; what a complete geometric model cannot absorb of it,
#   over the whole joint range with and without the payload: about 1.5 mm RMS (bench/compliance.py;
#   the arm in issue 17, measured in a smaller region, left 0.5 mm).
SAGGING_ARMS = {
    "cobot": dict(
        compliance={"j2": 5e-6, "j3": 1e-5},
        masses={"j2": (13.0, (0.306, 0.0, 0.175)), "j3": (4.0, (0.286, 0.0, 0.05)), "j6": (4.7, (0.0, 0.0, -0.08))},
        payload=(10.0, 0.0, 0.0, 0.1),
    ),
    "arm165": dict(
        compliance={"j2": 2e-7, "j3": 5e-7},
        masses={"j2": (60.0, (-0.54, 0.0, 0.0)), "j3": (180.0, (0.0, -0.4, 0.0)), "j6": (50.0, (0.0, 0.0, -0.1))},
        payload=(165.0, 0.0, 0.0, 0.2),
    ),
}


def sagging(model: KinematicModel, arm: str, *, frames_of: KinematicModel | None = None) -> KinematicModel:
    """``model`` with the joint compliance and lumped masses of one of :data:`SAGGING_ARMS` (no
    default payload). The masses' centres of gravity are given in DH link frames: ``frames_of``
    names the DH model they refer to when ``model`` is in another convention (a true robot made
    by :func:`perturbed` is in ``poe``)."""
    from .compliance import lumps_in_frames_of, physical_section, with_section

    fig: dict[str, Any] = SAGGING_ARMS[arm]
    masses = fig["masses"] if frames_of is None else lumps_in_frames_of(fig["masses"], frames_of, model)
    return with_section(model, physical_section(model, fig["compliance"], masses))
