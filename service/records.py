"""Stored rows and calibration's arrays, both directions in one place.

- :func:`measurements_of`: a session's stored ``Measurement`` rows as ``calibration``'s
  :class:`~calibration.identify.Measurements` (SI, one row each, the row number being the
  session's pose number);
- :func:`measurement_rows`: the other way, arrays as rows to store;
- :func:`position_errors`, :func:`registered_errors`: a model's errors on those measurements
  (``calibration.metrics``, the one definition);
- :func:`current_model`: the cell's best model (its last pose calibration, else its nominal
  model), as a :class:`~calibration.model.KinematicModel`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlmodel import Session, col, select

from calibration import metrics
from calibration.errors import RecalError
from calibration.identification import Measurements
from calibration.model import KinematicModel, model_from_dict

from .models import Calibration, Cell, Measurement, RunSession, utcnow
from .store import current_calibration


class NoMeasurementsError(RecalError, LookupError):
    """The session has no stored measurements."""


def stored_rows(db: Session, run: RunSession) -> list[Measurement]:
    """The session's measurement rows, in the order they were taken."""
    return list(
        db.exec(
            select(Measurement)
            .where(col(Measurement.session_id) == run.id)
            .order_by(col(Measurement.seq), col(Measurement.id))
        ).all()
    )


def payload_of(run: RunSession, seq: np.ndarray) -> np.ndarray | None:
    """The payload (N, 4) (kg, centre of gravity in the tool frame, m) each configuration ``seq``
    of a session with ``payloads`` was measured with: the plan is split between them in order
    (the first share of the configurations with the first payload, ...). None without payloads."""
    payloads = run.session_plan().payloads
    if not payloads:
        return None
    n = max(int(run.planned or 0), int(np.max(seq, initial=0)) + 1)
    return np.asarray(payloads, dtype=float)[np.asarray(seq, dtype=int) * len(payloads) // n]


def measurements_of(rows: list[Measurement], run: RunSession | None = None) -> Measurements:
    """Stored rows as :class:`Measurements` (SI; ``row`` and ``pose_id`` from the pose number; the
    payloads of ``run``'s plan, :func:`payload_of`)."""
    if not rows:
        raise NoMeasurementsError("the session has no measurements")
    has_quat = [r.qw is not None for r in rows]
    quat = (
        np.array([[r.qw, r.qx, r.qy, r.qz] if h else [np.nan] * 4 for r, h in zip(rows, has_quat)])
        if any(has_quat)
        else None
    )
    return Measurements(
        q=np.array([r.q for r in rows], dtype=float),
        p_world=np.array([[r.x, r.y, r.z] for r in rows]),
        quat=quat,
        target=np.array([r.target or None for r in rows], dtype=object),
        sigma=np.array([r.sigma if r.sigma else np.nan for r in rows]),
        pose_id=np.array([r.seq for r in rows]),
        row=np.array([r.seq + 1 for r in rows]),
        payload=None if run is None else payload_of(run, np.array([r.seq for r in rows])),
    )


def measurement_rows(session_id: int, data: Measurements) -> list[Measurement]:
    """The other way: :class:`Measurements` as rows of session ``session_id``, one per row, the
    row's index its pose number (``seq``); NaN orientations and uncertainties are stored empty."""
    assert data.sigma is not None and data.target is not None  # Measurements.__post_init__ fills them
    quat = data.quat if data.quat is not None else np.full((len(data), 4), np.nan)
    rows = []
    for i in range(len(data)):
        qw, qx, qy, qz = (None if np.isnan(v) else float(v) for v in quat[i])
        sigma = None if not np.isfinite(data.sigma[i]) else float(data.sigma[i])
        rows.append(
            Measurement(
                session_id=session_id,
                seq=i,
                target=data.target[i] or "",
                q=[float(v) for v in data.q[i]],
                x=float(data.p_world[i, 0]),
                y=float(data.p_world[i, 1]),
                z=float(data.p_world[i, 2]),
                qw=qw,
                qx=qx,
                qy=qy,
                qz=qz,
                sigma=sigma,
            )
        )
    return rows


# Rows inserted per statement by :func:`insert_measurements`: a few MB of parameters at a time.
INSERT_CHUNK_ROWS = 5000


def insert_measurements(db: Session, session_id: int, data: Measurements) -> None:
    """:func:`measurement_rows`' rows inserted in chunks through the database driver's own
    ``executemany`` (not committed): an ORM object per row cost 0.15 ms and a kilobyte each, and
    SQLAlchemy's per-row parameter processing another 20 µs; a 100,000-row import took 15 s.
    Each value is given as SQLAlchemy would bind it (the readings as JSON text, the time through
    the column type's own bind processing)."""
    import json

    conn = db.connection()
    assert data.sigma is not None and data.target is not None  # Measurements.__post_init__ fills them
    table = Measurement.__table__  # type: ignore[attr-defined]  # SQLAlchemy's, not in SQLModel's stubs
    names = ("session_id", "seq", "target", "q", "x", "y", "z", "qw", "qx", "qy", "qz", "sigma", "created_at")
    bind_time = table.c.created_at.type.bind_processor(conn.dialect)
    now = utcnow() if bind_time is None else bind_time(utcnow())
    mark = "?" if conn.dialect.paramstyle == "qmark" else "%s"
    sql = f"INSERT INTO {table.name} ({', '.join(names)}) VALUES ({', '.join([mark] * len(names))})"
    quat = data.quat if data.quat is not None else np.full((len(data), 4), np.nan)
    q_json = [json.dumps(row) for row in np.asarray(data.q, dtype=float).tolist()]
    p = np.asarray(data.p_world, dtype=float).tolist()
    null = np.array(None, dtype=object)  # SQL NULL as np.where's fill (the same as a bare None)
    quat_l = np.where(np.isnan(quat), null, quat).tolist()
    sigma_l = np.where(np.isfinite(data.sigma), data.sigma, null).tolist()
    target = [t or "" for t in data.target]
    for start in range(0, len(data), INSERT_CHUNK_ROWS):
        chunk = [
            (session_id, i, target[i], q_json[i], *p[i], *quat_l[i], sigma_l[i], now)
            for i in range(start, min(start + INSERT_CHUNK_ROWS, len(data)))
        ]
        conn.exec_driver_sql(sql, chunk)


def as_stored(run: RunSession, data: Measurements) -> Measurements:
    """``data`` as :func:`session_data` reads it back once :func:`insert_measurements` has stored
    it for ``run`` (the row's index as pose number, an empty target or uncertainty as none):
    what an import hands to its analysis instead of reading 100,000 rows back."""
    assert data.sigma is not None and data.target is not None  # Measurements.__post_init__ fills them
    n = len(data)
    seq = np.arange(n)
    quat = None if data.quat is None or np.all(np.isnan(data.quat[:, 0])) else np.asarray(data.quat, dtype=float)
    sigma = np.asarray(data.sigma, dtype=float)
    return Measurements(
        q=np.asarray(data.q, dtype=float),
        p_world=np.asarray(data.p_world, dtype=float),
        quat=quat,
        target=np.array([t or None for t in data.target], dtype=object),
        sigma=np.where(np.isfinite(sigma) & (sigma != 0.0), sigma, np.nan),
        pose_id=seq,
        row=seq + 1,
        payload=payload_of(run, seq),
    )


def session_data(db: Session, run: RunSession) -> Measurements:
    """The session's measurements as arrays (as :func:`measurements_of` makes them), read as plain
    columns, the readings' JSON decoded in one piece: no ORM object and no JSON parse per row (a
    100,000-row session reads in well under a second)."""
    import json

    from sqlalchemy import String, cast

    cols: tuple[Any, ...] = (
        Measurement.seq,
        Measurement.target,
        cast(Measurement.q, String),
        Measurement.x,
        Measurement.y,
    )
    cols += (Measurement.z, Measurement.qw, Measurement.qx, Measurement.qy, Measurement.qz, Measurement.sigma)
    rows = db.exec(
        select(*cols).where(col(Measurement.session_id) == run.id).order_by(col(Measurement.seq), col(Measurement.id))
    ).all()
    if not rows:
        raise NoMeasurementsError("the session has no measurements")
    seq_read, target, q_text, x, y, z, qw, qx, qy, qz, sigma = zip(*rows)
    seq = np.array(seq_read, dtype=int)

    def floats(values) -> np.ndarray:  # None (an empty column) as NaN
        return np.array([np.nan if v is None else v for v in values], dtype=float)

    quat = np.column_stack([floats(qw), floats(qx), floats(qy), floats(qz)])
    sig = floats(sigma)
    return Measurements(
        q=np.array(json.loads("[" + ",".join(q_text) + "]"), dtype=float),
        p_world=np.column_stack([x, y, z]).astype(float),
        quat=None if np.all(np.isnan(quat[:, 0])) else quat,
        target=np.array([t or None for t in target], dtype=object),
        sigma=np.where(sig == 0.0, np.nan, sig),  # as measurements_of: a zero sigma is none
        pose_id=seq,
        row=seq + 1,
        payload=payload_of(run, seq),
    )


def session_measurements(db: Session, run: RunSession) -> tuple[Measurements, list[Measurement]]:
    """The session's measurements as arrays, and the rows they came from."""
    rows = stored_rows(db, run)
    return measurements_of(rows, run), rows


def target_points(model: KinematicModel, data: Measurements) -> np.ndarray:
    """(N, 3) tool-frame point of each row: the model's position of the row's target."""
    assert data.target is not None  # Measurements.__post_init__ fills it
    return np.array([model.target(t) for t in data.target]).reshape(len(data.target), 3)


def position_errors(model: KinematicModel, data: Measurements) -> np.ndarray:
    """(N, 3) measured minus predicted target positions, m (``calibration.metrics``), the model's
    stored residual correction applied where it applies (:func:`corrected_errors`)."""
    return corrected_errors(model, data)[0]


def corrected_errors(model: KinematicModel, data: Measurements) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) measured minus predicted target positions, m, the prediction being the model as
    every verb uses it: the geometric model plus its stored residual correction
    (``calibration.residual_map.from_model``, whatever its family) inside the region it was fitted
    in, the geometric model alone elsewhere; and (N,) whether the correction applied (None: the
    model carries none). Verify sessions, the certificate and the result page judge a model by
    this, as ``recal accuracy`` does, so that the figures are of what compensation sends."""
    from calibration.residual_map import from_model

    p_tool = target_points(model, data)
    e = metrics.position_errors(model, data.q, data.p_world, p_tool, data.payload)
    correction = from_model(model)
    if correction is None:
        return e, None
    corr, inside = correction.evaluate(data.q, p_tool)
    return e - corr, np.asarray(inside, dtype=bool)


def registered_errors(model: KinematicModel, data: Measurements) -> np.ndarray:
    """(N, 3) errors, m, with the model's base placed where it fits best (``calibration.metrics``)."""
    return metrics.registered_errors(model, data.q, data.p_world, target_points(model, data), data.payload)[0]


def registered_points(model: KinematicModel, data: Measurements, q: np.ndarray, p_tool: np.ndarray) -> np.ndarray:
    """Where ``model`` puts the tool-frame points ``p_tool`` (N, 3) at readings ``q`` (N, n), in the
    instrument's frame, its base placed where it fits the measurements ``data`` best (and one
    common reflector offset absorbed), as :func:`registered_errors` places it. (N, 3), m."""
    X, c = metrics.registration(model, data.q, data.p_world, target_points(model, data), data.payload)
    return metrics.placed_points(model, X, c, q, p_tool)


def current_model(db: Session, cell: Cell) -> tuple[KinematicModel, Calibration | None]:
    """The cell's best model: its last pose calibration (from its present nominal model), else the
    nominal model."""
    cal = current_calibration(db, cell)
    return (model_from_dict(cal.model), cal) if cal is not None else (model_from_dict(cell.model), None)


# --------------------------------------------------------------------------- measurements as CSV, in and out


def measurements_csv(model, rows: list[Measurement]) -> str:
    """The measurement CSV of contracts §3 (``recal identify --data``) in ``model``'s units:
    ``q1..qN, x, y, z``, then ``qw, qx, qy, qz`` when a row has an orientation, ``target``,
    ``sigma`` and ``pose_id`` (the configuration's index in the session's plan); joint sessions
    add ``joint`` and ``reference`` (the reference encoder's reading), which identify ignores."""
    from .files import format_csv

    u = model.units
    L = u.length_m
    q_scale = np.array([u.angle_rad if j.revolute else L for j in model.joints])
    has_quat = any(r.qw is not None for r in rows)
    has_joint = any(r.joint is not None for r in rows)
    has_ref = any(getattr(r, "reference", None) is not None for r in rows)
    header = [f"q{i + 1}" for i in range(model.n_joints)] + ["x", "y", "z"]
    header += ["qw", "qx", "qy", "qz"] if has_quat else []
    header += ["target", "sigma", "pose_id"] + (["joint"] if has_joint else []) + (["reference"] if has_ref else [])

    def blank(v, scale=1.0):
        return "" if v is None else float(v) / scale

    out = []
    for r in rows:
        row = [float(v) for v in np.asarray(r.q, dtype=float) / q_scale] + [r.x / L, r.y / L, r.z / L]
        if has_quat:
            row += [blank(r.qw), blank(r.qx), blank(r.qy), blank(r.qz)]
        row += [r.target or "", blank(r.sigma, L), r.seq]
        if has_joint:
            row.append("" if r.joint is None else r.joint)
        if has_ref:
            row.append(blank(getattr(r, "reference", None), u.angle_rad))
        out.append(row)
    return format_csv(header, out)


def session_measurements_csv(db: Session, run: RunSession, cell: Cell) -> str:
    """The session's measurements as the CSV that ``recal identify`` reads (contracts §3), in the
    units of the cell's nominal model, under a comment line naming the session."""
    model = model_from_dict(cell.model)
    rows = stored_rows(db, run)
    return (
        f"# session {run.id} ({run.kind}, {run.state}) of cell {run.cell_id}, units {model.units.length}/"
        f"{model.units.angle}\n" + measurements_csv(model, rows)
    )
