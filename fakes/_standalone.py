"""Run one fake device alone in its own process (``python -m fakes.tracker``, ``python -m fakes.cmm``).

The whole simulated cell (``recal fake-cell``, ``fakes/cell.py``) is the usual way; this small
entry serves one device for tests across processes and for trying a driver by hand. It prints
one JSON line (contracts §7 keys plus ``"ready": true``) when the port accepts connections and
serves until SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import threading
from collections.abc import Callable

import numpy as np

from fakes.world import SimCell


def _vector(text: str) -> np.ndarray:
    values = [float(v) for v in text.split(",")]
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z; got {text!r}")
    return np.array(values)


def _named_vector(text: str) -> tuple[str, np.ndarray]:
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=x,y,z; got {text!r}")
    return name, _vector(rest)


def build_parser(description: str, default_port: int) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--truth", help="true robot model, a recal.model/1 JSON file")
    src.add_argument("--robot", default="ur5e", help="library robot used as the truth (default ur5e)")
    p.add_argument("--reflector", type=_vector, help="add a reflector target 'smr1' at x,y,z (m, tool frame)")
    p.add_argument(
        "--ball",
        type=_named_vector,
        action="append",
        default=[],
        help="add a tooling ball target NAME=x,y,z (m, tool frame); NAME should start with 'ball'",
    )
    p.add_argument(
        "--q",
        type=lambda s: np.array([float(v) for v in s.split(",")]),
        help="initial joint readings, comma separated (rad)",
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument(
        "--port", type=int, default=default_port, help=f"TCP port (default {default_port}; 0 = any free port)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-scale", type=float, default=0.0)
    return p


def cell_from_args(args: argparse.Namespace) -> SimCell:
    from calibration.model import model_from_dict
    from calibration.robots import nominal

    if args.truth:
        with open(args.truth, encoding="utf-8") as f:
            truth = model_from_dict(json.load(f))
    else:
        truth = nominal(args.robot)
    targets = dict(truth.targets)
    if args.reflector is not None:
        targets["smr1"] = args.reflector
    for name, p in args.ball:
        targets[name] = p
    if targets != dict(truth.targets):
        truth = dataclasses.replace(truth, targets=targets)
    return SimCell(truth, seed=args.seed, time_scale=args.time_scale, q_home=args.q)


def run_fake(
    factory: Callable[[SimCell, str, int], object],
    *,
    default_port: int,
    argv: list[str] | None = None,
    description: str = "Run one simulated device.",
) -> int:
    """Parse the command line, start the fake, print the ready line, wait for a signal."""
    args = build_parser(description, default_port).parse_args(argv)
    cell = cell_from_args(args)
    fake = factory(cell, args.host, args.port)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    fake.start()
    try:
        print(json.dumps({"ready": True, **fake.endpoint()}), flush=True)
        while not done.wait(0.5):
            pass
    finally:
        fake.stop()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit("run `python -m fakes.tracker` or `python -m fakes.cmm`")
