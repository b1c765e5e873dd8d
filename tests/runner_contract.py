"""The contract every session runner keeps (service.runners.SessionRunner), written once and run
against both: the embedded runner (tests/system/test_embedded_runner.py) and the fleet's
(tests/fleet/test_fleet_runner.py), each through the real service processes and simulated cells.

A subclass provides the ``deployment`` fixture, an object with:

- ``api(i=0)``: an ``Api`` client of API process ``i`` (the fleet has two; the embedded service
  one, whatever ``i``);
- ``add_cell(time_scale)``: a simulated cell registered with the service (its JSON);
- ``crash(session_id)``: kill -9 whatever runs the session (the embedded service process; the
  fleet's worker that holds it);
- ``after_crash()``: what an operator does next (restart the service; the fleet: nothing, its
  reaper and the other worker carry on);
- ``stored(session_id)``: the session's measurements as stored, ``{(seq, target): (id, x, y, z)}``.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time

import numpy as np

from service.client import ApiError

ENDED = ("completed", "failed", "aborted", "paused", "interrupted")


def start(api, cell: dict, **body) -> dict:
    return api.call("POST", f"/cells/{cell['id']}/sessions", body)


def wait_measured(api, sid: int, n: int, timeout_s: float = 60.0) -> dict:
    """Until the session has measured ``n`` configurations; it must still be running then."""
    s = api.wait_session(sid, timeout_s, measured=n, until=ENDED)
    assert s["measured"] >= n and s["state"] in ("planned", "running"), f"session {sid} did not progress: {s}"
    return s


def wait_state(api, sid: int, states: tuple[str, ...], timeout_s: float = 30.0) -> dict:
    s = api.wait_session(sid, timeout_s, until=states, poll_s=0.05)
    assert s["state"] in states, f"session {sid} is {s['state']}, expected one of {states}: {s}"
    return s


def _modbus_reader(endpoint: str):
    """The simulated robot's joints as its controller's Modbus server reports them (read-only,
    beside the connection the session drives it through)."""
    from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

    host, _, port = endpoint.rpartition(":")
    return ModbusRobot(ModbusRobotConfig(host=host, port=int(port)))


def _wait_until_it_stands_after_a_move(robot, timeout_s: float = 60.0) -> None:
    """Until the robot, once seen moving, stands still (two reads 50 ms apart agree to the
    registers' 1 mrad)."""
    deadline = time.monotonic() + timeout_s
    q, moved = robot.read_joints(), False
    while True:
        assert time.monotonic() < deadline, "the robot did not move and stop again"
        time.sleep(0.05)
        q2 = robot.read_joints()
        if np.abs(q2 - q).max() > 2e-3:
            moved = True
        elif moved:
            return
        q = q2


@contextlib.contextmanager
def _while_the_tracker_measures(host: str, port: int, busy_s: float = 0.2, timeout_s: float = 60.0):
    """Enters once the simulated emScon tracker is busy measuring, as seen from a second
    connection: it answers one command at a time, so a status request goes unanswered while a
    measurement (1 s here) holds the instrument, and is answered in a few ms otherwise (after a
    move, the only long command is StartMeasurement). On leaving, it waits for that late answer
    (the measurement's end) before it closes the connection."""
    from drivers.leica_emscon import C_GET_TRACKER_STATUS, pack_command

    deadline = time.monotonic() + timeout_s
    with socket.create_connection((host, port), timeout=5.0) as sock:
        while True:
            assert time.monotonic() < deadline, "the tracker did not start a measurement"
            sock.sendall(pack_command(C_GET_TRACKER_STATUS))
            answered, _, _ = select.select([sock], [], [], busy_s)
            if not answered:
                break
            sock.recv(4096)
            time.sleep(0.02)  # the polling interval
        yield
        late, _, _ = select.select([sock], [], [], 10.0)
        assert late, "the tracker's measurement did not end"
        sock.recv(4096)


def seqs(api, sid: int) -> list[int]:
    return sorted(m["seq"] for m in api.call("GET", f"/sessions/{sid}/measurements"))


class RunnerContract:
    def test_pause_then_resume_measures_every_configuration_once(self, deployment):
        cell = deployment.add_cell(time_scale=0.05)
        s = start(deployment.api(0), cell, kind="verify", count=12)
        wait_measured(deployment.api(1), s["id"], 2)
        deployment.api(1).call("POST", f"/sessions/{s['id']}/pause")
        p = wait_state(deployment.api(0), s["id"], ("paused",))
        assert p["reason"] == "paused on request" and p["measured"] < 12
        # nothing moves while paused: a second look, after the pose that was under way, agrees
        again = deployment.api(0).wait_session(s["id"], 0.5, until=("running",))
        assert again["measured"] == p["measured"] and again["state"] in ("paused", "timeout")
        deployment.api(0).call("POST", f"/sessions/{s['id']}/resume")
        done = deployment.api(1).wait_session(s["id"], 120)
        assert done["state"] == "completed" and done["measured"] == 12, done
        assert seqs(deployment.api(), s["id"]) == list(range(12))

    def test_abort_stops_within_one_pose(self, deployment):
        cell = deployment.add_cell(time_scale=0.05)
        s = start(deployment.api(0), cell, kind="pose", count=40)
        wait_measured(deployment.api(1), s["id"], 3)
        at_abort = deployment.api(1).call("GET", f"/sessions/{s['id']}")["measured"]
        deployment.api(1).call("POST", f"/sessions/{s['id']}/abort")
        a = wait_state(deployment.api(0), s["id"], ("aborted",))
        # the pose under way at the abort may finish; no other is measured
        assert a["measured"] <= at_abort + 1, f"{a['measured'] - at_abort} poses measured after the abort"
        assert seqs(deployment.api(), s["id"]) == list(range(a["measured"]))

    def test_an_abort_during_a_measurement_is_answered_before_that_measurement_is_stored(self, deployment):
        """The abort is answered, aborted and with the robot stopped, while the tracker is still
        measuring (1 s here; up to a second on a real tracker), not once the session's thread
        gets to it (before, the answer waited for the measurement); the session then stays
        aborted, keeps the pose under way and measures no other. The abort is sent once the
        robot, seen moving, stands still at a configuration and the tracker is seen measuring
        there (:func:`_while_the_tracker_measures`), not after a guessed delay."""
        cell = deployment.add_cell(time_scale=0.2)
        api = deployment.api(0)
        devices = cell["devices"]
        host, _, port = devices["emscon"].rpartition(":")
        # 5 s of stationary averaging in the simulated cell's time: 1 s of wall time per measurement
        slow = {"host": host, "port": int(port), "measure_time_s": 5.0}
        api.call("PATCH", f"/cells/{cell['id']}", {"devices": {**devices, "emscon": slow}})
        robot = _modbus_reader(devices["modbus"])
        try:
            s = start(api, cell, kind="verify", count=6)
            wait_measured(api, s["id"], 1)
            _wait_until_it_stands_after_a_move(robot)
            with _while_the_tracker_measures(host, int(port)):
                a = deployment.api(1).call("POST", f"/sessions/{s['id']}/abort")
            assert a["state"] == "aborted" and a["reason"] == "aborted on request", a
            assert a["device_state"]["robot"] == {"state": "ready", "detail": "stopped on abort"}
            # the pose under way, its measurement begun, is stored after the answer
            deployment.api(0).wait_session(s["id"], 5.0, measured=a["measured"] + 1, until=())
            after = deployment.api(0).call("GET", f"/sessions/{s['id']}")
            assert after["state"] == "aborted" and after["measured"] == a["measured"] + 1, (a, after)
            assert after["device_state"]["robot"] == {"state": "ready", "detail": "stopped on abort"}
            again = deployment.api(0).wait_session(s["id"], 1.0, measured=after["measured"] + 1, until=())
            assert again["measured"] == after["measured"], "a pose was measured after the abort"
            assert seqs(api, s["id"]) == list(range(after["measured"]))
        finally:
            robot.close()

    def test_a_crash_mid_session_interrupts_it_and_resume_loses_and_duplicates_nothing(self, deployment):
        cell = deployment.add_cell(time_scale=0.05)
        s = start(deployment.api(0), cell, kind="pose", count=25)
        wait_measured(deployment.api(0), s["id"], 5)
        deployment.crash(s["id"])  # kill -9: no chance to clean up
        before = deployment.stored(s["id"])
        assert len(before) >= 5
        deployment.after_crash()
        i = wait_state(deployment.api(1), s["id"], ("interrupted",), timeout_s=60)
        assert "resume" in i["reason"] and i["measured"] == len(before)
        # nothing moves until someone resumes it
        again = deployment.api(1).wait_session(s["id"], 1.0, until=("running", "planned"))
        assert again["measured"] == len(before) and again["state"] in ("interrupted", "timeout")
        deployment.api(1).call("POST", f"/sessions/{s['id']}/resume")
        done = deployment.api(1).wait_session(s["id"], 120)
        assert done["state"] == "completed", done
        assert seqs(deployment.api(), s["id"]) == list(range(25)), "every configuration measured exactly once"
        after = deployment.stored(s["id"])
        for key, value in before.items():
            assert after[key] == value, "a measurement taken before the crash changed"

    def test_two_simultaneous_starts_on_one_cell_exactly_one_runs(self, deployment):
        cell = deployment.add_cell(time_scale=0.02)
        for _ in range(3):
            barrier = threading.Barrier(2)
            results: list = [None, None]

            def go(i, barrier=barrier, results=results):
                barrier.wait()
                try:
                    results[i] = start(deployment.api(i), cell, kind="verify", count=6)
                except ApiError as exc:
                    results[i] = exc

            threads = [threading.Thread(target=go, args=(i,)) for i in (0, 1)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            ok = [r for r in results if isinstance(r, dict)]
            refused = [r for r in results if isinstance(r, ApiError)]
            assert len(ok) == 1 and len(refused) == 1, results
            assert refused[0].status == 409
            assert deployment.api().wait_session(ok[0]["id"], 60)["state"] == "completed"
