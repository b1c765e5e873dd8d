"""``recal controller-model --rtde HOST --out CONTROLLER.json [--robot NAME]``

The UR controller's own kinematics (its factory calibration), read from the controller: it is
asked for ``get_forward_kin(q)`` (``ur_rtde``'s ``getForwardKinematics``, tool offset zero) at
``--poses`` configurations and as many again for the check; **nothing moves** (connecting
uploads ``ur_rtde``'s control script, which stops a program that is running). The model is
fitted exactly (``calibration.controller``) and written as ``recal.model/1`` with a
``controller`` block of check figures, or, when it does not reproduce the controller within
``--tolerance``, refused with one line and no file. See docs/devices/ur.md.

The controller is reached through the device registry (``service.device_registry``: the
``rtde`` entry opens its driver and asks its dashboard what it is), as a session reaches it.
"""

from __future__ import annotations

import json

# Each request to the controller (its dashboard's answer, each forward-kinematics query) gets this
# long; connecting, which uploads the control script, at least the driver's own 15 s.
REQUEST_TIMEOUT_S = 5.0


def add_parser(s) -> None:
    s.add_argument("--rtde", required=True, metavar="HOST", help="the UR controller's address")
    s.add_argument("--out", required=True, help="model file to write (recal.model/1)")
    s.add_argument(
        "--robot",
        help="library robot whose published table the fit starts from and whose names, "
        "limits and units it keeps (default: from the dashboard's `get robot model`, e.g. UR5 -> ur5e)",
    )
    s.add_argument(
        "--poses",
        type=int,
        default=48,
        help="configurations for the fit, as many again for the check (default 48; at least 5)",
    )
    s.add_argument("--seed", type=int, default=0, help="seed of the configurations (default 0)")
    s.add_argument(
        "--tolerance",
        type=float,
        default=1.0,
        help="largest position difference to the controller, um (and urad in rotation) (default 1)",
    )


def run(args) -> int:
    from drivers.errors import DeviceError
    from service.cli import Fail, progress
    from service.controller import ControllerModelError, read_controller_model, reference_model
    from service.devices import DeviceConfigError, open_robot, parse_devices
    from service.files import check_output, write_atomic

    if args.poses < 5:
        raise Fail(f"--poses {args.poses}: expected at least 5 (30 parameters, 6 equations per pose)")
    if not args.tolerance > 0:
        raise Fail(f"--tolerance {args.tolerance}: expected a positive number of um")
    check_output(args.out)
    try:
        devices = parse_devices({"rtde": args.rtde})
    except DeviceConfigError as exc:
        raise Fail(f"--rtde {args.rtde}: {exc.message}") from None
    (entry,) = devices.present("robot")
    try:
        answer = None if args.robot or entry.robot_type is None else entry.robot_type(devices, REQUEST_TIMEOUT_S)
        reference = reference_model(args.robot, answer)
        progress(f"asking {args.rtde} for its forward kinematics at {2 * args.poses} configurations")
        with open_robot(devices, timeout_s=REQUEST_TIMEOUT_S) as robot:
            if robot.kinematics_source != "forward_kinematics":
                raise Fail(f"{robot.name} answers no forward kinematics: its model cannot be read")
            doc = read_controller_model(
                robot,
                reference,
                source=f"UR controller {args.rtde}",
                n_fit=args.poses,
                n_check=args.poses,
                seed=args.seed,
                tolerance_m=args.tolerance * 1e-6,
            )
    except ControllerModelError as exc:
        raise Fail(str(exc)) from None
    except DeviceError as exc:
        raise Fail(str(exc)) from None
    write_atomic(args.out, json.dumps(doc, indent=2) + "\n")
    check = doc["controller"]["check"]
    print(
        f"{args.out}: {doc['name']}, reproduces the controller to {check['position_max_um']:.2g} um and "
        f"{check['rotation_max_urad']:.2g} urad at {args.poses} check configurations"
    )
    return 0
