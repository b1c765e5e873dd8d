"""Benchmark of a measurement import and of a stored compensation's size (issue 22: a 31,487-row
import grew the service to 16.5 GB; one 4 MiB compensation stored about 84 MB).

1. **Import.** ``recal serve`` as a process on a fresh embedded store (SQLite), one per size. A
   measurement CSV (contracts §3, simulated tracker rows of a UR10e, a reflector 50 mm out) is
   posted to ``POST /api/v1/cells/{id}/measurements?kind=pose``; the time is measured at the
   client (upload, parse, store, identification, residual-map cross-validation, calibration
   stored, answer), the memory is the service process's peak resident set (``VmHWM``) minus its
   resident set when idle (after start-up and a first request). Baseline in the same run:
   ``--baseline`` rows (10,000), to show the cost is linear in rows. Targets: 100,000 rows in
   <= 10 s and <= 300 MB above idle.
2. **Compensation storage.** On the last service, the largest task CSV allowed
   (``max_task_bytes``, 4 MiB) is compensated with the imported calibration through
   ``POST /api/v1/calibrations/{id}/compensate``; the bytes the store holds for it (its
   ``output`` and ``report`` columns as stored) against the input's bytes. Target: <= about 2x.

Run: ``python bench/import_scale.py`` (about a minute).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sqlite3
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.model import model_from_dict
from calibration.robots import nominal_document
from calibration.simulate import perturbed, random_configurations, simulate_measurements
from service import records
from service.processes import free_port, start_service
from service.settings import Settings
from service.store import create_token, make_engine, migrate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from heavy import task_csv


def cell_document() -> dict:
    doc = nominal_document("ur10e")
    doc["targets"] = {"smr": [0, 0, 50]}
    return doc


def measurement_csv(n: int, seed: int = 0) -> bytes:
    """``n`` simulated tracker rows of a UR10e near its nominal model, as another program exports them."""
    nominal = model_from_dict(cell_document())
    rng = np.random.default_rng(seed)
    truth = dataclasses.replace(
        perturbed(nominal, np.random.default_rng(1), tool_length_m=0.0), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0])
    )
    data = simulate_measurements(truth, random_configurations(nominal, n, rng), rng, targets=("smr",))
    rows = records.measurement_rows(0, dataclasses.replace(data, sigma=np.full(n, 20e-6)))
    return records.measurements_csv(nominal, rows).encode()


def memory_kb(pid: int) -> dict[str, int]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


def cpu_s(pid: int) -> float:
    """The process's user + system CPU time so far, s (load from other processes does not count)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def post(url: str, token: str, path: str, body: bytes, timeout_s: float = 600.0) -> tuple[int, bytes, dict]:
    req = urllib.request.Request(
        url + "/api/v1" + path, data=body, method="POST", headers={"Authorization": f"Bearer {token}"}
    )
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            return resp.status, resp.read(), dict(resp.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), dict(exc.headers)


def get(url: str, token: str, path: str) -> bytes:
    req = urllib.request.Request(url + "/api/v1" + path, headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=60) as resp:
        return resp.read()


def fresh_service(home: Path):
    engine = make_engine(Settings(home=home).effective_database_url)
    migrate(engine)
    from sqlmodel import Session

    with Session(engine) as db:
        token = create_token(db, role="technician", name="bench")[1]
    engine.dispose()
    service = start_service(home, free_port(), log_path=home / "service.log")
    url = service.ready["url"].rstrip("/")
    req = urllib.request.Request(
        url + "/api/v1/cells",
        data=json.dumps({"name": "bench", "model": cell_document(), "devices": {}}).encode(),
        method="POST",
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=30) as resp:
        cell_id = json.loads(resp.read())["id"]
    return service, url, token, cell_id


def import_once(rows: int, text: bytes) -> dict:
    with tempfile.TemporaryDirectory(prefix="recal-bench-import-") as tmp:
        home = Path(tmp)
        service, url, token, cell_id = fresh_service(home)
        try:
            idle = memory_kb(service.popen.pid)["VmRSS"]
            cpu0 = cpu_s(service.popen.pid)
            t0 = time.perf_counter()
            status, answer, _ = post(url, token, f"/cells/{cell_id}/measurements?kind=pose&name=bench.csv", text)
            elapsed = time.perf_counter() - t0
            cpu = cpu_s(service.popen.pid) - cpu0
            peak = memory_kb(service.popen.pid)["VmHWM"]
            assert status == 201, answer[:500]
            session = json.loads(answer)
            out = {
                "rows": rows,
                "csv_bytes": len(text),
                "s": elapsed,
                "cpu_s": cpu,
                "idle_mb": idle / 1024,
                "peak_above_idle_mb": (peak - idle) / 1024,
                "state": session["state"],
                "calibration_id": session["calibration_id"],
            }
            out["compensation"] = compensation_size(home, url, token, session["calibration_id"])
            return out
        finally:
            service.stop()


def compensation_size(home: Path, url: str, token: str, calibration_id: int) -> dict:
    task = task_csv(model_from_dict(cell_document()), Settings().max_task_bytes).encode()
    t0 = time.perf_counter()
    status, answer, headers = post(url, token, f"/calibrations/{calibration_id}/compensate?name=max.csv", task)
    elapsed = time.perf_counter() - t0
    assert status == 200, answer[:500]
    comp = int(headers.get("X-Recal-Compensation") or headers.get("x-recal-compensation"))
    report = get(url, token, f"/compensations/{comp}/report")
    with sqlite3.connect(home / "recal.db") as db:
        out_len, rep_len = db.execute(
            "SELECT length(CAST(output AS BLOB)), length(CAST(report AS BLOB)) FROM compensation WHERE id = ?", (comp,)
        ).fetchone()
    return {
        "input_bytes": len(task),
        "answered_bytes": len(answer),
        "report_answer_bytes": len(report),
        "stored_output_bytes": out_len,
        "stored_report_bytes": rep_len,
        "stored_over_input": (out_len + rep_len) / len(task),
        "s": elapsed,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=100_000)
    ap.add_argument("--baseline", type=int, default=10_000)
    args = ap.parse_args(argv)
    runs = []
    for n in (args.baseline, args.rows):
        text = measurement_csv(n)
        runs.append(import_once(n, text))
        r = runs[-1]
        print(
            f"import {n:>7} rows ({r['csv_bytes'] / 1e6:.1f} MB): {r['s']:.2f} s ({r['cpu_s']:.2f} s of service CPU), "
            f"{r['peak_above_idle_mb']:.0f} MB above idle ({r['idle_mb']:.0f} MB), {r['state']}, "
            f"calibration {r['calibration_id']}",
            flush=True,
        )
    base, big = runs
    ratio = args.rows / args.baseline
    print(
        f"time ratio {big['s'] / base['s']:.2f}, CPU ratio {big['cpu_s'] / base['cpu_s']:.2f}, "
        f"for {ratio:.0f}x the rows (load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)"
    )
    c = big["compensation"]
    print(
        f"compensation of {c['input_bytes']} input bytes ({c['s']:.1f} s): stored output {c['stored_output_bytes']} + "
        f"report {c['stored_report_bytes']} bytes = {c['stored_over_input']:.2f}x the input "
        f"(answered: file {c['answered_bytes']}, report {c['report_answer_bytes']} bytes)"
    )
    print(
        json.dumps(
            {
                "machine": f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}",
                "runs": runs,
            }
        )
    )
    ok = big["s"] <= 10.0 and big["peak_above_idle_mb"] <= 300 and c["stored_over_input"] <= 2.0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
