"""``recal demo``: the main job — the service on its embedded default (SQLite) with a simulated
cell, and a calibration end to end through the REST API.

1. Make a "true" robot: the nominal one (``--robot``, default UR10e) with small random errors in
   every link, standing somewhere unknown in front of the laser tracker, with a reflector and
   three tooling balls mounted slightly off their drawings.
2. Start ``recal fake-cell`` with that truth (UR controller over RTDE, a Leica tracker on emScon
   (what the sessions measure with), the line-protocol tracker, CMM, encoders)
   and ``recal serve`` on SQLite in ``--dir``.
3. Through the API, as a technician would: register the cell with the nominal model, verify
   it (the nominal model's accuracy), run a pose session (observation-planned poses, each
   measured and committed), which identifies the robot, verify again, and compensate a task.
4. Print the accuracy before and after and where to look; keep the service and the cell
   running until Ctrl-C (``--exit`` stops at once).

``--offline`` skips the service: simulated measurement files and ``recal identify`` on them.
``--models-only`` writes the nominal model and the simulated robot's truth (``nominal.json``,
``truth.json`` in ``--dir``) and stops: what ``docker/compose.yaml`` starts its cell with.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from calibration import robots
from calibration.simulate import perturbed, random_configurations, simulate_measurements

BALLS = {"ball1": [0.06, 0.0, 0.04], "ball2": [-0.03, 0.052, 0.04], "ball3": [-0.03, -0.052, 0.04]}


def add_parser(s) -> None:
    s.add_argument("--robot", default="ur10e", help="library robot to simulate (default ur10e)")
    s.add_argument("--poses", type=int, default=40, help="configurations of the pose session (default 40)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--dir", default="demo-output", help="folder for the database, logs and files")
    s.add_argument("--host", default="127.0.0.2", help="loopback address of the simulated cell")
    s.add_argument("--port", type=int, default=8000, help="port of the service")
    s.add_argument("--exit", action="store_true", help="stop the service and the cell when done")
    s.add_argument("--offline", action="store_true", help="no service: files and `recal identify` only")
    s.add_argument("--models-only", action="store_true",
                   help="write nominal.json and truth.json (the simulated robot) into --dir, then stop")


def _truth_and_nominal(args):
    rng = np.random.default_rng(args.seed)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), **{k: np.array(v) for k, v in BALLS.items()}}
    nominal = dataclasses.replace(robots.nominal(args.robot), targets=targets)
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.8, -0.6, 0.3, 0.002, -0.004, np.deg2rad(130.0)]),  # where the tracker happens to stand
        targets={name: p + rng.normal(0, 0.8e-3, 3) for name, p in targets.items()},  # as really mounted
    )
    return nominal, truth, rng


def run(args) -> int:
    if args.models_only:
        return _models_only(args)
    return _offline(args) if args.offline else _live(args)


def _models_only(args) -> int:
    from service.files import save_model

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal, truth, _ = _truth_and_nominal(args)
    save_model(out / "nominal.json", nominal)
    save_model(out / "truth.json", truth)
    print(f"recal demo: {out / 'nominal.json'} (register the cell with it) and {out / 'truth.json'} "
          f"(the simulated {args.robot}, for recal fake-cell --truth)")
    return 0


def _live(args) -> int:
    from service.client import Api
    from service.files import save_model
    from service.processes import start_fake_cell, start_service
    from service.settings import Settings
    from service.store import create_token, make_engine, migrate
    from sqlmodel import Session

    out = Path(args.dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    nominal, truth, _ = _truth_and_nominal(args)
    save_model(out / "nominal.json", nominal)
    save_model(out / "truth.json", truth)
    db_file = out / "recal.db"
    for f in out.glob("recal.db*"):
        f.unlink()
    settings = Settings(home=out)
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        admin = create_token(db, role="admin", name="demo-admin")[1]
        tech = create_token(db, role="technician", name="demo-technician")[1]
    engine.dispose()
    (out / "tokens.txt").write_text(f"admin {admin}\ntechnician {tech}\n")

    def say(msg):
        print(msg, flush=True)

    cell = service = None
    try:
        cell = start_fake_cell(out / "truth.json", args.host, seed=args.seed, log_path=out / "fake-cell.log")
        say(f"simulated cell ready on {args.host}: {', '.join(k for k in cell.ready if k != 'ready')}")
        service = start_service(out, args.port, env={"RECAL_SETTLE_S": "0"}, log_path=out / "service.log")
        url = service.ready["url"]
        say(f"service ready at {url} (SQLite: {db_file})")
        api = Api(url, tech)
        c = api.call("POST", "/cells", {"name": f"demo-{args.robot}", "model": json.loads((out / "nominal.json").read_text()),
                                        "devices": cell.ready, "drift_threshold": 0.1})
        cid = c["id"]
        tty = sys.stdout.isatty()

        def show(s):
            if tty or s["state"] not in ("planned", "running"):
                end = "" if tty and s["state"] in ("planned", "running") else "\n"
                sys.stdout.write(f"\r  {s['kind']} session {s['id']}: {s['state']}, "
                                 f"{s['measured']}/{s['planned']} measured   {end}")
                sys.stdout.flush()

        def session(kind, count, **kw):
            s = api.call("POST", f"/cells/{cid}/sessions", {"kind": kind, "count": count, **kw})
            s = api.wait_session(s["id"], 600, on_progress=show)
            if s["state"] != "completed":
                raise RuntimeError(f"{kind} session {s['id']} ended {s['state']}: {s.get('reason')}")
            return s

        say("verifying the nominal model (tracker, 20 fresh configurations)...")
        before = session("verify", 20)["plan_info"]["verify"]
        say(f"calibrating (pose session, {args.poses} planned configurations)...")
        t0 = time.monotonic()
        pose = session("pose", args.poses)
        cal = api.call("GET", f"/calibrations/{pose['calibration_id']}")
        say(f"  identified {len(cal['report']['parameters'])} parameters in {time.monotonic() - t0:.1f} s; "
            f"residual RMS {cal['rms']:.4f} mm")
        say("verifying the calibrated model (20 fresh configurations)...")
        after = session("verify", 20)["plan_info"]["verify"]
        (out / "identified.json").write_text(json.dumps(cal["model"], indent=2) + "\n")
        (out / "report.json").write_text(json.dumps(cal["report"], indent=2) + "\n")
        say("")
        reg = before.get("registered", {})
        say(f"accuracy before: RMS {before['rms']:.1f} mm with the nominal model as it stands (the tracker's "
            f"placement is unknown); RMS {reg.get('rms', float('nan')):.3f} mm, max {reg.get('max', float('nan')):.3f} mm "
            f"even with its base placed where it fits best")
        say(f"accuracy after:  RMS {after['rms']:.4f} mm, max {after['max']:.4f} mm")
        say("parameters the data cannot determine (and why):")
        for u in cal["report"]["unidentifiable"][:8]:
            say(f"  - {u['name']}: {u['reason']}")
        say("")
        say(f"where to look: {url}/            (web page; log in with the technician token in {out / 'tokens.txt'})")
        say(f"               {url}/docs        (the REST API, OpenAPI at {url}/openapi.json)")
        say(f"               {out / 'identified.json'}, {out / 'report.json'}")
        if args.exit:
            return 0
        say("the service and the simulated cell keep running; Ctrl-C stops them")
        while service.popen.poll() is None:
            time.sleep(0.5)
        return 0
    except KeyboardInterrupt:
        return 0
    finally:
        for p in (service, cell):
            if p is not None:
                p.stop()


def _write_measurements(path: Path, model, data) -> None:
    from service.files import format_csv, write_atomic

    u = model.units
    qs = np.array([[v / (u.angle_rad if j.revolute else u.length_m) for v, j in zip(row, model.joints)] for row in data.q])
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z", "target", "pose_id"]
    rows = [list(qr) + list(p / u.length_m) + [t or "", pid]
            for qr, p, t, pid in zip(qs, data.p_world, data.target, data.pose_id)]
    write_atomic(path, "# simulated laser-tracker measurements (recal demo)\n" + format_csv(header, rows))


def _offline(args) -> int:
    from service.cli import main as recal
    from service.files import save_model

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal, truth, rng = _truth_and_nominal(args)
    save_model(out / "nominal.json", nominal)
    data = simulate_measurements(truth, random_configurations(nominal, args.poses, rng), rng, sigma_m=20e-6, targets=("smr",))
    holdout = simulate_measurements(truth, random_configurations(nominal, 200, rng), rng, sigma_m=20e-6, targets=("smr",))
    _write_measurements(out / "measurements.csv", nominal, data)
    _write_measurements(out / "holdout.csv", nominal, holdout)
    print(f"recal demo: simulated {args.robot} measured at {args.poses} configurations; files in {out}/")
    status = recal(["identify", "--model", str(out / "nominal.json"), "--data", str(out / "measurements.csv"),
                    "--validate", str(out / "holdout.csv"), "--out", str(out / "identified.json"),
                    "--report", str(out / "report.json")])
    if status != 0:
        return status
    report = json.loads((out / "report.json").read_text())
    v = report["validation"]
    print(f"accuracy on 200 fresh configurations: RMS {v['rms']:.4f} mm, max {v['max']:.4f} mm "
          f"(nominal model after registration: RMS {v['before']['rms']:.3f} mm, max {v['before']['max']:.3f} mm)")
    print(f"identified model: {out / 'identified.json'}   full report: {out / 'report.json'}")
    return 0
