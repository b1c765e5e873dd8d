"""Forward kinematics (calibration.kinematics) against 4x4 products written from contracts §2,
and the PUMA 560 regression values of the book's case study (ch. 6, extraction §5 B3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sample_models import (
    Pose,
    Rx,
    Ry,
    Rz,
    Trans,
    Tx,
    Tz,
    all_convention_docs,
    random_readings,
    reference_fk,
    screw,
    si_readings,
)

from calibration.kinematics import fk, joint_variables, points_world, target_positions, walk
from calibration.model import model_from_dict
from calibration.robots import nominal

DOCS = all_convention_docs()
IN = 0.0254
DEG = math.pi / 180


@pytest.mark.parametrize("doc_id", sorted(DOCS))
def test_fk_matches_contract_products(doc_id):
    """Every convention and feature (Hayati beta, mdh, poe, prismatic joints, coupling, gains,
    harmonics) against the product of elementary transforms of contracts §2."""
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    rng = np.random.default_rng(11)
    q_file = random_readings(doc, 8, rng)
    T = fk(model, si_readings(doc, q_file))
    assert T.shape == (8, 4, 4)
    for k in range(8):
        np.testing.assert_allclose(T[k], reference_fk(doc, q_file[k]), atol=1e-12)


def test_dh_link_written_out():
    """Two standard DH links, base and tool, written out by hand."""
    doc = {
        "format": "recal.model/1",
        "units": {"length": "m", "angle": "rad"},
        "convention": "dh",
        "base": [0.1, 0.2, 0.3, 0.1, 0.2, 0.3],
        "joints": [
            {"theta": 0.1, "d": 0.4, "a": 0.05, "alpha": -1.2},
            {"theta": -0.3, "d": 0.02, "a": 0.5, "alpha": 0.4},
        ],
        "tool": [0, 0.01, 0.2, 0.5, 0, 0],
    }
    q = np.array([0.7, -1.1])
    expected = (
        Trans(0.1, 0.2, 0.3)
        @ Rz(0.3)
        @ Ry(0.2)
        @ Rx(0.1)
        @ Rz(0.1 + 0.7)
        @ Tz(0.4)
        @ Tx(0.05)
        @ Rx(-1.2)
        @ Rz(-0.3 - 1.1)
        @ Tz(0.02)
        @ Tx(0.5)
        @ Rx(0.4)
        @ Trans(0, 0.01, 0.2)
        @ Rx(0.5)
    )
    np.testing.assert_allclose(fk(model_from_dict(doc), q)[0], expected, atol=1e-14)


def test_hayati_link_written_out():
    """dh with beta: Rz(theta + q)·Tx(a)·Rx(alpha)·Ry(beta), no d."""
    doc = {
        "format": "recal.model/1",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "joints": [
            {"theta": 0, "d": 100, "a": 0, "alpha": 90},
            {"theta": 5, "a": 400, "alpha": 0.2, "beta": -0.3},
            {"theta": 0, "d": 10, "a": 300, "alpha": 0},
        ],
    }
    q = np.array([20.0, -30.0, 45.0]) * DEG
    expected = (
        Rz(20 * DEG)
        @ Tz(0.1)
        @ Rx(90 * DEG)
        @ Rz(-25 * DEG)
        @ Tx(0.4)
        @ Rx(0.2 * DEG)
        @ Ry(-0.3 * DEG)
        @ Rz(45 * DEG)
        @ Tz(0.01)
        @ Tx(0.3)
    )
    np.testing.assert_allclose(fk(model_from_dict(doc), q)[0], expected, atol=1e-14)


def test_mdh_link_written_out():
    """mdh: Rx(alpha)·Tx(a)·Rz(theta + q)·Tz(d); prismatic: Tz(d + q)."""
    doc = {
        "format": "recal.model/1",
        "units": {"length": "m", "angle": "rad"},
        "convention": "mdh",
        "joints": [
            {"theta": 0.2, "d": 0.3, "a": 0.0, "alpha": 0.0},
            {"type": "prismatic", "theta": 0.1, "d": 0.05, "a": 0.2, "alpha": -1.5},
            {"theta": -0.4, "d": 0.0, "a": 0.1, "alpha": 0.7},
        ],
        "tool": [0.0, 0.0, 0.1, 0.0, 0.0, 0.0],
    }
    q = np.array([0.5, 0.25, -0.9])
    expected = (
        Rz(0.2 + 0.5)
        @ Tz(0.3)
        @ Rx(-1.5)
        @ Tx(0.2)
        @ Rz(0.1)
        @ Tz(0.05 + 0.25)
        @ Rx(0.7)
        @ Tx(0.1)
        @ Rz(-0.4 - 0.9)
        @ Tz(0.1)
    )
    np.testing.assert_allclose(fk(model_from_dict(doc), q)[0], expected, atol=1e-14)


def test_poe_written_out():
    """poe: rotation by theta + q about axis through point; prismatic: translation (d + q)·axis;
    then home, then tool."""
    doc = {
        "format": "recal.model/1",
        "units": {"length": "m", "angle": "rad"},
        "convention": "poe",
        "base": [1, 0, 0, 0, 0, 0.5],
        "joints": [
            {"axis": [0, 0, 1], "point": [0, 0, 0], "theta": 0.1},
            {"type": "prismatic", "axis": [0, 0.6, 0.8], "point": [9, 9, 9], "d": 0.02},
            {"axis": [1, 0, 0], "point": [0.3, 0.1, 0.5], "theta": 0.0},
        ],
        "home": [0.4, 0.1, 0.5, 0, 0.3, 0],
        "tool": [0, 0, 0.05, 0, 0, 0],
    }
    q = np.array([0.4, 0.1, -0.6])
    expected = (
        Trans(1, 0, 0)
        @ Rz(0.5)
        @ Rz(0.5)  # 0.1 + 0.4 about z through the origin
        @ Trans(0, 0.6 * 0.12, 0.8 * 0.12)
        @ screw([1, 0, 0], [0.3, 0.1, 0.5], -0.6)
        @ Trans(0.4, 0.1, 0.5)
        @ Ry(0.3)
        @ Tz(0.05)
    )
    np.testing.assert_allclose(fk(model_from_dict(doc), q)[0], expected, atol=1e-14)


def test_prismatic_dh_written_out():
    """dh prismatic: Rz(theta)·Tz(d + q)·Tx(a)·Rx(alpha); gains scale the reading (d + gain·q)."""
    doc = {
        "format": "recal.model/1",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "joints": [
            {"type": "prismatic", "theta": 10, "d": 100, "a": 20, "alpha": -90, "gain": 1.01},
            {"theta": 0, "d": 0, "a": 50, "alpha": 0, "gain": 0.99},
        ],
    }
    q = np.array([0.250, 30 * DEG])  # 250 mm, 30 deg
    expected = Rz(10 * DEG) @ Tz(0.1 + 1.01 * 0.25) @ Tx(0.02) @ Rx(-90 * DEG) @ Rz(0.99 * 30 * DEG) @ Tx(0.05)
    np.testing.assert_allclose(fk(model_from_dict(doc), q)[0], expected, atol=1e-14)


def test_coupling_maps_readings_before_theta():
    """Fanuc: angle_i = (C·q)_i + theta_i; the same robot without coupling, fed the mapped
    readings, gives the same poses."""
    doc = DOCS["dh_coupling"]
    m = model_from_dict(doc)
    uncoupled = {k: v for k, v in doc.items() if k != "coupling"}
    u = model_from_dict(uncoupled)
    rng = np.random.default_rng(3)
    q = si_readings(doc, random_readings(doc, 20, rng))
    C = np.asarray(doc["coupling"], float)
    np.testing.assert_allclose(joint_variables(m, q), q @ C.T)
    np.testing.assert_allclose(fk(m, q), fk(u, q @ C.T), atol=1e-13)
    # J3 relative to the horizon: moving J2 alone leaves the forearm's (and so the tool's)
    # orientation unchanged, since axes 2 and 3 are parallel and the DH angles counter-rotate.
    q0 = np.zeros((2, 6))
    q0[1, 1] = 0.3
    T = fk(m, q0)
    np.testing.assert_allclose(T[0, :3, :3], T[1, :3, :3], atol=1e-12)
    assert np.linalg.norm(T[0, :3, 3] - T[1, :3, 3]) > 0.1


def test_harmonic_joint_variable():
    doc = DOCS["dh_harmonic"]  # j2: 0.02 deg amplitude, k = 3, phase 40 deg
    m = model_from_dict(doc)
    q = np.array([[0.0, 0.5, 0, 0, 0, 0]])
    v = joint_variables(m, q)
    assert v[0, 1] == pytest.approx(0.5 + 0.02 * DEG * math.sin(3 * 0.5 + 40 * DEG))
    assert v[0, 4] == pytest.approx(0.01 * DEG * math.sin(-10 * DEG))


@pytest.mark.parametrize("doc_id", ["dh", "dh_hayati", "mdh", "poe", "poe_prismatic", "dh_coupling"])
def test_batched_equals_single(doc_id):
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    rng = np.random.default_rng(5)
    q = si_readings(doc, random_readings(doc, 17, rng))
    T = fk(model, q)
    for k in range(len(q)):
        np.testing.assert_array_equal(fk(model, q[k])[0], T[k])
    assert fk(model, q[0]).shape == (1, 4, 4)
    # a rigid transform each
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0, 0, 0, 1.0], (len(q), 4)))


def test_targets_and_points():
    doc = DOCS["dh"]
    m = model_from_dict(doc)
    rng = np.random.default_rng(6)
    q = si_readings(doc, random_readings(doc, 9, rng))
    T = fk(m, q)
    p = target_positions(m, q, "ball1")
    np.testing.assert_allclose(p, T[:, :3, 3] + T[:, :3, :3] @ np.array([0.04, 0.0, 0.03]), atol=1e-14)
    np.testing.assert_allclose(target_positions(m, q), T[:, :3, 3], atol=1e-15)
    per_row = rng.normal(size=(9, 3))
    np.testing.assert_allclose(
        points_world(m, q, per_row), T[:, :3, 3] + np.einsum("nij,nj->ni", T[:, :3, :3], per_row)
    )
    w = walk(m, q)
    np.testing.assert_allclose(w.R, T[:, :3, :3])
    with pytest.raises(KeyError, match="unknown target"):
        target_positions(m, q, "nope")


def test_wrong_joint_count_raises():
    m = nominal("ur10e")
    with pytest.raises(ValueError, match=r"shape \(N, 6\)"):
        fk(m, np.zeros((3, 5)))
    with pytest.raises(ValueError, match=r"shape \(N, 6\)"):
        fk(m, np.zeros((2, 3, 6)))


# --------------------------------------------------------------------------- the book's PUMA 560


def _in(T):
    """Translation in inches."""
    return T[:3, 3] / IN


def test_puma_dh_table_6_1_at_zero():
    """Extraction §5 B3: DH Table 6.1 at Θ = 0 gives [[0,−1,0,0.609],[0,0,1,33.944],[−1,0,0,27.008]]."""
    T = fk(nominal("puma560"), np.zeros(6))[0]
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [0, 0, 1], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(_in(T), [0.609, 33.944, 27.008], atol=5e-4)


def test_puma_dh_table_6_1_at_second_pose():
    """Θ = (10, −20, 30, −40, 50, −60) deg: p = (2.953577, 38.600605, 24.754036) in and R as printed."""
    T = fk(nominal("puma560"), np.radians([10, -20, 30, -40, 50, -60]))[0]
    np.testing.assert_allclose(_in(T), [2.953577, 38.600605, 24.754036], atol=2e-6)
    np.testing.assert_allclose(
        T[:3, :3],
        [[0.607452, 0.215533, 0.764557], [-0.783194, 0.323291, 0.531121], [-0.1327, -0.921427, 0.365188]],
        atol=2e-6,
    )


def test_puma_dh_table_6_1_at_third_pose():
    T = fk(nominal("puma560"), np.radians([-45, -90, 45, 30, -60, 120]))[0]
    np.testing.assert_allclose(_in(T), [-22.425998, 42.780278, 19.096748], atol=2e-6)


def test_puma_zrp_nominal():
    """ZRP nominal (Table 6.2 + T0, eq. 6.11) is T0 exactly at zero, and
    p = (3.542283, 38.618011, 25.474941) in at Θ = (10, −20, 30, −40, 50, −60)."""
    zrp = nominal("puma560-zrp")
    T = fk(zrp, np.zeros(6))[0]
    T0 = np.array([[0, -1, 0, 1.2 * IN], [0, 0, 1, 33.96 * IN], [-1, 0, 0, 27.73 * IN], [0, 0, 0, 1]])
    np.testing.assert_allclose(T, T0, atol=1e-12)
    T2 = fk(zrp, np.radians([10, -20, 30, -40, 50, -60]))[0]
    np.testing.assert_allclose(_in(T2), [3.542283, 38.618011, 25.474941], atol=2e-6)


def test_puma_nominal_dh_and_zrp_same_orientation_offset_position():
    """Extraction §5 B2: the nominal DH and ZRP PUMA have identical orientations for every Θ and
    positions that differ by about (−0.59, −0.02, −0.72) in (norm ≈ 0.93 in)."""
    rng = np.random.default_rng(8)
    q = np.radians(rng.uniform(-120, 120, (200, 6)))
    Td, Tz_ = fk(nominal("puma560"), q), fk(nominal("puma560-zrp"), q)
    np.testing.assert_allclose(Td[:, :3, :3], Tz_[:, :3, :3], atol=1e-12)
    offset = (Td[:, :3, 3] - Tz_[:, :3, 3]) / IN
    assert np.all(np.abs(np.linalg.norm(offset, axis=1) - 0.93) < 0.05)
    zero = (fk(nominal("puma560"), np.zeros(6))[0, :3, 3] - fk(nominal("puma560-zrp"), np.zeros(6))[0, :3, 3]) / IN
    np.testing.assert_allclose(zero, [-0.591, -0.016, -0.722], atol=1e-3)


def test_pose_helper_is_contract_pose():
    """The reference helpers themselves: Pose is Trans·Rz·Ry·Rx (guards the reference FK)."""
    from calibration.transforms import pose_to_matrix

    p = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    np.testing.assert_allclose(Pose(p), pose_to_matrix(p), atol=1e-15)
