"""``recal predict --model MODEL.json --joints JOINTS.csv [--target NAME] --out PRED.csv``"""

from __future__ import annotations


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="model file or library robot name")
    s.add_argument("--joints", required=True, help="CSV with q1..qN")
    s.add_argument("--target", help="write x, y, z of this target instead of the tool pose")
    s.add_argument("--out", required=True)


def run(args) -> int:
    import numpy as np

    from calibration.kinematics import fk
    from calibration.transforms import matrix_to_quat
    from service.files import InputError, check_output, format_csv, load_model, read_joints, write_atomic

    check_output(args.out)
    model = load_model(args.model)
    if args.target is not None and args.target not in model.targets:
        known = f"one of {', '.join(sorted(model.targets))}" if model.targets else "a target, but the model has none"
        raise InputError(args.model, f"field 'targets': no target {args.target!r} (asked for by --target); "
                                     f"expected {known}")
    q = read_joints(args.joints, model)
    T = fk(model, q)
    L = model.units.length_m
    if args.target is not None:
        p = (T[:, :3, :3] @ model.targets[args.target] + T[:, :3, 3]) / L
        text = format_csv(["x", "y", "z"], p.tolist())
    else:
        quat = matrix_to_quat(T[:, :3, :3])
        text = format_csv(["x", "y", "z", "qw", "qx", "qy", "qz"], np.hstack([T[:, :3, 3] / L, quat]).tolist())
    write_atomic(args.out, text)
    return 0
