"""``recal export --model MODEL.json --format urdf|ur-calibration|dh-csv|dh-md --out FILE``

Writes a (calibrated) model for other tools (calibration.export): a ROS-ready URDF whose joint
origins carry the calibrated values (UR's names for UR arms, ROS-Industrial's for the others,
velocity and effort limits from the model, the library or the flags), UR's calibration YAML for
ur_robot_driver, or the DH table as CSV or Markdown in the model's units. What the format cannot
represent (joint gains, coupling, harmonics in URDF) is said on stderr and in the file.
"""

from __future__ import annotations

import sys


def add_parser(s) -> None:
    from calibration.export import FORMATS, NAMINGS

    s.add_argument("--model", required=True, help="model file (recal.model/1) or a library robot name")
    s.add_argument("--format", required=True, choices=list(FORMATS), help="what to write")
    s.add_argument("--out", required=True, help="file to write")
    s.add_argument("--name", help="URDF robot name (default: the model's name)")
    s.add_argument("--prefix", default="", help="prefix for every URDF link and joint name")
    s.add_argument(
        "--names",
        default="auto",
        choices=list(NAMINGS),
        help="URDF link and joint names: ur (UR's), ros (ROS-Industrial's: joint_1.. for generic j1.. names), "
        "recal; auto: ur for an arm that moves as a library UR arm, ros otherwise",
    )
    s.add_argument(
        "--world",
        action="store_true",
        help="URDF: add a 'world' link (the instrument's frame) joined to base_link by the model's base "
        "(default: a robot-only URDF rooted at base_link)",
    )
    s.add_argument(
        "--velocity",
        type=float,
        metavar="RAD_PER_S",
        help="URDF velocity limit of every joint, rad/s (m/s for prismatic joints); "
        "default: the model's or the library's",
    )
    s.add_argument(
        "--effort",
        type=float,
        metavar="NM",
        help="URDF effort limit of every joint, N·m (N for prismatic joints); default: the model's or the library's",
    )


def run(args) -> int:
    from calibration.export import export, export_warnings
    from service.cli import Fail
    from service.files import load_model, write_atomic

    model = load_model(args.model)
    kw = {}
    if args.format == "urdf":
        kw = {
            "name": args.name,
            "prefix": args.prefix,
            "names": args.names,
            "velocity": args.velocity,
            "effort": args.effort,
            "world": args.world,
        }
    try:
        text = export(model, args.format, **kw)
    except ValueError as exc:
        raise Fail(f"{args.model}: {exc}") from None
    write_atomic(args.out, text)
    options = {"effort": args.effort, "world": args.world} if args.format == "urdf" else {}
    for w in export_warnings(model, args.format, **options):
        print(f"warning: {w}", file=sys.stderr)
    return 0
