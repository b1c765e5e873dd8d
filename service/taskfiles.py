"""Task files of ``recal compensate``: task CSVs (contracts §5) and Universal Robots URScript
programs.

Task CSV. One row per task point: ``x, y, z, qw, qx, qy, qz`` (desired tool pose in the world
frame, the model's length unit) and/or ``q1..qN`` (the configuration the program was taught or
planned with, the model's units). A row may leave the pose empty (a taught point: only its
joints) but not leave part of a group empty. The output has the input columns (their text as it
was, except the replaced ones), then ``q1..qN`` (joints mode) or ``x..qz`` (targets mode) where
the input had none, then ``converged``, ``residual``, ``flags``.

URScript. The poses of URScript programs as 4×4 matrices and back
(:func:`pose_to_matrix_ur`, :func:`matrix_to_pose_ur`); the programs themselves are read by
:mod:`service.programs.urscript`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.model import KinematicModel
from calibration.transforms import homogeneous, matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotvec_to_matrix

from .files import InputError, Table, read_table

POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
RESULT_COLUMNS = ("converged", "residual", "flags")
SCRIPT_SUFFIXES = (".script", ".urscript")


def is_script(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a URScript program (by its suffix)."""
    return Path(path).suffix.lower() in SCRIPT_SUFFIXES


# =============================================================================== task CSV


@dataclass(frozen=True, eq=False)
class Task:
    """A task CSV read for a model, SI. ``T_world_tool`` (N, 4, 4) desired poses (identity where
    a row has none); ``has_pose`` (N,); ``quat`` (N, 4) the rows' quaternions (NaN where none);
    ``q`` (N, n) readings (NaN where none); ``has_q`` (N,)."""

    path: str
    table: Table
    T_world_tool: np.ndarray
    has_pose: np.ndarray
    quat: np.ndarray
    q: np.ndarray
    has_q: np.ndarray

    def __len__(self) -> int:
        return len(self.table.rows)

    def where(self, i: int) -> dict:
        """Row and line of task point ``i`` (for errors and reports)."""
        return {"row": i + 1, "line": self.table.lines[i]}


def _group(table: Table, names: list[str], scales: list[float], what: str) -> tuple[np.ndarray, np.ndarray]:
    """Columns ``names`` as floats (N, k) (NaN where empty) and which rows have them all; a row
    with some but not all is an error naming the first empty cell."""
    vals = np.stack([table.numbers(c, scale=s, allow_empty=True) for c, s in zip(names, scales)], axis=1)
    empty = np.isnan(vals)
    partial = empty.any(axis=1) & ~empty.all(axis=1)
    if np.any(partial):
        r = int(np.nonzero(partial)[0][0])
        col = names[int(np.nonzero(empty[r])[0][0])]
        raise InputError(
            table.path,
            f"expected a number ({what} needs all of {', '.join(names)}, or none of them)",
            row=r + 1,
            line=table.lines[r],
            column=col,
        )
    return vals, ~empty.any(axis=1)


def read_task(path: str | os.PathLike, model: KinematicModel) -> Task:
    """Read a task CSV (contracts §5) for ``model``; errors name the file, row, line and column."""
    table = read_table(path)
    n = model.n_joints
    u = model.units
    present = [c for c in POSE_COLUMNS if table.has(c)]
    if present and len(present) != len(POSE_COLUMNS):
        missing = [c for c in POSE_COLUMNS if c not in present]
        raise InputError(path, f"missing column {missing[0]!r}: a desired pose needs all of {', '.join(POSE_COLUMNS)}")
    qcols = sorted((h for h in table.header if h[:1] == "q" and h[1:].isdigit()), key=lambda h: int(h[1:]))
    bad = [h for h in qcols if not 1 <= int(h[1:]) <= n]
    if bad:
        raise InputError(path, f"column {bad[0]!r}: the model has {n} joints (q1..q{n})")
    if qcols and len(qcols) != n:
        missing = [f"q{i}" for i in range(1, n + 1) if f"q{i}" not in qcols]
        raise InputError(path, f"missing joint column {missing[0]!r}: the model has {n} joints (q1..q{n})")
    if not present and not qcols:
        raise InputError(
            path,
            f"expected the columns {', '.join(POSE_COLUMNS)} (desired tool pose) and/or "
            f"q1..q{n} (taught or planned joints); the header has: {', '.join(table.header)}",
        )
    N = len(table.rows)
    if present:
        L = u.length_m
        vals, has_pose = _group(table, list(POSE_COLUMNS), [L, L, L, 1, 1, 1, 1], "a desired pose")
        quat = vals[:, 3:]
        norms = np.linalg.norm(quat, axis=1)
        off = has_pose & (np.abs(norms - 1.0) > 1e-3)
        if np.any(off):
            r = int(np.nonzero(off)[0][0])
            raise InputError(
                path,
                f"the quaternion has norm {norms[r]:.6g}; expected a unit quaternion",
                row=r + 1,
                line=table.lines[r],
                column="qw",
            )
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
        T[has_pose] = homogeneous(quat_to_matrix(quat[has_pose]), vals[has_pose, :3])
    else:
        has_pose = np.zeros(N, dtype=bool)
        quat = np.full((N, 4), np.nan)
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
    if qcols:
        scales = [u.angle_rad if j.revolute else u.length_m for j in model.joints]
        q, has_q = _group(table, [f"q{i}" for i in range(1, n + 1)], scales, "a joint vector")
    else:
        q, has_q = np.full((N, n), np.nan), np.zeros(N, dtype=bool)
    empty = ~has_pose & ~has_q
    if np.any(empty):
        r = int(np.nonzero(empty)[0][0])
        col = "x" if present else "q1"
        raise InputError(
            path, "the row has neither a desired pose nor joints", row=r + 1, line=table.lines[r], column=col
        )
    return Task(str(path), table, T, has_pose, quat, q, has_q)


def _num(v: float, digits: int = 12) -> str:
    s = f"{float(v):.{digits}g}"
    return "0" if s in ("-0", "0") else s


def format_task(
    task: Task,
    model: KinematicModel,
    mode: str,
    q: np.ndarray,
    T_command: np.ndarray,
    converged: np.ndarray,
    residual_m: np.ndarray,
    flags: list[str],
) -> str:
    """The compensated task CSV (contracts §5) in ``model``'s units: the input columns (text as
    read) with ``q1..qN`` (``mode == "joints"``) or ``x..qz`` (``"targets"``) replaced — appended
    where the input had none — then ``converged``, ``residual``, ``flags``. Quaternions keep the
    sign of the input's where it had one."""
    import csv
    import io

    n = model.n_joints
    u = model.units
    header = [h for h in task.table.header if h not in RESULT_COLUMNS]
    replaced = [f"q{i}" for i in range(1, n + 1)] if mode == "joints" else list(POSE_COLUMNS)
    out_header = header + [c for c in replaced if c not in header] + list(RESULT_COLUMNS)
    src = task.table.index
    if mode == "joints":
        scales = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
        new = q / scales
    else:
        quat = matrix_to_quat(T_command[:, :3, :3])
        flip = np.nansum(quat * task.quat, axis=1) < 0
        quat[flip] *= -1.0
        new = np.concatenate([T_command[:, :3, 3] / u.length_m, quat], axis=1)
    L = u.length_m
    # whole columns of text first (cheaper than a dict per row), then the rows
    cols = {c: [_num(v) for v in new[:, k]] for k, c in enumerate(replaced)}
    cols["converged"] = ["1" if c else "0" for c in converged]
    cols["residual"] = [_num(v, 6) for v in np.asarray(residual_m) / L]
    cols["flags"] = list(flags)
    getters = [(cols[c], None) if c in cols else (None, src[c]) for c in out_header]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(out_header)
    w.writerows(
        [
            [made[i] if made is not None else (row[k] if k < len(row) else "") for made, k in getters]
            for i, row in enumerate(task.table.rows)
        ]
    )
    return buf.getvalue()


# =============================================================================== URScript poses
# (the programs themselves are read by service.programs.urscript)


def pose_to_matrix_ur(pose6: np.ndarray) -> np.ndarray:
    """A URScript pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) (..., 6) -> (..., 4, 4)."""
    pose6 = np.asarray(pose6, dtype=float)
    return homogeneous(rotvec_to_matrix(pose6[..., 3:]), pose6[..., :3])


def matrix_to_pose_ur(T: np.ndarray, like: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 4) -> URScript poses (N, 6). With ``like`` (N, 6), each rotation vector is the
    equivalent one (angle ± 2πk along the same axis) nearest the original, so that a rewritten
    program keeps its style (UR writes e.g. ``[0, 3.14, 0]`` or ``[0, -3.14, 0]``)."""
    T = np.asarray(T, dtype=float)
    rv = matrix_to_rotvec(T[..., :3, :3])
    if like is not None:
        like = np.asarray(like, dtype=float)[..., 3:]
        ang = np.linalg.norm(rv, axis=-1, keepdims=True)
        axis = np.where(ang > 1e-12, rv / np.where(ang > 1e-12, ang, 1.0), 0.0)
        best = rv.copy()
        for k in (-2, -1, 1, 2):
            cand = axis * (ang + 2.0 * np.pi * k)
            closer = np.linalg.norm(cand - like, axis=-1) < np.linalg.norm(best - like, axis=-1)
            best = np.where(closer[..., None], cand, best)
        rv = best
    return np.concatenate([T[..., :3, 3], rv], axis=-1)
