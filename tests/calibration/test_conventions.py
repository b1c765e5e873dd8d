"""Exact conversions between conventions (calibration.conventions): the same forward kinematics."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from sample_models import all_convention_docs, random_readings, si_readings

from calibration.conventions import dh_to_mdh, hayati_for_parallel_axes, mdh_to_dh, to_poe
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.robots import nominal, nominal_document
from calibration.transforms import pose_to_matrix

DOCS = all_convention_docs()
PLAIN_DH = ["dh", "dh_gain", "dh_harmonic", "dh_coupling", "dh_prismatic", "5r1p"]


def _q(doc_id, n=25, seed=1):
    doc = DOCS[doc_id]
    return si_readings(doc, random_readings(doc, n, np.random.default_rng(seed)))


def _same_fk(a, b, q, atol=1e-12):
    np.testing.assert_allclose(fk(a, q), fk(b, q), atol=atol)


@pytest.mark.parametrize("doc_id", PLAIN_DH)
def test_dh_to_mdh_and_back(doc_id):
    m = model_from_dict(DOCS[doc_id])
    q = _q(doc_id)
    md = dh_to_mdh(m)
    assert md.convention == "mdh"
    _same_fk(m, md, q)
    back = mdh_to_dh(md)
    assert back.convention == "dh"
    _same_fk(m, back, q)
    # targets, coupling and gains travel with the model
    assert set(md.targets) == set(m.targets)
    np.testing.assert_array_equal(md.coupling_matrix, m.coupling_matrix)


@pytest.mark.parametrize("doc_id", ["mdh", "mdh_prismatic"])
def test_mdh_to_dh_and_back(doc_id):
    m = model_from_dict(DOCS[doc_id])
    q = _q(doc_id)
    d = mdh_to_dh(m)
    _same_fk(m, d, q)
    _same_fk(m, dh_to_mdh(d), q)


@pytest.mark.parametrize("doc_id", sorted(DOCS))
def test_to_poe_same_kinematics(doc_id):
    m = model_from_dict(DOCS[doc_id])
    q = _q(doc_id)
    p = to_poe(m)
    assert p.convention == "poe"
    _same_fk(m, p, q)
    for j in p.joints:
        assert np.linalg.norm(j.axis) == pytest.approx(1.0)
    if m.convention == "poe":
        assert p is m


def test_to_poe_of_puma_dh_matches_table_6_2_axes():
    """The nominal PUMA DH (Table 6.1) in zero-reference form has the axes of Table 6.2 (the
    two nominal models share their orientations, extraction §5 B2)."""
    p = to_poe(nominal("puma560"))
    zrp = nominal("puma560-zrp")  # its base is the identity: axes in the world (CMM) frame
    np.testing.assert_array_equal(p.base, nominal("puma560").base)  # poe axes are in the base frame
    R_world_base = pose_to_matrix(p.base)[:3, :3]
    for a, b in zip(p.joints, zrp.joints):
        np.testing.assert_allclose(R_world_base @ a.axis, b.axis, atol=1e-12)


def test_conversion_input_checks():
    with pytest.raises(ValueError, match="Hayati"):
        dh_to_mdh(nominal("puma560"))
    with pytest.raises(ValueError, match="mdh"):
        mdh_to_dh(nominal("ur10e"))


def test_hayati_for_parallel_axes_ur10e():
    """UR10e axes 2, 3, 4 are parallel: links 2 and 3 become Hayati links, exactly."""
    m = nominal("ur10e")
    h, notes = hayati_for_parallel_axes(m)
    assert [j.hayati for j in h.joints] == [False, True, True, False, False, False]
    assert len(notes) == 2 and all("Hayati" in n for n in notes)
    _same_fk(m, h, _q("dh"))
    # idempotent
    h2, notes2 = hayati_for_parallel_axes(h)
    assert notes2 == [] and [j.hayati for j in h2.joints] == [j.hayati for j in h.joints]


@pytest.mark.parametrize("alpha2,sign", [(0.0, 1.0), (180.0, -1.0)])
def test_hayati_moves_d_into_the_next_link(alpha2, sign):
    doc = copy.deepcopy(nominal_document("ur10e"))
    doc["joints"][1]["d"] = 60.0
    doc["joints"][1]["alpha"] = alpha2
    m = model_from_dict(doc)
    h, _notes = hayati_for_parallel_axes(m)
    assert h.joints[1].hayati and h.joints[1].d == 0.0
    # links 2 and 3 are both parallel to the next: the offset travels on to link 4
    assert h.joints[2].hayati and h.joints[2].d == 0.0
    assert h.joints[3].d == pytest.approx(m.joints[3].d + sign * 0.06)
    _same_fk(m, h, _q("dh"))


def test_nearly_parallel_with_d_is_left_and_reported():
    doc = copy.deepcopy(nominal_document("ur10e"))
    doc["joints"][1]["d"] = 60.0
    doc["joints"][1]["alpha"] = 0.5  # degrees: nearly, not exactly, parallel
    m = model_from_dict(doc)
    h, notes = hayati_for_parallel_axes(m)
    assert not h.joints[1].hayati
    assert any("j2" in n and "plain DH" in n for n in notes)
    _same_fk(m, h, _q("dh"))


def test_hayati_leaves_other_conventions():
    for doc_id in ("mdh", "poe"):
        m = model_from_dict(DOCS[doc_id])
        h, notes = hayati_for_parallel_axes(m)
        assert h is m and notes == []
