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
``--sag cobot|arm165`` gives the true robot joint compliance under gravity
(``calibration.simulate.SAGGING_ARMS``; with ``--offline``, half the poses carry the rated payload
and the rigid and compliant identifications are shown side by side).
``--models-only`` writes the nominal model and the simulated robot's truth (``nominal.json``,
``truth.json`` in ``--dir``) and stops: what ``docker/compose.yaml`` starts its cell with.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from calibration import robots
from calibration.simulate import perturbed, random_configurations, simulate_measurements

BALLS = {"ball1": [0.06, 0.0, 0.04], "ball2": [-0.03, 0.052, 0.04], "ball3": [-0.03, -0.052, 0.04]}

# The simulated cell's clock: every move and measurement takes this fraction of the time it takes
# on the real robot at the service's speed caps. 0.15 gives about one pose a second, slow enough
# to watch a session's progress on the web page (and pause or resume it); 0 is as fast as the
# machine goes (the tests).
DEMO_TIME_SCALE = 0.15
SHOWN = 8  # undetermined parameters listed; the rest are counted ("and N more")


def add_parser(s) -> None:
    s.add_argument("--robot", default="ur10e", help="library robot to simulate (default ur10e)")
    s.add_argument("--poses", type=int, default=40, help="configurations of the pose session (default 40)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument(
        "--dir",
        default=None,
        help="the demo's RECAL_HOME: its database, logs, tokens and files (default $RECAL_HOME if set, "
        "else demo-output)",
    )
    s.add_argument(
        "--time-scale",
        type=float,
        default=DEMO_TIME_SCALE,
        help=f"the simulated cell's speed: a fraction of real time (default {DEMO_TIME_SCALE:g}, about one "
        f"pose a second; 0: as fast as possible)",
    )
    s.add_argument("--host", default="127.0.0.2", help="loopback address of the simulated cell")
    s.add_argument("--port", type=int, default=8000, help="port of the service")
    s.add_argument("--exit", action="store_true", help="stop the service and the cell when done")
    s.add_argument(
        "--log-format",
        choices=["json", "text"],
        help="the service's log (service.log in --dir): JSON lines (default) or text (default: $RECAL_LOG_FORMAT, else json)",
    )
    s.add_argument("--offline", action="store_true", help="no service: files and `recal identify` only")
    s.add_argument(
        "--sag",
        choices=["cobot", "arm165"],
        help="the true robot sags under gravity (joint compliance of a cobot or a 165 kg-payload arm); "
        "offline, half the poses carry the rated payload and rigid and compliant are compared",
    )
    s.add_argument(
        "--models-only",
        action="store_true",
        help="write nominal.json and truth.json (the simulated robot) into --dir, then stop",
    )


def truth_and_nominal(args):
    """The demo's nominal model (``args.robot`` with a reflector and three tooling balls), the
    simulated robot's truth (every link a little off, placed where a tracker happens to see it)
    and the random generator that drew it (``args.seed``)."""
    rng = np.random.default_rng(args.seed)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), **{k: np.array(v) for k, v in BALLS.items()}}
    nominal = dataclasses.replace(robots.nominal(args.robot), targets=targets)
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.8, -0.6, 0.3, 0.002, -0.004, np.deg2rad(130.0)]),  # where the tracker happens to stand
        targets={name: p + rng.normal(0, 0.8e-3, 3) for name, p in targets.items()},  # as really mounted
    )
    if getattr(args, "sag", None):
        from calibration.simulate import sagging

        truth = sagging(truth, args.sag, frames_of=nominal)
    return nominal, truth, rng


def _cell_model(args, nominal):
    """The model a cell is registered with: with ``--sag``, the nominal one with a compliance
    section (every term 0), so that the service identifies the compliant model and its result
    page shows it against the rigid one."""
    if not args.sag:
        return nominal
    from calibration.compliance import default_section, with_section

    return with_section(nominal, default_section(nominal))


def run(args) -> int:
    from service.cli import Fail

    if args.dir is None:  # the live demo's service uses it as its RECAL_HOME, so `recal token create` finds it
        live = not (args.offline or args.models_only)
        args.dir = (os.environ.get("RECAL_HOME") if live else None) or "demo-output"
    if not (args.time_scale >= 0 and args.time_scale <= 100):
        raise Fail(f"--time-scale: expected a number from 0 to 100, got {args.time_scale}")
    if args.models_only:
        return _models_only(args)
    return _offline(args) if args.offline else _live(args)


def _models_only(args) -> int:
    from service.files import save_model

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal, truth, _ = truth_and_nominal(args)
    save_model(out / "nominal.json", _cell_model(args, nominal))
    save_model(out / "truth.json", truth)
    print(
        f"recal demo: {out / 'nominal.json'} (register the cell with it) and {out / 'truth.json'} "
        f"(the simulated {args.robot}, for recal fake-cell --truth)"
    )
    return 0


def _live(args) -> int:
    from service.client import Api
    from service.files import save_model
    from service.processes import start_fake_cell, start_service

    out = Path(args.dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    nominal, truth, _ = truth_and_nominal(args)
    save_model(out / "nominal.json", _cell_model(args, nominal))
    save_model(out / "truth.json", truth)
    admin, tech = _fresh_store(out)

    # `kill` (SIGTERM) stops the demo as Ctrl-C does: its service and simulated cell with it.
    def terminate(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, terminate)
    _say(
        f"RECAL_HOME={out}   (the demo's database, logs and tokens; `RECAL_HOME={out} recal token create "
        f"--role technician` makes another token for this service)"
    )
    _say(f"technician token: {tech}   (admin: {admin}; both in {out / 'tokens.txt'})")
    cell = service = None
    try:
        cell = start_fake_cell(
            out / "truth.json", args.host, seed=args.seed, time_scale=args.time_scale, log_path=out / "fake-cell.log"
        )
        _say(f"simulated cell ready on {args.host}: {', '.join(k for k in cell.ready if k != 'ready')}")
        service_env = {
            "RECAL_SETTLE_S": "0",
            **({"RECAL_LOG_FORMAT": args.log_format} if getattr(args, "log_format", None) else {}),
        }
        service = start_service(out, args.port, env=service_env, log_path=out / "service.log")
        url = service.ready["url"]
        _say(f"service ready at {url} (SQLite: {out / 'recal.db'})")
        api = Api(url, tech)
        c = api.call(
            "POST",
            "/cells",
            {
                "name": f"demo-{args.robot}",
                "model": json.loads((out / "nominal.json").read_text()),
                "devices": cell.ready,
                "drift_threshold": 0.1,
            },
        )
        before, cal, after = _calibrate_and_verify(api, c["id"], args, out)
        _summary(out, url, before, cal, after)
        if args.exit:
            return 0
        _say("the service and the simulated cell keep running; Ctrl-C stops them")
        while service.popen.poll() is None:
            time.sleep(0.5)
        return 0
    except KeyboardInterrupt:
        return 0
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        for p in (service, cell):
            if p is not None:
                p.stop()
        signal.signal(signal.SIGTERM, previous)


def _say(msg: str) -> None:
    print(msg, flush=True)


def _fresh_store(out: Path) -> tuple[str, str]:
    """A new demo database in ``out`` with an admin and a technician token (also written to
    tokens.txt): ``(admin, technician)``."""
    from sqlmodel import Session

    from service.settings import Settings
    from service.store import create_token, make_engine, migrate

    for f in out.glob("recal.db*"):
        f.unlink()
    engine = make_engine(Settings(home=out).effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        admin = create_token(db, role="admin", name="demo-admin")[1]
        tech = create_token(db, role="technician", name="demo-technician")[1]
    engine.dispose()
    (out / "tokens.txt").write_text(f"admin {admin}\ntechnician {tech}\n")
    return admin, tech


def _calibrate_and_verify(api, cid: int, args, out: Path) -> tuple[dict, dict, dict]:
    """The demo's three sessions (verify the nominal, calibrate, verify the calibration), their
    files written to ``out``: ``(verify before, calibration, verify after)``."""
    tty = sys.stdout.isatty()

    def show(s):
        if tty or s["state"] not in ("planned", "running"):
            end = "" if tty and s["state"] in ("planned", "running") else "\n"
            sys.stdout.write(
                f"\r  {s['kind']} session {s['id']}: {s['state']}, {s['measured']}/{s['planned']} measured   {end}"
            )
            sys.stdout.flush()

    def session(kind, count, **kw):
        s = api.call("POST", f"/cells/{cid}/sessions", {"kind": kind, "count": count, **kw})
        s = api.wait_session(s["id"], 600, on_progress=show)
        if s["state"] != "completed":
            raise RuntimeError(f"{kind} session {s['id']} ended {s['state']}: {s.get('reason')}")
        return s

    _say("verifying the nominal model (tracker, 20 fresh configurations)...")
    before = session("verify", 20)["plan_info"]["verify"]
    _say(f"calibrating (pose session, {args.poses} planned configurations)...")
    t0 = time.monotonic()
    pose = session("pose", args.poses)
    cal = api.call("GET", f"/calibrations/{pose['calibration_id']}")
    _say(
        f"  identified {len(cal['report']['parameters'])} parameters; residual RMS {cal['rms']:.4f} mm "
        f"(the session, {pose['measured']} poses moved to and measured, then the identification, took "
        f"{time.monotonic() - t0:.1f} s)"
    )
    comp = cal["report"].get("compliance")
    if comp:  # --sag: the cell's model is compliant; the service compared it with the rigid one
        _say(
            f"  rigid against compliant ({comp['folds']}-fold cross-validation on the session's data): RMS "
            f"{comp['cv_rms_rigid']:.4f} mm against {comp['cv_rms_compliant']:.4f} mm (see the result page)"
        )
    _say("verifying the calibrated model (20 fresh configurations)...")
    after_session = session("verify", 20)
    (out / "identified.json").write_text(json.dumps(cal["model"], indent=2) + "\n")
    (out / "report.json").write_text(json.dumps(cal["report"], indent=2) + "\n")
    # the sessions' measurements as the CLI reads them (contracts §3, the units of nominal.json):
    # `recal identify` and `recal accuracy` can be tried on what the service measured
    csvs = {"measurements.csv": pose["id"], "verify-after.csv": after_session["id"]}
    for name, sid in csvs.items():
        (out / name).write_text(api.call("GET", f"/sessions/{sid}/measurements.csv"))
    return before, cal, after_session["plan_info"]["verify"]


def _summary(out: Path, url: str, before: dict, cal: dict, after: dict) -> None:
    """Before and after, what the data cannot determine, and where to look."""
    _say("")
    reg = before.get("registered")
    if reg:  # the robot's own inaccuracy first; where the tracker stands is not the robot's error
        _say(
            f"accuracy before: RMS {reg['rms']:.3f} mm, max {reg['max']:.3f} mm (the nominal model, with the "
            f"robot placed where it fits the tracker best; {before['rms']:.0f} mm RMS before the tracker's "
            f"placement is known)"
        )
    else:
        _say(f"accuracy before: RMS {before['rms']:.3f} mm, max {before['max']:.3f} mm (the nominal model)")
    _say(
        f"accuracy after:  RMS {after['rms']:.4f} mm, max {after['max']:.4f} mm (the calibrated model, "
        f"on {after['n']} fresh configurations)"
    )
    _say("parameters the data cannot determine (and why):")
    undetermined = cal["report"]["unidentifiable"]
    for u in undetermined[:SHOWN]:
        _say(f"  - {u['name']}: {u['reason']}")
    if len(undetermined) > SHOWN:
        _say(f"  ... and {len(undetermined) - SHOWN} more ({out / 'report.json'} lists all {len(undetermined)})")
    _say("")
    _say(f"where to look: {url}/            (web page; log in with the technician token in {out / 'tokens.txt'})")
    _say(f"               {url}/docs        (the REST API, OpenAPI at {url}/openapi.json)")
    _say(f"               {out / 'identified.json'}, {out / 'report.json'}")
    _say(
        f"               {out / 'measurements.csv'} (the pose session's), {out / 'verify-after.csv'} "
        f"(the last verification's): try the CLI on them, e.g."
    )
    _say(f"                 recal accuracy --model {out / 'identified.json'} --data {out / 'verify-after.csv'}")
    _say(
        f"                 recal identify --model {out / 'nominal.json'} --data {out / 'measurements.csv'} "
        f"--out {out / 'cli-identified.json'}"
    )


def _write_measurements(path: Path, model, data) -> None:
    from service.files import format_csv, write_atomic

    u = model.units
    qs = np.array(
        [[v / (u.angle_rad if j.revolute else u.length_m) for v, j in zip(row, model.joints)] for row in data.q]
    )
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z", "target", "pose_id"]
    rows = [
        list(qr) + list(p / u.length_m) + [t or "", pid]
        for qr, p, t, pid in zip(qs, data.p_world, data.target, data.pose_id)
    ]
    if data.payload is not None:  # the payload each pose was measured with (kg, centre of gravity in mm)
        header += ["payload_kg", "payload_x", "payload_y", "payload_z"]
        rows = [r + [pl[0], *(pl[1:] / u.length_m)] for r, pl in zip(rows, data.payload)]
    write_atomic(path, "# simulated laser-tracker measurements (recal demo)\n" + format_csv(header, rows))


def _offline(args) -> int:
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    _simulate_files(args, out)
    print(f"recal demo: simulated {args.robot} measured at {args.poses} configurations; files in {out}/")
    status = _identify(out, "identified.json", "report.json")
    # a sagging arm: the rigid model cannot explain the data and `recal identify` says so with
    # exit 3 (model and report written); the compliant identification below is the answer
    if status != 0 and not (args.sag and status == 3):
        return status
    report = json.loads((out / "report.json").read_text())
    v = report["validation"]
    print(
        f"accuracy on 200 fresh configurations: RMS {v['rms']:.4f} mm, max {v['max']:.4f} mm "
        f"(nominal model after registration: RMS {v['before']['rms']:.3f} mm, max {v['before']['max']:.3f} mm)"
    )
    print(f"identified model: {out / 'identified.json'}   full report: {out / 'report.json'}")
    if args.sag:
        status = _identify(out, "identified-compliant.json", "report-compliant.json", "--compliance", "auto")
        if status != 0:
            return status
        c = json.loads((out / "report-compliant.json").read_text())
        print(
            f"rigid against compliant on 200 fresh configurations: RMS {v['rms']:.4f} mm against "
            f"{c['validation']['rms']:.4f} mm; inside the predicted 95 % bound {100 * v['inside_predicted_95']:.1f} % "
            f"against {100 * c['validation']['inside_predicted_95']:.1f} % (noise floor {np.sqrt(3) * 0.02:.4f} mm)"
        )
    return 0


def _simulate_files(args, out: Path) -> None:
    """The nominal model, the simulated measurements and 200 hold-out ones written in ``out``."""
    from service.files import save_model

    nominal, truth, rng = truth_and_nominal(args)
    save_model(out / "nominal.json", nominal)
    payload = None
    if args.sag:  # every other pose with the rated payload: two payloads separate the arm's weight from it
        from calibration.simulate import SAGGING_ARMS

        rated = np.array(SAGGING_ARMS[args.sag]["payload"])
        payload = lambda n: np.array([rated if i % 2 else np.zeros(4) for i in range(n)])  # noqa: E731
    from fakes.world import Noise

    sigma_m = Noise().tracker_m  # the simulated cell's line-protocol tracker: what its fake adds
    data = simulate_measurements(
        truth,
        random_configurations(nominal, args.poses, rng),
        rng,
        sigma_m=sigma_m,
        targets=("smr",),
        payload=payload(args.poses) if payload else None,
    )
    holdout = simulate_measurements(
        truth,
        random_configurations(nominal, 200, rng),
        rng,
        sigma_m=sigma_m,
        targets=("smr",),
        payload=payload(200) if payload else None,
    )
    _write_measurements(out / "measurements.csv", nominal, data)
    _write_measurements(out / "holdout.csv", nominal, holdout)


def _identify(out: Path, model_name: str, report_name: str, *extra: str) -> int:
    """``recal identify`` on the demo's files in ``out``, validated on the hold-out; its status."""
    from service.cli import main as recal

    return recal(
        [
            "identify",
            "--model",
            str(out / "nominal.json"),
            "--data",
            str(out / "measurements.csv"),
            "--validate",
            str(out / "holdout.csv"),
            "--out",
            str(out / model_name),
            "--report",
            str(out / report_name),
            *extra,
        ]
    )
