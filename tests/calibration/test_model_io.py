"""Model documents (contracts §2): reading, writing, units, conventions, malformed input."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from sample_models import (
    LENGTH,
    all_convention_docs,
    fanuc_r2000ic_doc,
    prismatic_doc,
    random_readings,
    si_readings,
)

from calibration.kinematics import fk
from calibration.model import KinematicModel, ModelFormatError, Units, model_from_dict, model_to_dict

DOCS = all_convention_docs()
UNIT_SYSTEMS = [Units(length, angle) for length in ("mm", "m", "in") for angle in ("deg", "rad")]


def _same_model(a: KinematicModel, b: KinematicModel, *, atol: float = 1e-9) -> None:
    """Every SI field of two models agrees."""
    assert a.convention == b.convention and a.n_joints == b.n_joints and a.name == b.name
    for key in ("base", "tool"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), atol=atol)
    if a.home is not None or b.home is not None:
        np.testing.assert_allclose(a.home, b.home, atol=atol)
    assert set(a.targets) == set(b.targets)
    for t in a.targets:
        np.testing.assert_allclose(a.targets[t], b.targets[t], atol=atol)
    assert (a.coupling is None) == (b.coupling is None)
    if a.coupling is not None:
        np.testing.assert_allclose(a.coupling, b.coupling, atol=1e-12)
    for ja, jb in zip(a.joints, b.joints):
        assert (ja.name, ja.type, ja.hayati) == (jb.name, jb.type, jb.hayati)
        for f in ("theta", "d", "a", "alpha", "gain", "lower", "upper"):
            assert getattr(ja, f) == pytest.approx(getattr(jb, f), abs=atol), f"{ja.name}.{f}"
        if ja.hayati:
            assert ja.beta == pytest.approx(jb.beta, abs=atol)
        for f in ("axis", "point"):
            if getattr(ja, f) is not None:
                np.testing.assert_allclose(getattr(ja, f), getattr(jb, f), atol=atol)
        assert (ja.harmonic is None) == (jb.harmonic is None)
        if ja.harmonic is not None:
            np.testing.assert_allclose(ja.harmonic, jb.harmonic, rtol=1e-9, atol=atol)


def _same_document(a, b, path="doc"):
    """Equal JSON structures, numbers to 1e-11 (an axis is renormalised when read)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), path
        for k in a:
            _same_document(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same_document(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and not isinstance(b, str):
        assert a == pytest.approx(b, rel=1e-11, abs=1e-11), path
    else:
        assert a == b, path


@pytest.mark.parametrize("doc_id", sorted(DOCS))
@pytest.mark.parametrize("units", UNIT_SYSTEMS, ids=lambda u: f"{u.length}-{u.angle}")
def test_round_trip_in_every_unit_system(doc_id, units):
    """Written in any units and read back (through JSON text), the model is the same robot, and
    writing it again gives the same document."""
    model = model_from_dict(DOCS[doc_id])
    doc = model_to_dict(model, units=units)
    assert doc["units"] == {"length": units.length, "angle": units.angle}
    text = json.dumps(doc)
    back = model_from_dict(json.loads(text))
    assert back.units == units
    _same_model(model, back)
    _same_document(model_to_dict(back), doc)
    # and the same kinematics
    rng = np.random.default_rng(7)
    q = si_readings(DOCS[doc_id], random_readings(DOCS[doc_id], 5, rng))
    np.testing.assert_allclose(fk(back, q), fk(model, q), atol=1e-9)


def test_numbers_are_written_in_the_requested_units():
    model = model_from_dict(DOCS["dh"])  # UR10e, d1 = 180.7 mm, alpha1 = 90 deg
    for length, angle in (("mm", "deg"), ("m", "rad"), ("in", "deg")):
        doc = model_to_dict(model, units=Units(length, angle))
        j1 = doc["joints"][0]
        assert j1["d"] == pytest.approx(0.1807 / LENGTH[length], rel=1e-12)
        assert j1["alpha"] == pytest.approx(90.0 if angle == "deg" else math.pi / 2, rel=1e-12)
        assert doc["base"][0] == pytest.approx(1.5 / LENGTH[length], rel=1e-12)
        assert doc["base"][5] == pytest.approx(120.0 if angle == "deg" else math.radians(120), rel=1e-12)
        assert doc["targets"]["smr1"][2] == pytest.approx(0.05 / LENGTH[length], rel=1e-12)
        assert j1["upper"] == pytest.approx(360.0 if angle == "deg" else 2 * math.pi, rel=1e-12)


def test_si_values_inside():
    m = model_from_dict(DOCS["dh"])
    assert m.joints[0].d == pytest.approx(0.1807)
    assert m.joints[1].a == pytest.approx(-0.6127)
    assert m.joints[0].alpha == pytest.approx(math.pi / 2)
    assert m.joints[0].lower == pytest.approx(-2 * math.pi)
    np.testing.assert_allclose(m.base, [1.5, -0.8, 0.2, math.radians(2), math.radians(-3), math.radians(120)])
    p = model_from_dict(DOCS["poe"])  # PUMA ZRP in inches
    np.testing.assert_allclose(p.joints[1].point, np.array([-15.0, 14.7, 27.73]) * 0.0254)
    np.testing.assert_allclose(p.home[:3], np.array([1.2, 33.96, 27.73]) * 0.0254)
    # prismatic readings and limits are lengths
    s = model_from_dict(DOCS["5r1p"])
    assert s.joints[2].type == "prismatic"
    np.testing.assert_allclose(s.joint_limits[2], np.array([12.0, 48.0]) * 0.0254)
    np.testing.assert_allclose(s.joint_limits[0], np.radians([0.0, 300.0]))


def test_model_is_immutable():
    m = model_from_dict(DOCS["dh"])
    with pytest.raises(AttributeError):
        m.name = "x"  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.base[0] = 1.0
    with pytest.raises(TypeError):
        m.targets["new"] = np.zeros(3)  # type: ignore[index]


def test_fanuc_coupling_of_contracts_example():
    """Contracts §2: the DH angle of joint 3 is -(J2 + J3); J4-J6 reversed; theta2 = -90 deg."""
    doc = fanuc_r2000ic_doc()
    m = model_from_dict(doc)
    C = m.coupling_matrix
    np.testing.assert_array_equal(C, np.asarray(doc["coupling"], float))
    q = np.radians([10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    v = C @ q
    np.testing.assert_allclose(v, np.radians([10, 20, -50, -40, -50, -60]))
    assert m.joints[1].theta == pytest.approx(-math.pi / 2)
    out = model_to_dict(m)
    assert out["coupling"] == doc["coupling"]
    assert all("gain" not in j for j in out["joints"])


def test_gain_round_trip_and_default_coupling():
    m = model_from_dict(DOCS["dh_gain"])
    np.testing.assert_allclose(np.diag(m.coupling_matrix), [1.001, 0.999, 1.0005, 1.0, 0.998, 1.002])
    assert m.coupling is None
    out = model_to_dict(m)
    assert out["joints"][0]["gain"] == 1.001
    assert "gain" not in out["joints"][3]  # the default is not written


def test_prismatic_harmonic_frequency_follows_the_length_unit():
    """A lead-screw harmonic with a 5 mm period is the same robot whether the file is in m or mm."""
    doc_m = DOCS["dh_prismatic_harmonic"]
    m = model_from_dict(doc_m)
    doc_mm = model_to_dict(m, units=Units("mm", "deg"))
    amp, k, phase = doc_mm["joints"][1]["harmonic"]
    assert amp == pytest.approx(0.2)
    assert 2 * math.pi / k == pytest.approx(5.0)  # period in mm
    assert phase == pytest.approx(math.degrees(0.3))
    assert model_from_dict(doc_mm).joints[1].harmonic == pytest.approx(m.joints[1].harmonic)


def test_identification_block_and_unknown_fields_are_kept():
    doc = copy.deepcopy(DOCS["dh"])
    doc["identification"] = {"success": True, "rows": 3}
    doc["x-vendor"] = "abc"
    out = model_to_dict(model_from_dict(doc))
    assert out["identification"] == {"success": True, "rows": 3}
    assert out["x-vendor"] == "abc"


def test_defaults_for_optional_fields():
    doc = {
        "format": "recal.model/1",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "joints": [{"d": 100}, {"type": "prismatic", "alpha": 90}],
    }
    m = model_from_dict(doc)
    assert [j.name for j in m.joints] == ["j1", "j2"]
    assert m.joints[0].revolute and not m.joints[1].revolute
    np.testing.assert_array_equal(m.base, np.zeros(6))
    np.testing.assert_array_equal(m.tool, np.zeros(6))
    assert dict(m.targets) == {}
    assert m.joints[0].lower == pytest.approx(-2 * math.pi) and m.joints[1].upper == pytest.approx(10.0)
    np.testing.assert_array_equal(m.target(None), np.zeros(3))
    with pytest.raises(KeyError, match="unknown target 'nope'"):
        m.target("nope")


# --------------------------------------------------------------------------- malformed documents


def _ur():
    return copy.deepcopy(DOCS["dh"])


def _set(doc, path, value):
    """Set ``doc[path...] = value``; ``value`` is ``_DEL`` to delete."""
    *head, last = path
    d = doc
    for k in head:
        d = d[k]
    if value is _DEL:
        del d[last]
    else:
        d[last] = value
    return doc


_DEL = object()

MALFORMED = [
    # (base document, path, value, field named in the error)
    ("dh", ("format",), "recal.model/2", "format"),
    ("dh", ("format",), _DEL, "format"),
    ("dh", ("units",), _DEL, "units"),
    ("dh", ("units", "length"), "cm", "units.length"),
    ("dh", ("units", "angle"), "grad", "units.angle"),
    ("dh", ("convention",), "craig", "convention"),
    ("dh", ("joints",), [], "joints"),
    ("dh", ("joints",), {"j1": {}}, "joints"),
    ("dh", ("joints", 2), "j3", "joints[2]"),
    ("dh", ("joints", 1, "alpha"), "90", "joints[1].alpha"),
    ("dh", ("joints", 1, "a"), float("nan"), "joints[1].a"),
    ("dh", ("joints", 4, "d"), float("inf"), "joints[4].d"),
    ("dh", ("joints", 0, "theta"), True, "joints[0].theta"),
    ("dh", ("joints", 3, "type"), "spherical", "joints[3].type"),
    ("dh", ("joints", 1, "name"), "j1", "joints[1].name"),
    ("dh", ("joints", 2, "lower"), 400, "joints[2].lower"),
    ("dh", ("joints", 5, "harmonic"), [0.1, 2], "joints[5].harmonic"),
    ("dh", ("joints", 5, "harmonic"), [0.1, 2, "x"], "joints[5].harmonic[2]"),
    ("dh", ("base",), [0, 0, 0, 0, 0], "base"),
    ("dh", ("base",), [0, 0, "z", 0, 0, 0], "base[2]"),
    ("dh", ("tool",), "0 0 0 0 0 0", "tool"),
    ("dh", ("tool",), [0, 0, 0, 0, None, 0], "tool[4]"),
    ("dh", ("targets",), [[0, 0, 50]], "targets"),
    ("dh", ("targets", "smr1"), [0, 50], "targets.smr1"),
    ("dh", ("targets", "ball1"), [0, 0, float("nan")], "targets.ball1[2]"),
    ("dh", ("coupling",), [[1, 0], [0, 1]], "coupling"),
    ("dh_coupling", ("coupling", 2), [0, -1, -1, 0, 0], "coupling[2]"),
    ("dh_coupling", ("joints", 1, "gain"), 1.01, "joints[1].gain"),
    ("mdh", ("joints", 1, "beta"), 0.0, "joints[1].beta"),
    ("dh_hayati", ("joints", 1, "d"), 3.0, "joints[1].d"),
    ("poe", ("joints", 2, "axis"), _DEL, "joints[2].axis"),
    ("poe", ("joints", 2, "axis"), [0, 0, 0], "joints[2].axis"),
    ("poe", ("joints", 3, "point"), [1, 2], "joints[3].point"),
    ("poe", ("home",), _DEL, "home"),
    ("poe", ("home",), [1, 2, 3], "home"),
]


@pytest.mark.parametrize("base,path,value,field", MALFORMED, ids=[f"{m[0]}:{m[3]}" for m in MALFORMED])
def test_malformed_document_names_the_field(base, path, value, field):
    doc = _set(copy.deepcopy(DOCS[base]), path, value)
    with pytest.raises(ModelFormatError) as err:
        model_from_dict(doc)
    assert err.value.field == field
    assert str(err.value).startswith(f"{field}: ")
    assert isinstance(err.value, ValueError)  # callers may catch ValueError


def test_not_an_object():
    with pytest.raises(ModelFormatError, match="JSON object"):
        model_from_dict([1, 2, 3])  # type: ignore[arg-type]


def test_expected_value_is_stated():
    doc = _set(_ur(), ("units", "length"), "cm")
    with pytest.raises(ModelFormatError, match="mm, m, in"):
        model_from_dict(doc)
    doc = _set(copy.deepcopy(DOCS["poe"]), ("home",), _DEL)
    with pytest.raises(ModelFormatError, match="flange pose"):
        model_from_dict(doc)


def test_prismatic_document_variants_load():
    for conv in ("dh", "mdh", "poe"):
        m = model_from_dict(prismatic_doc(conv))
        assert [j.type for j in m.joints] == ["revolute", "prismatic", "revolute", "revolute"]
        assert m.convention == conv
