"""A million position rows through ``recal identify``, whole process (issue 25, case 7): wall time
and peak resident set of the CLI reading the CSV, identifying and writing the model, with the
CSV read by the columnar reader (pyarrow) against the Python ``csv`` reader in the same run.

Method: the benchmark robot of ``bench/identify.py`` (a UR10e with a 6-DOF error on every link,
base and tool errors, a reflector 30 mm off the flange axis, 0.02 mm noise per axis), ``N`` rows
simulated once and written as a measurement CSV (contracts §3: q1..q6 in degrees, x, y, z in mm,
a ``target`` column) with the nominal model file beside it. Each case is a fresh ``recal identify
--quiet`` process; its peak resident set is the kernel's ``ru_maxrss`` of that child alone
(``os.wait4``), its time the wall clock around it. The baseline is the same command with
``RECAL_CSV_READER=python`` (the reader Recal had before: every cell through ``csv`` and
``float``). Cases alternate, ``--repeat`` times each; the table gives the median. BLAS
single-threaded, as the CLI runs it.

Run: ``python bench/million_rows.py`` (1,000,000 rows; about two minutes), ``--rows 100000`` for
a quick look. The figures are in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.append(str(ROOT / "bench"))  # after ROOT: bench/service.py must not hide the service package


def write_case(N: int, folder: Path) -> tuple[Path, Path]:
    """The nominal model file and an ``N``-row measurement CSV of the benchmark robot."""
    import numpy as np
    from identify import SIGMA_M, scenario  # the benchmark robot of bench/identify.py

    from calibration.simulate import random_configurations, simulate_measurements
    from service.files import save_model

    nominal, truth, rng, _, _ = scenario()
    data = simulate_measurements(truth, random_configurations(nominal, N, rng), rng, sigma_m=SIGMA_M)
    model_path, csv_path = folder / "nominal.json", folder / f"rows_{N}.csv"
    save_model(model_path, nominal)
    target = next(iter(nominal.targets)) if nominal.targets else None
    u = nominal.units
    q = np.degrees(data.q) if u.angle == "deg" else data.q
    p = data.p_world / u.length_m
    header = [f"q{i + 1}" for i in range(q.shape[1])] + ["x", "y", "z"] + (["target"] if target else [])
    with open(csv_path, "w") as f:
        f.write(",".join(header) + "\n")
        cols = np.concatenate([q, p], axis=1)
        suffix = f",{target}\n" if target else "\n"
        for start in range(0, N, 100_000):
            block = cols[start : start + 100_000]
            f.write(suffix.join(",".join(f"{v:.9g}" for v in row) for row in block) + suffix)
    return model_path, csv_path


# The command runs under a small launcher that forks it and reads its resources: a child forked
# from this process would count this process's memory (the simulated rows) in its peak until it
# execs (subprocess forks with vfork: ru_maxrss then read 554 MB for a process whose own peak was
# 411 MB). The launcher is a bare interpreter (-S: no site packages), a few MB.
LAUNCHER = r"""
import os, sys, time
t = time.perf_counter()
pid = os.fork()
if pid == 0:
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.execv(sys.argv[1], sys.argv[1:])
_, status, usage = os.wait4(pid, 0)
print(time.perf_counter() - t, usage.ru_maxrss, usage.ru_utime + usage.ru_stime, os.waitstatus_to_exitcode(status))
"""


def run(model: Path, data: Path, out: Path, reader: str) -> dict:
    """One ``recal identify`` process: wall time (s), peak resident set (bytes), CPU time (s),
    exit status."""
    env = {**os.environ, "RECAL_CSV_READER": reader}
    recal = str(Path(sys.executable).with_name("recal"))
    cmd = [recal, "identify", "--model", str(model), "--data", str(data), "--out", str(out), "--quiet"]
    done = subprocess.run(
        [sys.executable, "-S", "-c", LAUNCHER, *cmd], env=env, capture_output=True, text=True, check=True
    )
    wall, maxrss_kb, cpu, code = done.stdout.split()
    return {
        "time_s": float(wall),
        "peak_bytes": int(maxrss_kb) * 1024,
        "cpu_s": float(cpu),
        "exit": int(code),
        "stderr": done.stderr[-300:],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--keep", type=Path, help="a folder for the case's files (kept), instead of a temporary one")
    args = ap.parse_args(argv)
    from identify import machine

    print(f"machine: {machine()}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        model, data = write_case(args.rows, folder)
        print(f"{args.rows:,} rows, {data.stat().st_size / 2**20:.0f} MB of CSV")
        results: dict[str, list[dict]] = {"arrow": [], "python": []}
        for _ in range(args.repeat):
            for reader, runs in results.items():
                r = run(model, data, folder / f"out-{reader}.json", reader)
                if r["exit"] not in (0, 3):
                    print(f"{reader}: exit {r['exit']}: {r['stderr']}")
                    return 1
                runs.append(r)
        same = json.loads((folder / "out-arrow.json").read_text()) == json.loads(
            (folder / "out-python.json").read_text()
        )
        print(f"{'reader':>8} | {'time s':>7} | {'CPU s':>6} | {'peak MB':>8} | exit")
        for reader, rs in results.items():
            t = statistics.median(r["time_s"] for r in rs)
            c = statistics.median(r["cpu_s"] for r in rs)
            m = statistics.median(r["peak_bytes"] for r in rs)
            print(f"{reader:>8} | {t:7.2f} | {c:6.2f} | {m / 2**20:8.0f} | {rs[0]['exit']}")
        print(f"identical model files from both readers: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
