"""Whole sessions against the real service process and a simulated cell (issue: sessions)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from runner_contract import wait_measured
from sqlmodel import Session

from calibration.kinematics import fk
from calibration.model import model_from_dict
from service.settings import Settings
from service.store import make_engine

from .conftest import emscon_sigma_m

BOTH_DATABASES = pytest.mark.parametrize("db_url", ["sqlite", "postgres"], indirect=True)


def _start(api, cell, **body):
    return api.call("POST", f"/cells/{cell['id']}/sessions", body)


@BOTH_DATABASES
def test_pose_session_calibrates_the_cell_to_the_noise_floor(stack, models, register):
    cell, _ = register()
    api = stack.api()
    s = _start(api, cell, kind="pose", count=40)
    s = api.wait_session(s["id"], 120)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert s["measured"] == s["planned"] == 40 and s["calibration_id"] is not None
    assert s["device_state"]["robot"]["state"] == "ready" and s["device_state"]["tracker"]["state"] == "ready"
    meas = api.call("GET", f"/sessions/{s['id']}/measurements")
    assert len(meas) == 40 and sorted(m["seq"] for m in meas) == list(range(40))
    # measured through the Leica tracker's emScon driver (the simulated cell's default)
    assert np.allclose([m["sigma"] for m in meas], emscon_sigma_m(meas), rtol=1e-3)
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    model = model_from_dict(cal["model"])
    truth = models["truth_model"]
    rng = np.random.default_rng(3)
    q = rng.uniform(-np.pi, np.pi, (300, 6))
    p_true = fk(truth, q)[:, :3, :3] @ truth.targets["smr"] + fk(truth, q)[:, :3, 3]
    p_model = fk(model, q)[:, :3, :3] @ model.targets["smr"] + fk(model, q)[:, :3, 3]
    err = np.linalg.norm(p_true - p_model, axis=1)
    # 40 poses, tracker noise about 0.008 mm per axis: the model is good to a few hundredths of a mm
    assert np.sqrt(np.mean(err**2)) < 0.05e-3, np.sqrt(np.mean(err**2))
    assert cal["report"]["success"] and cal["report"]["residuals"]["rms"] < 0.06


def test_verify_then_recalibrate_uses_the_previous_calibration_as_prior(stack, models, register):
    cell, _ = register()
    api = stack.api()
    first = api.wait_session(_start(api, cell, kind="pose", count=30)["id"], 120)
    assert first["state"] == "completed"
    v = api.wait_session(_start(api, cell, kind="verify", count=10)["id"], 60)
    assert v["state"] == "completed" and v["plan_info"]["verify"]["rms"] < 0.08
    short = api.wait_session(_start(api, cell, kind="pose", count=6)["id"], 60)
    assert short["state"] == "completed", short
    cal = api.call("GET", f"/calibrations/{short['calibration_id']}")
    assert cal["report"]["prior"]["calibration_id"] == first["calibration_id"]
    # six poses alone could not identify 25 parameters; with the prior the residual stays small
    assert cal["report"]["residuals"]["rms"] < 0.08


def test_beam_breaks_are_retried_and_the_session_completes(stack, models, register):
    cell, _ = register(fake_args=["--fault", "beam_break_at=3,7"])
    api = stack.api()
    # 14: a first calibration needs 13 poses (spare equations to check the fit, issue 14)
    s = api.wait_session(_start(api, cell, kind="pose", count=14)["id"], 60)
    assert s["state"] == "completed", (s["state"], s.get("reason"))
    assert s["measured"] == 14


def test_persistent_beam_break_pauses_with_the_reason_and_resume_finishes(stack, models, register):
    # three breaks in a row exceed the retry policy (2 retries): the session pauses, says why
    cell, _ = register(fake_args=["--fault", "beam_break_at=4,5,6"])
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=14)["id"], 60)
    assert s["state"] == "paused", s
    assert "beam" in s["reason"].lower() and s["measured"] == 3
    assert s["device_state"]["tracker"]["state"] == "fault" and "beam" in s["device_state"]["tracker"]["detail"]
    assert s["device_state"]["robot"] == {"state": "ready", "detail": "the session is paused: the tracker failed"}
    s = api.call("POST", f"/sessions/{s['id']}/resume")
    s = api.wait_session(s["id"], 60)
    assert s["state"] == "completed" and s["measured"] == 14


def test_protective_stop_pauses_the_session_at_once(stack, models, register):
    cell, _ = register(fake_args=["--fault", "protective_stop_at_move=3"])
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=10)["id"], 60)
    assert s["state"] == "paused", s
    assert "stop" in s["reason"].lower()
    assert s["measured"] == 2
    assert s["device_state"]["robot"]["state"] == "protective stop", s["device_state"]
    # the tracker says its own state, not the robot's error as its detail (issue 22)
    tracker = s["device_state"]["tracker"]
    assert tracker["state"] == "ready" and tracker["detail"] == "the session is paused: the robot failed", tracker
    assert s["device_state"]["robot"]["detail"] not in tracker["detail"]


def _dashboard(host: str, command: str) -> str:
    """One command to the simulated UR controller's dashboard (what a technician does at the
    teach pendant: unlock a protective stop, power the arm on, ...)."""
    import socket

    with socket.create_connection((host, 29999), timeout=5) as sock:
        reader = sock.makefile("rb")
        reader.readline()  # greeting
        sock.sendall(command.encode() + b"\n")
        return reader.readline().decode().strip()


@pytest.mark.parametrize(
    "stop, release",
    [
        ("protective", ["unlock protective stop"]),
        ("emergency", ["sim emergency stop release", "power on", "brake release"]),
    ],
)
def test_a_safety_stop_is_still_named_on_resume_until_it_is_released(stack, models, register, stop, release):
    # Recal never releases a safety stop. Resumed before the technician has, the session pauses
    # again saying which stop holds the robot and what releases it (not "cannot open the cell's
    # devices"), and the robot's state still says so; once released, resume finishes the session.
    cell, fake = register(fake_args=["--fault", f"{stop}_stop_at_move=3"])
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=14)["id"], 60)
    assert s["state"] == "paused" and s["measured"] == 2, s
    first_reason = s["reason"]
    assert f"{stop} stop" in first_reason, first_reason
    for _ in range(2):  # twice: a stop still named after a second resume too
        api.call("POST", f"/sessions/{s['id']}/resume")
        s = api.wait_session(s["id"], 60, until=("paused", "completed", "failed", "aborted"))
        assert s["state"] == "paused", s
        assert f"{stop} stop" in s["reason"] and "cannot open" not in s["reason"], s["reason"]
        assert ("unlock" if stop == "protective" else "power") in s["reason"], s["reason"]
        assert s["device_state"]["robot"]["state"] == f"{stop} stop", s["device_state"]
        assert s["measured"] == 2
    for command in release:
        _dashboard(fake.ready["rtde"], command)
    api.call("POST", f"/sessions/{s['id']}/resume")
    s = api.wait_session(s["id"], 60)
    assert s["state"] == "completed" and s["measured"] == 14, s


def test_server_sent_events_report_progress_to_the_end(stack, models, register):
    import json
    import urllib.request

    cell, _ = register(time_scale=0.05)
    api = stack.api()
    s = _start(api, cell, kind="verify", count=8)
    # as the page opens it: a single-use ticket in the URL, never the token (issue 12)
    ticket = stack.api("viewer").call("POST", f"/sessions/{s['id']}/events/ticket")["ticket"]
    url = f"{stack.service.ready['url']}/api/v1/sessions/{s['id']}/events?ticket={ticket}"
    events = []
    with urllib.request.urlopen(url, timeout=60) as resp:
        for raw in resp:
            line = raw.decode().strip()
            if line.startswith("data:"):
                events.append(json.loads(line[5:]))
    assert events[-1]["state"] == "completed"
    measured = [e["measured"] for e in events]
    assert measured == sorted(measured) and measured[-1] == 8
    # the devices' state travels with each committed pose: the robot on its way to the next one
    moving = [e["device_state"]["robot"] for e in events if e["state"] == "running" and 0 < e["measured"] < 8]
    assert moving and all(r["state"] == "moving" and r["detail"].endswith("of 8") for r in moving)


# --------------------------------------------------------------------------- the robot, observed


def _modbus_reader(fake):
    """The simulated robot's joints as its controller's Modbus server reports them (read-only,
    beside the RTDE connection the session drives it through)."""
    from drivers.modbus_robot import ModbusRobot, ModbusRobotConfig

    host, _, port = fake.ready["modbus"].rpartition(":")
    return ModbusRobot(ModbusRobotConfig(host=host, port=int(port)))


CAP, ACCEL = 0.4, 2.0  # rad/s, rad/s²: below the defaults


@pytest.mark.parametrize("stack_env", [{"RECAL_MAX_JOINT_SPEED": str(CAP), "RECAL_MAX_JOINT_ACCEL": str(ACCEL)}])
def test_moves_run_at_the_capped_speed_and_abort_stops_the_robot_short_of_its_target(stack, register):
    import threading

    from service.models import RunSession

    scale = 0.25  # wall seconds per robot second
    cell, fake = register(time_scale=scale)
    api = stack.api()
    robot = _modbus_reader(fake)
    samples: list[tuple[float, np.ndarray, float]] = []  # (read's midpoint, joints, read's duration)
    watching = threading.Event()
    watching.set()

    def watch():
        while watching.is_set():
            t0 = time.monotonic()
            q = robot.read_joints()
            t1 = time.monotonic()
            samples.append(((t0 + t1) / 2, q, t1 - t0))
            time.sleep(0.005)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    s = _start(api, cell, kind="verify", count=12)
    wait_measured(api, s["id"], 2)
    engine = make_engine(Settings(home=stack.home).effective_database_url)
    with Session(engine) as db:
        plan = np.array(db.get(RunSession, s["id"]).plan)
    engine.dispose()
    # Abort while it moves and is still far (0.2 rad) from every configuration of the plan: it
    # brakes within v²/2a = 0.04 rad, so reaching a target after that would be a missed abort.
    # (Aborting at any moment once failed by chance: a move caught in its last 0.02 rad.)
    deadline = time.monotonic() + 60
    while np.abs(samples[-1][1] - samples[-3][1]).max() < 2e-3 or np.abs(plan - samples[-1][1]).max(axis=1).min() < 0.2:
        assert time.monotonic() < deadline, "the robot never moved far from its targets"
        time.sleep(0.01)
    a = api.call("POST", f"/sessions/{s['id']}/abort")
    time.sleep(0.5)
    watching.clear()
    watcher.join()
    assert a["state"] == "aborted" and a["measured"] < 12, a
    assert a["device_state"]["robot"] == {"state": "ready", "detail": "stopped on abort"}
    # it stands still where it stopped, short of every configuration of the plan
    still = robot.read_joints()
    time.sleep(0.5)
    assert np.abs(robot.read_joints() - still).max() <= 1e-3
    robot.close()
    assert np.abs(plan - still).max(axis=1).min() > 0.02, "the robot reached a target after the abort"
    # The speed of every joint, over windows of 1 s of wall time (4 s of the robot's), from the
    # reads that took under 20 ms: a sample's time is its read's midpoint, so a slow read on a
    # loaded machine (the server answering late in it) would misplace it by up to half its
    # duration; 10 % still tells the cap from the default (0.5 rad/s, +25 %).
    quick = [x for x in samples if x[2] < 0.02]
    t = np.array([x[0] for x in quick])
    q = np.array([x[1] for x in quick])
    ends = np.searchsorted(t, t + 1.0)
    ok = ends < len(t)
    assert ok.sum() > 50, f"too few quick reads ({len(quick)} of {len(samples)})"
    speeds = np.abs(q[ends[ok]] - q[ok]).max(axis=1) / (t[ends[ok]] - t[ok]) * scale
    assert 0.75 * CAP < speeds.max() <= 1.10 * CAP, speeds.max()


def test_cmm_pose_session_calibrates_from_full_poses(stack, models, register):
    import json

    from calibration.geometry import pose_from_points
    from calibration.transforms import matrix_to_rotvec

    # The truth's tooling balls sit about 0.5 mm off their drawing. The CMM measures the frame
    # their drawn layout fits best on the real balls (book eq. 6.12-6.15): the true tool frame
    # times a constant X, which the calibration takes as the tool frame.
    truth = models["truth_model"]
    drawn = model_from_dict(json.loads(models["nominal"].read_text())).targets
    balls = sorted(k for k in drawn if k.startswith("ball"))
    X, misfit = pose_from_points(np.array([drawn[k] for k in balls]), np.array([truth.targets[k] for k in balls]))
    assert misfit > 0.2e-3  # off the drawing by far more than the CMM's noise
    cell, _ = register()
    api = stack.api()
    # the CMM probes where the cell's model puts the balls, which a nominal model does not know
    # well enough (where the robot stands): a tracker calibration first, as on a real cell; it
    # cannot see the tool orientation, and its reflector's offset stands in for the tool's
    first = api.wait_session(_start(api, cell, kind="pose", count=20)["id"], 120)
    assert first["state"] == "completed", first["reason"]
    s = api.wait_session(_start(api, cell, kind="pose", count=15, device="cmm")["id"], 120)
    assert s["state"] == "completed", (s["reason"], s["device_state"])
    assert s["device_state"]["cmm"]["state"] == "ready"
    meas = api.call("GET", f"/sessions/{s['id']}/measurements")
    assert len(meas) == 15 and all(m["qw"] is not None for m in meas)
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    report = cal["report"]
    assert report["prior"]["calibration_id"] == first["calibration_id"]
    # the fit reaches the CMM's noise (not held off by the tracker calibration's prior)
    assert report["residuals"]["chi2"] / report["residuals"]["dof"] < 2.0, report["residuals"]
    assert report["residuals"]["rms"] < 0.01, report["residuals"]  # mm
    # the tool orientation and offset the tracker could not see are the CMM data's
    source = {p["name"]: p["source"] for p in report["parameters"]}
    assert {"tool.tx", "tool.ty", "tool.tz", "tool.rx", "tool.ry"} <= set(report["prior"]["released"])
    assert all(source[f"tool.{f}"] == "data" for f in ("tx", "ty", "tz", "rx", "ry"))
    model = model_from_dict(cal["model"])
    q = np.random.default_rng(5).uniform(-np.pi, np.pi, (200, 6))
    T_true, T_model = fk(truth, q) @ X, fk(model, q)
    err = np.linalg.norm(T_true[:, :3, 3] - T_model[:, :3, 3], axis=1)
    angle = np.linalg.norm(matrix_to_rotvec(T_model[:, :3, :3] @ np.swapaxes(T_true[:, :3, :3], 1, 2)), axis=1)
    # 15 full poses from the CMM (2 µm a probed point): the tool frame to a few hundredths of a mm
    assert np.sqrt(np.mean(err**2)) < 0.05e-3, np.sqrt(np.mean(err**2))
    assert np.degrees(angle.max()) < 0.01, np.degrees(angle.max())
    # and the reflector is still where the tracker measured it: its offset moved with the tool
    smr = lambda m: fk(m, q)[:, :3, :3] @ m.targets["smr"] + fk(m, q)[:, :3, 3]  # noqa: E731
    assert np.sqrt(np.mean(np.sum((smr(truth) - smr(model)) ** 2, axis=1))) < 0.05e-3


def test_configurations_outside_the_limits_or_the_region_are_refused_before_anything_moves(stack, models, register):
    import json

    cell, fake = register()
    api = stack.api()
    dry = api.wait_session(_start(api, cell, kind="verify", count=6, dry_run=True)["id"], 30)
    assert dry["state"] == "completed"
    lo, hi = np.array(dry["plan_info"]["joint_ranges_deg"]).T
    robot = _modbus_reader(fake)
    before = robot.read_joints()
    # the cell's allowed region narrowed after the plan was checked: joint 1 only up to its midrange
    region = [[-180, 180]] * 6
    region[0] = [-180, float((lo[0] + hi[0]) / 2)]
    api.call("PATCH", f"/cells/{cell['id']}", {"allowed_region": region})
    s = api.wait_session(api.call("POST", f"/sessions/{dry['id']}/run")["id"], 30)
    assert s["state"] == "failed" and s["measured"] == 0, s
    assert s["reason"].startswith("unsafe plan: configuration") and "joint 1" in s["reason"]
    # the model's own joint limits narrowed (a replaced nominal model): refused the same way
    api.call("PATCH", f"/cells/{cell['id']}", {"allowed_region": None})
    model = json.loads(models["nominal"].read_text())
    model["joints"][2]["lower"], model["joints"][2]["upper"] = float(lo[2] + hi[2]) / 2, 180.0
    api.call("PATCH", f"/cells/{cell['id']}", {"model": model})
    s = api.wait_session(api.call("POST", f"/sessions/{dry['id']}/run")["id"], 30)
    assert s["state"] == "failed" and s["measured"] == 0 and "joint 3" in s["reason"], s
    assert np.abs(robot.read_joints() - before).max() <= 1e-3  # nothing moved
    robot.close()


def test_verify_with_repeats_visits_each_configuration_from_the_same_side(stack, models, register):
    cell, _ = register()
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="verify", count=3, repeats=4)["id"], 60)
    assert s["state"] == "completed" and s["measured"] == s["planned"] == 12, s
    meas = api.call("GET", f"/sessions/{s['id']}/measurements")
    q = np.array([m["q"] for m in meas]).reshape(3, 4, 6)
    assert np.abs(q - q[:, :1]).max() < 1e-4  # each configuration four times over
    iso = s["plan_info"]["verify"]["iso9283"]
    assert iso["poses"] == 3 and [p["visits"] for p in iso["per_pose"]] == [4, 4, 4]
    assert iso["repeatability"]["max"] < 0.1  # the simulated robot repeats exactly: the tracker's noise


def test_cmm_pose_session_after_a_tracker_calibration_on_the_demo_cell(stack, tmp_path):
    # The demo's cell (recal demo: a UR10e standing where the tracker happens to be, its
    # reflector and tooling balls mounted about 0.8 mm off their drawings), no fault injected:
    # a CMM session after the tracker calibration finds every ball and completes.
    import argparse
    import json

    from service.commands.demo import truth_and_nominal
    from service.processes import start_fake_cell

    from .conftest import next_host

    nominal, truth, _ = truth_and_nominal(argparse.Namespace(seed=1, robot="ur10e"))
    from service.files import save_model

    save_model(tmp_path / "nominal.json", nominal)
    save_model(tmp_path / "truth.json", truth)
    host = next_host()
    fake = start_fake_cell(tmp_path / "truth.json", host, seed=1, log_path=stack.home / "cell-demo.log")
    stack.cells.append(fake)
    api = stack.api()
    cell = api.call(
        "POST",
        "/cells",
        {
            "name": "demo-ur10e",
            "model": json.loads((tmp_path / "nominal.json").read_text()),
            "devices": fake.ready,
            "drift_threshold": 0.1,
        },
    )
    first = api.wait_session(_start(api, cell, kind="pose", count=40)["id"], 180)
    assert first["state"] == "completed", first["reason"]
    s = api.wait_session(_start(api, cell, kind="pose", count=15, device="cmm")["id"], 180)
    assert s["state"] == "completed", (s["reason"], s["device_state"])
    assert s["measured"] == 15
    cal = api.call("GET", f"/calibrations/{s['calibration_id']}")
    res = cal["report"]["residuals"]
    assert res["rms"] < 0.01 and res["chi2"] / res["dof"] < 2.0, res  # mm: the CMM's noise


@pytest.mark.parametrize("fault", ["drop_connection_at=3", "garble_at=3", "garble_at=8", "error_status_at=5"])
def test_a_passing_fault_while_the_devices_open_is_retried_not_paused(stack, models, register, fault):
    """Issue 22: a dropped connection or a garbled packet while the emScon tracker is being set
    up paused the session before its first pose ("cannot open the cell's devices"), and it took a
    resume to do what a second try does. Opening is retried as a measurement is. A garbled reply
    to Initialize (request 3 of a tracker that is not initialised) held the session ``running``
    for Initialize's two-minute deadline: the driver now knows a wrong size within a second."""
    cell, _ = register(fake_args=["--fault", fault])
    api = stack.api()
    s = api.wait_session(_start(api, cell, kind="pose", count=14)["id"], 90)
    assert s["state"] == "completed" and s["measured"] == 14, s
