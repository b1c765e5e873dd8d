"""Identification at scale (issue 14): time and peak memory of ``identify()`` on 10,000, 100,000 and
1,000,000 position rows, this tree against a baseline revision (default: the implementation
before issue 14) side by side in one run.

Method: the benchmark robot of ``bench/identify.py`` (a UR10e with a 6-DOF error on every link,
base and tool errors, a reflector 30 mm off the flange axis, 0.02 mm noise per axis). The rows are
simulated once per size and saved to a temporary ``.npz``; each case then runs in a fresh process
that loads them, notes its resident set (``VmRSS``: Python, numpy, scipy and the data), resets
the kernel's peak mark (``/proc/self/clear_refs``), calls ``identify(nominal, data)`` once and
reports the wall time of that call and the process's peak resident set during it (``VmHWM``). "Above the data" is the peak less what the process held before the call: the memory
identification itself takes. The baseline is the ``calibration`` package of ``--baseline-rev``
(``git archive``), run the same way. BLAS single-threaded (as bench/identify.py).

``--tool-on-axis``: the same robot with its tool nominally on the flange axis (the nominal tool
(0, 0, 80) mm; the real one about 1 mm off the axis): the case where the re-selection at the
answer frees the parameters only the real geometry determines and the fit runs again.

Run: ``python bench/identify_scale.py`` (10k and 100k, both implementations: about a minute);
``--sizes 1000000 --no-baseline`` for the million rows of this tree alone (run it once, on a quiet
machine: about 10 s and under 1 GB; the baseline needs about 4 GB there); add ``--tool-on-axis``
for the on-axis case.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CHILD = r"""
import json, sys, time
import numpy as np
from calibration import robots
from calibration.identification import Measurements
from calibration.identify import identify
import dataclasses
z = np.load(sys.argv[1])
data = Measurements(z["q"], z["p"])
nominal = dataclasses.replace(robots.nominal("ur10e"), tool=np.array(json.loads(sys.argv[2])))
def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
before = status("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # reset the peak (VmHWM) to the resident set now
t = time.perf_counter()
res = identify(nominal, data, sigma_m=20e-6)
dt = time.perf_counter() - t
peak = status("VmHWM")
import calibration
print(json.dumps({"package": calibration.__file__, "time_s": dt, "peak_bytes": peak, "before_bytes": before, "rms_m": res.rms_m,
                  "iterations": res.iterations, "parameters": len(res.params)}))
"""


# the tool moved onto the flange axis (x 30 mm -> 0), in the nominal and, with its errors, in the truth
ON_AXIS_SHIFT_M = 0.03


def simulate(N: int, path: Path, *, tool_on_axis: bool) -> list[float]:
    """Simulate ``N`` rows into ``path``; the nominal tool (x, y, z, rx, ry, rz) the child starts from."""
    import dataclasses

    import numpy as np

    from calibration.simulate import random_configurations, simulate_measurements

    sys.path.insert(0, str(ROOT / "bench"))
    from identify import SIGMA_M, scenario  # the benchmark robot of bench/identify.py

    nominal, truth, rng, _, _ = scenario()
    if tool_on_axis:
        shift = np.array([ON_AXIS_SHIFT_M, 0, 0, 0, 0, 0])
        nominal = dataclasses.replace(nominal, tool=nominal.tool - shift)
        truth = dataclasses.replace(truth, tool=truth.tool - shift)
    data = simulate_measurements(truth, random_configurations(nominal, N, rng), rng, sigma_m=SIGMA_M)
    np.savez(path, q=data.q, p=data.p_world)
    return [float(v) for v in nominal.tool]


def run(pythonpath: Path, npz: Path, tool: list[float]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    # cwd: the data's directory, so that `-c` (which puts the working directory first on the path)
    # imports the calibration package of ``pythonpath``
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(npz), json.dumps(tool)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        cwd=npz.parent,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--baseline-rev", default="65c8eae", help="git revision whose calibration package is the baseline")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--tool-on-axis", action="store_true", help="the tool nominally on the flange axis")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "bench"))
    from identify import machine

    print(f"machine: {machine()}")
    print(
        f"{'N':>8} | {'impl':>8} | {'time s':>7} {'us/row':>7} | {'peak MB':>8} {'above data MB':>13} "
        f"{'B/row':>7} | {'iter':>4} {'P':>3} {'RMS um':>7}"
    )
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        impls = [("this", ROOT)]
        if not args.no_baseline:
            base = d / "baseline"
            base.mkdir()
            archive = subprocess.run(
                ["git", "-C", str(ROOT), "archive", args.baseline_rev, "calibration"], capture_output=True, check=True
            ).stdout
            subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
            impls.append((args.baseline_rev, base))
        for N in args.sizes:
            npz = d / f"rows_{N}.npz"
            tool = simulate(N, npz, tool_on_axis=args.tool_on_axis)
            for name, path in impls:
                r = run(path, npz, tool)
                above = r["peak_bytes"] - r["before_bytes"]
                print(
                    f"{N:>8} | {name:>8} | {r['time_s']:7.2f} {r['time_s'] / N * 1e6:7.2f} | "
                    f"{r['peak_bytes'] / 2**20:8.0f} {above / 2**20:13.0f} {above / N:7.0f} | "
                    f"{r['iterations']:>4} {r['parameters']:>3} {r['rms_m'] * 1e6:7.2f}",
                    flush=True,
                )
    print(
        "peak MB: the process's peak resident set (Python, numpy, scipy, the data and identification); above data: "
        "that peak less the resident set before identify() (what identification takes); B/row: above data per row."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
