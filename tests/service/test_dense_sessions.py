"""Sessions that gather what a learned correction needs (issue 28) and plans that say what they
cannot determine (issue 27): a pose session of 1,200 configurations is a dense set over the
cell's allowed region (200 planned D-optimally, the rest a Latin hypercube of the region); its
plan shows, before anything moves, the accuracy the current calibration's learning curve
predicts for that many poses; a short plan says how many poses, or which kind of measurement,
would determine what it cannot."""

from __future__ import annotations

import numpy as np

from service.store import make_engine

from .conftest import REGION_CENTRE_DEG, auth, register_cell

REGION_DEG = 50.0


def _dry_plan(client, settings, tokens, cell_id: int, count: int) -> dict:
    from service.session_loop import run_session

    t = auth(tokens["technician"])
    r = client.post(
        f"/api/v1/cells/{cell_id}/sessions", json={"kind": "pose", "count": count, "dry_run": True}, headers=t
    )
    assert r.status_code == 201, r.text
    engine = make_engine(settings.effective_database_url)
    try:
        assert run_session(engine, settings, r.json()["id"]) == "completed"
    finally:
        engine.dispose()
    return client.get(f"/api/v1/sessions/{r.json()['id']}/plan", headers=auth(tokens["viewer"])).json()


def _region(client, tokens, cell_id: int) -> np.ndarray:
    lim = np.stack([np.array(REGION_CENTRE_DEG) - REGION_DEG, np.array(REGION_CENTRE_DEG) + REGION_DEG], axis=1)
    r = client.patch(
        f"/api/v1/cells/{cell_id}", json={"allowed_region": lim.tolist()}, headers=auth(tokens["technician"])
    )
    assert r.status_code == 200, r.text
    return lim


def test_a_dense_pose_session_fills_the_region_and_shows_the_accuracy_its_learning_curve_predicts(
    idle_app, tokens, stored_session, settings
):
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "dense")["id"]
        lim = _region(client, tokens, cell)
        # an earlier calibration of the cell, from 80 poses of the region: its report has a learning curve
        cal = stored_session(cell, seed=2, n=80, region_deg=REGION_DEG)[1]
        report = client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["report"]
        curve = report["residual_map"]["learning_curve"]
        assert len(curve) >= 2 and all(p["rms"] > 0 for p in curve)
        plan = _dry_plan(client, settings, tokens, cell, 1200)
    assert plan["configurations"] == 1200 and plan["check"]["ok"]
    assert plan["method"].startswith("dense: 200 poses")
    assert "from the 200 planned poses: the 1000 filling" in plan["predicted"]["note"]
    # the region evenly: every joint's values in each tenth of its allowed range, none outside it
    for j, joint in enumerate(plan["joints"]):
        v = np.array(joint["values"])
        assert lim[j, 0] - 1e-6 <= v.min() and v.max() <= lim[j, 1] + 1e-6
        tenths = np.floor((v - lim[j, 0]) / (lim[j, 1] - lim[j, 0]) * 10).clip(0, 9)
        assert np.bincount(tenths.astype(int), minlength=10).min() >= 100  # 1,000 fill the tenths evenly
    lc = plan["learning_curve"]
    assert lc["available"] and lc["calibration_id"] == cal and lc["poses"] == 1200 and lc["extrapolated"]
    # more poses than the curve saw: predicted at most its last point, never below the noise
    assert np.sqrt(3) * lc["noise"] <= lc["rms"] <= curve[-1]["rms"] * 1.0001
    assert "power law" in lc["note"]


def test_a_short_plan_says_how_many_poses_or_which_kind_would_determine_what_it_cannot(idle_app, tokens, settings):
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "short")["id"]
        plan = _dry_plan(client, settings, tokens, cell, 5)
        js = client.get("/web/js/views/cells.js").text
    sf = plan["predicted"]["shortfall"]
    assert sf["count"] == 5 and sf["more_poses"] == sf["poses_needed"] - 5 > 0
    needs = {k["category"]: k for k in sf["by_kind"]}
    assert "orientation measurements" in needs["tool_orientation"]["needs"]
    assert f"{sf['more_poses']} more" in sf["message"]
    # no earlier calibration: no learning curve to predict from, and it says so
    assert not plan["learning_curve"]["available"] and "no earlier learning curve" in plan["learning_curve"]["reason"]
    assert "plan-shortfall" in js and "learning-curve" in js  # the page's plan view shows both
