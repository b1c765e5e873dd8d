"""Service settings, in one place, read from the environment (no globals: ``Settings.from_env()``
is called by whoever builds the app)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

from calibration.errors import RecalError

ENGINES = ("embedded", "procrastinate")

# What each numeric setting may be: (lowest, highest, environment variable, unit). The speed and
# acceleration ceilings are the robot drivers' own (``ur_rtde``'s moveJ accepts at most 3.14 rad/s
# and 40 rad/s²; the fastest UR joint turns at 180 °/s): a cap above them caps nothing, so a
# setting beyond is a mistake (a unit slip, deg/s for rad/s) and the service refuses to start.
LIMITS: dict[str, tuple[float, float, str, str]] = {
    "max_joint_speed_rad_s": (1e-3, 3.14, "RECAL_MAX_JOINT_SPEED", "rad/s"),
    "max_joint_accel_rad_s2": (1e-3, 40.0, "RECAL_MAX_JOINT_ACCEL", "rad/s²"),
    "settle_s": (0.0, 60.0, "RECAL_SETTLE_S", "s"),
    "device_retries": (0, 20, "RECAL_DEVICE_RETRIES", "retries"),
    "retry_backoff_s": (0.0, 60.0, "RECAL_RETRY_BACKOFF_S", "s"),
    "device_timeout_s": (0.1, 600.0, "RECAL_DEVICE_TIMEOUT_S", "s"),
    "lease_ttl_s": (1.0, 3600.0, "RECAL_LEASE_TTL_S", "s"),
    # Heavy work (compensation, PDF rendering) runs in this many worker processes, never on the
    # event loop; requests beyond wait their turn (docs/service.md, "Heavy work and limits").
    "heavy_workers": (1, 64, "RECAL_HEAVY_WORKERS", "processes"),
    # Request bodies: JSON documents (a cell's model and devices, a session request) and task
    # files (a compensation's task CSV or URScript, a task file registered with a cell). Beyond,
    # 413 before anything is parsed (docs/service.md).
    "max_body_bytes": (1024, 1 << 30, "RECAL_MAX_BODY_BYTES", "bytes"),
    "max_task_bytes": (1024, 1 << 30, "RECAL_MAX_TASK_BYTES", "bytes"),
    # A measurement import (POST /cells/{id}/measurements): its CSV's bytes (413 beyond) and rows
    # (422 beyond, counted before anything is parsed or stored).
    "max_import_bytes": (1024, 1 << 30, "RECAL_MAX_IMPORT_BYTES", "bytes"),
    "max_import_rows": (1, 10_000_000, "RECAL_MAX_IMPORT_ROWS", "rows"),
}

INTEGER_SETTINGS = (
    "device_retries",
    "heavy_workers",
    "max_body_bytes",
    "max_task_bytes",
    "max_import_bytes",
    "max_import_rows",
)


class SettingsError(RecalError, ValueError):
    """A setting is missing its form or out of its range: one line naming the variable."""


@dataclass(frozen=True)
class Settings:
    """``database_url``: any SQLAlchemy URL; default an embedded SQLite file in ``home``.
    ``home``: the data directory (``RECAL_HOME``, default ``~/.recal``).
    Safety caps apply to every session whatever it asks for.
    ``engine``: ``embedded`` (sessions run in threads of the API process, the default) or
    ``procrastinate`` (sessions run by ``recal worker`` processes, docs/fleet.md).
    ``lease_ttl_s``: how long a session's hold on its cell lasts unless renewed; default
    ``max(30, 3 * device_timeout_s)``."""

    home: Path = field(default_factory=lambda: Path(os.path.expanduser("~/.recal")))
    database_url: str | None = None
    max_joint_speed_rad_s: float = 0.5
    max_joint_accel_rad_s2: float = 1.0
    settle_s: float = 0.2
    device_retries: int = 2
    retry_backoff_s: float = 0.5
    device_timeout_s: float = 10.0
    engine: str = "embedded"
    lease_ttl_s: float | None = None
    heavy_workers: int = 2
    # 1 MiB: a cell's model and devices documents are a few kB, a session request under 1 kB.
    max_body_bytes: int = 1 << 20
    # 4 MiB: a task CSV row (name, pose, six joints) is about 140 bytes, so some 29,000 points;
    # real robot programs have hundreds to a few thousand (a URScript program of 5,000 moves is
    # under 1 MiB). Compensating the largest allowed file takes seconds in a worker process.
    max_task_bytes: int = 4 << 20
    # 16 MiB and 100,000 rows: a measurement row at full precision is about 125 bytes, so the
    # largest allowed import fits both; importing it takes a few seconds and under 300 MB
    # (bench/import_scale.py, docs/benchmarks.md).
    max_import_bytes: int = 16 << 20
    max_import_rows: int = 100_000

    def __post_init__(self):
        for f in fields(self):
            if f.name not in LIMITS:
                continue
            value = getattr(self, f.name)
            lo, hi, env, unit = LIMITS[f.name]
            if value is None and f.name == "lease_ttl_s":
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
                raise SettingsError(f"environment variable {env}: expected {lo:g} to {hi:g} {unit}, got {value!r}")
        if self.engine not in ENGINES:
            raise SettingsError(
                f"environment variable RECAL_ENGINE: expected one of {', '.join(ENGINES)}, got {self.engine!r}"
            )

    @property
    def effective_lease_ttl_s(self) -> float:
        return self.lease_ttl_s if self.lease_ttl_s else max(30.0, self.device_timeout_s * 3)

    @property
    def effective_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.home / 'recal.db'}"

    @classmethod
    def from_env(cls, env: dict[str, str] | None = None) -> Settings:
        env = dict(os.environ if env is None else env)
        kw: dict = {}
        if env.get("RECAL_HOME"):
            kw["home"] = Path(env["RECAL_HOME"]).expanduser()
        if env.get("RECAL_DATABASE_URL"):
            kw["database_url"] = env["RECAL_DATABASE_URL"]
        if env.get("RECAL_DATABASE_PASSWORD_FILE"):
            kw["database_url"] = _with_password(kw.get("database_url"), env["RECAL_DATABASE_PASSWORD_FILE"])
        if env.get("RECAL_ENGINE"):
            kw["engine"] = env["RECAL_ENGINE"].strip().lower()
        for name, (_, _, key, _) in LIMITS.items():
            if env.get(key):
                conv = int if name in INTEGER_SETTINGS else float
                try:
                    kw[name] = conv(env[key])
                except ValueError:
                    raise SettingsError(f"environment variable {key}: expected a number, got {env[key]!r}") from None
        return cls(**kw)


def _with_password(url: str | None, password_file: str) -> str:
    """``url`` with the password read from ``password_file`` (a Docker or systemd secret, so the
    password is in no environment variable, compose file or process listing)."""
    if not url:
        raise SettingsError(
            "environment variable RECAL_DATABASE_PASSWORD_FILE: expected RECAL_DATABASE_URL too "
            "(the database the password is for)"
        )
    try:
        password = Path(password_file).read_text(encoding="utf-8").rstrip("\r\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise SettingsError(
            f"environment variable RECAL_DATABASE_PASSWORD_FILE: cannot read {password_file}: "
            f"{getattr(exc, 'strerror', None) or exc}"
        ) from None
    if not password:
        raise SettingsError(
            f"environment variable RECAL_DATABASE_PASSWORD_FILE: {password_file} is empty; "
            f"expected the database password"
        )
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).set(password=password).render_as_string(hide_password=False)
    except Exception as exc:  # noqa: BLE001 - any malformed URL: one line naming the variable
        raise SettingsError(f"environment variable RECAL_DATABASE_URL: not a database URL ({exc})") from None


def worker_concurrency(env: dict[str, str] | None = None) -> int:
    """How many sessions one ``recal worker`` runs at once unless ``--concurrency`` says:
    ``RECAL_WORKER_CONCURRENCY``, else four per CPU core the process may use.

    Why four: a session whose robot moves costs its worker about a sixth of a core (the RTDE
    stream at 500 Hz and the wait for the move), planning and identification a core for a
    fraction of a second each. Four per core keeps a worker's cores busy but not saturated while
    robots move, so that leases are renewed, requests answered and database connections opened
    in time; more sessions than that only wait longer for the same cores (and hold a database
    connection each). Sessions beyond the limit wait in the queue, ``planned``."""
    env = os.environ if env is None else env
    raw = (env.get("RECAL_WORKER_CONCURRENCY") or "").strip()
    if raw:
        try:
            value = int(raw)
        except ValueError:
            raise SettingsError(
                f"environment variable RECAL_WORKER_CONCURRENCY: expected a whole number, got {raw!r}"
            ) from None
        if value < 1:
            raise SettingsError(f"environment variable RECAL_WORKER_CONCURRENCY: expected at least 1, got {value}")
        return value
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 4 * max(1, cores)
