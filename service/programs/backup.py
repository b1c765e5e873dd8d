"""Controller backup folders (``recal compensate --task DIR --out OUTDIR``): which files are
programs, in which language, and what each needs from the others, as the controller resolves
them.

- KUKA archive: every ``.src`` (with the ``.dat`` beside it) under the folder; the
  ``$config.dat`` found in it (``KRC/R1/System/$config.dat``) gives ``TOOL_DATA``/``BASE_DATA``
  and the globals, unless ``--config-dat`` names another.
- ABB backup: every ``.mod``/``.modx``/``.prg`` under ``RAPID/TASK*/PROGMOD``; the task's other
  modules (its ``PROGMOD`` and ``SYSMOD`` ``.mod``/``.sys``) give the tooldata and wobjdata.
- A folder of Fanuc ``.ls`` files: every ``.ls``; user and tool frames from the controller's
  frame data in the folder (``SYSFRAME.VA``, ``FRAMEVAR.VA``: service.programs.fanuc_frames),
  and from ``--base-frame``/``--tool-frame`` for numbers the frame data does not set.

Every other file is copied byte for byte; the layout of the output is the input's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

RAPID_MODULES = (".mod", ".modx", ".prg", ".sys", ".sysx")
FANUC_FRAME_FILES = ("sysframe.va", "framevar.va")


@dataclass(frozen=True)
class Job:
    """One program of the backup: ``path`` (absolute), ``rel`` (its path in the folder),
    ``fmt``, the ``config_dat`` (KRL) and ``modules`` (RAPID) it resolves its frames with."""

    path: Path
    rel: Path
    fmt: str
    config_dat: str | None = None
    modules: tuple = ()
    frame_data: tuple = ()  # Fanuc: the backup's SYSFRAME.VA / FRAMEVAR.VA


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def plan(root: Path, config_dat: str | None = None) -> tuple[str, list[Job]]:
    """The backup's layout (``"kuka"``, ``"abb"``, ``"fanuc"``) and its programs, in path order.
    Raises ``ValueError`` when the folder holds none of the three."""
    files = _files(root)
    suffix = {p: p.suffix.lower() for p in files}
    srcs = [p for p in files if suffix[p] == ".src"]
    if srcs:
        if config_dat is None:
            found = [p for p in files if p.name.lower() == "$config.dat"]
            config_dat = str(found[0]) if found else None
        return "kuka", [Job(p, p.relative_to(root), "krl", config_dat) for p in srcs]
    progs = [p for p in files if suffix[p] in RAPID_MODULES[:3] and "progmod" in (q.lower() for q in p.parts)]
    if progs:
        jobs = []
        for p in progs:
            task = next(q for q in p.parents if q.name.lower() == "progmod").parent
            others = [str(q) for q in _files(task) if suffix.get(q) in RAPID_MODULES and q != p]
            jobs.append(Job(p, p.relative_to(root), "rapid", None, tuple(others)))
        return "abb", jobs
    ls = [p for p in files if suffix[p] == ".ls"]
    if ls:
        va = tuple(str(p) for p in files if p.name.lower() in FANUC_FRAME_FILES)
        return "fanuc", [Job(p, p.relative_to(root), "fanuc-tp", frame_data=va) for p in ls]
    raise ValueError(
        "expected a controller backup: a KUKA archive (.src programs, KRC/R1/System/$config.dat), an ABB backup "
        "(RAPID/TASK*/PROGMOD, SYSMOD) or a folder of Fanuc .ls programs; found none of their programs"
    )
