"""Compensation through the API: a task CSV posted to ``/calibrations/{id}/compensate`` comes
back with the commands that bring the identified robot to each pose (checked with the library's
forward kinematics, not with the endpoint's own report), stored and readable again; the task
files registered with a cell are compensated again by ``/cells/{id}/tasks/compensate`` (what
the nightly job does after a recalibration), a bad one reported without stopping the others."""

from __future__ import annotations

import csv
import io

import numpy as np

from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.transforms import matrix_to_quat

from .conftest import auth

Q = [f"q{i}" for i in range(1, 7)]


def _task(model, n=8, seed=4) -> tuple[str, np.ndarray, np.ndarray]:
    """A task CSV: poses the identified robot reaches at ``q_goal`` (deg), taught at ``q_taught``
    a few tenths of a degree away (which picks the inverse-kinematics branch)."""
    rng = np.random.default_rng(seed)
    q_taught = np.column_stack(
        [
            rng.uniform(-150, 150, n),
            rng.uniform(-140, -40, n),
            rng.uniform(40, 140, n),
            rng.uniform(-150, 150, n),
            rng.uniform(40, 140, n),
            rng.uniform(-150, 150, n),
        ]
    )
    q_goal = q_taught + rng.uniform(-0.3, 0.3, q_taught.shape)
    T = fk(model, np.radians(q_goal))
    quat = matrix_to_quat(T[:, :3, :3])
    lines = ["name,x,y,z,qw,qx,qy,qz," + ",".join(Q)]
    for i in range(n):
        lines.append(
            f"P{i},"
            + ",".join(f"{v:.10f}" for v in T[i, :3, 3] * 1000)
            + ","
            + ",".join(f"{v:.15f}" for v in quat[i])
            + ","
            + ",".join(f"{v:.6f}" for v in q_taught[i])
        )
    return "\n".join(lines) + "\n", q_taught, q_goal


def test_the_compensate_endpoint_answers_commands_that_reach_the_poses(calibrated, tokens):
    client, _, cal = calibrated
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    text, q_taught, q_goal = _task(model)
    r = client.post(
        f"/api/v1/calibrations/{cal}/compensate?mode=joints&name=weld.csv", content=text, headers=auth(tokens["job"])
    )
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert len(rows) == 8 and all(row["converged"] == "1" for row in rows)
    q_comp = np.array([[float(row[c]) for c in Q] for row in rows])
    np.testing.assert_allclose(q_comp, q_goal, atol=1e-4)  # the identified robot's own joints, deg
    assert np.abs(q_comp - q_taught).max() > 0.05  # not the taught ones
    reached = fk(model, np.radians(q_comp))
    wanted = np.array([[float(row[c]) for c in ("x", "y", "z")] for row in rows]) / 1000
    assert np.abs(reached[:, :3, 3] - wanted).max() < 1e-6
    # stored: readable again, with its per-point report
    comp = r.headers["x-recal-compensation"]
    assert client.get(f"/api/v1/compensations/{comp}", headers=auth(tokens["viewer"])).text == r.text
    report = client.get(f"/api/v1/compensations/{comp}/report", headers=auth(tokens["viewer"])).json()
    assert report["name"] == "weld.csv" and report["report"]["summary"]["converged"] == 8
    # bad input names the line; a viewer may not compensate
    bad = client.post(f"/api/v1/calibrations/{cal}/compensate", content="x,y\n1,2\n", headers=auth(tokens["job"]))
    assert bad.status_code == 422 and bad.json()["detail"]["field"] == "body"
    assert (
        client.post(f"/api/v1/calibrations/{cal}/compensate", content=text, headers=auth(tokens["viewer"])).status_code
        == 403
    )


def test_registered_task_files_are_compensated_again(calibrated, tokens, stored_session):
    client, cell, cal = calibrated
    t = auth(tokens["technician"])
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=t).json()["model"])
    text, _, q_goal = _task(model, n=4)
    for name, content in (("weld.csv", text), ("broken.csv", "q1,q2\nnot,numbers\n")):
        assert (
            client.post(f"/api/v1/cells/{cell}/tasks", json={"name": name, "content": content}, headers=t).status_code
            == 201
        )
    r = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["calibration_id"] == cal  # the cell's current calibration
    good, broken = out["tasks"]
    assert good["name"] == "weld.csv" and good["summary"]["converged"] == 4
    assert broken["name"] == "broken.csv" and "broken.csv" in broken["error"] and "compensation_id" not in broken
    rows = list(
        csv.DictReader(io.StringIO(client.get(f"/api/v1/compensations/{good['compensation_id']}", headers=t).text))
    )
    np.testing.assert_allclose([[float(row[c]) for c in Q] for row in rows], q_goal, atol=1e-4)
    # after a recalibration the current calibration stays the default until the new one is put in
    # use (issue 27: activated, not overwritten), then the new one is
    newer = stored_session(cell, seed=3)[1]
    assert client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=t).json()["calibration_id"] == cal
    assert client.post(f"/api/v1/calibrations/{newer}/activate", headers=t).status_code == 200
    assert client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=t).json()["calibration_id"] == newer
    assert (
        client.post(f"/api/v1/cells/{cell}/tasks/compensate?calibration_id={cal}", headers=t).json()["calibration_id"]
        == cal
    )
    assert client.post(f"/api/v1/cells/{cell}/tasks/compensate?calibration_id=999", headers=t).status_code == 404


def test_the_compensate_endpoint_takes_the_task_payload(calibrated, tokens):
    """``?payload=KG,X,Y,Z`` reaches the compensation (a calibration without joint compliance does
    not sag under it, so the commands are those without it); a malformed one names the field."""
    client, _, cal = calibrated
    model = model_from_dict(client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"])
    text, _, _ = _task(model, n=3)
    url = f"/api/v1/calibrations/{cal}/compensate?mode=joints&name=pick.csv"
    plain = client.post(url, content=text, headers=auth(tokens["job"]))
    loaded = client.post(url + "&payload=10,0,0,100", content=text, headers=auth(tokens["job"]))
    assert plain.status_code == loaded.status_code == 200, loaded.text
    assert loaded.text == plain.text
    bad = client.post(url + "&payload=ten", content=text, headers=auth(tokens["job"]))
    assert bad.status_code == 422
    assert bad.json()["detail"]["field"] == "query.payload" and "KG or KG,X,Y,Z" in bad.json()["detail"]["message"]
