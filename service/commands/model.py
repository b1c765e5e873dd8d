"""``recal model [NAME] [--out FILE]``: list the robot library (with a short description), or
write a nominal model. ``recal model --from-urdf ROBOT.urdf [--base LINK] [--tip LINK] --out
MODEL.json``: the model of a URDF's serial chain (calibration.urdf)."""

from __future__ import annotations

import json
import sys


def add_parser(s) -> None:
    s.add_argument(
        "name", nargs="?", help="library robot name (e.g. ur10e, kr16, irb4600, fr3); without it, the library is listed"
    )
    s.add_argument("--out", help="file to write (default: stdout)")
    s.add_argument("--from-urdf", metavar="FILE", help="read the model from a URDF robot description")
    s.add_argument("--base", metavar="LINK", help="with --from-urdf: the chain's first link (default: the root link)")
    s.add_argument(
        "--tip",
        metavar="LINK",
        help="with --from-urdf: the chain's last link, the model's flange "
        "(default: the only leaf; required where the tree branches)",
    )
    s.add_argument(
        "--convention",
        choices=["auto", "dh", "poe"],
        default="auto",
        help="with --from-urdf: standard DH (Hayati links for parallel axes; what the links cannot "
        "hold goes to base and tool) or product of exponentials, both exact; auto (default): DH "
        "when it starts on the base link and ends on the tip, else POE",
    )


def run(args) -> int:
    from calibration import robots
    from calibration.model import model_to_dict
    from service.cli import Fail
    from service.files import write_atomic

    if args.from_urdf:
        if args.name:
            raise Fail("give a library robot name or --from-urdf FILE, not both")
        from calibration.urdf import UrdfError, import_urdf

        try:
            with open(args.from_urdf, encoding="utf-8") as f:
                text = f.read()
        except OSError as exc:
            raise Fail(f"{args.from_urdf}: cannot read: {exc.strerror or exc}") from None
        try:
            model, notes = import_urdf(text, base=args.base, tip=args.tip, convention=args.convention)
        except UrdfError as exc:
            raise Fail(f"{args.from_urdf}: {exc}") from None
        # Joints off the chain are ignored as ROS's chain solvers ignore them; say which.
        for note in notes:
            print(f"note: {args.from_urdf}: {note}", file=sys.stderr)
        doc = model_to_dict(model)
        doc = {
            "format": doc.pop("format"),
            "name": doc.pop("name"),
            "source": f"URDF {args.from_urdf}, chain {args.base or '(root)'} -> {args.tip or '(default tip)'}",
            **doc,
        }
    elif args.base or args.tip or args.convention != "auto":
        raise Fail("--base, --tip and --convention go with --from-urdf FILE")
    elif args.name is None:
        width = max(len(n) for n in robots.names())
        print("\n".join(f"{n:<{width}}  {robots.describe(n)}" for n in robots.names()))
        return 0
    else:
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
