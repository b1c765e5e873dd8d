"""What a use case refuses, in its own words, apart from HTTP: the API answers each with its
status (``service/api/app.py``: :data:`STATUS`) and the body ``{"detail": ...}`` the OpenAPI
document declares; the CLI prints the message.

- :class:`NotFound` (404): the named record does not exist;
- :class:`Conflict` (409): the request is fine, the state of things refuses it now;
- :class:`Invalid` (422): a request field at fault, named (``field``: ``body.target``,
  ``query.kind``, ...).
"""

from __future__ import annotations

from calibration.errors import RecalError


class NotFound(RecalError, LookupError):
    """The named record does not exist."""


class Conflict(RecalError, RuntimeError):
    """The state of things refuses the request now (a busy cell, a finished session)."""


class Invalid(RecalError, ValueError):
    """A request field at fault: ``field`` names it, the message says what was expected."""

    def __init__(self, field: str, message: str):
        self.field, self.message = field, message
        super().__init__(f"{field}: {message}")

    def detail(self) -> dict:
        return {"field": self.field, "message": self.message}


STATUS = {NotFound: 404, Conflict: 409, Invalid: 422}


def detail_of(exc: RecalError):
    """The answer's ``detail``: the field and message of an :class:`Invalid`, else the message."""
    return exc.detail() if isinstance(exc, Invalid) else str(exc)
