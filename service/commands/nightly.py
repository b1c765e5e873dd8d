"""``recal nightly --cell CELL``: check a cell's accuracy and recalibrate it when it drifted.

Through the REST API with a ``job`` token (``RECAL_TOKEN`` or ``--token-file``): a ``verify``
session; if its RMS error exceeds the cell's ``drift_threshold`` (or ``--threshold``), a ``pose``
session (identified with the previous calibration as a prior), then every task file registered
with the cell compensated again. Prints one line fit for cron or a systemd timer.

Exit status: 0 the cell is within its threshold; 10 it drifted and was recalibrated;
1 a session failed, paused or timed out (a person must look); 2 bad arguments;
3 the service cannot be reached or refused the token.
"""

from __future__ import annotations

import os
import sys

from service.client import Api, ApiError, ServiceError

EXIT_OK, EXIT_RECALIBRATED, EXIT_FAILED, EXIT_USAGE, EXIT_SERVICE = 0, 10, 1, 2, 3


def add_parser(s) -> None:
    s.add_argument("--cell", required=True, help="cell id or name")
    s.add_argument("--url", default=os.environ.get("RECAL_URL", "http://127.0.0.1:8000"), help="service URL")
    s.add_argument("--token-file", help="file holding the job token (default: $RECAL_TOKEN)")
    s.add_argument("--verify-count", type=int, default=12, help="configurations of the verify session")
    s.add_argument("--count", type=int, default=30, help="configurations of the recalibration session")
    s.add_argument("--threshold", type=float, help="RMS error (model length unit) beyond which to recalibrate "
                   "(default: the cell's drift_threshold)")
    s.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for each session")
    s.add_argument("--device", default="tracker", choices=["tracker", "cmm"])


def _find_cell(api: Api, ref: str) -> dict:
    if ref.isdigit():
        return api.call("GET", f"/cells/{ref}")
    for c in api.call("GET", "/cells"):
        if c["name"] == ref:
            return c
    raise ApiError(404, f"no cell named {ref!r}", "find cell")


def nightly(api: Api, cell_ref: str, *, verify_count: int, count: int, threshold: float | None, timeout_s: float,
            device: str) -> tuple[int, str]:
    """Run the nightly check of one cell; returns (exit status, one-line summary)."""
    cell = _find_cell(api, cell_ref)
    name = cell["name"]
    unit = cell["model"].get("units", {}).get("length", "")
    limit = threshold if threshold is not None else cell.get("drift_threshold")
    v = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "verify", "count": verify_count, "device": device})
    v = api.wait_session(v["id"], timeout_s)
    if v["state"] != "completed":
        return EXIT_FAILED, f"{name}: verify session {v['id']} {v['state']}: {v.get('reason') or ''}".strip()
    rms = v["plan_info"]["verify"]["rms"]
    if limit is None or rms <= limit:
        lim = "no threshold set" if limit is None else f"threshold {limit:g} {unit}"
        return EXIT_OK, f"{name}: accurate, verify RMS {rms:.4g} {unit} ({lim}); nothing to do"
    p = api.call("POST", f"/cells/{cell['id']}/sessions", {"kind": "pose", "count": count, "device": device})
    p = api.wait_session(p["id"], timeout_s)
    if p["state"] != "completed" or p.get("calibration_id") is None:
        return EXIT_FAILED, (f"{name}: drifted (verify RMS {rms:.4g} {unit} > {limit:g}); recalibration session "
                             f"{p['id']} {p['state']}: {p.get('reason') or ''}").strip()
    cal = api.call("GET", f"/calibrations/{p['calibration_id']}")
    tasks = api.call("POST", f"/cells/{cell['id']}/tasks/compensate?calibration_id={cal['id']}")
    failed = [t for t in tasks["tasks"] if "error" in t]
    msg = (f"{name}: drifted (verify RMS {rms:.4g} {unit} > {limit:g}) -> recalibrated: calibration {cal['id']}, "
           f"residual RMS {cal['rms']:.4g} {unit}; {len(tasks['tasks']) - len(failed)} task files compensated")
    if failed:
        return EXIT_FAILED, msg + f", {len(failed)} failed ({failed[0]['name']}: {failed[0]['error']})"
    return EXIT_RECALIBRATED, msg


def run(args) -> int:
    token = os.environ.get("RECAL_TOKEN", "")
    if args.token_file:
        try:
            token = open(args.token_file, encoding="utf-8").read().strip()
        except OSError as exc:
            print(f"recal nightly: --token-file {args.token_file}: {exc.strerror}", file=sys.stderr)
            return EXIT_USAGE
    if not token:
        print("recal nightly: no token: set RECAL_TOKEN or pass --token-file (a `job` token)", file=sys.stderr)
        return EXIT_USAGE
    api = Api(args.url, token)
    try:
        status, line = nightly(api, args.cell, verify_count=args.verify_count, count=args.count,
                               threshold=args.threshold, timeout_s=args.timeout, device=args.device)
    except ServiceError as exc:
        print(f"recal nightly: {exc}", file=sys.stderr)
        return EXIT_SERVICE
    except ApiError as exc:
        print(f"recal nightly: {exc}", file=sys.stderr)
        return EXIT_FAILED
    print(line)
    return status
