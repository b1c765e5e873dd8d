"""``recal demo [--robot ur10e] [--poses 60] [--seed 1] [--dir demo-output]``: a whole calibration, end to end, on a simulated robot.

Until the service and its sessions exist, the demo runs the same files and commands a
technician would: it makes a "true" robot (the nominal one with small random errors in every
link, an unknown instrument placement and reflector offset), measures it at random
configurations with a simulated laser tracker (0.02 mm noise), writes the nominal model and the
measurement files, runs ``recal identify`` on them with a hold-out set, and prints the report.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from calibration import robots
from calibration.simulate import perturbed, random_configurations, simulate_measurements


def _write_measurements(path: Path, model, data) -> None:
    from service.files import format_csv, write_atomic

    u = model.units
    qs = np.array([[v / (u.angle_rad if j.revolute else u.length_m) for v, j in zip(row, model.joints)] for row in data.q])
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z", "target", "pose_id"]
    rows = [list(qr) + list(p / u.length_m) + [t or "", pid]
            for qr, p, t, pid in zip(qs, data.p_world, data.target, data.pose_id)]
    write_atomic(path, "# simulated laser-tracker measurements (recal demo)\n" + format_csv(header, rows))


def add_parser(s) -> None:
    s.add_argument("--robot", default="ur10e", help="library robot to simulate (default ur10e)")
    s.add_argument("--poses", type=int, default=60, help="configurations to measure (default 60)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--dir", default="demo-output", help="folder for the files the demo writes")


def run(args) -> int:
    from service.cli import main as recal

    rng = np.random.default_rng(args.seed)
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal = dataclasses.replace(robots.nominal(args.robot), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth, base=np.array([1.8, -0.6, 0.3, 0.002, -0.004, np.deg2rad(130.0)]),  # where the tracker stands
        targets={"smr": np.array([0.0008, -0.0012, 0.0512])},  # the reflector as really mounted
    )
    from service.files import save_model

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
    print("parameters the data cannot determine:")
    for u in report["unidentifiable"]:
        print(f"  - {u['name']}: {u['reason']}")
    print(f"identified model: {out / 'identified.json'}   full report: {out / 'report.json'}")
    return 0
