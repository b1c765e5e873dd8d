"""Controller backups compensated: a folder (``recal compensate --task DIR --out OUTDIR``) or a
zip of one (``POST /api/v1/calibrations/{id}/compensate-backup``). Every program the backup holds
(service.programs.backup) is compensated as ``--task PROGRAM`` compensates it, every other file
copied byte for byte, the layout kept; one report, a row per target and a summary per file.

A zip is opened defensively (it comes from the network): an entry whose name is absolute or
climbs out of the folder (``..``), an encrypted one, or a total uncompressed size beyond the
input bound (``RECAL_MAX_INPUT_BYTES``, service.files) refuses the whole zip before anything is
written, so neither a zip-slip nor a zip bomb reaches the disk.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from calibration.errors import RecalError

from .files import write_atomic
from .programs import backup
from .task_compensation import CompensationRequest, NoTargetsError, compensate_task

# The report's name in a compensated zip, beside the backup's own top-level entries.
REPORT_NAME = "recal-compensation-report.json"


@dataclass(frozen=True)
class BackupResult:
    """``layout`` (kuka, abb, fanuc), the ``report`` document, the programs and points
    compensated, and ``short``: one line per program with targets not compensated (exit 3)."""

    layout: str
    report: dict
    programs: int
    points: int
    short: list[str]

    @property
    def not_compensated(self) -> int:
        return int(sum((f.get("summary") or {}).get("not_compensated", 0) for f in self.report["files"]))


def compensate_folder(
    root: Path, out: Path, model, request: Callable[[backup.Job, Path], CompensationRequest], config_dat=None
) -> BackupResult:
    """Compensate the backup folder ``root`` into ``out`` (new or empty). ``request(job, out_path)``
    gives each program's :class:`CompensationRequest` (the caller's models, settings and frames).
    Nothing is written unless every program could be read (the first refusal is raised)."""
    try:
        layout, jobs = backup.plan(root, config_dat)
    except ValueError as exc:
        raise NotABackup(str(exc)) from None
    results = []
    for job in jobs:
        try:
            results.append((job, compensate_task(model, request(job, out / job.rel))))
        except NoTargetsError as exc:  # a program without targets (a KUKA cell.src): copied as it is
            results.append((job, exc.report or {"summary": {"points": 0}, "uninterpreted": []}))
    shutil.copytree(root, out, dirs_exist_ok=True)  # every byte that is no target's number
    points, files, short = [], [], []
    for job, result in results:
        if isinstance(result, dict):
            files.append(
                {
                    "file": str(job.rel),
                    "summary": result.get("summary"),
                    "uninterpreted": result.get("uninterpreted", []),
                }
            )
            continue
        for path, data in result.outputs:
            write_atomic(path, data)
        doc = result.report()
        rel = {str(job.path): str(job.rel), str(job.path.with_suffix(".dat")): str(job.rel.with_suffix(".dat"))}
        for p in doc["points"] + doc["uninterpreted"]:
            p["file"] = rel.get(p.get("file", str(job.path)), p.get("file", str(job.rel)))
        points += doc["points"]
        files.append({"file": str(job.rel), "summary": doc["summary"], "uninterpreted": doc["uninterpreted"]})
        if result.shortfall():
            short.append(f"{job.rel}: {result.shortfall()}")
    report = {
        "format": "recal.compensation-report/1",
        "task": str(root),
        "layout": layout,
        "files": files,
        "points": points,
    }
    n = sum(len(r.comp) for _, r in results if not isinstance(r, dict))
    return BackupResult(layout, report, len(results), n, short)


def with_frame_data(frames, job: backup.Job, root: Path):
    """``frames`` with a Fanuc job's user and tool frames from the backup's frame data
    (``SYSFRAME.VA``): numbers the options give stay the options'. A file that cannot be read
    is a ``ValueError`` naming it (its path in the backup)."""
    from dataclasses import replace

    from .programs.fanuc_frames import read_frame_data

    if not job.frame_data:
        return frames
    tools, bases = {}, {}
    for path in job.frame_data:
        p = Path(path)
        data = read_frame_data(p.read_bytes().decode("utf-8", "replace"), str(p.relative_to(root)))
        tools.update(data["tools"])
        bases.update(data["bases"])
    return replace(frames, tools={**tools, **frames.tools}, bases={**bases, **frames.bases})


class NotABackup(RecalError, ValueError):
    """A folder that holds none of the three backups' programs."""


class UnsafeZip(RecalError, ValueError):
    """A zip refused before anything of it is written; ``too_large``: beyond the input bound."""

    def __init__(self, message: str, too_large: bool = False):
        super().__init__(message)
        self.too_large = too_large

    def __reduce__(self):  # raised in a worker process, re-raised in the API's with its flag
        return (UnsafeZip, (str(self), self.too_large))


def _safe_name(name: str) -> PurePosixPath:
    """An entry's path inside the folder, or :class:`UnsafeZip` for one that could land outside
    it (absolute, a drive, ``..``); backslashes count as separators (zips written on Windows)."""
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or (p.parts and p.parts[0].endswith(":")) or ".." in p.parts:
        raise UnsafeZip(f"zip entry {name!r}: an absolute path or '..' (it would be written outside the backup)")
    return p


def unpack_zip(data: bytes, dest: Path, limit: int) -> list[str]:
    """Write the zip ``data`` under ``dest`` after checking every entry (module docstring); the
    entries' names in order. ``limit``: the bound on the total uncompressed size (bytes)."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, OSError) as exc:
        raise UnsafeZip(f"expected a zip of a controller backup: {exc}") from None
    with zf:
        infos = zf.infolist()
        total = 0
        for info in infos:
            _safe_name(info.filename)
            if info.flag_bits & 0x1:
                raise UnsafeZip(f"zip entry {info.filename!r} is encrypted")
            total += info.file_size  # zipfile reads no more than this per entry
        if total > limit:
            raise UnsafeZip(
                f"the zip unpacks to {total} bytes, beyond the input bound of {limit} bytes (RECAL_MAX_INPUT_BYTES)",
                too_large=True,
            )
        for info in infos:
            target = dest / _safe_name(info.filename)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                target.write_bytes(zf.read(info))
            except (zipfile.BadZipFile, OSError, RuntimeError) as exc:  # a bad CRC, a truncated entry
                raise UnsafeZip(f"zip entry {info.filename!r}: {exc}") from None
        return [i.filename for i in infos]


def pack_zip(root: Path, names: list[str], extra: dict[str, bytes]) -> bytes:
    """The folder ``root`` as a zip whose entries are ``names`` in their order (the uploaded
    zip's), plus ``extra`` (name -> bytes)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in names:
            path = root / _safe_name(name)
            if name.endswith("/") or path.is_dir():
                zf.writestr(zipfile.ZipInfo(name), b"")
            else:
                zf.writestr(name, path.read_bytes())
        for name, data in extra.items():
            zf.writestr(name, data)
    return buf.getvalue()


def report_bytes(result: BackupResult) -> bytes:
    return (json.dumps(result.report, indent=1) + "\n").encode()
