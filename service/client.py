"""A small client of Recal's REST API (standard library only): the nightly job, the demo and
the system tests talk to the service through it."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

from calibration.errors import RecalError


class ServiceError(RecalError, RuntimeError):
    """The service cannot be reached, or refused the token (401/403)."""


class ServiceUnreachableError(ServiceError, ConnectionError):
    """No answer from the service: refused, reset or timed out (worth trying again later)."""


class ApiError(RecalError, RuntimeError):
    """The service answered with an error status; ``status`` and ``detail`` say which."""

    def __init__(self, status: int, detail: str, what: str):
        self.status, self.detail = status, detail
        super().__init__(f"{what}: {status} {detail}")


class Api:
    def __init__(self, url: str, token: str, timeout_s: float = 30.0):
        self.url, self.token, self.timeout_s = url.rstrip("/"), token, timeout_s

    def call(self, method: str, path: str, body: dict | None = None, *, raw: str | None = None):
        """``method`` ``/api/v1`` + ``path`` with a JSON ``body`` (or ``raw`` text); the JSON answer
        (or text for a text answer)."""
        data = raw.encode() if raw is not None else (None if body is None else json.dumps(body).encode())
        ctype = "text/plain" if raw is not None else "application/json"
        req = urllib.request.Request(
            self.url + "/api/v1" + path,
            data=data,
            method=method,
            headers={"Authorization": f"Bearer {self.token}", "Content-Type": ctype},
        )
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                payload = resp.read()
                if resp.headers.get_content_type() == "application/json":
                    return json.loads(payload or b"null")
                return payload.decode()
        except urllib.error.HTTPError as exc:
            detail = exc.read().decode(errors="replace")
            if exc.code in (401, 403):
                raise ServiceError(f"{method} {path}: {exc.code} {detail}") from None
            raise ApiError(exc.code, detail, f"{method} {path}") from None
        except (urllib.error.URLError, OSError) as exc:
            raise ServiceUnreachableError(f"cannot reach {self.url}: {getattr(exc, 'reason', exc)}") from None

    def call_patiently(self, method: str, path: str, body: dict | None = None, *, deadline: float):
        """``call``, repeated while the service does not answer or says it is busy (502, 503,
        504: a replica restarting, a database away), until ``time.monotonic()`` passes
        ``deadline``. Only for requests that are safe to repeat."""
        delay = 1.0
        while True:
            try:
                return self.call(method, path, body)
            except (ServiceError, ApiError) as exc:
                if not transient(exc) or time.monotonic() + delay > deadline:
                    raise
            time.sleep(delay)
            delay = min(2 * delay, 10.0)

    def wait_session(
        self,
        session_id: int,
        timeout_s: float,
        *,
        until=("completed", "failed", "aborted", "paused", "interrupted"),
        measured: int | None = None,
        on_progress=None,
        poll_s: float = 0.2,
        patient: bool = False,
    ) -> dict:
        """Poll a session every ``poll_s`` until its state is in ``until``, or (``measured``) it
        has measured that many configurations (or the timeout: state ``timeout``). ``patient``:
        wait through a service that is briefly away or busy (:meth:`call_patiently`) instead of
        raising."""
        deadline = time.monotonic() + timeout_s
        last = None
        while True:
            if patient:
                s = self.call_patiently("GET", f"/sessions/{session_id}", deadline=deadline)
            else:
                s = self.call("GET", f"/sessions/{session_id}")
            if on_progress is not None and (s["state"], s["measured"]) != last:
                last = (s["state"], s["measured"])
                on_progress(s)
            if s["state"] in until or (measured is not None and s["measured"] >= measured):
                return s
            if time.monotonic() > deadline:
                return {**s, "state": "timeout"}
            time.sleep(poll_s)


# Answers that say "not now": a load balancer without a live replica, or a replica whose
# database is away or overloaded (503).
BUSY_STATUSES = (502, 503, 504)


def transient(exc: Exception) -> bool:
    """No answer, or one that says to try again later (as opposed to a refused token or a bad
    request, which trying again cannot mend)."""
    return isinstance(exc, ServiceUnreachableError) or (isinstance(exc, ApiError) and exc.status in BUSY_STATUSES)
