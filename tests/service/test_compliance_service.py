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
        # the next session starts from this calibration, its covariance as the prior (compliance terms included)
        _, cal2 = stored_session(r.json()["id"], n=40, seed=5, sag="cobot")
        rep = client.get(f"/api/v1/calibrations/{cal2}/result", headers=auth(tokens["viewer"])).json()["report"]
        assert rep["prior"] is not None and rep["compliance"]["cv_rms_compliant"] < 0.05
        assert any(p["name"].startswith("compliance.") and p["source"] == "data + prior" for p in rep["parameters"])
