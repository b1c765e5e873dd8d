"""Benchmark: the service's answers while it does the heaviest work it allows (issue 12: with
compensation on the event loop, an abort took 19.3 s and the robot measured 9 more poses).

Set-up: one simulated UR10e cell (``recal fake-cell``, time scale ``--time-scale``: a pose every
few tenths of a second) and ``recal serve`` (SQLite), as processes. A pose session gives the
calibration; a task CSV of ``RECAL_MAX_TASK_BYTES`` (the largest body the compensate route
takes, 4 MiB by default: about 29,000 points) is built from it.

Two runs, the same requests in each, in this order:

- *baseline*: nothing heavy runs;
- *loaded*: the task file is being compensated (``POST /calibrations/{id}/compensate``, in the
  service's worker pool), the requests start once it was sent and end before it is answered.

In each: a verify session moves the robot; once it measured 2 poses the compensation is sent
(loaded run), then ``GET /api/v1/health`` and ``GET /sessions/{id}`` are sent every 50 ms
(latency at the client) for as long as the compensation runs (at least 20 times); after the
10th, ``POST .../abort`` (latency at the client: the route stops the robot at once, then answers
when the session's end is stored, at most 3 s; its ``Server-Timing`` says when, inside the
service, the robot was told to stop and the end was read back), and the poses committed after
the abort was answered are counted. Both runs are repeated ``--repeat`` times, alternately (each
abort lands at its own moment of a pose: in a move, or while the tracker measures).

Run: ``python bench/heavy.py`` (about two minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration import robots
from calibration.kinematics import fk
from calibration.model import model_from_dict
from calibration.simulate import perturbed
from calibration.transforms import matrix_to_quat
from service.client import Api
from service.files import save_model
from service.processes import free_port, start_fake_cell, start_service
from service.settings import Settings
from service.store import create_token, make_engine, migrate


def task_csv(model, max_bytes: int, seed: int = 4) -> str:
    """A task CSV of poses the robot reaches, as many rows as fit in ``max_bytes``."""
    rng = np.random.default_rng(seed)
    n = max_bytes // 150 + 1000
    q = np.column_stack(
        [
            rng.uniform(-150, 150, n),
            rng.uniform(-140, -40, n),
            rng.uniform(40, 140, n),
            rng.uniform(-150, 150, n),
            rng.uniform(40, 140, n),
            rng.uniform(-150, 150, n),
        ]
    )
    T = fk(model, np.radians(q))
    quat = matrix_to_quat(T[:, :3, :3])
    out, size = ["name,x,y,z,qw,qx,qy,qz,q1,q2,q3,q4,q5,q6\n"], 0
    for i in range(n):
        row = (
            f"P{i},"
            + ",".join(f"{v:.6f}" for v in T[i, :3, 3] * 1000)
            + ","
            + ",".join(f"{v:.9f}" for v in quat[i])
            + ","
            + ",".join(f"{v:.4f}" for v in q[i])
            + "\n"
        )
        if size + len(row) + len(out[0]) > max_bytes:
            break
        out.append(row)
        size += len(row)
    return "".join(out)


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def abort(api: Api, session_id: int) -> tuple[dict, dict[str, float]]:
    """POST .../abort; (the session it answers, the route's ``Server-Timing``: ``robot-stop``
    and ``session-end``, ms after the request reached it)."""
    import urllib.request

    req = urllib.request.Request(
        f"{api.url}/api/v1/sessions/{session_id}/abort",
        data=b"{}",
        method="POST",
        headers={"Authorization": f"Bearer {api.token}", "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        timing = {}
        for entry in r.headers.get("Server-Timing", "").split(","):
            name, _, dur = entry.strip().partition(";dur=")
            if dur:
                timing[name] = float(dur)
        return json.loads(r.read()), timing


def probe(api: Api, viewer: Api, cell_id: int, begin, running) -> dict:
    """One run: a verify session moves the robot; once it measured 2 poses, ``begin()`` (the
    heavy work, or nothing); then health and status are polled every 50 ms, the session is
    aborted after 10 polls, and polling goes on while ``running()`` (at least 20 polls)."""
    s = api.call(
        "POST", f"/cells/{cell_id}/sessions", {"kind": "verify", "count": 200, "device": "tracker", "target": "smr"}
    )
    deadline = time.monotonic() + 120
    while viewer.call("GET", f"/sessions/{s['id']}")["measured"] < 2:
        if time.monotonic() > deadline:
            raise RuntimeError("the verify session did not start measuring")
        time.sleep(0.05)
    begin()
    health, status = [], []
    abort_s = after = None
    while len(health) < 20 or running():
        dt, _ = timed(lambda: viewer.call("GET", "/health"))
        health.append(dt)
        dt, _ = timed(lambda: viewer.call("GET", f"/sessions/{s['id']}"))
        status.append(dt)
        if len(health) == 10:
            abort_s, (done, timing) = timed(lambda: abort(api, s["id"]))
            if done["state"] != "aborted":
                raise RuntimeError(f"the abort answered {done['state']!r}, not 'aborted'")
            at_abort = done["measured"]
            after = api.wait_session(s["id"], 30, poll_s=0.05)["measured"] - at_abort
            abort_during = running()
        time.sleep(0.05)
    return {
        "health": np.array(health) * 1e3,
        "status": np.array(status) * 1e3,
        "abort_ms": abort_s * 1e3,
        "stop_ms": timing.get("robot-stop", float("nan")),
        "end_ms": timing.get("session-end", float("nan")),
        "after": after,
        "polls": len(health),
        "abort_during": abort_during,
    }


def prepare_home(home: Path) -> tuple[str, str]:
    """The models (a nominal UR10e and its perturbed truth) and a migrated store in ``home``; a
    technician's token and a viewer's."""
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    save_model(home / "truth.json", perturbed(nominal, np.random.default_rng(1), tool_length_m=0.0))
    save_model(home / "nominal.json", nominal)
    engine = make_engine(Settings(home=home).effective_database_url)
    migrate(engine)
    from sqlmodel import Session

    with Session(engine) as db:
        token = create_token(db, role="technician", name="bench")[1]
        viewer_token = create_token(db, role="viewer", name="bench-viewer")[1]
    engine.dispose()
    return token, viewer_token


@dataclasses.dataclass
class Runs:
    """The task compensated, the probes of the baseline and loaded runs, and how long each
    compensation took to be answered (s)."""

    task: str
    baseline: list[dict]
    loaded: list[dict]
    compensation_s: list[float]


def calibrate(api: Api, home: Path, cell, max_bytes: int) -> tuple[int, int, str]:
    """The cell added and calibrated by a 30-pose session; (the cell's id, the calibration's id, a
    task CSV of ``max_bytes`` from its model)."""
    doc = json.loads((home / "nominal.json").read_text())
    cell_id = api.call("POST", "/cells", {"name": "bench", "model": doc, "devices": cell.ready})["id"]
    s = api.call(
        "POST",
        f"/cells/{cell_id}/sessions",
        {"kind": "pose", "count": 30, "device": "tracker", "target": "smr"},
    )
    s = api.wait_session(s["id"], 300, poll_s=0.5)
    cal = s["calibration_id"]
    model = model_from_dict(api.call("GET", f"/calibrations/{cal}")["model"])
    return cell_id, cal, task_csv(model, max_bytes)


def run_probes(api: Api, viewer: Api, home: Path, cell, args, max_bytes: int) -> Runs:
    """The calibration, then ``--repeat`` baseline and loaded runs, alternately (the loaded run's
    compensation in a thread of its own)."""
    cell_id, cal, task = calibrate(api, home, cell, max_bytes)
    runs = Runs(task, [], [], [])
    for _ in range(args.repeat):
        runs.baseline.append(probe(api, viewer, cell_id, lambda: None, lambda: False))
        done = threading.Event()

        def compensate(done=done):
            t0 = time.perf_counter()
            api.call("POST", f"/calibrations/{cal}/compensate?name=task.csv", raw=task)
            runs.compensation_s.append(time.perf_counter() - t0)
            done.set()

        worker = threading.Thread(target=compensate)
        runs.loaded.append(probe(api, viewer, cell_id, worker.start, lambda done=done: not done.is_set()))
        worker.join()
    return runs


def print_runs(args, runs: Runs) -> None:
    task, loaded = runs.task, runs.loaded
    rows = task.count("\n") - 1
    print(
        f"# {platform.processor() or platform.machine()}, {multiprocessing.cpu_count()} cores, "
        f"Python {platform.python_version()}, {platform.system()} {platform.release()}"
    )
    during = sum(r["abort_during"] for r in loaded)
    print(
        f"\ncompensation: {len(task) / 2**20:.2f} MiB, {rows} points, answered in "
        f"{', '.join(f'{x:.1f}' for x in runs.compensation_s)} s; {during} of {len(loaded)} aborts answered while "
        f"it ran; time scale {args.time_scale}\n"
    )
    print(
        "| run | health p50 | health p99 | health max | status p99 | robot told to stop | end stored | "
        "abort answered | poses after abort | polls |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")

    def each(runs, key, fmt="{:.0f}"):
        return " / ".join(fmt.format(r[key]) for r in runs) + " ms"

    for name, rs in (("baseline (nothing heavy)", runs.baseline), ("during the compensation", loaded)):
        h = np.concatenate([r["health"] for r in rs])
        st = np.concatenate([r["status"] for r in rs])
        print(
            f"| {name} | {np.percentile(h, 50):.1f} ms | {np.percentile(h, 99):.1f} ms | {h.max():.1f} ms | "
            f"{np.percentile(st, 99):.1f} ms | {each(rs, 'stop_ms', '{:.1f}')} | {each(rs, 'end_ms')} | "
            f"{each(rs, 'abort_ms')} | {max(r['after'] for r in rs)} | {sum(r['polls'] for r in rs)} |"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default="127.0.4.3", help="loopback address of the simulated cell")
    ap.add_argument("--time-scale", type=float, default=0.2)
    ap.add_argument("--repeat", type=int, default=3, help="runs of each kind (baseline, loaded), alternately")
    args = ap.parse_args(argv)
    max_bytes = Settings().max_task_bytes
    with tempfile.TemporaryDirectory(prefix="recal-bench-heavy-") as tmp:
        home = Path(tmp)
        token, viewer_token = prepare_home(home)
        cell = start_fake_cell(home / "truth.json", args.host, time_scale=args.time_scale, log_path=home / "cell.log")
        try:
            service = start_service(
                home,
                free_port(),
                env={"RECAL_SETTLE_S": "0", "OPENBLAS_NUM_THREADS": "1"},
                log_path=home / "service.log",
            )
            try:
                api, viewer = Api(service.ready["url"], token, timeout_s=120), Api(service.ready["url"], viewer_token)
                runs = run_probes(api, viewer, home, cell, args, max_bytes)
            finally:
                service.stop()
        finally:
            cell.stop()
    print_runs(args, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
