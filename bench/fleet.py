"""Benchmark of the fleet (issue "A fleet of cells", target: 50 cells through two workers,
engine overhead under 10 % of the embedded default's per-session time).

N simulated cells (``recal fake-cell``, time scale 0: moves are instant, so what is measured is
the software) each get the nightly job's work: a verify session, then (every cell is off: they
were never calibrated) a recalibration (pose) session, driven by ``recal nightly --all`` as in
production. Three set-ups on the same cells:

- ``embedded``: the embedded default, one ``recal serve`` process on SQLite, sessions in its
  threads;
- ``embedded-pg``: the same on PostgreSQL (separates the store's share from the engine's);
- ``fleet``: ``RECAL_ENGINE=procrastinate`` on PostgreSQL, two API processes, two workers
  (``recal worker --site a --site b``), the cells in sites ``a`` and ``b``; one
  ``recal nightly --all --site ...`` per site, each against its own API process.

Like with like: at most ``--parallel`` sessions (default 10) run at once in every set-up. The
embedded ones get ``recal nightly --all --parallel 10``; the fleet gets workers of concurrency
``--parallel / --workers`` and one ``nightly --parallel`` of half of it per site, so sessions
are created only when a worker is free (the per-session time, from the store's timestamps, is
then the same thing in every set-up: no time waiting in a queue). 10 at once on 2 cores keeps
the machine loaded (every simulated session wants a core), not swamped. ``--parallel 0
--fleet-concurrency 25`` (with ``--modes fleet``) is the stress run of the first measurement:
every cell at once, 50 sessions in two workers on 2 cores, the queue and the leases under a
load average of tens.

For each: the wall time of the whole run; per session (from the store's timestamps: created
by the API -> final state written) the mean and median time; the count of sessions and
measurements (checked: every configuration exactly once). Then a sequential run (one cell,
``--sequential`` rounds of verify + pose, one session at a time, nothing else running) gives
each set-up's per-session time without contention, broken down (to the first measurement
stored, measuring, after the last). The fleet's minus embedded-pg's is the engine's
per-session overhead (queueing through PostgreSQL, the worker's claim, lease and monitor); the
fleet's minus the embedded default's is what moving to a fleet costs, the store included.
The cells run only the devices the sessions use (UR and tracker). Results and their reading:
docs/benchmarks.md#fleet.

Run: ``python bench/fleet.py`` (about 8 minutes; needs PostgreSQL: ``--postgres URL``, default
``$RECAL_TEST_POSTGRES_URL`` or postgres@127.0.0.1). Cells listen on ``--host-prefix``
(default 127.0.3.) 1..N.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, text
from sqlalchemy.pool import NullPool
from sqlmodel import Session

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from calibration import robots
from calibration.simulate import perturbed
from service.client import Api
from service.files import save_model
from service.processes import free_port, start_fake_cell, start_service, start_worker
from service.store import create_token, make_engine, migrate

ENV = {"RECAL_SETTLE_S": "0", "RECAL_RETRY_BACKOFF_S": "0.05", "OPENBLAS_NUM_THREADS": "1"}


def models(d: Path) -> dict:
    rng = np.random.default_rng(11)
    nominal = dataclasses.replace(robots.nominal("ur5e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    save_model(d / "nominal.json", nominal)
    save_model(d / "truth.json", truth)
    return {"nominal": d / "nominal.json", "truth": d / "truth.json"}


class Database:
    def __init__(self, admin_url: str):
        self.admin_url = admin_url
        self.name = f"recal_bench_{uuid.uuid4().hex[:10]}"
        self._admin(f'CREATE DATABASE "{self.name}"')
        self.url = f"{admin_url.rpartition('/')[0]}/{self.name}"

    def _admin(self, *sql):
        eng = create_engine(self.admin_url, isolation_level="AUTOCOMMIT", poolclass=NullPool)
        with eng.connect() as conn:
            for q in sql:
                conn.execute(text(q))
        eng.dispose()

    def drop(self):
        self._admin(
            f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{self.name}'",
            f'DROP DATABASE IF EXISTS "{self.name}"',
        )


def elapsed_s(a, b) -> float:
    """Seconds from ``a`` to ``b``, two of the store's timestamps (SQLite hands them back as text)."""
    if isinstance(a, str):
        a, b = datetime.fromisoformat(a), datetime.fromisoformat(b)
    return (b - a).total_seconds()


def session_stats(db_url: str, exclude=()) -> dict:
    """Sessions and measurements in the store; times of the sessions that completed in one go."""
    eng = make_engine(db_url)
    with eng.connect() as conn:
        rows = conn.execute(text("SELECT kind, state, created_at, updated_at, id FROM session ORDER BY id")).all()
        meas = conn.execute(
            text(
                "SELECT count(*), (SELECT count(*) FROM (SELECT DISTINCT session_id, seq "
                "FROM measurement) AS d) FROM measurement"
            )
        ).one()
    eng.dispose()

    def secs(r):
        return elapsed_s(r[2], r[3])

    out = {"sessions": len(rows), "states": {}, "measurements": meas[0], "distinct_configurations": meas[1]}
    for r in rows:
        out["states"][r[1]] = out["states"].get(r[1], 0) + 1
    timed = [r for r in rows if r[1] == "completed" and r[4] not in exclude]
    for kind in ("verify", "pose"):
        t = [secs(r) for r in timed if r[0] == kind]
        if t:
            out[kind] = {"n": len(t), "mean_s": statistics.fmean(t), "median_s": statistics.median(t), "max_s": max(t)}
    t = [secs(r) for r in timed]
    out["all"] = {"n": len(t), "mean_s": statistics.fmean(t), "median_s": statistics.median(t)} if t else {}
    return out


def store_tokens(db_url: str) -> dict[str, str]:
    """A fresh store at ``db_url``, migrated; a token of each role the bench uses (technician, job)."""
    engine = make_engine(db_url)
    migrate(engine)
    with Session(engine) as s:
        tokens = {r: create_token(s, role=r, name=r)[1] for r in ("technician", "job")}
    engine.dispose()
    return tokens


def start_processes(mode: str, home: Path, env: dict, args, cells: int, log_dir: Path, procs: list) -> list:
    """The set-up's API processes (two for the fleet, else one) and the fleet's workers, each added to
    ``procs`` as it starts (so that the caller stops it whatever fails next); the API processes."""
    apis = []
    for i in range(2 if mode == "fleet" else 1):
        apis.append(start_service(home, free_port(), env=env, log_path=log_dir / f"{mode}-api{i}.log"))
        procs.append(apis[-1])
    if mode == "fleet":
        for i in range(args.workers):
            procs.append(
                start_worker(
                    home,
                    ["a", "b"],
                    env=env,
                    name=f"w{i + 1}",
                    concurrency=fleet_concurrency(args, cells),
                    log_path=log_dir / f"{mode}-w{i + 1}.log",
                )
            )
    return apis


def add_cells(api: Api, mdl: dict, fakes: list) -> list[dict]:
    """One cell per simulated cell, in sites ``a`` and ``b`` in turn, all with the nominal model."""
    nominal = json.loads(mdl["nominal"].read_text())
    return [
        api.call(
            "POST",
            "/cells",
            {
                "name": f"cell{i:03d}",
                "site": "ab"[i % 2],
                "model": nominal,
                "devices": f.ready,
                "drift_threshold": 0.1,
            },
        )
        for i, f in enumerate(fakes)
    ]


def nightly_commands(mode: str, apis: list, args) -> list[list[str]]:
    """The nightly run of the whole fleet: one ``recal nightly --all`` (the fleet: one per site,
    each against its own API process, half of the sessions at once each)."""
    common = ["--verify-count", str(args.verify_count), "--count", str(args.count), "--timeout", "1800"]
    nightly = [sys.executable, "-m", "service.cli", "nightly", "--all"]
    if mode == "fleet":
        return [
            [
                *nightly,
                "--site",
                site,
                "--url",
                apis[i % len(apis)].ready["url"],
                "--parallel",
                str(-(-args.parallel // 2)),
                *common,
            ]
            for i, site in enumerate(("a", "b"))
        ]
    return [[*nightly, "--url", apis[0].ready["url"], "--parallel", str(args.parallel), *common]]


def run_nightly(mode: str, apis: list, tokens: dict, args, cells: int, log_dir: Path, db_url: str) -> dict:
    """The nightly run, timed; the set-up's result so far (wall time, exit statuses, the nightly's
    summary lines, the store's session times and counts)."""
    nenv = {**os.environ, "RECAL_TOKEN": tokens["job"]}
    t0 = time.monotonic()
    runs = [
        subprocess.Popen(c, env=nenv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for c in nightly_commands(mode, apis, args)
    ]
    outs = [r.communicate()[0] for r in runs]
    wall = time.monotonic() - t0
    (log_dir / f"{mode}-nightly.txt").write_text("\n\n".join(outs))
    result = {
        "mode": mode,
        "cells": cells,
        "wall_s": wall,
        "parallel": args.parallel,
        "worker_concurrency": fleet_concurrency(args, cells) if mode == "fleet" else None,
        "nightly_exit": [r.returncode for r in runs],
        "summary": [next((ln for ln in o.splitlines() if " cells: " in ln), "") for o in outs],
        "concurrent": session_stats(db_url),
    }
    result["concurrent_incomplete"] = sum(v for k, v in result["concurrent"]["states"].items() if k != "completed")
    return result


def last_session_id(db_url: str) -> int:
    eng = make_engine(db_url)
    with eng.connect() as conn:
        last = conn.execute(text("SELECT max(id) FROM session")).scalar()
    eng.dispose()
    return last


def sequential_sessions(api: Api, cell: dict, args) -> set[int]:
    """``--sequential`` rounds of a verify and a pose session on one cell, one at a time; the
    sessions a device fault paused (resumed, and left out of the times)."""
    resumed: set[int] = set()
    for _ in range(args.sequential):
        for kind, n in (("verify", args.verify_count), ("pose", args.count)):
            s = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": kind, "count": n})
            s = api.wait_session(s["id"], 300, poll_s=0.05)
            for _attempt in range(3):
                if s["state"] != "paused":
                    break
                print(f"  session {s['id']} paused ({s['reason']}): resumed, not timed", file=sys.stderr)
                resumed.add(s["id"])
                api.call("POST", f"/sessions/{s['id']}/resume")
                s = api.wait_session(s["id"], 300, poll_s=0.05)
            assert s["state"] == "completed", s
    return resumed


def sequential_breakdown(db_url: str, cell_id: int, after_id: int, resumed: set[int]) -> dict:
    """Where a sequential session's time goes, per kind (the cell's sessions after ``after_id``,
    not ``resumed``): created -> first measurement stored (queue, claim, devices opened, planning,
    first move), first -> last measurement, last measurement -> final state (analysis, results
    stored)."""
    eng = make_engine(db_url)
    with eng.connect() as conn:
        rows = [
            r
            for r in conn.execute(
                text(
                    "SELECT s.kind, s.created_at, s.updated_at, s.id, min(m.created_at), max(m.created_at) "
                    "FROM session s JOIN measurement m ON m.session_id = s.id WHERE s.cell_id = :c "
                    "GROUP BY s.id, s.kind, s.created_at, s.updated_at ORDER BY s.id"
                ),
                {"c": cell_id},
            ).all()
            if r[3] > after_id and r[3] not in resumed
        ]
    eng.dispose()
    out = {}
    for kind in ("verify", "pose"):
        mine = [r for r in rows if r[0] == kind]
        t = [elapsed_s(r[1], r[2]) for r in mine]
        out[kind] = {
            "n": len(t),
            "mean_s": statistics.fmean(t),
            "median_s": statistics.median(t),
            "to_first_measurement_s": statistics.median(elapsed_s(r[1], r[4]) for r in mine),
            "measuring_s": statistics.median(elapsed_s(r[4], r[5]) for r in mine),
            "after_last_measurement_s": statistics.median(elapsed_s(r[5], r[2]) for r in mine),
        }
    return out


def run_setup(mode: str, fakes: list, mdl: dict, args, pg_admin: str, log_dir: Path) -> dict:
    """One set-up on the cells: its store and processes, the nightly run of every cell at once,
    then the sequential sessions on the first cell; its figures."""
    home = Path(tempfile.mkdtemp(prefix=f"recal-bench-{mode}-"))
    db = Database(pg_admin) if mode in ("embedded-pg", "fleet") else None
    env = dict(ENV)
    if db is not None:
        env["RECAL_DATABASE_URL"] = db.url
    if mode == "fleet":
        env["RECAL_ENGINE"] = "procrastinate"
    db_url = db.url if db is not None else f"sqlite:///{home / 'recal.db'}"
    procs: list = []
    try:
        tokens = store_tokens(db_url)
        apis = start_processes(mode, home, env, args, len(fakes), log_dir, procs)
        api = Api(apis[0].ready["url"], tokens["technician"])
        cells = add_cells(api, mdl, fakes)
        result = run_nightly(mode, apis, tokens, args, len(cells), log_dir, db_url)
        nightly_last = last_session_id(db_url)
        # sequential: one cell, one session at a time
        resumed = sequential_sessions(api, cells[0], args)
        stats = session_stats(db_url)
        result["sequential"] = sequential_breakdown(db_url, cells[0]["id"], nightly_last, resumed)
        result["checks"] = {
            "measurements": stats["measurements"],
            "distinct": stats["distinct_configurations"],
            "sequential_resumed": len(resumed),
        }
        return result
    finally:
        for p in reversed(procs):
            p.stop(30)
        if db is not None:
            db.drop()


def fleet_concurrency(args, cells: int) -> int:
    """Sessions each worker runs at once: ``--fleet-concurrency``, else its share of ``--parallel``
    (of every cell when ``--parallel 0``)."""
    if args.fleet_concurrency:
        return args.fleet_concurrency
    return -(-(args.parallel or cells) // args.workers)


def machine() -> dict:
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    info = {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "os": platform.platform()}
    try:
        import procrastinate

        info["procrastinate"] = (
            procrastinate.__version__
            if hasattr(procrastinate, "__version__")
            else __import__("importlib.metadata").metadata.version("procrastinate")
        )
    except ImportError:
        pass
    return info


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", type=int, default=50)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--verify-count", type=int, default=12)
    ap.add_argument("--count", type=int, default=30)
    ap.add_argument("--sequential", type=int, default=10, help="rounds of verify + pose, one session at a time")
    ap.add_argument("--modes", default="embedded,embedded-pg,fleet")
    ap.add_argument("--parallel", type=int, default=10, help="sessions at once in every set-up (0: every cell at once)")
    ap.add_argument(
        "--fleet-concurrency", type=int, default=0, help="each worker's concurrency (default: its share of --parallel)"
    )
    ap.add_argument("--host-prefix", default="127.0.3.")
    ap.add_argument(
        "--postgres",
        default=os.environ.get("RECAL_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"),
    )
    ap.add_argument("--out", help="write the results as JSON here")
    return ap.parse_args(argv)


def start_fakes(args, mdl: dict, log_dir: Path) -> list:
    """The simulated cells, on ``--host-prefix`` 1..N, started 16 at a time."""
    hosts = [f"{args.host_prefix}{i}" for i in range(1, args.cells + 1)]
    with ThreadPoolExecutor(16) as pool:
        # Only the devices the sessions use (the UR and the tracker): fifty idle CMMs and CAN
        # buses (heartbeats every 0.1 s) would take a good share of the two cores from what is
        # measured.
        return list(
            pool.map(
                lambda h: start_fake_cell(
                    mdl["truth"],
                    h,
                    time_scale=0.0,
                    timeout_s=120,
                    extra=["--no-can", "--no-cmm", "--no-modbus"],
                    log_path=log_dir / f"cell-{h}.log",
                ),
                hosts,
            )
        )


def run_setups(fakes: list, mdl: dict, args, log_dir: Path) -> list[dict]:
    """Every set-up of ``--modes`` in turn on the same cells, each summed up on stderr as it ends;
    the simulated cells stopped at the end."""
    setups = []
    try:
        for mode in args.modes.split(","):
            print(f"{mode}: {args.cells} cells ...", file=sys.stderr, flush=True)
            r = run_setup(mode, fakes, mdl, args, args.postgres, log_dir)
            setups.append(r)
            c, s = r["concurrent"], r["sequential"]
            print(
                f"  wall {r['wall_s']:.1f} s; per session (concurrent) verify {c['verify']['mean_s']:.3f} s, pose "
                f"{c['pose']['mean_s']:.3f} s; sequential verify {s['verify']['mean_s']:.3f} s, pose "
                f"{s['pose']['mean_s']:.3f} s; {r['summary']}",
                file=sys.stderr,
                flush=True,
            )
    finally:
        for f in fakes:
            f.stop()
    return setups


def overhead(b: dict, f: dict, e: dict) -> dict:
    """The fleet ``f`` against the set-up ``b``, each difference in % of the embedded default's
    (``e``) time: sequential (per kind and over both), concurrent per session, and wall."""
    out = {}
    for stat in ("mean_s", "median_s"):
        seq_b = statistics.fmean([b["sequential"][k][stat] for k in ("verify", "pose")])
        seq_f = statistics.fmean([f["sequential"][k][stat] for k in ("verify", "pose")])
        seq_e = statistics.fmean([e["sequential"][k][stat] for k in ("verify", "pose")])
        out[f"sequential_{stat[:-2]}_per_session_s"] = seq_f - seq_b
        out[f"sequential_{stat[:-2]}_pct"] = 100 * (seq_f - seq_b) / seq_e
        for k in ("verify", "pose"):
            out[f"sequential_{stat[:-2]}_{k}_pct"] = (
                100 * (f["sequential"][k][stat] - b["sequential"][k][stat]) / e["sequential"][k][stat]
            )
    con_b, con_f = b["concurrent"]["all"]["mean_s"], f["concurrent"]["all"]["mean_s"]
    out.update(
        {
            "concurrent_per_session_s": con_f - con_b,
            "concurrent_pct": 100 * (con_f - con_b) / con_b,
            "wall_pct": 100 * (f["wall_s"] - b["wall_s"]) / b["wall_s"],
        }
    )
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    log_dir = Path(tempfile.mkdtemp(prefix="recal-bench-fleet-"))
    print(f"logs: {log_dir}", file=sys.stderr)
    mdl = models(log_dir)
    fakes = start_fakes(args, mdl, log_dir)
    results = {"machine": machine(), "args": vars(args), "setups": run_setups(fakes, mdl, args, log_dir)}
    by = {r["mode"]: r for r in results["setups"]}
    # The fleet against the embedded default (SQLite), and against the embedded service on the
    # fleet's store (PostgreSQL: the engine's own share), each in % of the embedded default's time.
    for base in ("embedded", "embedded-pg"):
        if base not in by or "fleet" not in by or "embedded" not in by:
            continue
        out = overhead(by[base], by["fleet"], by["embedded"])
        results["overhead" if base == "embedded" else "overhead_vs_embedded_pg"] = out
    print(json.dumps(results, indent=2, default=str))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
