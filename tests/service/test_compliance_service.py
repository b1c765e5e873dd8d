"""A cell whose nominal model carries a joint-compliance section: its pose sessions identify the
compliant model, and the result shows it against the rigid one (cross-validated on the same
data), which the web result page displays."""

from __future__ import annotations

from .conftest import auth


def test_compliant_cell_result_shows_rigid_against_compliant(idle_app, tokens, stored_session):
    from calibration.robots import nominal_document

    doc = nominal_document("ur10e")
    doc["targets"] = {"smr": [0, 0, 50]}
    doc["compliance"] = {"joints": ["j2", "j3"], "lumps": ["j2", "j3", "j6"]}  # every term from 0
    with idle_app() as client:
        r = client.post(
            "/api/v1/cells", json={"name": "sagging", "model": doc, "devices": {}}, headers=auth(tokens["technician"])
        )
        assert r.status_code == 201, r.text
        _, cal = stored_session(r.json()["id"], n=60, sag="cobot")
        res = client.get(f"/api/v1/calibrations/{cal}/result", headers=auth(tokens["viewer"]))
        assert res.status_code == 200, res.text
        comp = res.json()["report"]["compliance"]
        assert comp["joints"] == ["j2", "j3"] and comp["folds"] == 5
        assert comp["cv_rms_compliant"] < 0.2 * comp["cv_rms_rigid"]  # mm: the arm sags, the compliant model knows
        assert comp["cv_rms_compliant"] < 0.05
        model = client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"]
        assert model["compliance"]["terms"]  # the identified terms are in the stored model
        # every residual correction was tried (as `recal identify --residual-map auto`) and left
        # out: the compliant model leaves only the tracker's noise, which no function of the joints predicts
        rmap = res.json()["report"]["residual_map"]
        assert rmap["folds"] == 5 and rmap["chosen"] == "none" and "residual_map" not in model
        fams = rmap["families"]
        assert set(fams) | set(rmap["not_tried"]) == {"none", "map", "transmission", "trees"}
        assert min(f["rms"] for k, f in fams.items() if k != "none") > (1 - rmap["min_gain"]) * fams["none"]["rms"]
        # the next session starts from this calibration, its covariance as the prior (compliance terms included)
        _, cal2 = stored_session(r.json()["id"], n=40, seed=5, sag="cobot")
        rep = client.get(f"/api/v1/calibrations/{cal2}/result", headers=auth(tokens["viewer"])).json()["report"]
        assert rep["prior"] is not None and rep["compliance"]["cv_rms_compliant"] < 0.05
        assert any(p["name"].startswith("compliance.") and p["source"] == "data + prior" for p in rep["parameters"])


def test_a_pose_session_keeps_a_residual_map_where_it_helps(idle_app, tokens, stored_session):
    """A rigid cell whose arm sags, measured in one region (every joint within 40° of one working
    configuration): what the rigid model leaves is smooth in the joints there, so the session's
    finish keeps a residual map (as `recal identify --residual-map auto`), stores it with the
    calibration, and the service's compensation applies it inside the region and flags a point
    outside it."""
    import csv
    import io

    import numpy as np

    from calibration.robots import nominal_document

    from .conftest import REGION_CENTRE_DEG

    doc = nominal_document("ur10e")
    doc["targets"] = {"smr": [0, 0, 50]}
    with idle_app() as client:
        r = client.post(
            "/api/v1/cells",
            json={"name": "sagging-rigid", "model": doc, "devices": {}},
            headers=auth(tokens["technician"]),
        )
        assert r.status_code == 201, r.text
        _, cal = stored_session(r.json()["id"], n=100, sag="cobot", region_deg=40.0)
        res = client.get(f"/api/v1/calibrations/{cal}/result", headers=auth(tokens["viewer"])).json()
        assert "compliance" not in (res["report"] or {}) or res["report"]["compliance"] is None
        rmap = res["report"]["residual_map"]
        fams = rmap["families"]
        assert fams[rmap["chosen"]]["rms"] < 0.9 * fams["none"]["rms"], rmap
        model = client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"]
        assert model["residual_map"]["format"] == "recal.residual_map/1"
        assert len(model["residual_map"]["configurations"]) == 100
        inside = REGION_CENTRE_DEG
        outside = [90.0, -60.0, 90.0, -120.0, -90.0, 0.0]  # joint 1 50° beyond what the session measured
        task = "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(map(str, q)) for q in (inside, outside)) + "\n"
        out = client.post(
            f"/api/v1/calibrations/{cal}/compensate?mode=joints", content=task, headers=auth(tokens["technician"])
        )
        assert out.status_code == 200, out.text
        rows = list(csv.DictReader(io.StringIO(out.text)))
        assert "outside_mapped_region" not in rows[0]["flags"] and "outside_mapped_region" in rows[1]["flags"], rows
        assert np.all(np.isfinite([float(rows[0][f"q{i}"]) for i in range(1, 7)]))
