"""Sessions through the Leica emScon tracker (the simulated cell's default): a beam break is
repaired by pointing the tracker at where the model puts the reflector, and counted; what is
stored is every configuration's own fresh measurement."""

from __future__ import annotations

import time

import numpy as np

from calibration.kinematics import target_positions

from .conftest import emscon_sigma_m

POSES = 21
# Every other pose from the third on (10 poses): with two measured points the nominal model is
# placed (a shift and a turn about the vertical); at the first two nothing places it yet.
BROKEN_POSES = list(range(3, POSES + 1, 2))
# One StartMeasurement per pose, and one more at a broken pose (the measurement after the
# search): the break at the j-th broken pose (pose 2j + 1) is StartMeasurement 3j.
BREAKS = [3 * j for j in range(1, len(BROKEN_POSES) + 1)]


def _start(api, cell, **body):
    return api.call("POST", f"/cells/{cell['id']}/sessions", body)


def _run_to_the_end(api, session_id: int, timeout_s: float = 120.0) -> tuple[dict, list[str]]:
    """Wait for the session to end; resume it whenever it pauses. Returns it and the pauses' reasons."""
    deadline = time.monotonic() + timeout_s
    pauses = []
    while True:
        s = api.wait_session(session_id, max(deadline - time.monotonic(), 1.0))
        if s["state"] != "paused" or len(pauses) >= 3:
            return s, pauses
        pauses.append(s["reason"])
        api.call("POST", f"/sessions/{session_id}/resume")


def test_beam_breaks_at_ten_poses_are_recovered_without_a_pause(stack, models, register):
    cell, fake = register(fake_args=["--fault", "beam_break_at=" + ",".join(map(str, BREAKS))])
    assert "emscon" in fake.ready
    api = stack.api()
    s, pauses = _run_to_the_end(api, _start(api, cell, kind="pose", count=POSES)["id"])
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert len(pauses) <= 1, pauses
    assert s["beam_recoveries"] >= 9 and s["beam_recoveries"] + len(pauses) == len(BROKEN_POSES)
    assert s["measured"] == POSES

    # Nothing stale or invented: one row per configuration, each the reflector where the true
    # robot put it at that row's own joint readings (within the tracker's noise).
    rows = api.call("GET", f"/sessions/{s['id']}/measurements")
    assert sorted(r["seq"] for r in rows) == list(range(POSES))
    truth = models["truth_model"]
    q = np.array([r["q"] for r in rows])
    p = np.array([[r["x"], r["y"], r["z"]] for r in rows])
    sigma = np.array([r["sigma"] for r in rows])
    error = np.linalg.norm(p - target_positions(truth, q, "smr"), axis=1)
    assert np.all(error < 5 * np.sqrt(3) * sigma), error / sigma
    assert len({tuple(np.round(v, 9)) for v in p}) == POSES  # no value stored twice
    assert np.allclose(sigma, emscon_sigma_m(rows), rtol=1e-3)  # measured through emScon, not the line tracker


def test_a_reflector_not_where_the_model_puts_it_pauses_with_the_reason(stack, models, register):
    """A break at the first pose: nothing measured yet to place the nominal model (the robot
    stands 1.3 m from where its nominal base says), so the tracker is pointed at the wrong place
    and does not find the reflector: the session pauses at once and says so; resumed, it finishes."""
    cell, _ = register(fake_args=["--fault", "beam_break_at=1"])
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=6)["id"], 60)
    assert s["state"] == "paused", s
    assert "did not find the reflector where the model puts it" in s["reason"]
    assert s["measured"] == 0 and s["beam_recoveries"] == 0
    assert s["device_state"]["tracker"]["state"] == "fault"
    # The reflector is still lost; resumed, the session points at the same wrong place again ...
    s = api.wait_session(api.call("POST", f"/sessions/{s['id']}/resume")["id"], 60)
    assert s["state"] == "paused" and s["measured"] == 0


def test_the_line_protocol_tracker_still_drives_sessions(stack, models, register):
    """A cell whose tracker is on the line protocol (a bridge): breaks are retried as before,
    nothing is pointed, nothing counted."""
    cell, fake = register(fake_args=["--no-emscon", "--fault", "beam_break_at=3,7"])
    assert "emscon" not in fake.ready
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=14)["id"], 60)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert s["beam_recoveries"] == 0
    assert api.call("GET", f"/sessions/{s['id']}/measurements")[0]["sigma"] == 20e-6
