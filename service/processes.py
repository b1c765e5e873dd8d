"""Starting Recal's own processes for the demo and the system tests: a simulated cell
(``recal fake-cell``) and the service (``recal serve``), each waited for until it is ready."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Proc:
    """A child process and what it said when it became ready."""

    popen: subprocess.Popen
    ready: dict
    log_path: Path | None = None

    def stop(self, timeout_s: float = 10.0) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout_s)

    def kill(self) -> None:
        """kill -9: no chance to clean up (what a crash or a power loss does)."""
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(10)


def _recal() -> list[str]:
    return [sys.executable, "-m", "service.cli"]


def start_fake_cell(
    truth: str | Path,
    host: str,
    *,
    seed: int = 0,
    time_scale: float = 0.0,
    extra: list[str] | None = None,
    timeout_s: float = 30.0,
    log_path: Path | None = None,
) -> Proc:
    """``recal fake-cell`` in its own process; returns once it printed its endpoint line."""
    err = open(log_path, "ab") if log_path else subprocess.DEVNULL  # noqa: SIM115 (the child's stderr, handed to Popen)
    p = subprocess.Popen(
        _recal()
        + [
            "fake-cell",
            "--truth",
            str(truth),
            "--host",
            host,
            "--seed",
            str(seed),
            "--time-scale",
            str(time_scale),
            *(extra or []),
        ],
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    deadline = time.monotonic() + timeout_s
    line = ""
    try:
        while time.monotonic() < deadline:
            line = p.stdout.readline()
            if line.strip():
                break
            if p.poll() is not None:
                raise RuntimeError(f"recal fake-cell exited with status {p.returncode} before it was ready")
        ready = json.loads(line)
    except json.JSONDecodeError:
        p.kill()
        raise RuntimeError(f"recal fake-cell printed {line!r} instead of its endpoint line") from None
    except BaseException:  # Ctrl-C or SIGTERM (recal demo) while it starts: no orphan
        _kill(p)
        raise
    return Proc(p, ready, log_path)


def _kill(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.kill()
        p.wait(10)


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def start_service(
    home: Path,
    port: int,
    *,
    env: dict | None = None,
    timeout_s: float = 30.0,
    log_path: Path | None = None,
    host: str = "127.0.0.1",
    log_level: str = "info",
) -> Proc:
    """``recal serve`` in its own process with ``RECAL_HOME=home``; returns once /health answers.
    Its log (``log_path``): access, sessions, device faults and refusals, in the service's format
    (service/logs.py; ``RECAL_LOG_FORMAT`` in ``env`` or the environment)."""
    e = {**os.environ, "RECAL_HOME": str(home), **(env or {})}
    out = open(log_path, "ab") if log_path else subprocess.DEVNULL  # noqa: SIM115 (the child's output, handed to Popen)
    p = subprocess.Popen(
        _recal() + ["serve", "--host", host, "--port", str(port), "--log-level", log_level],
        env=e,
        stdout=out,
        stderr=subprocess.STDOUT,
    )
    url = f"http://{host}:{port}"
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if p.poll() is not None:
                raise RuntimeError(
                    f"recal serve exited with status {p.returncode} before it was ready"
                    + (f" (log: {log_path})" if log_path else "")
                )
            try:
                with urllib.request.urlopen(url + "/api/v1/health", timeout=1) as r:
                    if r.status == 200:
                        return Proc(p, {"url": url}, log_path)
            except OSError:
                time.sleep(0.1)
    except BaseException:  # Ctrl-C or SIGTERM (recal demo) while it starts: no orphan
        _kill(p)
        raise
    p.kill()
    raise RuntimeError(f"recal serve did not answer on {url} within {timeout_s} s")


def start_worker(
    home: Path,
    sites: list[str] | None,
    *,
    env: dict | None = None,
    name: str = "worker",
    concurrency: int = 8,
    timeout_s: float = 60.0,
    log_path: Path | None = None,
) -> Proc:
    """``recal worker`` (the fleet, docs/fleet.md) in its own process; returns once it printed
    its ready line (``ready`` holds it: ``owner``, ``pid``...)."""
    e = {**os.environ, "RECAL_HOME": str(home), "RECAL_ENGINE": "procrastinate", **(env or {})}
    err = open(log_path, "ab") if log_path else subprocess.DEVNULL  # noqa: SIM115 (the child's stderr, handed to Popen)
    site_args = ["--all-sites"] if sites is None else [a for s in sites for a in ("--site", s)]
    p = subprocess.Popen(
        _recal() + ["worker", *site_args, "--name", name, "--concurrency", str(concurrency)],
        env=e,
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if line.strip():
            try:
                return Proc(p, json.loads(line), log_path)
            except json.JSONDecodeError:
                p.kill()
                raise RuntimeError(f"recal worker printed {line!r} instead of its ready line") from None
        if p.poll() is not None:
            raise RuntimeError(
                f"recal worker exited with status {p.returncode} before it was ready"
                + (f" (log: {log_path})" if log_path else "")
            )
    p.kill()
    raise RuntimeError(f"recal worker was not ready within {timeout_s} s")
