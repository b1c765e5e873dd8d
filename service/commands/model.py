"""``recal model [NAME] [--out FILE]``: list the robot library (with a short description), or
write a nominal model. ``recal model --from-urdf ROBOT.urdf [--base LINK] [--tip LINK] --out
MODEL.json``: the model of a URDF's serial chain (calibration.urdf), joints off the chain named
on stderr. ``recal model --from-ur-calibration FILE --robot UR --out MODEL.json``: the model UR's
calibration YAML describes, read as ur_description reads it (calibration.export)."""

from __future__ import annotations

import json
import sys


def add_parser(s) -> None:
    s.add_argument(
        "name", nargs="?", help="library robot name (e.g. ur10e, kr16, irb4600, fr3); without it, the library is listed"
    )
    s.add_argument("--out", help="file to write (default: stdout)")
    s.add_argument("--from-urdf", metavar="FILE", help="read the model from a URDF robot description")
    s.add_argument(
        "--from-ur-calibration",
        metavar="FILE",
        help="read the model from UR's calibration YAML (what ur_calibration writes), read as ur_description "
        "reads it; needs --robot",
    )
    s.add_argument(
        "--robot", metavar="UR", help="with --from-ur-calibration: the library UR arm (ur3e, ur5e, ur10e, ur16e)"
    )
    s.add_argument("--base", metavar="LINK", help="with --from-urdf: the chain's first link (default: the root link)")
    s.add_argument(
        "--tip",
        metavar="LINK",
        help="with --from-urdf: the chain's last link, the model's flange "
        "(default: down the one branch with joints that move on their own, to its end or to where it "
        "forks into fixed frames; required where two branches move)",
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

    if args.from_ur_calibration or args.robot:
        doc = _from_ur_calibration(args)
    elif args.from_urdf:
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


def _from_ur_calibration(args) -> dict:
    from calibration.export import model_from_ur_calibration, parse_ur_calibration_yaml
    from calibration.model import model_to_dict
    from service.cli import Fail

    if not (args.from_ur_calibration and args.robot):
        raise Fail("--from-ur-calibration FILE and --robot UR go together")
    if args.name or args.from_urdf or args.base or args.tip or args.convention != "auto":
        raise Fail("--from-ur-calibration takes --robot and --out only")
    path = args.from_ur_calibration
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError as exc:
        raise Fail(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        model = model_from_ur_calibration(parse_ur_calibration_yaml(text), args.robot)
    except ValueError as exc:
        raise Fail(f"{path}: {exc}") from None
    doc = model_to_dict(model)
    return {
        "format": doc.pop("format"),
        "name": doc.pop("name"),
        "source": f"UR calibration {path} (read as ur_description reads it; base: base_link_inertia, flange: tool0), "
        f"limits of the library {args.robot.lower()}",
        **doc,
    }
