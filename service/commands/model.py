"""``recal model [NAME] [--out FILE]``: list the robot library, or write a nominal model."""

from __future__ import annotations

import json
import sys


def add_parser(s) -> None:
    s.add_argument("name", nargs="?", help="library robot name (e.g. ur10e, puma560, puma560-zrp)")
    s.add_argument("--out", help="file to write (default: stdout)")


def run(args) -> int:
    from calibration import robots
    from service.cli import Fail
    from service.files import write_atomic

    if args.name is None:
        print("\n".join(robots.names()))
        return 0
    try:
        doc = robots.nominal_document(args.name)
    except KeyError as exc:
        raise Fail(str(exc.args[0])) from None
    text = json.dumps(doc, indent=2) + "\n"
    if args.out:
        write_atomic(args.out, text)
    else:
        sys.stdout.write(text)
    return 0
