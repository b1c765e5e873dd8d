"""Drift over time (``GET /cells/{id}/drift``) and the comparison of two calibrations
(``GET /calibrations/{a}/compare/{b}``): parameters, residuals and predicted accuracy of each
calibration, verify sessions' measured accuracy (with ISO 9283 pose accuracy and repeatability
when a verify session repeated its configurations). Sessions are simulated measurements stored
as the session loop stores them; "the robot changed" is a robot with other link errors."""

from __future__ import annotations

import pytest

from .conftest import auth, register_cell


@pytest.fixture
def history(idle_app, tokens, stored_session):
    """A cell calibrated twice, verified (each configuration three times), then calibrated
    after its robot changed."""
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "drifting")["id"]
        first = stored_session(cell, seed=2)[1]
        second = stored_session(cell, seed=3)[1]
        verify = stored_session(cell, kind="verify", seed=4, n=5, repeats=3)[0]
        changed = stored_session(cell, seed=5, truth_seed=9)[1]
        yield client, {"cell": cell, "cals": [first, second, changed], "verify": verify}


def test_drift_gives_parameters_predicted_accuracy_and_verify_accuracy_over_time(history, tokens):
    client, h = history[0], auth(tokens["viewer"])
    ids = history[1]
    d = client.get(f"/api/v1/cells/{ids['cell']}/drift", headers=h).json()
    cals = d["calibrations"]
    assert [c["id"] for c in cals] == ids["cals"]
    for c in cals:
        # the predicted accuracy stored with each calibration is what its result page shows
        ws = client.get(f"/api/v1/calibrations/{c['id']}/result", headers=h).json()["workspace"]["stats95"]
        assert c["predicted"]["radius95_mean"] == pytest.approx(ws["mean"], rel=1e-4)
        assert c["predicted"]["radius95_max"] == pytest.approx(ws["max"], rel=1e-4)
        assert c["predicted"]["unit"] == "mm" and c["nominal_version"] == 1
    # the robot that changed is known less well (the prior disagrees with its data)
    assert cals[2]["predicted"]["radius95_mean"] > cals[1]["predicted"]["radius95_mean"]
    listed = client.get(f"/api/v1/cells/{ids['cell']}/calibrations", headers=h).json()
    assert [c["predicted"] for c in reversed(listed)] == [c["predicted"] for c in cals]
    # each parameter over time; its change in sigmas: small for the same robot, large once it changed
    series = d["parameters"]["j2.a"]
    assert [e["calibration_id"] for e in series] == ids["cals"] and "change" not in series[0]
    same = max(s[1]["change_sigmas"] for s in d["parameters"].values() if len(s) == 3 and "change_sigmas" in s[1])
    moved = max(s[2]["change_sigmas"] for s in d["parameters"].values() if len(s) == 3 and "change_sigmas" in s[2])
    assert same < 3 < moved, (same, moved)
    # the verify session between: when, against which calibration, RMS and ISO 9283 figures
    (v,) = d["verify"]
    session = client.get(f"/api/v1/sessions/{ids['verify']}", headers=h).json()
    measured = session["plan_info"]["verify"]
    assert v["session_id"] == ids["verify"] and v["calibration_id"] == ids["cals"][1]
    assert v["at"] == session["updated_at"] and v["n"] == 15 and v["rms"] == measured["rms"]
    assert 0 < v["iso9283"]["RP_max"] < 0.2 and v["iso9283"]["repeats"] == 3  # tracker noise 0.02 mm a axis
    assert v["iso9283"]["AP_max"] == measured["iso9283"]["accuracy"]["max"]
    # the verify session's own result: ISO 9283 per pose
    iso = measured["iso9283"]
    assert iso["poses"] == 5 and [p["visits"] for p in iso["per_pose"]] == [3] * 5
    assert iso["repeatability"]["max"] == max(p["RP"] for p in iso["per_pose"])
    assert iso["accuracy"]["mean"] == pytest.approx(sum(p["AP"] for p in iso["per_pose"]) / 5)
    # the same robot, well calibrated: every pose within a few noise levels of its command
    assert all(p["AP"] < 0.1 for p in iso["per_pose"])


def test_compare_two_calibrations(history, tokens):
    client, ids = history
    first, second, changed = ids["cals"]
    h = auth(tokens["viewer"])
    same = client.get(f"/api/v1/calibrations/{first}/compare/{second}", headers=h).json()
    other = client.get(f"/api/v1/calibrations/{second}/compare/{changed}", headers=h).json()
    assert same["from"] == first and same["to"] == second and same["nominal_versions"] == [1, 1]
    assert same["predicted_to"] == client.get(f"/api/v1/calibrations/{second}", headers=h).json()["predicted"]
    for row in same["parameters"] + other["parameters"]:
        if row["group"] in ("base", "tool"):  # frames: the step between them, along and about their axes
            assert row["from"] is None and row["change"] is not None
        elif row["from"] is not None and row["to"] is not None:
            assert row["change"] == pytest.approx(row["to"] - row["from"])
        assert row["moved"] == (row["change_sigmas"] is not None and row["change_sigmas"] > 2)
    both = [r for r in other["parameters"] if r["status"] == "both" and r["group"] in ("joint", "target")]
    assert sum(r["moved"] for r in same["parameters"]) <= 2
    assert sum(r["moved"] for r in both) >= len(both) // 2
    moved = [r["change_sigmas"] for r in other["parameters"] if r["moved"]]
    assert moved == sorted(moved, reverse=True)  # what moved most first
    assert client.get(f"/api/v1/calibrations/{first}/compare/999", headers=h).status_code == 404
