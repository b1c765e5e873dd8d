"""Exports (calibration.export): a URDF parsed back reproduces ``fk``; a DH table read back is the
same robot; what cannot be exported is said."""

from __future__ import annotations

import csv
import io
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from sample_models import all_convention_docs, random_readings, si_readings

from calibration.export import dh_table, export, export_warnings, to_dh_csv, to_dh_markdown, to_urdf
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.robots import nominal
from calibration.simulate import perturbed

DOCS = all_convention_docs()
EXACT = [
    k
    for k, d in DOCS.items()
    if d.get("coupling") is None and not any("gain" in j or "harmonic" in j for j in d["joints"])
]


# --------------------------------------------------------------------------- a tiny URDF reader


def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx  # URDF: fixed-axis roll, pitch, yaw


def _vec(text):
    return np.array([float(v) for v in text.split()])


def urdf_fk(text: str, q: np.ndarray, tip: str) -> np.ndarray:
    """T_root_tip (4, 4) of a URDF chain at joint positions ``q`` (in the order the movable joints
    appear along the chain), written from the URDF specification only."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    chain = []
    link = tip
    while link in by_child:
        j = by_child[link]
        chain.append(j)
        link = j.find("parent").get("link")
    chain.reverse()
    T = np.eye(4)
    k = 0
    for j in chain:
        o = j.find("origin")
        To = np.eye(4)
        To[:3, :3] = _rpy(*_vec(o.get("rpy")))
        To[:3, 3] = _vec(o.get("xyz"))
        T = T @ To
        jt = j.get("type")
        if jt in ("revolute", "continuous", "prismatic"):
            axis = _vec(j.find("axis").get("xyz"))
            axis = axis / np.linalg.norm(axis)
            M = np.eye(4)
            if jt == "prismatic":
                M[:3, 3] = axis * q[k]
            else:
                K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
                M[:3, :3] = np.eye(3) + np.sin(q[k]) * K + (1 - np.cos(q[k])) * K @ K
            T = T @ M
            k += 1
    assert k == len(q)
    return T


@pytest.mark.parametrize("doc_id", EXACT)
def test_urdf_reproduces_fk(doc_id):
    """The URDF's chain (tool link, and every target link) equals fk for random readings."""
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    text = to_urdf(model, names="recal", velocity=1.0, effort=10.0, world=True)
    assert export_warnings(model, "urdf", effort=10.0, world=True) == []
    rng = np.random.default_rng(3)
    q = si_readings(doc, random_readings(doc, 5, rng))
    T = fk(model, q)
    for i in range(len(q)):
        np.testing.assert_allclose(urdf_fk(text, q[i], "tool"), T[i], atol=1e-10)
        for t, p in model.targets.items():
            Tt = urdf_fk(text, q[i], f"target_{t}")
            np.testing.assert_allclose(Tt[:3, 3], T[i, :3, :3] @ p + T[i, :3, 3], atol=1e-10)


def test_urdf_of_a_perturbed_robot_and_its_structure():
    """An identified-like model (every axis tilted and shifted, poe form) exports exactly; the
    URDF names the links and joints, carries the limits and is in metres and radians."""
    rng = np.random.default_rng(7)
    base = nominal("ur10e")
    truth = perturbed(base, rng, base_length_m=0.01, base_angle_rad=0.01, tool_length_m=0.01, tool_angle_rad=0.01)
    text = to_urdf(truth, prefix="r1_", names="recal", world=True)
    q = rng.uniform(-3, 3, (4, 6))
    for qi, Ti in zip(q, fk(truth, q)):
        np.testing.assert_allclose(urdf_fk(text, qi, "r1_tool"), Ti, atol=1e-10)
    root = ET.fromstring(text)
    moving = [j for j in root.findall("joint") if j.get("type") != "fixed"]
    assert [j.get("name") for j in moving] == [f"r1_j{i}" for i in range(1, 7)]
    lim = moving[0].find("limit")
    assert float(lim.get("upper")) == pytest.approx(2 * np.pi)  # 360 deg, written in rad
    links = {l.get("name") for l in root.findall("link")}
    assert {"r1_world", "r1_base_link", "r1_flange", "r1_tool"} <= links


@pytest.mark.parametrize("doc_id", ["dh_gain", "dh_coupling", "dh_harmonic"])
def test_urdf_says_what_it_cannot_represent(doc_id):
    model = model_from_dict(DOCS[doc_id])
    warnings = export_warnings(model, "urdf", effort=10.0)
    assert warnings
    text = to_urdf(model, velocity=1.0, effort=10.0)
    assert text.count("warning:") == len(warnings)


# --------------------------------------------------------------------------- DH tables


def _read_dh_csv(text: str, units: dict) -> dict:
    """A recal.model/1 document from a DH CSV export (the comments carry base, tool, targets)."""
    comments = {}
    body = []
    for line in text.splitlines():
        if line.startswith("# ") and ": " in line:
            k, v = line[2:].split(": ", 1)
            comments[k] = v
        elif not line.startswith("#"):
            body.append(line)
    rows = list(csv.DictReader(io.StringIO("\n".join(body))))
    nums = lambda s: [float(v) for v in s.split(",")]  # noqa: E731
    joints = []
    for r in rows:
        j = {
            "name": r["joint"],
            "type": r["type"],
            "theta": float(r["theta"]),
            "a": float(r["a"]),
            "alpha": float(r["alpha"]),
            "lower": float(r["lower"]),
            "upper": float(r["upper"]),
        }
        if r.get("beta"):
            j["beta"] = float(r["beta"])
            if r["type"] == "prismatic":
                j["d"] = float(r["d"])
        else:
            j["d"] = float(r["d"])
        joints.append(j)
    targets = {k[7:]: nums(v) for k, v in comments.items() if k.startswith("target ")}
    return {
        "format": "recal.model/1",
        "units": units,
        "convention": comments["convention"],
        "base": nums(comments["base"]),
        "tool": nums(comments["tool"]),
        "joints": joints,
        "targets": targets,
    }


@pytest.mark.parametrize("doc_id", EXACT)
def test_dh_csv_read_back_is_the_same_robot(doc_id):
    """Every model (poe ones converted to DH) written as a DH CSV and read back gives the same
    tool poses, in the model's own units."""
    doc = DOCS[doc_id]
    model = model_from_dict(doc)
    back = model_from_dict(_read_dh_csv(to_dh_csv(model), doc["units"]))
    q = si_readings(doc, random_readings(doc, 6, np.random.default_rng(1)))
    np.testing.assert_allclose(fk(back, q), fk(model, q), atol=1e-6 * model.units.length_m + 1e-9)
    assert set(back.targets) == set(model.targets)


def test_dh_table_values_in_model_units():
    """The UR10e table is the published one, in mm and degrees."""
    t = dh_table(nominal("ur10e"))
    assert t["kind"] == "dh" and t["units"] == {"length": "mm", "angle": "deg"}
    assert t["header"] == ["joint", "type", "theta", "d", "a", "alpha", "lower", "upper"]
    assert t["rows"][0][3] == pytest.approx(180.7) and t["rows"][0][5] == pytest.approx(90.0)
    assert t["rows"][2][4] == pytest.approx(-571.55) and t["rows"][0][7] == pytest.approx(360.0)


def test_dh_table_of_a_perturbed_poe_robot_uses_hayati_for_parallel_axes():
    truth = perturbed(nominal("ur10e"), np.random.default_rng(2))
    t = dh_table(truth)
    assert t["convention"] == "poe" and t["kind"] == "dh" and "beta" in t["header"]
    betas = [row[t["header"].index("beta")] for row in t["rows"]]
    assert betas[1] != "" and betas[2] != "" and betas[0] == ""  # axes 2-3-4 of a UR are parallel


def test_markdown_and_gains_and_coupling():
    md = to_dh_markdown(model_from_dict(DOCS["dh_gain"]))
    assert "| joint | type | theta (deg) | d (mm) | a (mm) | alpha (deg) | gain | lower | upper |" in md
    assert "| j1 | revolute | 0 | 180.7 | 0 | 90 | 1.001 | -360 | 360 |" in md
    coupled = to_dh_csv(model_from_dict(DOCS["dh_coupling"]))
    assert "# coupling row 3: 0, -1, -1, 0, 0, 0" in coupled
    assert "harmonic" in to_dh_csv(model_from_dict(DOCS["dh_harmonic"]))


def test_export_dispatch_rejects_unknown_format():
    model = nominal("ur10e")
    assert export(model, "dh-md") == to_dh_markdown(model)
    with pytest.raises(ValueError, match="urdf, ur-calibration, dh-csv, dh-md"):
        export(model, "sdf")
