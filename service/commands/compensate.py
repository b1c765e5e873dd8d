"""``recal compensate --model MODEL.json --task TASK.csv --out OUT.csv [--mode joints|targets] [--nominal NOMINAL.json]``

Compensated task files (contracts §5), from an identified model:

- task CSV, ``joints`` mode: ``q1..qN`` replaced by the commands that bring the identified robot
  to each row's pose (rows with only joints: to the pose those joints gave the robot they were
  taught or planned on);
- task CSV, ``targets`` mode: ``x..qz`` replaced by the targets a controller that knows only the
  nominal model must be sent (in the nominal model's world frame: for a library robot, its base
  frame);
- URScript program (``.script``/``.urscript``): pose targets rewritten for the nominal controller,
  joint targets rewritten as joint commands, every other byte kept; lines that cannot be
  interpreted are reported (stderr and ``--report``), not guessed;
- ABB RAPID (``.mod``/``.modx``/``.prg``), KUKA KRL (``.src`` with its ``.dat``) and Fanuc TP
  (``.ls``) programs, the same way (``service.programs``): Cartesian targets for the nominal
  controller in their written configuration, joint targets as joint commands.

The nominal model is ``--nominal`` or the one the identified model records
(``identification.controller``, a UR cell's controller model, written by the service; else
``identification.nominal``, written by ``recal identify``); in joints mode without one, rows
without joints start from the identified model's own inverse kinematics. Robots without a
closed-form inverse use the numerical one (``calibration.ik.numerical_ik``: from the row's joints
or ``--qnear``, the previous row's solution, seeds over the joint limits). See
docs/compensation.md.
"""

from __future__ import annotations

import json
import re
import sys

import numpy as np


def add_parser(s) -> None:
    s.add_argument("--model", required=True, help="identified model (recal.model/1)")
    _add_task_options(s)
    _add_output_and_model_options(s)
    _add_solver_options(s)


def _add_task_options(s) -> None:
    """The task file or program, its format, and the frames and modules a program refers to."""
    s.add_argument(
        "--task",
        required=True,
        help="task CSV (docs/contracts.md §5) or robot program: URScript (.script, "
        ".urscript), ABB RAPID (.mod, .modx, .prg, .sys), KUKA KRL (.src, with its .dat beside it), Fanuc TP (.ls); "
        "or a controller backup folder (KUKA archive, ABB backup, folder of .ls): --out is then a new folder",
    )
    s.add_argument(
        "--format",
        choices=["csv", "urscript", "rapid", "krl", "fanuc-tp"],
        help="the task file's format (default: from its extension)",
    )
    s.add_argument(
        "--tool-frame",
        action="append",
        metavar="[N=]X,Y,Z,A,B,C",
        help="KRL/TP: a tool frame in the "
        "flange (mm; KUKA A,B,C or Fanuc W,P,R in degrees); N= numbers it (TOOL_DATA[N], UT N), without "
        "it the tool active when the program starts (KRL) or of every target (TP). Repeatable",
    )
    s.add_argument(
        "--base-frame",
        action="append",
        metavar="[N=]X,Y,Z,A,B,C",
        help="KRL/TP: a base (user) frame in the robot's base frame, as --tool-frame (BASE_DATA[N], UF N). Repeatable",
    )
    s.add_argument(
        "--config-dat",
        metavar="$config.dat",
        help="KRL: the controller's $config.dat, whose "
        "TOOL_DATA[N] and BASE_DATA[N] give the frames the program selects",
    )
    s.add_argument(
        "--module",
        action="append",
        metavar="MODULE",
        help="RAPID: another module of the task (a system module, a data module) whose tooldata and "
        "wobjdata the program's moves use; read, not rewritten. Repeatable",
    )
    s.add_argument(
        "--work-object",
        action="append",
        metavar="NAME=X,Y,Z,Q1,Q2,Q3,Q4",
        help="RAPID: a wobjdata the program uses but no module declares (its user and object frames in one: "
        "mm and a quaternion). Repeatable; RAPID's --tool-frame is NAME=X,Y,Z,Q1,Q2,Q3,Q4 likewise",
    )


def _add_output_and_model_options(s) -> None:
    """What is written, and the models and conditions besides the identified one."""
    s.add_argument("--out", required=True, help="compensated task file to write")
    s.add_argument(
        "--mode",
        choices=["joints", "targets"],
        default="joints",
        help="CSV: replace q1..qN (joints, default) or x..qz for a nominal controller (targets)",
    )
    s.add_argument(
        "--nominal", help="the nominal model the controller uses (default: the one the identified model records)"
    )
    s.add_argument(
        "--taught-on",
        metavar="MODEL",
        help="identified model of the robot the task's joint vectors were "
        "taught on, same world frame (default: they were planned on the nominal model)",
    )
    s.add_argument("--report", help="per-point report to write (JSON)")
    s.add_argument(
        "--payload",
        metavar="KG[,X,Y,Z]",
        help="the task's payload, for a compliant model: mass (kg) and centre of gravity in the tool frame "
        "(model length unit)",
    )
    s.add_argument(
        "--calibration-data",
        metavar="MEAS.csv",
        help="the identification measurements: their joint "
        "ranges are the calibrated region (default: the ranges the identified model records)",
    )


def _add_solver_options(s) -> None:
    """How the inverse kinematics chooses and judges each row's commands."""
    s.add_argument(
        "--qnear",
        help="comma-separated joints (model units) that choose the branch of rows without "
        "q1..qN (default: all zero): the solution nearest it is taken, as UR's get_inverse_kin does; "
        "for robots without a closed form it is also where the numerical inverse kinematics starts",
    )
    s.add_argument("--tolerance", type=float, help="position residual to reach, model length unit (default 1e-9 m)")
    s.add_argument(
        "--singular-tol",
        type=float,
        default=0.02,
        help="near_singular below this smallest dimensionless singular value of the Jacobian (default 0.02)",
    )
    s.add_argument(
        "--max-correction",
        type=float,
        help="branch_change above this joint correction, model angle unit (default 5 degrees)",
    )


# ----------------------------------------------------------------------------- models


def _models(args):
    from calibration.model import ModelFormatError, model_from_dict
    from service.cli import Fail
    from service.files import load_model

    model = load_model(args.model)
    if args.payload is not None:  # a compliant model sags under it (a rigid one ignores it)
        from calibration.compliance import with_payload
        from service.files import parse_payload

        try:
            model = with_payload(model, parse_payload(args.payload, model))
        except ValueError as exc:
            raise Fail(str(exc)) from None
    nominal = None
    if args.nominal:
        nominal = load_model(args.nominal)
    else:
        # a UR cell's calibration records its controller's own model (issue 16): that, not the
        # published table, is what the controller computes with
        ident = model.metadata.get("identification") or {}
        key = "controller" if ident.get("controller") is not None else "nominal"
        doc = ident.get(key)
        if doc is not None:
            try:
                nominal = model_from_dict(doc)
            except ModelFormatError as exc:
                raise Fail(
                    f"{args.model}: field 'identification.{key}.{exc.field}': {str(exc).split(': ', 1)[-1]}"
                ) from None
    taught = load_model(args.taught_on) if args.taught_on else None
    for m, what in ((nominal, args.nominal or "identification.nominal"), (taught, args.taught_on)):
        if m is not None and m.n_joints != model.n_joints:
            raise Fail(f"{what}: has {m.n_joints} joints, the identified model {model.n_joints}")
    return model, nominal, taught


def published_table_warning(args, fmt: str, model, nominal) -> str | None:
    """The one line (stderr) when a UR arm's program is compensated against a published DH table: a
    UR controller computes with its own factory calibration (up to about 1 mm from the table), and
    the page and the API use it where the cell keeps it (service.controller.controller_nominal).
    The controller model comes from ``--nominal`` or from the calibration (``identification.controller``,
    written by the service for a cell that had one); without either, this names the table assumed."""
    from calibration import robots

    if fmt == "csv" and args.mode == "joints":
        return None  # the desired poses are reached by the identified model; no controller in between
    if nominal is None or args.nominal or (model.metadata.get("identification") or {}).get("controller") is not None:
        return None  # without a nominal, what needs one is refused where it is needed
    ur = next((n for n in (nominal.name, model.name) if robots.is_ur(n)), None)
    if ur is None:
        return None
    what = f"{nominal.name} (identification.nominal), UR's published DH table of the {ur.lower().split('-')[0]}"
    return (
        f"warning: {args.model}: no controller model (no --nominal, no identification.controller): compensating "
        f"against {what}, not the kinematics the controller computes with (its factory calibration, up to about "
        f"1 mm apart); give --nominal CONTROLLER.json (`recal controller-model --rtde HOST`, or the cell's "
        f"GET /api/v1/cells/ID/controller-model)"
    )


def _calibrated_range(args, model):
    """(n, 2) joint ranges of the calibration data (``--calibration-data``), else the ones the
    identified model records, SI, or None."""
    from service.cli import Fail
    from service.files import read_joints
    from service.task_compensation import CompensationInputError, calibrated_range_of

    if args.calibration_data:
        q = read_joints(args.calibration_data, model)
        return np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
    try:
        return calibrated_range_of(model)
    except CompensationInputError as exc:
        raise Fail(f"{args.model}: {exc}") from None


def _settings(args, model):
    from service.cli import Fail

    u = model.units
    kw = {"singular_tol": args.singular_tol}
    if args.tolerance is not None:
        if not args.tolerance > 0:
            raise Fail(f"--tolerance: expected a positive number, got {args.tolerance}")
        kw["position_tol_m"] = args.tolerance * u.length_m
        kw["rotation_tol_rad"] = args.tolerance * u.length_m  # per metre of reach
    if args.max_correction is not None:
        if not args.max_correction > 0:
            raise Fail(f"--max-correction: expected a positive number, got {args.max_correction}")
        kw["max_correction_rad"] = args.max_correction * u.angle_rad
    qnear = np.zeros(model.n_joints)
    if args.qnear:
        try:
            vals = [float(v) for v in args.qnear.split(",")]
        except ValueError:
            raise Fail(f"--qnear: expected {model.n_joints} comma-separated numbers, got {args.qnear!r}") from None
        if len(vals) != model.n_joints:
            raise Fail(f"--qnear: expected {model.n_joints} numbers, got {len(vals)}")
        qnear = np.array([v * (u.angle_rad if j.revolute else u.length_m) for v, j in zip(vals, model.joints)])
    return kw, qnear


# ----------------------------------------------------------------------------- running


def _frames(args):
    """``--tool-frame``, ``--base-frame`` and ``--config-dat`` for the program parsers."""
    from service.cli import Fail
    from service.programs.frames import Frames

    try:
        return Frames.from_options(
            args.tool_frame or [],
            args.base_frame or [],
            args.config_dat,
            modules=args.module or [],
            rapid=args.fmt == "rapid",
            wobjs=args.work_object or [],
        )
    except ValueError as exc:
        raise Fail(str(exc)) from None


# Lines that only one of the formats writes: what a file looks like, when --format (or its
# extension) says otherwise. Each marker is matched at the start of a line (after blanks).
_MARKERS = {
    "urscript": re.compile(r"^\s*(movel|movej|movep|movec|servoj|set_tcp)\s*\(|^\s*def\s+\w+\s*\(\s*\)\s*:", re.M),
    "rapid": re.compile(r"^\s*(%%%|MODULE\s+\w+|ENDMODULE\b|(CONST|PERS|VAR)\s+robtarget\b|Move[LJC]\s+\w)", re.M),
    "krl": re.compile(r"^\s*(&ACCESS\b|DEF\s+\w+\s*\(|DEFDAT\b|(PTP|LIN|CIRC)\s+[{\w])", re.M),
    "fanuc-tp": re.compile(r"^\s*/(PROG|MN|POS|ATTR|END)\b", re.M),
}
_NAMES = {
    "csv": "a task CSV",
    "urscript": "a URScript program",
    "rapid": "an ABB RAPID program",
    "krl": "a KUKA KRL program",
    "fanuc-tp": "a Fanuc TP program",
}


def looks_like(text: str) -> str | None:
    """The program language ``text`` is written in, by the lines only that language writes
    (None when no language's lines are there, or two are equally there)."""
    counts = {fmt: len(pattern.findall(text)) for fmt, pattern in _MARKERS.items()}
    best = max(counts, key=counts.get)
    ranked = sorted(counts.values(), reverse=True)
    return best if ranked[0] > 0 and ranked[0] > ranked[1] else None


def check_format(path, fmt: str, given: str | None) -> None:
    """Refuse a task file whose content is plainly another language than the one it is read as
    (``--format rapid`` on a URScript program found "no move target" before): say so, and how
    to read it."""
    from pathlib import Path

    from service.cli import Fail

    p = Path(path)
    if not p.is_file():
        return  # a controller backup folder, or a missing file: reported where it is read
    with open(p, encoding="utf-8", errors="replace") as f:
        text = f.read(1 << 20)  # the language shows in its first lines
    seen = looks_like(text)
    if seen is None or seen == fmt or _MARKERS.get(fmt, re.compile("(?!)")).search(text):
        return
    how = f"--format {fmt}" if given else f"its extension {p.suffix or '(none)'}"
    raise Fail(
        f"{path}: looks like {_NAMES[seen]}, not {_NAMES[fmt]} (read as such because of {how}); "
        f"give --format {seen}" + (" or leave --format out" if given else "")
    )


def run(args) -> int:
    from pathlib import Path

    from service.cli import progress
    from service.files import InputError, check_output, write_atomic
    from service.programs import format_of
    from service.task_compensation import CompensationRequest, NoTargetsError, compensate_task

    if Path(args.task).is_dir():
        return _run_backup(args)
    fmt = format_of(args.task, getattr(args, "format", None), text=_head_of(args.task))
    check_format(args.task, fmt, getattr(args, "format", None))
    if fmt == "csv" and str(args.task).lower().endswith(".dat"):
        raise InputError(
            args.task,
            "a KRL program is compensated from its .src (the .dat beside it is read and "
            "written with it): give --task PROGRAM.src",
        )
    for path in (args.out, args.report):  # before any work: a run never ends unable to write
        if path:
            check_output(path)
    args.fmt = fmt
    if fmt != "rapid" and (args.module or args.work_object):
        from service.cli import Fail

        raise Fail(f"--module and --work-object are for RAPID programs; {args.task} is read as {fmt}")
    model, nominal, taught = _models(args)
    kw, qnear = _settings(args, model)
    req = CompensationRequest(
        task=args.task,
        out=args.out,
        model_label=args.model,
        fmt=fmt,
        mode=args.mode,
        nominal=nominal,
        taught=taught,
        calibrated=_calibrated_range(args, model),
        settings=kw,
        qnear=qnear,
        frames=_frames(args) if fmt not in ("csv", "urscript") else None,
        report=bool(args.report),
    )
    try:
        result = compensate_task(model, req, progress=progress)
    except NoTargetsError as exc:
        if args.report and exc.report is not None:  # the report says which lines were left alone, and why
            write_atomic(args.report, json.dumps(exc.report, indent=1) + "\n")
        raise
    if args.report:
        write_atomic(args.report, result.report_text())
    for path, data in result.outputs:
        write_atomic(path, data)
    for s in result.skipped:
        print(
            f"warning: {s.get('file', args.task)}, line {s['line']}: not compensated ({s['reason']}): {s['text']}",
            file=sys.stderr,
        )
    warning = published_table_warning(args, fmt, model, nominal)
    if warning:  # after the work: bad input stays one line
        print(warning, file=sys.stderr)
    summary = result.summary
    for note in summary["notes"]:
        print(f"note: {note}", file=sys.stderr)
    flagged = ", ".join(f"{k} {v}" for k, v in summary["flags"].items() if v)
    label = {"urscript": "URScript", "rapid": "RAPID", "krl": "KRL", "fanuc-tp": "Fanuc TP"}.get(fmt)
    print(
        f"compensated {len(result.comp)} points ({label or args.mode + ' mode'}): "
        f"{summary['converged']} converged, residual max {_shown(summary['residual_max'])} {model.units.length}"
        + (f"; flagged: {flagged}" if flagged else "")
        + f"; wrote {', '.join(str(p) for p, _ in result.outputs)}"
    )
    short = result.shortfall()
    if short:  # written, but not everything asked was done: exit 3, naming what (contracts §6)
        print(f"recal compensate: {short}" + (f" (rows in {args.report})" if args.report else ""), file=sys.stderr)
        return 3
    return 0


def _run_backup(args) -> int:
    """``--task DIR --out OUTDIR``: every program of a controller backup compensated
    (service.backups), every other file copied, the same layout; one report (a row per
    target, a summary per file). Nothing is written unless every program could be read."""
    from dataclasses import replace
    from pathlib import Path

    from service.backups import NotABackup, compensate_folder, report_bytes, with_frame_data
    from service.cli import Fail
    from service.files import write_atomic
    from service.task_compensation import CompensationRequest

    root, out = Path(args.task), Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise Fail(f"--out {args.out}: expected a new or empty folder for the compensated backup")
    model, nominal, taught = _models(args)
    kw, qnear = _settings(args, model)

    def request(job, out_path):
        args.fmt, args.module = job.fmt, list(job.modules)
        frames = replace(_frames(args), config_dat=job.config_dat) if job.fmt == "krl" else _frames(args)
        try:
            frames = with_frame_data(frames, job, root)
        except ValueError as exc:
            raise Fail(str(exc)) from None
        return CompensationRequest(
            task=str(job.path),
            out=str(out_path),
            model_label=args.model,
            fmt=job.fmt,
            mode=args.mode,
            nominal=nominal,
            taught=taught,
            calibrated=_calibrated_range(args, model),
            settings=kw,
            qnear=qnear,
            frames=frames,
            report=True,
        )

    try:
        result = compensate_folder(root, out, model, request, args.config_dat)
    except NotABackup as exc:
        raise Fail(f"--task {args.task}: {exc}") from None
    if args.report:
        write_atomic(args.report, report_bytes(result).decode())
    print(f"compensated {result.programs} programs ({result.layout} backup), {result.points} points; wrote {out}")
    for line in result.short:
        print(f"recal compensate: {line}", file=sys.stderr)
    return 3 if result.short else 0


def _head_of(path) -> str | None:
    """The start of the task file's text, to tell its format when its extension says nothing
    (``None`` where it cannot be read: the parser reports that)."""
    try:
        with open(path, "rb") as f:
            return f.read(1 << 16).decode("utf-8", "replace")
    except OSError:
        return None


def _shown(v: float | None) -> str:
    """A figure for the summary line; ``None`` where the report holds no finite number."""
    return "n/a" if v is None else f"{v:.3g}"
