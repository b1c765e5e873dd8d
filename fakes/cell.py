"""``recal fake-cell``: one process that simulates a whole robot cell (contracts §7).

It loads the truth model, builds one ``SimCell`` and starts every device fake that exists
around it, each on its real protocol and its usual port of ``--host``:

==========  ===================================  ============================
key         fake                                 port(s)
==========  ===================================  ============================
``rtde``    ``fakes.ur_controller``              30004, 29999, 30003
``modbus``  ``fakes.modbus_server``              502 (an ephemeral port if 502 cannot be bound)
``tracker`` ``fakes.tracker``                    10001
``emscon``  ``fakes.leica_tracker``              700 (an ephemeral port if 700 cannot be bound)
``cmm``     ``fakes.cmm``                        1294
``can``     ``fakes.canopen_nodes``              29536
==========  ===================================  ============================

When every endpoint accepts connections it prints exactly one line of JSON on stdout (the
endpoint line, merged from each fake's ``endpoint()``), then serves until SIGINT or SIGTERM
and shuts everything down. The fakes are the modules of ``fakes`` with a ``CELL_FAKE`` line
(:func:`find_fakes`); ``--only KEY`` starts one of them alone.

Extension flags (beyond the contract): ``--fault NAME=VALUE`` sets a field of
``fakes.world.Faults`` (lists as comma-separated counts: ``--fault protective_stop_at_move=3``,
``--fault beam_break_rate=0.1``), ``--noise NAME=VALUE`` a field of ``fakes.world.Noise``
(SI units), ``--no-ur`` / ``--no-modbus`` / ``--no-tracker`` / ``--no-emscon`` / ``--no-cmm`` /
``--no-can`` leave a device out, ``--modbus-port`` moves the Modbus server, ``--emscon-port``
the emScon server; ``--reflector-axis X,Y,Z`` (tool frame) and ``--arm-radius M`` turn on the
emScon tracker's beam geometry (the reflector's acceptance angle, the arm blocking the line of
sight: fakes/leica_tracker.py). A fake's own options are declared by its module (``options`` on
its ``CELL_FAKE`` line: the Modbus and emScon ports, the beam geometry).

The UR controller's factory calibration (``fakes.world.FactoryCalibration``, docs/devices/ur.md):
the truth file's ``ur_factory_calibration`` block (``published``, ``delta_theta``, ``delta_a``,
``delta_d``, ``delta_alpha``: 6 values each, SI), else, when the truth is a UR arm (nearest
published table within 5 cm), one drawn with ``--factory-seed N`` (default 0);
``--no-factory-calibration`` makes the controller compute with the published table.

The faults (``--help`` lists them too). Counts are 1-based and each device counts its own
requests, so one fault may hit several devices: leave out the devices a test does not use.

- ``drop_connection_at``: requests whose connection is closed instead of answered;
- ``delay_s``, ``delay_at``: extra latency before every reply, or only before the replies to
  the ``delay_at`` requests (tracker, CMM, CAN, commands to the UR control script);
- ``garble_at``, ``garble_rate``: garbled replies (tracker, CMM: non-printable bytes; CAN: a
  bad SDO command byte or a short PDO; Modbus: a junk PDU; UR: a malformed RTDE package on
  every stream);
- ``beam_break_at``, ``beam_break_rate``: tracker measurements that find the beam broken (the
  emScon tracker then has lost the reflector until it is found again);
- ``error_status_at``: emScon commands answered with an error packet;
- ``no_touch_at``: CMM ``PtMeas`` that touch nothing (I++ error 1003);
- ``silent_nodes``: CAN node ids that send nothing (no answer, PDO, heartbeat or EMCY);
- ``sensor_fault_at``: CAN position requests answered with a sensor fault and an EMCY;
- ``protective_stop_at_move``: robot moves that stop halfway in a protective stop;
- ``emergency_stop_at_move``: robot moves that stop halfway in an emergency stop (the arm
  stays powered off until the button is released and it is powered on again).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import pkgutil
import signal
import sys
import threading
from pathlib import Path

from calibration.errors import RecalError
from calibration.model import KinematicModel, model_from_dict
from fakes.world import (
    FactoryCalibration,
    Faults,
    Noise,
    SimCell,
    draw_factory_calibration,
    published_ur_for,
)

PROG = "recal fake-cell"


def find_fakes() -> list[dict]:
    """Every device fake of the package, in start order: the ``CELL_FAKE`` line of each module
    of ``fakes`` (its --no-KEY flag's key, its order, its class, its keyword arguments from the
    parsed command line, and its own command-line ``options``: ``(flag, argparse keywords)``
    pairs). A new fake, or a new option of one, is its module alone; nothing here names it."""
    import fakes

    found = []
    for info in pkgutil.iter_modules(fakes.__path__):
        if info.name.startswith("_") or info.name == "cell":
            continue
        entry = getattr(importlib.import_module(f"fakes.{info.name}"), "CELL_FAKE", None)
        if entry is not None:
            found.append(entry)
    return sorted(found, key=lambda e: (e["order"], e["key"]))


FAKES = find_fakes()


class CellError(RecalError, ValueError):
    """Bad input or a fake that cannot start; the message is the one stderr line."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Run a simulated robot cell.",
        epilog=_faults_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--truth", required=True, help="truth model (recal.model/1 JSON)")
    parser.add_argument("--host", default="127.0.0.2", help="address to serve on (default 127.0.0.2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise and faults")
    parser.add_argument(
        "--time-scale",
        type=float,
        default=0.0,
        help="wall time per second of real robot motion (0: moves are instant)",
    )
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="inject a fault (a field of fakes.world.Faults); repeatable",
    )
    parser.add_argument(
        "--noise",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="instrument noise (a field of fakes.world.Noise, SI units); repeatable",
    )
    parser.add_argument(
        "--factory-seed",
        type=int,
        default=0,
        help="seed of the UR controller's factory calibration drawn when the truth file has no "
        "ur_factory_calibration block (default 0)",
    )
    parser.add_argument(
        "--no-factory-calibration",
        action="store_true",
        help="the UR controller computes with the published DH table (all deltas zero)",
    )
    for fake in FAKES:  # a fake's own options, declared on its CELL_FAKE line
        for flag, spec in fake.get("options", ()):
            parser.add_argument(flag, **spec)
    for fake in FAKES:
        parser.add_argument(f"--no-{fake['key']}", action="store_true", help=f"do not simulate {fake['key']}")
    parser.add_argument(
        "--only",
        choices=[fake["key"] for fake in FAKES],
        default=None,
        help="simulate this device alone (python -m fakes.modbus_server, fakes.ur_controller)",
    )
    return parser


def _faults_help() -> str:
    """The list of --fault names and what each injects (from ``Faults``' field metadata)."""
    lines = ["faults (--fault NAME=VALUE; lists are comma-separated 1-based counts of each", "device's own requests):"]
    for f in dataclasses.fields(Faults):
        lines.append(f"  {f.name:<24} {f.metadata['help']}")
    return "\n".join(lines)


def load_truth(path: str) -> KinematicModel:
    """Read a ``recal.model/1`` file; units are the model module's business."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise CellError(f"{path}: cannot read the truth model: {exc.strerror}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CellError(f"{path}: line {exc.lineno}, column {exc.colno}: {exc.msg}") from exc
    try:
        return model_from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise CellError(f"{path}: {exc}") from exc


def factory_calibration(truth: KinematicModel, args: argparse.Namespace) -> FactoryCalibration | None:
    """The UR controller's factory calibration: the truth file's ``ur_factory_calibration``
    block, else one drawn with ``--factory-seed`` for the published UR the truth is nearest
    (``--no-factory-calibration``: zero deltas); ``None`` when the robot is no UR arm."""
    block = truth.metadata.get("ur_factory_calibration")
    if block is not None:
        try:
            return FactoryCalibration.from_dict(block)
        except ValueError as exc:
            raise CellError(f"{args.truth}: {exc}") from exc
    published = published_ur_for(truth)
    if published is None:
        return None
    if args.no_factory_calibration:
        return FactoryCalibration(published, *([(0.0,) * 6] * 4))
    return draw_factory_calibration(published, args.factory_seed)


def parse_fields(items: list[str], cls, flag: str):
    """``NAME=VALUE`` strings -> an instance of the dataclass ``cls`` (Faults or Noise).

    A field's default decides the type: lists take comma-separated integers, numbers floats.
    """
    defaults = cls()
    fields = {f.name for f in dataclasses.fields(cls)}
    values = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or name not in fields:
            known = ", ".join(sorted(fields))
            raise CellError(f"{flag} {item!r}: expected NAME=VALUE with NAME one of: {known}")
        try:
            if isinstance(getattr(defaults, name), list):
                values[name] = [int(v) for v in text.split(",") if v.strip()]
            else:
                values[name] = float(text)
        except ValueError as exc:
            raise CellError(f"{flag} {item!r}: {exc}") from exc
    return cls(**values)


def start_fakes(cell: SimCell, args: argparse.Namespace) -> list:
    """Construct and start every available fake; stop them all again if one fails."""
    started = []
    try:
        for entry in FAKES:
            key, cls = entry["key"], entry["cls"]
            if getattr(args, f"no_{key}") or args.only not in (None, key):
                continue
            kwargs = entry.get("kwargs", lambda _args: {})(args)
            try:
                fake = cls(cell, host=args.host, **kwargs)
            except ValueError as exc:  # this device cannot simulate this robot
                print(f"{PROG}: no {key} fake: {exc}", file=sys.stderr)
                continue
            try:
                fake.start()
            except OSError as exc:
                raise CellError(f"cannot start the {key} fake on {args.host}: {exc}") from exc
            started.append(fake)
    except BaseException:
        stop_fakes(started)
        raise
    return started


def stop_fakes(fakes: list) -> None:
    for fake in reversed(fakes):
        try:
            fake.stop()
        except Exception as exc:  # noqa: BLE001 - keep stopping the others
            print(f"{PROG}: stopping {type(fake).__name__}: {exc}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the cell until SIGINT/SIGTERM. Returns the process exit code."""
    args = build_parser().parse_args(argv)
    endpoint_out = sys.stdout
    sys.stdout = sys.stderr  # nothing but the endpoint line may reach stdout
    done = threading.Event()
    previous = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            if args.time_scale < 0:
                raise CellError(f"--time-scale {args.time_scale}: must be >= 0")
            truth = load_truth(args.truth)
            factory = factory_calibration(truth, args)
            cell = SimCell(
                truth,
                seed=args.seed,
                time_scale=args.time_scale,
                noise=parse_fields(args.noise, Noise, "--noise"),
                faults=parse_fields(args.fault, Faults, "--fault"),
                factory=factory,
            )
            fakes = start_fakes(cell, args)
        except CellError as exc:
            print(f"{PROG}: {exc}", file=sys.stderr)
            return 1
        line = {"ready": True}
        for fake in fakes:
            line.update(fake.endpoint())
        endpoint_out.write(json.dumps(line) + "\n")
        endpoint_out.flush()
        while not done.wait(0.5):
            pass
        stop_fakes(fakes)
        return 0
    finally:
        sys.stdout = endpoint_out
        for signum, handler in previous.items():
            signal.signal(signum, handler)


if __name__ == "__main__":
    sys.exit(main())
