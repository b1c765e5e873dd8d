"""Service settings, in one place, read from the environment (no globals: ``Settings.from_env()``
is called by whoever builds the app)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

ENGINES = ("embedded", "procrastinate")


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

    @property
    def effective_lease_ttl_s(self) -> float:
        return self.lease_ttl_s if self.lease_ttl_s else max(30.0, self.device_timeout_s * 3)

    @property
    def effective_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.home / 'recal.db'}"

    @classmethod
    def from_env(cls, env: dict[str, str] | None = None) -> "Settings":
        env = dict(os.environ if env is None else env)
        kw: dict = {}
        if env.get("RECAL_HOME"):
            kw["home"] = Path(env["RECAL_HOME"]).expanduser()
        if env.get("RECAL_DATABASE_URL"):
            kw["database_url"] = env["RECAL_DATABASE_URL"]
        if env.get("RECAL_ENGINE"):
            kw["engine"] = env["RECAL_ENGINE"].strip().lower()
            if kw["engine"] not in ENGINES:
                raise ValueError(f"environment variable RECAL_ENGINE: expected one of {', '.join(ENGINES)}, "
                                 f"got {env['RECAL_ENGINE']!r}")
        for name, key, conv in (
            ("max_joint_speed_rad_s", "RECAL_MAX_JOINT_SPEED", float),
            ("max_joint_accel_rad_s2", "RECAL_MAX_JOINT_ACCEL", float),
            ("settle_s", "RECAL_SETTLE_S", float),
            ("device_retries", "RECAL_DEVICE_RETRIES", int),
            ("retry_backoff_s", "RECAL_RETRY_BACKOFF_S", float),
            ("device_timeout_s", "RECAL_DEVICE_TIMEOUT_S", float),
            ("lease_ttl_s", "RECAL_LEASE_TTL_S", float),
        ):
            if env.get(key):
                try:
                    kw[name] = conv(env[key])
                except ValueError:
                    raise ValueError(f"environment variable {key}: expected a number, got {env[key]!r}") from None
        return cls(**kw)
