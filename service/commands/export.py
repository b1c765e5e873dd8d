"""``recal export --model MODEL.json --format urdf|dh-csv|dh-md --out FILE``

Writes a (calibrated) model for other tools (calibration.export): a URDF whose joint origins carry
the calibrated values, or the DH table as CSV or Markdown in the model's units. What the format
cannot represent (joint gains, coupling, harmonics in URDF) is said on stderr and in the file.
"""

from __future__ import annotations

import sys


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="model file (recal.model/1) or a library robot name")
    s.add_argument("--format", required=True, choices=["urdf", "dh-csv", "dh-md"], help="what to write")
    s.add_argument("--out", required=True, help="file to write")
    s.add_argument("--name", help="URDF robot name (default: the model's name)")
    s.add_argument("--prefix", default="", help="prefix for every URDF link and joint name")


def run(args) -> int:
    from calibration.export import export, export_warnings
    from service.cli import Fail
    from service.files import load_model, write_atomic

    model = load_model(args.model)
    kw = {"name": args.name, "prefix": args.prefix} if args.format == "urdf" else {}
    try:
        text = export(model, args.format, **kw)
    except ValueError as exc:
        raise Fail(f"{args.model}: {exc}") from None
    write_atomic(args.out, text)
    for w in export_warnings(model, args.format):
        print(f"warning: {w}", file=sys.stderr)
    return 0
