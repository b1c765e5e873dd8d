"""Identifiability facts from the book as tests: the completeness count N = 4R + 2P + 6
(book eq. 2.63, extraction ``ch2_ch3.md`` §3.3) and the 5R1P identification study of Driels &
Pathre (book §4.5.2, Table 4.1; extraction ``ch4a.md`` §4.3 and §6.2).

Ranks are numerical ranks of the identification Jacobian (columns of round-off size dropped,
the others scaled to unit norm, singular values below 1e-8 of the largest counted as zero). The
condition numbers of the 5R1P study are cond₂ of the position Jacobian in inch/radian units,
which is what the book's κ tracks (extraction §6.2).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from sample_models import craig_puma_mdh_doc, stanford_5r1p_doc

from calibration.conventions import hayati_for_parallel_axes, to_poe
from calibration.identification import Measurements
from calibration.identify import identify
from calibration.jacobian import predict
from calibration.kinematics import target_positions
from calibration.model import model_from_dict
from calibration.parameters import Parameter, apply_step, candidate_parameters, parameter_values
from calibration.robots import nominal
from calibration.simulate import random_configurations

IN = 0.0254
DEG = math.pi / 180


def _rank(model, *, full_pose: bool, n: int = 40, seed: int = 0, p_tool=np.zeros(3)) -> tuple[int, int]:  # noqa: B008 (read only)
    """(number of candidate parameters, numerical rank) of the full model's Jacobian: base, every
    link parameter and the tool free."""
    q = random_configurations(model, n, np.random.default_rng(seed))
    params = candidate_parameters(model)
    pred = predict(model, q, p_tool, params)
    J = pred.Jp.reshape(-1, len(params))
    if full_pose:
        J = np.vstack([J, pred.Jr.reshape(-1, len(params))])
    norms = np.linalg.norm(J, axis=0)
    live = norms > 1e-12 * norms.max()  # a column of round-off is a parameter with no effect
    s = np.linalg.svd(J[:, live] / norms[live], compute_uv=False)
    return len(params), int(np.sum(s > 1e-8 * s[0]))


def _one_joint(joint_type: str):
    return model_from_dict(
        {
            "format": "recal.model/1",
            "units": {"length": "m", "angle": "rad"},
            "convention": "dh",
            "joints": [
                {
                    "type": joint_type,
                    "d": 0.1,
                    "a": 0.2,
                    "alpha": 0.3,
                    "lower": 0.0 if joint_type == "prismatic" else -3.0,
                    "upper": 0.5 if joint_type == "prismatic" else 3.0,
                }
            ],
        }
    )


# --------------------------------------------------------------------------- completeness


@pytest.mark.parametrize(
    "name,model,expected",
    [
        ("PUMA 560 (DH + Hayati, Table 6.1)", nominal("puma560"), 30),
        ("PUMA 560 ZRP (Table 6.2)", nominal("puma560-zrp"), 30),
        ("UR10e with Hayati links", hayati_for_parallel_axes(nominal("ur10e"))[0], 30),
        ("UR10e in poe", to_poe(nominal("ur10e")), 30),
        ("5R1P of Table 4.1 (Stanford-like)", model_from_dict(stanford_5r1p_doc()), 28),
        ("single revolute joint", _one_joint("revolute"), 10),
        ("single prismatic joint", _one_joint("prismatic"), 8),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_completeness_count_is_the_rank_with_full_pose_data(name, model, expected):
    """N = 4R + 2P + 6 (eq. 2.63): PUMA 560 -> 30, Stanford arm (5R1P) -> 28, one revolute joint
    -> 10, one prismatic joint -> 8 (book L868-L876). With the base free as well, the rank of the
    full model's Jacobian is exactly N: more candidates than that are dependent."""
    R = sum(j.revolute for j in model.joints)
    P = model.n_joints - R
    assert expected == 4 * R + 2 * P + 6
    n_params, rank = _rank(model, full_pose=True)
    assert n_params > expected
    assert rank == expected


@pytest.mark.parametrize(
    "model,parallel_pairs",
    [
        (nominal("ur10e"), 2),
        (model_from_dict(craig_puma_mdh_doc()), 1),
    ],
    ids=["ur10e-dh", "puma-mdh"],
)
def test_plain_dh_with_parallel_axes_is_not_complete(model, parallel_pairs):
    """Book §2.6: standard (and Craig's) DH cannot describe a tilt of the second of two parallel
    axes about the common normal's perpendicular; each parallel pair costs one rank. Hayati's
    beta (book eq. 2.64) restores it."""
    _, rank = _rank(model, full_pose=True)
    assert rank == 30 - parallel_pairs


def test_position_only_data_lose_the_tool_orientation():
    """Position-only data (one point) see 3 fewer parameters: the tool orientation (extraction
    ch4a §4.3: "α6 is unidentifiable, because it never affects position")."""
    ur = hayati_for_parallel_axes(nominal("ur10e"))[0]
    off_axis = np.array([0.04, 0.0, 0.05])  # a reflector not on the last joint axis
    assert _rank(ur, full_pose=True, p_tool=off_axis)[1] == 30
    assert _rank(ur, full_pose=False, p_tool=off_axis)[1] == 27
    stanford = model_from_dict(stanford_5r1p_doc())
    assert _rank(stanford, full_pose=False)[1] == 28 - 3
    # A point exactly ON the last joint axis is a degenerate place: the last joint's offset does
    # not move it, and the direction of its (zero) distance from the axis is undefined: 2 fewer.
    assert _rank(ur, full_pose=False, p_tool=np.array([0.0, 0.0, 0.05]))[1] == 25


# --------------------------------------------------------------------------- the 5R1P study

FIXED_5R1P = ("j3.a", "j4.d", "j6.alpha")  # l_3, r_4 (prismatic axis through frame 3), alpha_6

RANGES_DEG_IN = {  # Table 4.7 (theta in deg, r_3 in inches); the wrist always in its normal range
    "N": [(0, 300), (-120, 120), (12, 48), (0, 360), (-120, 120), (0, 360)],
    "F": [(0, 360), (-180, 180), (12, 48), (0, 360), (-120, 120), (0, 360)],
    "H": [(0, 180), (-90, 90), (30, 48), (0, 360), (-120, 120), (0, 360)],
    "Q": [(0, 90), (-45, 45), (39, 48), (0, 360), (-120, 120), (0, 360)],
    "E": [(0, 45), (-22, 22), (44, 48), (0, 360), (-120, 120), (0, 360)],
}


def _limits(R: str) -> np.ndarray:
    return np.array(
        [(lo * IN, hi * IN) if i == 2 else (lo * DEG, hi * DEG) for i, (lo, hi) in enumerate(RANGES_DEG_IN[R])]
    )


def _params_21(model, extra: tuple[str, ...] = ()) -> list[Parameter]:
    """The book's identified set: every link parameter of Table 4.1 except l_3, r_4 and alpha_6
    (the base frame is the measurement frame, the tool is link 6)."""
    return [
        p for p in candidate_parameters(model, base=False, tool=False) if p.name not in FIXED_5R1P or p.name in extra
    ]


def _jacobian_in_inch_rad(model, q, params) -> np.ndarray:
    pred = predict(model, q, np.zeros(3), params)
    J = pred.Jp.reshape(-1, len(params)) / IN
    return J * np.array([IN if p.kind == "length" else 1.0 for p in params])


def _kappa(model, q, params) -> float:
    s = np.linalg.svd(_jacobian_in_inch_rad(model, q, params), compute_uv=False)
    return float(s[0] / s[-1])


def _strategy(S: int, R: str, m: int, rng) -> np.ndarray:
    """Book §4.5.2 strategies (the held values and increments of S1-S3 are not printed; these
    are the obvious choices): S1 all joints together by constant increments (one space curve),
    S2 one joint at a time, S3 one joint held while the others move together, S4 Monte Carlo."""
    lim = _limits(R)
    lo, hi, mid = lim[:, 0], lim[:, 1], lim.mean(axis=1)
    if S == 4:
        return rng.uniform(lo, hi, (m, 6))
    if S == 1:
        return lo + np.linspace(0, 1, m)[:, None] * (hi - lo)
    out = []
    for j in range(6):
        for t in np.linspace(0, 1, m // 6):
            if S == 2:
                q = mid.copy()
                q[j] = lo[j] + t * (hi[j] - lo[j])
            else:
                q = lo + t * (hi - lo)
                q[j] = mid[j]
            out.append(q)
    return np.array(out)


def test_5r1p_rank_21_and_alpha_6_unidentifiable():
    """Extraction ch4a §6.2: rank 21 with the 21-parameter set; adding alpha_6 (or l_3, or r_4)
    with position-only data gives rank 21 of 22."""
    model = model_from_dict(stanford_5r1p_doc(10.0))
    q = _strategy(4, "N", 36, np.random.default_rng(0))
    params = _params_21(model)
    assert len(params) == 21
    s = np.linalg.svd(_jacobian_in_inch_rad(model, q, params), compute_uv=False)
    assert s[-1] > 1e-3 * s[0]
    for extra in FIXED_5R1P:
        s = np.linalg.svd(_jacobian_in_inch_rad(model, q, _params_21(model, (extra,))), compute_uv=False)
        assert len(s) == 22 and s[-1] < 1e-12 * s[0], extra


def test_5r1p_identify_names_the_same_parameters():
    """``identify`` with the base and tool frames fixed drops exactly l_3, r_4 and alpha_6, and
    says why alpha_6 cannot be seen."""
    model = model_from_dict(stanford_5r1p_doc(10.0))
    rng = np.random.default_rng(1)
    q = _strategy(4, "N", 36, rng)
    data = Measurements(q, target_positions(model, q))
    result = identify(model, data, fixed=("base.*", "tool.*"), register="never")
    assert {u.name for u in result.unidentifiable} == set(FIXED_5R1P)
    assert len(result.params) == 21
    why = {u.name: u.reason for u in result.unidentifiable}
    assert "no effect" in why["j6.alpha"] or "same motion" in why["j6.alpha"]


def test_5r1p_condition_number_ranks_the_strategies():
    """Table 4.6: "the better a strategy, the lower its condition number": κ(S1) ≫ κ(S2) >
    κ(S3) ≳ κ(S4) (book 20000+ / 1100-1200 / 360-430 / 190-540; extraction's repro ≈ 4000 /
    420 / 170 / 130)."""
    model = model_from_dict(stanford_5r1p_doc(10.0))
    params = _params_21(model)
    k = {S: _kappa(model, _strategy(S, "N", 36, None), params) for S in (1, 2, 3)}
    k[4] = float(np.median([_kappa(model, _strategy(4, "N", 36, np.random.default_rng(s)), params) for s in range(7)]))
    assert k[1] > 5 * k[2]
    assert k[2] > k[3]
    assert k[3] > 0.8 * k[4]
    assert k[1] > 10 * k[4]


def test_5r1p_condition_number_grows_as_the_joint_range_shrinks():
    """Table 4.7 (l_6 = r_6 = 5 in, S4, m = 36): κ rises by an order of magnitude from the full
    range F to the eighth range E (book 239 / 501 / 1696 / 4804)."""
    model = model_from_dict(stanford_5r1p_doc(5.0))
    params = _params_21(model)
    k = {
        R: float(np.median([_kappa(model, _strategy(4, R, 36, np.random.default_rng(s)), params) for s in range(7)]))
        for R in "FHQE"
    }
    assert k["F"] < k["H"] < k["Q"] < k["E"]
    assert k["E"] > 10 * k["F"]


def _identify_5r1p(lever_in: float, seed: int) -> tuple[float, float]:
    """One run of the book's simulation (Table 4.2 settings): true errors +5 deg on every theta
    and alpha and +0.5 in on every r and l of the 21-parameter set, 36 Monte-Carlo poses, uniform
    noise ±0.001 in on positions and ±0.001 deg (in) on the joint readings; identification from
    the nominal table. Returns δ_rms of the angles (deg) and lengths (in)."""
    rng = np.random.default_rng(seed)
    nominal_model = model_from_dict(stanford_5r1p_doc(lever_in))
    params = _params_21(nominal_model)
    truth = apply_step(nominal_model, params, [5 * DEG if p.kind == "angle" else 0.5 * IN for p in params])
    q = _strategy(4, "N", 36, rng)
    p_meas = target_positions(truth, q) + rng.uniform(-0.001, 0.001, (36, 3)) * IN
    q_read = q + rng.uniform(-0.001, 0.001, q.shape) * np.where(np.arange(6) == 2, IN, DEG)
    result = identify(
        nominal_model,
        Measurements(q_read, p_meas),
        sigma_m=0.001 / math.sqrt(3) * IN,
        fixed=("base.*", "tool.*") + FIXED_5R1P,
        register="never",
    )
    assert result.success and len(result.params) == 21
    err = parameter_values(result.model, params) - parameter_values(truth, params)
    angle = np.array([p.kind == "angle" for p in params])
    err[angle] = (err[angle] + math.pi) % (2 * math.pi) - math.pi
    return float(np.sqrt(np.mean((err[angle] / DEG) ** 2))), float(np.sqrt(np.mean((err[~angle] / IN) ** 2)))


def test_5r1p_accuracy_degrades_as_the_tool_lever_arm_shrinks():
    """Table 4.2: the wrist angles act on position only through the tool's lever arm, so the
    angle accuracy falls as l_6 = r_6 shrinks (book 0.00078 deg at 10 in, 0.0083 at 1 in, 0.017
    at 0.5 in) while the length accuracy stays about 0.0002 in; κ rises (book 260 -> 1848 at
    0.1 in). The start (5 deg, 0.5 in off) does not matter (Table 4.3)."""
    runs = {L: np.array([_identify_5r1p(L, s) for s in range(3)]) for L in (10.0, 1.0, 0.5)}
    angle = {L: float(np.median(r[:, 0])) for L, r in runs.items()}
    length = {L: float(np.median(r[:, 1])) for L, r in runs.items()}
    assert angle[10.0] < 0.003  # book 0.00078, extraction's repro 0.0011
    assert angle[1.0] > 2 * angle[10.0]
    assert angle[0.5] > 3 * angle[10.0]
    assert all(v < 0.001 for v in length.values())  # book ≈ 0.0002 in for every lever arm
    kappa = {
        L: float(
            np.median(
                [
                    _kappa(
                        model_from_dict(stanford_5r1p_doc(L)),
                        _strategy(4, "N", 36, np.random.default_rng(s)),
                        _params_21(model_from_dict(stanford_5r1p_doc(L))),
                    )
                    for s in range(5)
                ]
            )
        )
        for L in (10.0, 0.1)
    }
    assert kappa[0.1] > 4 * kappa[10.0]
