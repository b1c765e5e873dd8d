"""Benchmark of the service (issue "Measurement sessions, run store, REST API", targets:
orchestrator overhead per pose under 20 ms with the cell at time scale 0;
``GET /api/v1/sessions/{id}`` p99 under 50 ms with 50 concurrent clients).

Set-up: one simulated UR10e cell (``recal fake-cell``, time scale 0) and ``recal serve`` on its
embedded default (SQLite), as processes, with ``RECAL_SETTLE_S=0``.

1. **EmbeddedRunner overhead per pose.** A pose session of ``--poses`` configurations through the
   API. Its time per pose is the interval between consecutive measurements' commit times in
   the store (planning before and identification after are not per pose). Side by side, in
   the same run and on the same cell, the baseline: the same configurations through the same
   drivers in a plain loop (``move_joints``, ``read_joints``, ``measure``), with nothing else.
   The difference is what the session loop adds per pose: the limit check, the retry wrapper,
   the commit of each measurement before the next move, the lease renewal.
2. **GET latency under load.** ``--clients`` clients (threads spread over
   ``--client-processes`` processes, each client on its own keep-alive connection) each send
   ``--requests`` requests of ``GET /api/v1/sessions/{id}`` (the completed session above);
   latencies are measured at the client. Two loads:
   - *polling*: each client sends one request every ``--interval`` seconds (default 0.1 s, with
     a random phase), as pages and jobs poll a session (the nightly job polls every 0.2 s or
     slower, the page follows server-sent events): 50 clients offer 500 requests a second;
   - *saturated*: each client sends its next request as soon as the answer arrives (a closed
     loop, like ``wrk -c 50``): the server's throughput; every request then waits behind the
     other 49, so its latency is about 50 / throughput by construction.
   Baseline in the same run, same clients: ``GET /api/v1/health`` (no token, no database), what
   the server and the clients cost by themselves on this machine.

Run: ``python bench/service.py`` (about half a minute).
"""

from __future__ import annotations

import argparse
import dataclasses
import http.client
import json
import multiprocessing
import os
import platform
import random
import statistics
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration import robots
from calibration.simulate import perturbed
from service.client import Api
from service.files import save_model
from service.processes import free_port, start_fake_cell, start_service
from service.settings import Settings
from service.store import create_token, make_engine, migrate


def _ts(v) -> float:
    return (datetime.fromisoformat(v) if isinstance(v, str) else v).timestamp()


def session_per_pose(api: Api, cell_id: int, poses: int) -> tuple[int, list[float], np.ndarray]:
    """Run a pose session; (its id, the intervals between consecutive commits (s), readings)."""
    s = api.call(
        "POST", f"/cells/{cell_id}/sessions", {"kind": "pose", "count": poses, "device": "tracker", "target": "smr"}
    )
    s = api.wait_session(s["id"], 300, poll_s=0.5)
    if s["state"] != "completed":
        raise RuntimeError(f"the pose session ended {s['state']}: {s.get('reason')}")
    rows = api.call("GET", f"/sessions/{s['id']}/measurements")
    t = np.array([_ts(r["created_at"]) for r in rows])
    return s["id"], list(np.diff(t)), np.array([r["q"] for r in rows])


def drivers_per_pose(endpoint: dict, configs: np.ndarray) -> list[float]:
    """The baseline: the same moves and measurements through the same drivers, in a loop."""
    from drivers.tracker import LineTracker, TrackerConfig
    from drivers.ur_rtde import UrRtdeConfig, UrRtdeRobot

    settings = Settings()
    robot = UrRtdeRobot(UrRtdeConfig(host=endpoint["rtde"]))
    tracker = LineTracker(TrackerConfig(url=endpoint["tracker"]))
    out = []
    try:
        t_prev = time.time()
        for q in configs:
            robot.move_joints(
                q, speed_rad_s=settings.max_joint_speed_rad_s, accel_rad_s2=settings.max_joint_accel_rad_s2
            )
            robot.read_joints()
            tracker.measure()
            now = time.time()
            out.append(now - t_prev)
            t_prev = now
    finally:
        tracker.close()
        robot.close()
    return out[1:]  # as the session's: intervals between consecutive poses


def _client(args) -> list[float]:
    """One client process: ``threads`` keep-alive clients, each ``requests`` GETs in turn."""
    host, port, path, token, threads, requests, start_at, interval_s = args
    paths = path if isinstance(path, (list, tuple)) else [path]
    lat: list[float] = []
    lock = threading.Lock()
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    def run(phase_s: float, first: int):
        conn = http.client.HTTPConnection(host, port, timeout=30)
        mine = []
        t_next = time.perf_counter() + phase_s
        for k in range(requests):
            path = paths[(first + k) % len(paths)]  # a page's polls: its routes in turn
            if interval_s:  # polling: one request per interval, whenever the last answer came
                time.sleep(max(0.0, t_next - time.perf_counter()))
                t_next += interval_s
            t0 = time.perf_counter()
            conn.request("GET", path, headers=headers)
            r = conn.getresponse()
            r.read()
            mine.append((paths.index(path), time.perf_counter() - t0) if len(paths) > 1 else time.perf_counter() - t0)
            if r.status != 200:
                raise RuntimeError(f"GET {path}: {r.status}")
        conn.close()
        with lock:
            lat.extend(mine)

    while time.time() < start_at:  # every client starts together
        time.sleep(0.001)
    rng = random.Random(os.getpid())
    ts = [
        threading.Thread(target=run, args=(rng.uniform(0, interval_s), rng.randrange(len(paths))))
        for _ in range(threads)
    ]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return lat


def load(
    url: str, path: str, token: str | None, clients: int, procs: int, requests: int, interval_s: float = 0.0
) -> dict:
    host, port = url.split("//")[1].split(":")
    per = [clients // procs + (i < clients % procs) for i in range(procs)]
    start_at = time.time() + 1.0
    t0 = time.perf_counter()
    with multiprocessing.Pool(procs) as pool:
        parts = pool.map(_client, [(host, int(port), path, token, n, requests, start_at, interval_s) for n in per])
    wall = time.perf_counter() - t0 - 1.0
    lat = np.sort(np.concatenate([np.array(p) for p in parts])) * 1e3
    return {
        "n": lat.size,
        "p50": float(np.percentile(lat, 50)),
        "p95": float(np.percentile(lat, 95)),
        "p99": float(np.percentile(lat, 99)),
        "max": float(lat[-1]),
        "rps": lat.size / wall,
    }


def page_load(
    url: str, paths: list[str], token: str, clients: int, procs: int, requests: int, interval_s: float
) -> dict:
    """``clients`` pages polling ``paths`` in turn; latency (ms) over all, and per path."""
    host, port = url.split("//")[1].split(":")
    per = [clients // procs + (i < clients % procs) for i in range(procs)]
    start_at = time.time() + 1.0
    t0 = time.perf_counter()
    with multiprocessing.Pool(procs) as pool:
        parts = pool.map(_client, [(host, int(port), paths, token, n, requests, start_at, interval_s) for n in per])
    wall = time.perf_counter() - t0 - 1.0
    rows = np.array([x for p in parts for x in p])
    out = {}
    for name, sel in [("all", np.ones(len(rows), bool))] + [(p, rows[:, 0] == k) for k, p in enumerate(paths)]:
        lat = np.sort(rows[sel, 1]) * 1e3
        out[name] = {
            "n": lat.size,
            "p50": float(np.percentile(lat, 50)),
            "p95": float(np.percentile(lat, 95)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat[-1]),
            "rps": lat.size / wall,
        }
    return out


def over_50ms(url: str) -> dict[str, tuple[int, int]]:
    """Per route, from the service's own request histogram (/metrics): (requests, of which
    took more than 50 ms inside the service)."""
    import urllib.request

    from prometheus_client.parser import text_string_to_metric_families

    with urllib.request.urlopen(url + "/metrics", timeout=30) as r:
        text = r.read().decode()
    out: dict[str, list[int]] = {}
    for family in text_string_to_metric_families(text):
        if family.name != "recal_request_duration_seconds":
            continue
        for sample in family.samples:
            route = sample.labels.get("route")
            if sample.name.endswith("_count"):
                out.setdefault(route, [0, 0])[0] += int(sample.value)
            elif sample.name.endswith("_bucket") and sample.labels["le"] == "0.05":
                out.setdefault(route, [0, 0])[1] += int(sample.value)
    return {k: (n, n - fast) for k, (n, fast) in out.items()}


def page_routes(api: Api, cell_id: int, session_id: int) -> list[str]:
    """What the page polls while a technician watches (service/web/js/views): the overview, the
    cell's summary, the session, its measurements and live residuals, its calibration's result."""
    cal = api.call("GET", f"/sessions/{session_id}")["calibration_id"]
    return [
        "/api/v1/overview?limit=50&offset=0",
        f"/api/v1/cells/{cell_id}/summary",
        f"/api/v1/sessions/{session_id}",
        f"/api/v1/sessions/{session_id}/measurements",
        f"/api/v1/sessions/{session_id}/live",
        f"/api/v1/calibrations/{cal}/result",
    ]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=60)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--client-processes", type=int, default=5)
    ap.add_argument("--requests", type=int, default=100, help="requests per client")
    ap.add_argument("--interval", type=float, default=0.1, help="polling: seconds between a client's requests")
    ap.add_argument("--host", default="127.0.4.2", help="loopback address of the simulated cell")
    ap.add_argument(
        "--page-only",
        action="store_true",
        help="only the page's routes against the baseline (skip the per-pose and single-route loads)",
    )
    ap.add_argument("--page-requests", type=int, default=60, help="requests per page client")
    return ap.parse_args(argv)


@dataclasses.dataclass
class Figures:
    """What a run measured: per pose (s) in the session and in the drivers' plain loop; the
    single-route loads by (load, route); the page's routes, the service's own count of requests
    over 50 ms, and the baseline of the page's clients."""

    session_dt: list[float]
    driver_dt: list[float]
    loads: dict[tuple[str, str], dict]
    page: dict[str, dict]
    server_side: dict[str, tuple[int, int]]
    page_base: dict


def prepare_home(home: Path) -> str:
    """The models (a nominal UR10e and its perturbed truth) and a migrated store in ``home``; a
    technician's token."""
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    save_model(home / "truth.json", perturbed(nominal, np.random.default_rng(1), tool_length_m=0.0))
    save_model(home / "nominal.json", nominal)
    engine = make_engine(Settings(home=home).effective_database_url)
    migrate(engine)
    from sqlmodel import Session

    with Session(engine) as db:
        token = create_token(db, role="technician", name="bench")[1]
    engine.dispose()
    return token


def measure(args, home: Path, url: str, token: str, cell) -> Figures:
    """Against the running service at ``url`` and the simulated ``cell``: the pose session and its
    baseline, the single-route loads, then the page's routes and their baseline."""
    api = Api(url, token)
    doc = json.loads((home / "nominal.json").read_text())
    cell_id = api.call("POST", "/cells", {"name": "bench", "model": doc, "devices": cell.ready})["id"]
    session_id, session_dt, configs = session_per_pose(api, cell_id, args.poses)
    driver_dt = [] if args.page_only else drivers_per_pose(cell.ready, configs)
    path = f"/api/v1/sessions/{session_id}"
    loads = {}
    for mode, interval in () if args.page_only else (("polling", args.interval), ("saturated", 0.0)):
        for name, p, tok in ((path, path, token), ("/api/v1/health", "/api/v1/health", None)):
            loads[mode, name] = load(url, p, tok, args.clients, args.client_processes, args.requests, interval)
    # 3. The page's own routes, polled by 50 pages, and the baseline in the same run.
    routes = page_routes(api, cell_id, session_id)
    page = page_load(url, routes, token, args.clients, args.client_processes, args.page_requests, args.interval)
    server_side = over_50ms(url)
    page_base = load(
        url, "/api/v1/health", None, args.clients, args.client_processes, args.page_requests, args.interval
    )
    return Figures(session_dt, driver_dt, loads, page, server_side, page_base)


def print_page(args, fig: Figures) -> None:
    print(
        f"\n## The page's routes: {args.clients} pages each polling one every {args.interval:g} s, "
        f"in turn ({args.page_requests} requests each; latency in ms)\n"
    )
    print("| request | requests | p50 | p95 | p99 | max |")
    print("|---|---|---|---|---|---|")
    for name, r in fig.page.items():
        what = "all the page's routes" if name == "all" else "GET " + name.split("?")[0]
        print(f"| {what} | {r['n']} | {r['p50']:.1f} | {r['p95']:.1f} | {r['p99']:.1f} | {r['max']:.1f} |")
    base = fig.page_base
    print(
        f"| GET /api/v1/health (baseline, same clients) | {base['n']} | {base['p50']:.1f} | "
        f"{base['p95']:.1f} | {base['p99']:.1f} | {base['max']:.1f} |"
    )
    print("\nInside the service (its /metrics histogram, every request of the run so far): requests over 50 ms")
    for route, (n, slow) in sorted(fig.server_side.items()):
        if n >= 100:
            print(f"- {route}: {slow} of {n}")


def print_per_pose(args, fig: Figures) -> None:
    print(f"\n## Per pose, {args.poses} poses, time scale 0 (ms)\n")
    print("| | mean | median | p95 |")
    print("|---|---|---|---|")
    for name, dt in (
        ("pose session (orchestrator + drivers + store)", fig.session_dt),
        ("drivers alone (baseline)", fig.driver_dt),
    ):
        d = np.array(dt) * 1e3
        print(f"| {name} | {d.mean():.2f} | {np.median(d):.2f} | {np.percentile(d, 95):.2f} |")
    over = (statistics.fmean(fig.session_dt) - statistics.fmean(fig.driver_dt)) * 1e3
    over_med = (statistics.median(fig.session_dt) - statistics.median(fig.driver_dt)) * 1e3
    print(f"\norchestrator overhead per pose: {over:.2f} ms (mean), {over_med:.2f} ms (median)")


def print_loads(args, fig: Figures) -> None:
    print(f"\n## {args.clients} concurrent clients x {args.requests} requests (latency in ms)\n")
    print("| load | request | requests | p50 | p95 | p99 | max | requests/s |")
    print("|---|---|---|---|---|---|---|---|")
    for (mode, name), r in fig.loads.items():
        what = "GET /api/v1/sessions/{id}" if name != "/api/v1/health" else "GET /api/v1/health (baseline)"
        load_name = f"polling every {args.interval:g} s" if mode == "polling" else "saturated"
        print(
            f"| {load_name} | {what} | {r['n']} | {r['p50']:.1f} | {r['p95']:.1f} | {r['p99']:.1f} | "
            f"{r['max']:.1f} | {r['rps']:.0f} |"
        )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="recal-bench-service-") as tmp:
        home = Path(tmp)
        token = prepare_home(home)
        cell = start_fake_cell(home / "truth.json", args.host, time_scale=0.0, log_path=home / "cell.log")
        try:
            service = start_service(
                home,
                free_port(),
                env={"RECAL_SETTLE_S": "0", "OPENBLAS_NUM_THREADS": "1"},
                log_path=home / "service.log",
            )
            try:
                fig = measure(args, home, service.ready["url"], token, cell)
            finally:
                service.stop()
        finally:
            cell.stop()

    print(
        f"# {platform.processor() or platform.machine()}, {multiprocessing.cpu_count()} cores, "
        f"Python {platform.python_version()}, {platform.system()} {platform.release()}"
    )
    print_page(args, fig)
    if args.page_only:
        return 0
    print_per_pose(args, fig)
    print_loads(args, fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
