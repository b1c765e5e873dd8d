"""``recal predict --model MODEL.json --joints JOINTS.csv [--target NAME] --out PRED.csv [--uncertainty]``"""

from __future__ import annotations

UNCERTAINTY_COLUMNS = ["sigma_x", "sigma_y", "sigma_z", "u95"]
# with the tool pose (no --target), the orientation's too (issue 25: a position-only fit's
# orientation came without one, and was 4 deg off on a real UR10)
ORIENTATION_COLUMNS = ["r95"]


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="model file or library robot name")
    s.add_argument("--joints", required=True, help="CSV with q1..qN")
    s.add_argument("--target", help="write x, y, z of this target instead of the tool pose")
    s.add_argument("--out", required=True)
    s.add_argument(
        "--payload",
        metavar="KG[,X,Y,Z]",
        help="the task's payload for a compliant model: mass (kg) and centre of gravity in the tool frame "
        "(model length unit); rows of JOINTS.csv with payload_kg columns carry their own",
    )
    s.add_argument(
        "--uncertainty",
        action="store_true",
        help="append sigma_x, sigma_y, sigma_z (standard uncertainty per axis) and u95 (95 %% radius) of "
        "the predicted position, in the model's length unit, from the covariance an identified "
        "model stores, or inside a residual correction's region from its cross-validated error "
        "(the model's own uncertainty; the instrument's noise is not included); "
        "without --target also r95, a 95 %% bound on the tool orientation's rotation angle error, in the "
        "model's angle unit (held parameters at their prior width: a position-only fit's orientation)",
    )


def run(args) -> int:
    import numpy as np

    from calibration.compliance import with_payload
    from calibration.kinematics import fk
    from calibration.transforms import matrix_to_quat
    from service.cli import Fail, progress
    from service.files import (
        InputError,
        check_output,
        format_csv,
        load_model,
        parse_payload,
        read_joints,
        read_payload,
        read_table,
        write_atomic,
    )

    check_output(args.out)
    model = load_model(args.model)
    if args.target is not None and args.target not in model.targets:
        known = f"one of {', '.join(sorted(model.targets))}" if model.targets else "a target, but the model has none"
        raise InputError(
            args.model, f"field 'targets': no target {args.target!r} (asked for by --target); expected {known}"
        )
    if args.uncertainty:
        _stored_covariance(args.model, model)
    if args.payload is not None:
        try:
            model = with_payload(model, parse_payload(args.payload, model))
        except ValueError as exc:
            raise Fail(str(exc)) from None
    progress(f"reading {args.joints} ...")
    table = read_table(args.joints)
    q = read_joints(args.joints, model, table)
    progress(f"predicting {len(q)} configurations{' with their uncertainty' if args.uncertainty else ''} ...")
    payload = read_payload(table, model)  # per row, where the CSV gives it
    T = fk(model, q, payload)
    flags = _residual_map(args, model, q, T)
    L = model.units.length_m
    if args.target is not None:
        p = (T[:, :3, :3] @ model.targets[args.target] + T[:, :3, 3]) / L
        header, rows = ["x", "y", "z"], p
    else:
        quat = matrix_to_quat(T[:, :3, :3])
        header, rows = ["x", "y", "z", "qw", "qx", "qy", "qz"], np.hstack([T[:, :3, 3] / L, quat])
    if args.uncertainty:
        header, rows = (
            header + UNCERTAINTY_COLUMNS,
            np.hstack([rows, _uncertainty(model, q, args.target, payload)]),
        )
        if args.target is None:
            header, rows = header + ORIENTATION_COLUMNS, np.hstack([rows, _orientation_bound(model, q, payload)])
    rows = rows.tolist()
    outside = _outside_calibrated_region(args, model, q)
    if outside is not None and (args.uncertainty or (flags is not None and outside.any())):
        # with --uncertainty the bounds are marked where the identification's data never tested
        # them (a column of its own, whatever the rows: a CSV's shape does not depend on its data)
        flags = flags or [""] * len(rows)
        flags = [
            ";".join(x for x in (f, "outside_calibrated_region" if o else "") if x) for f, o in zip(flags, outside)
        ]
    if flags is not None:  # where a residual map applied, and where the prediction extrapolates
        header, rows = header + ["flags"], [r + [f] for r, f in zip(rows, flags)]
    progress(f"writing {args.out} ...")
    write_atomic(args.out, format_csv(header, rows))
    return 0


def _outside_calibrated_region(args, model, q):
    """(N,) bool: the rows outside the joint ranges an identified model's data covered (None for
    a model that records none); said on stderr, since there the prediction (and the bounds of
    ``--uncertainty``, which the identification's data never tested) is an extrapolation: the
    same UR10 identified on one series was 1.5 mm off on another with disjoint ranges, its 95 %
    bounds covering 23 % of those errors."""
    import sys

    import numpy as np

    from calibration.metrics import outside_joint_ranges
    from service.files import InputError
    from service.task_compensation import CompensationInputError, calibrated_range_of

    try:
        ranges = calibrated_range_of(model)
    except CompensationInputError as exc:
        raise InputError(args.model, str(exc)) from None
    if ranges is None:
        return None
    outside = outside_joint_ranges(q, ranges)
    if outside.any():
        first = ", ".join(str(int(i) + 1) for i in np.flatnonzero(outside)[:10])
        print(
            f"warning: {int(outside.sum())} of {len(q)} configurations lie outside the joint ranges the "
            f"identification measured (rows {first}{', ...' if outside.sum() > 10 else ''}): there the prediction "
            "is extrapolated and its uncertainty not covered (with --uncertainty: flagged outside_calibrated_region)",
            file=sys.stderr,
        )
    return outside


def _stored_covariance(path, model):
    """Check, before any output, that the model stores what ``--uncertainty`` needs."""
    from calibration.uncertainty import (
        CovarianceError,
        correction_sigma_from_model,
        covariance_from_block,
        orientation_from_block,
        structure_sigma_from_block,
    )
    from service.files import InputError

    try:
        covariance_from_block(model)
        structure_sigma_from_block(model)
        if model.metadata.get("residual_map") is not None:  # inside its region the bound is its CV error
            correction_sigma_from_model(model)
        orientation_from_block(model)
    except CovarianceError as exc:
        raise InputError(path, f"field {exc.field!r}: {exc} (needed by --uncertainty)") from None


def _uncertainty(model, q, target, payload=None):
    """(N, 4) sigma_x, sigma_y, sigma_z, u95 of the predicted position, model length unit."""
    import numpy as np

    from calibration.uncertainty import radius_95, stored_position_covariance

    C = stored_position_covariance(model, q, target, payload)
    sigma = np.sqrt(np.maximum(np.diagonal(C, axis1=1, axis2=2), 0.0))
    return np.hstack([sigma, radius_95(C)[:, None]]) / model.units.length_m


def _orientation_bound(model, q, payload=None):
    """(N, 1) r95: a 95 % bound on the rotation angle of the tool orientation's error, model angle
    unit (the largest principal axis of its covariance times sqrt(chi2_3(0.95)), as u95)."""
    from calibration.uncertainty import radius_95, stored_orientation_covariance

    return (radius_95(stored_orientation_covariance(model, q, payload)) / model.units.angle_rad)[:, None]


def _residual_map(args, model, q, T):
    """Apply the model's residual correction (whatever its family: a smooth map, book §5.4; joint
    transmission errors; boosted trees) to the tool poses ``T`` (N, 4, 4) in place (a translation
    of the tool frame, computed at the ``--target`` point when one is asked for); the per-row flags (``outside_mapped_region`` where it does not
    apply), or None for a model without a map."""
    import numpy as np

    from calibration.residual_map import ResidualMapError, from_model
    from service.files import InputError

    try:
        rmap = from_model(model)
    except ResidualMapError as exc:
        raise InputError(args.model, f"field {exc.field!r}: {str(exc).split(': ', 1)[-1]}") from None
    if rmap is None:
        return None
    # a transmission correction moves each point by its own amount: the one asked for (--target)
    p_tool = model.targets[args.target] if args.target is not None else None
    corr, inside = rmap.evaluate(q, p_tool)
    T[:, :3, 3] += corr
    return np.where(inside, "", "outside_mapped_region").tolist()
