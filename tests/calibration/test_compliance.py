"""Joint compliance under gravity (calibration.compliance): the compliant forward kinematics
against a complete reference written here (explicit DH matrices, lumped masses, torques by
cross products), the analytic Jacobian columns of the compliance terms against central finite
differences, and the model file's compliance section."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from calibration import compliance as C
from calibration.conventions import to_poe
from calibration.jacobian import predict
from calibration.kinematics import fk, target_positions
from calibration.model import ModelFormatError, model_from_dict, model_to_dict
from calibration.parameters import apply_step, candidate_parameters, parameter_values
from calibration.robots import nominal, nominal_document
from calibration.simulate import SAGGING_ARMS, heavy_arm_nominal, sagging

G0 = 9.80665


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    i, k = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(4)
    R[i, i] = R[k, k] = c
    R[i, k], R[k, i] = -s, s
    return R


def _trans(axis: int, d: float) -> np.ndarray:
    T = np.eye(4)
    T[axis, 3] = d
    return T


def _pose(p) -> np.ndarray:
    return _trans(0, p[0]) @ _trans(1, p[1]) @ _trans(2, p[2]) @ _rot(2, p[5]) @ _rot(1, p[4]) @ _rot(0, p[3])


def _reference(model, q, compliance, masses, payload, gravity):
    """Tool origin (3,) of a standard-DH arm sagging under gravity, from first principles:
    frames T_i = B·A_1···A_i; joint i turns about z of frame i-1 through its origin; lump L
    sits at T_L · r; τ_i = Σ z·((c − o) × m g ĝ_world) over the lumps at or after link i and the
    payload; the joints deflect by compliance × torque at the rigid configuration."""
    B = _pose(model.base)
    g_world = B[:3, :3] @ (np.asarray(gravity) / np.linalg.norm(gravity))

    def frames(qq):
        Ts, T = [B], B
        for j, v in zip(model.joints, qq):
            T = T @ _rot(2, j.theta + v) @ _trans(2, j.d) @ _trans(0, j.a) @ _rot(0, j.alpha)
            Ts.append(T)
        return Ts

    Ts = frames(q)
    tool = Ts[-1] @ _pose(model.tool)
    names = [j.name for j in model.joints]
    dq = np.zeros(len(q))
    for i, name in enumerate(names):
        if name not in compliance:
            continue
        z, o = Ts[i][:3, 2], Ts[i][:3, 3]
        tau = 0.0
        for lump, (m, r) in masses.items():
            L = names.index(lump)
            if L < i:
                continue
            c = Ts[L + 1][:3, :3] @ np.asarray(r) + Ts[L + 1][:3, 3]
            tau += z @ np.cross(c - o, m * G0 * g_world)
        c = tool[:3, :3] @ np.asarray(payload[1:]) + tool[:3, 3]
        tau += z @ np.cross(c - o, payload[0] * G0 * g_world)
        dq[i] = compliance[name] * tau
    return (frames(q + dq)[-1] @ _pose(model.tool))[:3, 3]


def test_compliant_fk_matches_first_principles_reference():
    model = dataclasses.replace(
        nominal("ur10e"),
        base=np.array([0.3, -0.2, 0.1, 0.2, -0.1, 0.4]),
        tool=np.array([0.01, 0.02, 0.1, 0.1, 0.0, 0.2]),
    )
    fig = SAGGING_ARMS["cobot"]
    gravity = (0.1, -0.2, -1.0)  # not along the base z: the section's gravity is in the base frame
    section = C.physical_section(model, fig["compliance"], fig["masses"], gravity=gravity)
    cm = C.with_section(model, section)
    rng = np.random.default_rng(2)
    q = rng.uniform(-np.pi, np.pi, (6, 6))
    payload = np.array([10.0, 0.02, -0.01, 0.12])
    ours = fk(cm, q, payload)[:, :3, 3]
    rigid = fk(model, q)[:, :3, 3]
    for n in range(len(q)):
        ref = _reference(model, q[n], fig["compliance"], fig["masses"], payload, gravity)
        assert np.linalg.norm(ours[n] - ref) < 1e-8  # the O(δ²) small-deflection terms agree too: same rule
        assert np.linalg.norm(ours[n] - rigid[n]) > 1e-4  # and the arm does sag (0.1 mm or more)


def test_gravity_torques_match_reference_and_vanish_about_a_vertical_axis():
    model = nominal("ur10e")
    fig = SAGGING_ARMS["cobot"]
    q = np.array([[0.3, -1.2, 0.8, -0.4, 1.1, 0.2], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    payload = np.array([10.0, 0.0, 0.0, 0.1])
    tau = C.gravity_torques(model, q, fig["masses"], payload)
    assert np.allclose(tau[:, 0], 0.0, atol=1e-9)  # j1 is vertical
    # the upper arm horizontal (q2 = 0): its own weight alone gives m g times its lever
    only_upper = {"j2": fig["masses"]["j2"]}
    t2 = C.gravity_torques(model, q[1:], only_upper)[0, 1]
    m, r = only_upper["j2"]
    assert abs(abs(t2) - m * G0 * (0.6127 - r[0])) < 1e-9  # lever from the shoulder: |a2| - r_x


def test_small_deflection_error_is_second_order():
    """Torques at the rigid configuration: evaluating them again at the deflected one changes
    the position by far less than a tracker's noise (what makes the rule enough)."""
    model = nominal("ur10e")
    cm = sagging(model, "cobot")
    rng = np.random.default_rng(5)
    q = rng.uniform(-np.pi, np.pi, (50, 6))
    payload = np.array(SAGGING_ARMS["cobot"]["payload"])
    dv, _ = C.deflections(cm, q, payload)
    once = fk(cm, q, payload)[:, :3, 3]
    dv2, _ = C.deflections(cm, q + dv, payload)  # torques at the deflected configuration
    again = fk(model, q + dv2)[:, :3, 3]
    sag = np.linalg.norm(once - fk(model, q)[:, :3, 3], axis=1)
    assert sag.max() > 1e-3
    assert np.linalg.norm(again - once, axis=1).max() < 5e-6


@pytest.mark.parametrize("convention", ["dh", "poe"])
def test_compliance_jacobian_columns_match_finite_differences(convention):
    model = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.02, 0.05])})
    if convention == "poe":
        model = to_poe(model)
    model = sagging(model, "cobot", frames_of=nominal("ur10e") if convention == "poe" else None)
    params = [p for p in candidate_parameters(model, targets=("smr",)) if p.name.startswith("compliance.")]
    assert {p.kind for p in params} == {"angle_per_torque", "angle_per_length", "angle"}
    rng = np.random.default_rng(7)
    q = rng.uniform(-np.pi, np.pi, (8, 6))
    payload = np.column_stack([rng.uniform(0, 10, 8), rng.normal(0, 0.05, (8, 3))])
    names = np.array(["smr"] * 8, dtype=object)
    p_tool = np.tile(model.targets["smr"], (8, 1))
    pred = predict(model, q, p_tool, params, names, payload)
    for k, par in enumerate(params):
        h = {"angle_per_torque": 1e-7, "angle_per_length": 1e-5, "angle": 1e-5}[par.kind]
        step = np.zeros(len(params))
        step[k] = h
        plus = predict(apply_step(model, params, step), q, p_tool, payload=payload).p_world
        minus = predict(apply_step(model, params, -step), q, p_tool, payload=payload).p_world
        fd = (plus - minus) / (2 * h)
        scale = max(np.abs(fd).max(), 1e-3)
        assert np.abs(pred.Jp[:, :, k] - fd).max() < 1e-6 * scale, par.name
    # the step moves the term's value, and parameter_values reads it back
    moved = apply_step(model, params, np.arange(len(params)) * 1e-9)
    assert np.allclose(
        parameter_values(moved, params) - parameter_values(model, params), np.arange(len(params)) * 1e-9, atol=1e-15
    )


def test_rigid_model_is_untouched_by_a_payload():
    model = nominal("ur10e")
    q = np.random.default_rng(1).uniform(-3, 3, (4, 6))
    assert np.array_equal(fk(model, q), fk(model, q, np.array([50.0, 0, 0, 0.3])))
    assert candidate_parameters(model) == candidate_parameters(C.with_section(model, None))


def test_section_payload_is_the_default_for_rows_without_one():
    cm = sagging(nominal("ur10e"), "cobot")
    q = np.random.default_rng(3).uniform(-3, 3, (4, 6))
    pay = np.array([8.0, 0.0, 0.01, 0.1])
    assert np.allclose(target_positions(C.with_payload(cm, pay), q), target_positions(cm, q, payload=pay))
    assert not np.allclose(target_positions(cm, q), target_positions(cm, q, payload=pay))


def test_model_file_round_trip_in_file_units():
    model = sagging(model_from_dict(nominal_document("ur10e")), "cobot")
    model = C.with_payload(model, (10.0, 0.0, 0.0, 0.1))
    doc = json.loads(json.dumps(model_to_dict(model)))
    sec = doc["compliance"]
    assert sec["joints"] == ["j2", "j3"] and sec["lumps"] == ["j2", "j3", "j6"]
    assert sec["term_units"] == {"k": "deg/(N·m)", "m": "deg/mm", "x|y|z": "deg"}
    assert sec["terms"]["j2.k"] == pytest.approx(np.rad2deg(5e-6))  # deg per N·m
    assert sec["terms"]["j2.j3.m"] == pytest.approx(np.rad2deg(5e-6 * 4.0 * G0) / 1000)  # deg per mm
    assert sec["payload"] == [10.0, 0.0, 0.0, 100.0]  # kg, then mm
    back = model_from_dict(doc)
    q = np.random.default_rng(4).uniform(-3, 3, (5, 6))
    assert np.allclose(fk(back, q), fk(model, q), atol=1e-12)
    for k, v in model.compliance.values.items():
        assert back.compliance.values[k] == pytest.approx(v, rel=1e-10)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"joints": ["j9"]}, "compliance.joints[0]"),
        ({"lumps": ["j2", "nope"]}, "compliance.lumps[1]"),
        ({"terms": {"j3.j2.m": 1.0}}, "compliance.terms.j3.j2.m"),
        ({"terms": {"j2.k": "x"}}, "compliance.terms.j2.k"),
        ({"gravity": [0, 0, 0]}, "compliance.gravity"),
        ({"payload": [-1, 0, 0, 0]}, "compliance.payload[0]"),
    ],
)
def test_bad_compliance_section_names_the_field(change, field):
    doc = nominal_document("ur10e")
    doc["compliance"] = {"joints": ["j2"], "lumps": ["j2", "j6"], "terms": {}, **change}
    with pytest.raises(ModelFormatError) as exc:
        model_from_dict(doc)
    assert exc.value.field == field


def test_prismatic_joint_cannot_deflect():
    doc = nominal_document("ur10e")
    doc["joints"][1]["type"] = "prismatic"
    doc["compliance"] = {"joints": ["j2"], "lumps": ["j2"]}
    with pytest.raises(ModelFormatError, match="prismatic"):
        model_from_dict(doc)


def test_default_section_skips_a_vertical_first_axis():
    assert C.default_section(nominal("ur10e")).joints == ("j2", "j3")
    assert C.default_section(heavy_arm_nominal()).lumps == ("j2", "j3", "j6")
    tilted = dataclasses.replace(nominal("ur10e"))
    # gravity along the base x axis (a wall-mounted arm): j1 feels gravity too
    assert C.default_section(tilted, gravity=(1.0, 0.0, 0.0)).joints[0] == "j1"


@pytest.mark.parametrize("convert", ["poe", "hayati", "mdh"])
def test_converting_the_convention_keeps_the_sag(convert):
    """The lumps sit in link frames, which a conversion moves: re-expressed, the converted model
    sags exactly as the original (identification converts mdh to dh and parallel axes to Hayati
    links before it starts)."""
    from calibration.conventions import dh_to_mdh, hayati_for_parallel_axes, mdh_to_dh

    base = dataclasses.replace(
        nominal("ur10e"),
        base=np.array([0.2, 0.1, 0.3, 0.3, -0.2, 1.0]),
        tool=np.array([0.0, 0.01, 0.12, 0.0, 0.1, 0.0]),
    )
    if convert == "mdh":
        source = sagging(dh_to_mdh(base), "cobot")
        converted = mdh_to_dh(dataclasses.replace(source, compliance=None))
    else:
        source = sagging(base, "cobot")
        rigid = dataclasses.replace(source, compliance=None)
        converted = to_poe(rigid) if convert == "poe" else hayati_for_parallel_axes(rigid)[0]
    moved = C.reexpress(converted, source)
    q = np.random.default_rng(6).uniform(-3, 3, (10, 6))
    payload = np.array([7.0, 0.01, 0.0, 0.09])
    assert np.abs(fk(moved, q, payload) - fk(source, q, payload)).max() < 1e-12
    if convert != "hayati":  # (the UR's parallel links have d = 0: Hayati's form keeps their frames)
        naive = dataclasses.replace(converted, compliance=source.compliance)  # frames moved, terms not
        assert np.abs(fk(naive, q, payload)[:, :3, 3] - fk(source, q, payload)[:, :3, 3]).max() > 1e-5
