"""Axis lines -> DH (calibration.conventions.poe_to_dh) and Sklar's line geometry (book
§4.6.5.2 with the corrections of ch4b §10): exact conversion for every convention and feature,
parameters reproduced for DH robots, and the book's acceptance tests T8-T9."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sample_models import all_convention_docs, random_readings, si_readings

from calibration.conventions import common_normal, joint_angle, mutual_moment, poe_to_dh, to_poe
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.robots import nominal
from calibration.simulate import perturbed
from calibration.transforms import homogeneous, rot

DOCS = all_convention_docs()


@pytest.mark.parametrize("doc_id", sorted(DOCS))
def test_poe_to_dh_is_exact(doc_id):
    """Same kinematics after conversion, with and without a reference, for the model and for
    a perturbed (all axes tilted and shifted) version of it."""
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    rng = np.random.default_rng(20)
    q = si_readings(doc, random_readings(doc, 40, rng))
    for m in (model, perturbed(model, rng)):
        for ref in (None, model):
            dh = poe_to_dh(m, reference=ref)
            assert dh.convention == "dh" and dh.home is None
            assert np.abs(fk(dh, q) - fk(m, q)).max() < 1e-12
            assert [j.name for j in dh.joints] == [j.name for j in m.joints]
            assert all(j.beta is None or j.revolute is False or j.d == 0.0 for j in dh.joints)


@pytest.mark.parametrize("name", ["ur10e", "ur5e", "puma560"])
def test_dh_robots_come_back_as_they_were(name):
    """dh -> poe -> dh with the original as reference reproduces every parameter, the base and
    the tool (the UR's parallel axes 2-4 come back in Hayati's form with beta = 0)."""
    m = nominal(name)
    back = poe_to_dh(to_poe(m), reference=m)
    for j0, j1 in zip(m.joints, back.joints):
        assert j1.theta == pytest.approx(j0.theta, abs=1e-12)
        assert j1.d == pytest.approx(j0.d, abs=1e-12)
        assert j1.a == pytest.approx(j0.a, abs=1e-12)
        assert j1.alpha == pytest.approx(j0.alpha, abs=1e-12)
        assert (j1.beta or 0.0) == pytest.approx(j0.beta or 0.0, abs=1e-12)
    assert np.allclose(back.base, m.base, atol=1e-12) and np.allclose(back.tool, m.tool, atol=1e-12)


def test_without_reference_a_is_non_negative():
    m = nominal("ur10e")
    dh = poe_to_dh(to_poe(m))
    assert all(j.a >= -1e-12 for j in dh.joints)
    assert all(-math.pi < j.theta <= math.pi and -math.pi < j.alpha <= math.pi for j in dh.joints)
    assert [j.hayati for j in dh.joints] == [False, True, True, False, False, False]


def _line_pair(a: float, alpha: float, d_j: float = 3.0):
    """Axis j along z through (1, 2, 3) rotated somewhere; axis k at distance a along the
    common normal x, twisted by alpha about it."""
    T = homogeneous(rot(2, 0.4) @ rot(1, -0.7) @ rot(0, 0.2), np.array([1.0, 2.0, 3.0]))
    s_j, r_j = T[:3, 2], T[:3, 3] + d_j * T[:3, 2]
    P_j = T[:3, 3]
    P_k = P_j + a * T[:3, 0]
    s_k = T[:3, :3] @ (rot(0, alpha) @ np.array([0.0, 0.0, 1.0]))
    return s_j, r_j, s_k, P_k + 7.0 * s_k, P_j, P_k, T[:3, 0]


def test_sklar_skew_lines_t8():
    """T8: a = 25, alpha = 250°: MM = −a sin(alpha) = +23.49 (so alpha > 180°, L3892), the
    normal from j to k recovered with a = 25 (eq. 4.338 corrected; printed: −25), the feet
    exact, and the corrected eq. 4.339-4.340 give the same feet as method 2."""
    alpha = np.deg2rad(250.0)
    s_j, r_j, s_k, r_k, P_j, P_k, x = _line_pair(25.0, alpha)
    mm = mutual_moment(s_j, r_j, s_k, r_k)
    assert mm == pytest.approx(-25.0 * np.sin(alpha)) and mm == pytest.approx(23.49, abs=0.01)
    cn = common_normal(s_j, r_j, s_k, r_k)
    assert cn.kind == "skew" and cn.length == pytest.approx(25.0)
    assert np.allclose(cn.direction, x) and np.isclose(np.cos(cn.twist - alpha), 1.0)
    assert np.allclose(cn.foot_j, P_j) and np.allclose(cn.foot_k, P_k)
    assert (r_j - r_k) @ cn.direction == pytest.approx(-25.0)  # the printed 4.338
    n, s0j, s0k = cn.direction, np.cross(r_j, s_j), np.cross(r_k, s_k)
    Pj = (np.cross(np.cross(n, s_k), s0j) - (s0k @ n) * s_j) / (np.cross(n, s_k) @ s_j)
    Pk = (np.cross(np.cross(n, s_j), s0k) - (s0j @ n) * s_k) / (np.cross(n, s_j) @ s_k)
    assert np.allclose(Pj, P_j) and np.allclose(Pk, P_k)


def test_sklar_intersecting_and_parallel_t9():
    s_j, r_j, s_k, r_k, P_j, _, _ = _line_pair(0.0, np.deg2rad(60.0))
    cn = common_normal(s_j, r_j, s_k, r_k)
    assert cn.kind == "intersecting" and cn.length == 0.0
    assert np.allclose(cn.foot_j, P_j) and np.allclose(cn.foot_k, P_j)
    assert 0 < cn.twist < np.pi and np.isclose(cn.twist, np.deg2rad(60.0))
    for alpha in (0.0, np.pi):
        s_j, r_j, s_k, r_k, _, _, x = _line_pair(30.0, alpha)
        cn = common_normal(s_j, r_j, s_k, r_k)
        assert cn.kind == "parallel" and cn.length == pytest.approx(30.0)  # eq. 4.348
        assert np.allclose(cn.direction, x) and np.isclose(np.cos(cn.twist), np.cos(alpha))
        assert abs(mutual_moment(s_j, r_j, s_k, r_k)) < 1e-12


def test_joint_angle_right_hand_rule():
    """Eq. 4.329-4.330: the rotation about s that takes the incoming normal into the outgoing."""
    s = np.array([0.0, 0.0, 1.0])
    for theta in (0.3, 2.0, -2.5):
        assert joint_angle([1.0, 0, 0], rot(2, theta) @ [1.0, 0, 0], s) == pytest.approx(theta)
