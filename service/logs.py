"""One log format for the service, its workers and the demo (docs/service.md, "Logs"): JSON lines
by default, one object a line, or text lines (``RECAL_LOG_FORMAT=text``, ``recal serve
--log-format text``). uvicorn's own lines (start, stop, errors) go through the same handler:
:func:`logging_config` is given to uvicorn as its ``log_config``.

Each JSON line has ``time`` (UTC, ISO 8601), ``level``, ``logger`` and ``message``, then the
record's ``fields`` (``logger.info(..., extra={"fields": {...}})``): the access log's method,
route, status, duration; a session's id, kind, cell and state. Nothing secret is written: an API
token (``rc_...``), a bearer credential or a password in a database URL is replaced by ``***``
in every line, whoever logged it.
"""

from __future__ import annotations

import json
import logging
import os
import re
from datetime import UTC, datetime

FORMATS = ("json", "text")
DEFAULT_FORMAT = "json"
LEVELS = ("critical", "error", "warning", "info", "debug")

# What must never reach a log: API tokens (service.store.create_token: "rc_" + 43 URL-safe
# characters), bearer credentials, and the password of a URL's user (postgresql://user:pw@host).
_SECRETS = (
    (re.compile(r"\brc_[A-Za-z0-9_\-]{8,}"), "rc_***"),
    (re.compile(r"(?i)\b(bearer)\s+[A-Za-z0-9._~+/=\-]+"), r"\1 ***"),
    (re.compile(r"(\b[a-z][a-z0-9+.\-]*://[^/\s:@]+:)[^@\s/]+@"), r"\1***@"),
)


def redact(text: str) -> str:
    """``text`` with every secret-looking value replaced by ``***``.

    >>> redact("token rc_AbCdEfGhIjKl12 at postgresql+psycopg://recal:s3cret@db:5432/recal")
    'token rc_*** at postgresql+psycopg://recal:***@db:5432/recal'
    """
    for pattern, replacement in _SECRETS:
        text = pattern.sub(replacement, text)
    return text


def log_format() -> str:
    """The format the environment asks for (``RECAL_LOG_FORMAT``), else JSON lines."""
    value = os.environ.get("RECAL_LOG_FORMAT", DEFAULT_FORMAT).strip().lower() or DEFAULT_FORMAT
    if value not in FORMATS:
        raise ValueError(f"RECAL_LOG_FORMAT: expected one of {', '.join(FORMATS)}, got {value!r}")
    return value


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time, level, logger, message, then the record's ``fields``."""

    def format(self, record: logging.LogRecord) -> str:
        doc = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in (getattr(record, "fields", None) or {}).items():
            doc.setdefault(key, value)
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return redact(json.dumps(doc, default=str, ensure_ascii=False, separators=(",", ":")))


class TextFormatter(logging.Formatter):
    """``time LEVEL logger: message key=value ...``: the same records for a person at a terminal."""

    def __init__(self):
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        fields = getattr(record, "fields", None) or {}
        extra = " ".join(f"{k}={json.dumps(v, default=str, ensure_ascii=False)}" for k, v in fields.items())
        return redact(f"{line} {extra}" if extra else line)


def logging_config(level: str = "info", fmt: str = DEFAULT_FORMAT) -> dict:
    """The ``logging.config.dictConfig`` of the service (and uvicorn's ``log_config``): one handler
    on stderr in ``fmt``, which the root logger and uvicorn's loggers all write through."""
    if fmt not in FORMATS:
        raise ValueError(f"log format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    formatter = JsonFormatter if fmt == "json" else TextFormatter
    lvl = level.upper()
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"recal": {"()": f"{__name__}.{formatter.__name__}"}},
        "handlers": {"recal": {"class": "logging.StreamHandler", "formatter": "recal", "stream": "ext://sys.stderr"}},
        "root": {"handlers": ["recal"], "level": lvl},
        # uvicorn's loggers write through the root's handler (none of their own: no second format)
        "loggers": {
            "uvicorn": {"handlers": [], "level": lvl, "propagate": True},
            "uvicorn.error": {"handlers": [], "level": lvl, "propagate": True},
            # each request is the service's own access line (recal.access), secrets redacted
            "uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": True},
        },
    }


def configure(level: str = "info", fmt: str | None = None) -> dict:
    """Configure this process's logging (``fmt`` default :func:`log_format`); returns the
    configuration, for uvicorn's ``log_config``."""
    import logging.config

    config = logging_config(level, fmt or log_format())
    logging.config.dictConfig(config)
    return config
