"""``recal nightly --cell CELL``: check a cell's accuracy and recalibrate it when it drifted.
``recal nightly --all [--site SITE ...]``: the same for every cell (of those sites), all at once.

Through the REST API with a ``job`` token (``RECAL_TOKEN`` or ``--token-file``): a ``verify``
session; if its RMS error exceeds the cell's ``drift_threshold`` (or ``--threshold``), a ``pose``
session (identified with the previous calibration as a prior); on a cell that had a calibration
the new one waits as a candidate, and a second ``verify`` session puts it in use when it is at
least as accurate as the current one (else exit 1, nothing recompensated); then every task file
registered with the cell compensated again. Prints one line fit for cron or a systemd timer.

Exit status: 0 the cell is within its threshold; 10 it drifted and was recalibrated;
1 a session failed, paused or timed out (a person must look); 2 bad arguments;
3 the service cannot be reached or refused the token, or the cell was recalibrated but some
targets of its task files were left as written or did not converge (as ``recal compensate``
exits 3; the line counts them and names the files and compensations whose report rows say which).

With ``--all`` (or ``--site`` alone) every cell's check runs concurrently (the fleet's workers
share them out; ``--parallel`` caps how many at once) and a summary table is printed when all
are done, then the line of each cell that needs a person. Exit status: 3 if the service could
not be reached for any cell, else 1 if any cell needs a person, else 3 if any cell's task files
have targets not compensated, else 10 if any was recalibrated, else 0.

A service that is slow to answer, busy (502/503/504) or briefly away (a busy night, an API
replica restarting) is waited for, up to each session's ``--timeout``: reads are repeated, and a
start whose answer was lost is looked up before it is sent again (a session is never started
twice). One that cannot be reached when the job starts is an error at once (exit 3).
"""

from __future__ import annotations

import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from service.client import Api, ApiError, ServiceError, transient

EXIT_OK, EXIT_RECALIBRATED, EXIT_FAILED, EXIT_USAGE, EXIT_SERVICE = 0, 10, 1, 2, 3
# recalibrated, but targets of the task files left as written or not converged: the compensate
# verbs' exit 3 (the line tells it from an unreachable service, which prints no cell line)
EXIT_SHORTFALL = 3


def add_parser(s) -> None:
    which = s.add_mutually_exclusive_group()
    which.add_argument("--cell", help="cell id or name")
    which.add_argument("--all", action="store_true", help="every cell (of the --site sites, if given)")
    s.add_argument(
        "--site",
        action="append",
        default=[],
        metavar="SITE",
        help="with --all (or alone): only the cells of this site (repeatable)",
    )
    s.add_argument(
        "--parallel",
        type=int,
        default=0,
        help="with --all: at most this many cells at once "
        "(default: every cell at once; the workers' concurrency is the real limit)",
    )
    s.add_argument("--url", default=os.environ.get("RECAL_URL", "http://127.0.0.1:8000"), help="service URL")
    s.add_argument("--token-file", help="file holding the job token (default: $RECAL_TOKEN)")
    s.add_argument("--verify-count", type=int, default=12, help="configurations of the verify session")
    s.add_argument("--count", type=int, default=30, help="configurations of the recalibration session")
    s.add_argument(
        "--threshold",
        type=float,
        help="RMS error (model length unit) beyond which to recalibrate (default: the cell's drift_threshold)",
    )
    s.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for each session")
    s.add_argument("--device", default="tracker", choices=["tracker", "cmm"])


def _find_cell(api: Api, ref: str) -> dict:
    if ref.isdigit():
        return api.call("GET", f"/cells/{ref}")
    for c in api.call("GET", "/cells"):
        if c["name"] == ref:
            return c
    raise ApiError(404, f"no cell named {ref!r}", "find cell")


def nightly(
    api: Api, cell_ref: str, *, verify_count: int, count: int, threshold: float | None, timeout_s: float, device: str
) -> tuple[int, str]:
    """Run the nightly check of one cell; returns (exit status, one-line summary)."""
    r = check_cell(
        api,
        _find_cell(api, cell_ref),
        verify_count=verify_count,
        count=count,
        threshold=threshold,
        timeout_s=timeout_s,
        device=device,
    )
    return r["status"], r["line"]


def check_cell(
    api: Api,
    cell: dict,
    *,
    verify_count: int,
    count: int,
    threshold: float | None,
    timeout_s: float,
    device: str,
    poll_s: float = 0.2,
) -> dict:
    """The nightly check of one cell: ``{"status", "line", "result", "verify_rms", "unit",
    "threshold", "calibration_id", "tasks"}``."""
    name = cell["name"]
    unit = cell["model"].get("units", {}).get("length", "")
    limit = threshold if threshold is not None else cell.get("drift_threshold")
    out = {
        "cell": name,
        "site": cell.get("site", ""),
        "unit": unit,
        "threshold": limit,
        "verify_rms": None,
        "calibration_id": None,
        "tasks": None,
    }
    v = start_session(api, cell["id"], {"kind": "verify", "count": verify_count, "device": device}, timeout_s)
    v = api.wait_session(v["id"], timeout_s, poll_s=poll_s, patient=True)
    if v["state"] != "completed":
        return _done(
            out,
            EXIT_FAILED,
            f"verify {v['state']}",
            f"{name}: verify session {v['id']} {v['state']}: {v.get('reason') or ''}".strip(),
        )
    verified = v["plan_info"]["verify"]
    rms = out["verify_rms"] = verified["rms"]
    if limit is None or rms <= limit:
        return _done(out, EXIT_OK, "accurate", _accurate_line(name, rms, limit, unit, verified))
    drifted = f"{name}: drifted (verify RMS {rms:.4g} {unit} > {limit:g})"
    p = start_session(api, cell["id"], {"kind": "pose", "count": count, "device": device}, timeout_s)
    p = api.wait_session(p["id"], timeout_s, poll_s=poll_s, patient=True)
    if p["state"] != "completed" or p.get("calibration_id") is None:
        return _done(
            out,
            EXIT_FAILED,
            f"drifted, recalibration {p['state']}",
            f"{drifted}; recalibration session {p['id']} {p['state']}: {p.get('reason') or ''}".strip(),
        )
    cal = api.call_patiently("GET", f"/calibrations/{p['calibration_id']}", deadline=time.monotonic() + timeout_s)
    out["calibration_id"] = cal["id"]
    if cal.get("status") == "candidate":  # the cell had a calibration: the new one is used once verified
        refused = _verify_candidate(api, cell, cal, verify_count, device, timeout_s, poll_s)
        if refused is not None:
            return _done(
                out,
                EXIT_FAILED,
                "drifted, recalibration not verified",
                f"{drifted} -> calibration {cal['id']} {refused}",
            )
    return _compensate_tasks(api, cell, cal, out, drifted)


def _done(out: dict, status: int, result: str, line: str) -> dict:
    return {**out, "status": status, "result": result, "line": line}


def _accurate_line(name: str, rms: float, limit: float | None, unit: str, verified: dict) -> str:
    """The line of a cell found accurate, with how many verify configurations lay outside the
    calibrated joint ranges, or outside the region of the model's residual correction."""
    lim = "no threshold set" if limit is None else f"threshold {limit:g} {unit}"
    outside = verified.get("outside_calibrated_region") or 0
    where = (
        f"; {outside} of {verified['n']} configurations outside the calibrated joint ranges (extrapolated)"
        if outside
        else ""
    )
    corr = verified.get("residual_correction") or {}
    if corr.get("outside_mapped_region"):  # the verify RMS there is the geometric model's alone
        where += (
            f"; {corr['outside_mapped_region']} of {verified['n']} outside the region its residual correction "
            f"({corr.get('family', 'map')}) was fitted in (the geometric model alone there)"
        )
    return f"{name}: accurate, verify RMS {rms:.4g} {unit} ({lim}){where}; nothing to do"


def _compensate_tasks(api: Api, cell: dict, cal: dict, out: dict, drifted: str) -> dict:
    """After a recalibration: every task file of the cell compensated with calibration ``cal``,
    and the night's outcome (``drifted``: the line's start)."""
    unit = out["unit"]
    # Not repeated: each call stores a compensation of every task file (a failure needs a person).
    tasks = api.call("POST", f"/cells/{cell['id']}/tasks/compensate?calibration_id={cal['id']}")
    failed = [t for t in tasks["tasks"] if "error" in t]
    out["tasks"] = len(tasks["tasks"]) - len(failed)
    msg = (
        f"{drifted} -> recalibrated: calibration {cal['id']}, "
        f"residual RMS {cal['rms']:.4g} {unit}; {len(tasks['tasks']) - len(failed)} task files compensated"
    )
    if failed:
        return _done(
            out,
            EXIT_FAILED,
            f"recalibrated, {len(failed)} task files failed",
            msg + f", {len(failed)} failed ({failed[0]['name']}: {failed[0]['error']})",
        )
    short = shortfalls(tasks["tasks"])
    if short:
        r = _done(out, EXIT_SHORTFALL, f"recalibrated, {short[0]} targets not compensated", msg + f"; {short[1]}")
        return {**r, "shortfall": short[0]}
    return _done(out, EXIT_RECALIBRATED, f"recalibrated (RMS {cal['rms']:.4g} {unit})", msg)


def _verify_candidate(
    api: Api, cell: dict, cal: dict, verify_count: int, device: str, timeout_s: float, poll_s: float
) -> str | None:
    """A verify session of the new calibration, which waits as a candidate (docs/service.md, "Which
    calibration is current"): None when it passed and is now the cell's current calibration, else
    why not (the task files are then left as they are, for a person to look)."""
    body = {"kind": "verify", "count": verify_count, "device": device}
    v = start_session(api, cell["id"], body, timeout_s)
    v = api.wait_session(v["id"], timeout_s, poll_s=poll_s, patient=True)
    if v["state"] != "completed":
        return f"not verified: verify session {v['id']} {v['state']}: {v.get('reason') or ''}".strip()
    verdict = (v["plan_info"]["verify"] or {}).get("candidate") or {}
    if verdict.get("passed"):
        return None
    unit = cell["model"].get("units", {}).get("length", "")
    against = verdict.get("against") or {}
    return (
        f"not put in use: verify session {v['id']} found it less accurate ({v['plan_info']['verify']['rms']:.4g} "
        f"{unit} RMS) than calibration {against.get('calibration_id')} ({against.get('rms', float('nan')):.4g} {unit}); "
        "task files not recompensated"
    )


def shortfalls(tasks: list[dict]) -> tuple[int, str] | None:
    """The targets of the recompensated task files left as written (unreachable) or not
    converged: their count and a phrase naming each file with its stored compensation (whose
    report's rows say which targets), or ``None`` when every target was compensated."""
    short = [(t, int((t.get("summary") or {}).get("not_compensated", 0))) for t in tasks if "error" not in t]
    short = [(t, n) for t, n in short if n]
    if not short:
        return None
    total = sum(n for _, n in short)
    where = ", ".join(f"{t['name']}: {n} (compensation {t['compensation_id']})" for t, n in short)
    return total, f"{total} targets not compensated ({where}; rows in GET /compensations/ID/report)"


def start_session(api: Api, cell_id: int, body: dict, timeout_s: float) -> dict:
    """Start a session on the cell. If the service does not answer, or answers that it is busy,
    the request may still have gone through: the cell's newest sessions say, before the start
    is sent again (a session is never started twice)."""
    deadline = time.monotonic() + timeout_s
    path = f"/cells/{cell_id}/sessions"
    newest = api.call_patiently("GET", f"{path}?limit=1", deadline=deadline)
    before = newest[0]["id"] if newest else 0
    lost, delay = False, 1.0  # lost: a start was sent whose outcome is unknown
    while True:
        busy = None
        try:
            return api.call("POST", path, body)
        except (ServiceError, ApiError) as exc:
            if isinstance(exc, ApiError) and exc.status == 409 and lost:
                busy = exc  # perhaps with our own start, whose answer was lost
            elif not transient(exc) or time.monotonic() + delay > deadline:
                raise
            else:
                lost = True
        mine = [
            s
            for s in api.call_patiently("GET", f"{path}?limit=5", deadline=deadline)
            if s["id"] > before and s["kind"] == body["kind"]
        ]
        if mine:
            return mine[-1]  # newest first: the first one after ours was sent
        if busy is not None:
            raise busy  # another session is driving the cell
        time.sleep(delay)
        delay = min(2 * delay, 10.0)


def nightly_fleet(api: Api, sites: list[str], *, parallel: int, **kw) -> tuple[int, str]:
    """The nightly check of every cell (of ``sites``), concurrently; (exit status, report)."""
    if sites:
        cells = [c for site in dict.fromkeys(sites) for c in api.call("GET", f"/cells?site={_quote(site)}")]
    else:
        cells = api.call("GET", "/cells")
    if not cells:
        return EXIT_OK, "no cells" + (f" in site {', '.join(sites)}" if sites else "")
    kw.setdefault("poll_s", min(5.0, 0.5 + len(cells) / 50))  # keep the polling load on the API moderate

    def one(cell: dict) -> dict:
        t0 = time.monotonic()
        try:
            r = check_cell(api, cell, **kw)
        except ServiceError as exc:
            r = {
                "cell": cell["name"],
                "site": cell.get("site", ""),
                "status": EXIT_SERVICE,
                "result": "service error",
                "line": f"{cell['name']}: {exc}",
                "verify_rms": None,
                "unit": "",
                "threshold": None,
                "calibration_id": None,
                "tasks": None,
            }
        except ApiError as exc:
            what = "busy" if exc.status == 409 else f"error {exc.status}"
            r = {
                "cell": cell["name"],
                "site": cell.get("site", ""),
                "status": EXIT_FAILED,
                "result": what,
                "line": f"{cell['name']}: {exc}",
                "verify_rms": None,
                "unit": "",
                "threshold": None,
                "calibration_id": None,
                "tasks": None,
            }
        r["seconds"] = time.monotonic() - t0
        return r

    width = len(cells) if parallel <= 0 else min(parallel, len(cells))
    with ThreadPoolExecutor(max_workers=min(width, 512), thread_name_prefix="nightly") as pool:
        results = list(pool.map(one, cells))
    return fleet_status(results), _report(results)


def fleet_status(results: list[dict]) -> int:
    """The job's exit status from its cells' results: 3 when the service could not be reached for
    any, else 1 when any needs a person, else 3 when any has targets not compensated (a cell's 3
    with ``shortfall``), else 10 when any was recalibrated, else 0."""
    statuses = {r["status"] for r in results}
    if any(r["status"] == EXIT_SERVICE and not r.get("shortfall") for r in results):
        return EXIT_SERVICE
    if EXIT_FAILED in statuses:
        return EXIT_FAILED
    if any(r.get("shortfall") for r in results):
        return EXIT_SHORTFALL
    return EXIT_RECALIBRATED if EXIT_RECALIBRATED in statuses else EXIT_OK


def _quote(s: str) -> str:
    from urllib.parse import quote

    return quote(s, safe="")


def _report(results: list[dict]) -> str:
    def fmt(v, unit=""):
        return "-" if v is None else f"{v:.4g} {unit}".strip() if isinstance(v, float) else str(v)

    rows = [("cell", "site", "verify RMS", "threshold", "result", "calibration", "tasks", "time")]
    for r in results:
        rows.append(
            (
                r["cell"],
                r["site"],
                fmt(r["verify_rms"], r["unit"]),
                fmt(r["threshold"]),
                r["result"],
                fmt(r["calibration_id"]),
                fmt(r["tasks"]),
                f"{r['seconds']:.1f} s",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    short = [r for r in results if r.get("shortfall")]
    n = {k: sum(r["status"] == k for r in results) for k in (EXIT_OK, EXIT_RECALIBRATED, EXIT_FAILED, EXIT_SERVICE)}
    lines.append("")
    lines.append(
        f"{len(results)} cells: {n[EXIT_OK]} accurate, {n[EXIT_RECALIBRATED] + len(short)} recalibrated"
        + (f" ({len(short)} with targets not compensated)" if short else "")
        + f", {n[EXIT_FAILED] + n[EXIT_SERVICE] - len(short)} need a person"
    )
    for r in results:
        if r["status"] in (EXIT_FAILED, EXIT_SERVICE):  # a shortfall's line names its targets
            lines.append("  " + r["line"])
    return "\n".join(lines)


def run(args) -> int:
    token = os.environ.get("RECAL_TOKEN", "")
    if args.token_file:
        try:
            with open(args.token_file, encoding="utf-8") as f:
                token = f.read().strip()
        except OSError as exc:
            print(f"recal nightly: --token-file {args.token_file}: {exc.strerror}", file=sys.stderr)
            return EXIT_USAGE
    if not token:
        print("recal nightly: no token: set RECAL_TOKEN or pass --token-file (a `job` token)", file=sys.stderr)
        return EXIT_USAGE
    if args.cell is None and not args.all and not args.site:
        print("recal nightly: say which cells: --cell CELL, --all, or --site SITE", file=sys.stderr)
        return EXIT_USAGE
    api = Api(args.url, token)
    try:
        if args.cell is not None:
            if args.site:
                print("recal nightly: --site goes with --all, not --cell", file=sys.stderr)
                return EXIT_USAGE
            status, line = nightly(
                api,
                args.cell,
                verify_count=args.verify_count,
                count=args.count,
                threshold=args.threshold,
                timeout_s=args.timeout,
                device=args.device,
            )
        else:
            status, line = nightly_fleet(
                api,
                args.site,
                parallel=args.parallel,
                verify_count=args.verify_count,
                count=args.count,
                threshold=args.threshold,
                timeout_s=args.timeout,
                device=args.device,
            )
    except ServiceError as exc:
        print(f"recal nightly: {exc}", file=sys.stderr)
        return EXIT_SERVICE
    except ApiError as exc:
        print(f"recal nightly: {exc}", file=sys.stderr)
        return EXIT_FAILED
    print(line)
    return status
