"""Heavy work of the API (compensating a task file, rendering a certificate's PDF) in a pool of
worker processes, never on the event loop nor in the API's own threads.

Why processes and not threads: the work is numpy and Python loops; in a thread it holds the GIL
most of the time, and the event loop then gets it back only every switch interval (5 ms) for a
moment, so a large compensation made every other request wait seconds (issue 12: an abort
answered after 19 s). A worker process costs the API nothing but a pipe. The pool is bounded
(``Settings.heavy_workers``): requests beyond it wait in the pool's queue, and the API answers
health, status, pause and abort meanwhile. Workers start on first use (from a clean
interpreter, no copy of the API's threads or database connections) and live until shutdown.
"spawn" imports the program's main module again in each worker, as ``__mp_main__``: a script
that builds the app must keep its work under ``if __name__ == "__main__":`` (``recal`` does).
A worker whose service died without shutting the pool down (``kill -9``) notices within a
second and exits.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any


class HeavyPool:
    """``await pool.run(fn, *args)`` from a coroutine, ``pool.call(fn, *args)`` from a thread:
    ``fn`` (a module-level function, its arguments and result picklable) in a worker process."""

    def __init__(self, workers: int):
        self.workers = workers
        self._executor: ProcessPoolExecutor | None = None

    def _pool(self) -> ProcessPoolExecutor:
        if self._executor is None:
            self._executor = ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_exit_with_parent,
                initargs=(os.getpid(),),
            )
        return self._executor

    def submit(self, fn: Callable, *args: Any, **kw: Any):
        try:
            return self._pool().submit(fn, *args, **kw)
        except BrokenProcessPool:  # a worker died (out of memory, killed): a new pool for what follows
            self._executor = None
            return self._pool().submit(fn, *args, **kw)

    async def run(self, fn: Callable, *args: Any, **kw: Any):
        return await asyncio.wrap_future(self.submit(fn, *args, **kw))

    def call(self, fn: Callable, *args: Any, **kw: Any):
        return self.submit(fn, *args, **kw).result()

    def shutdown(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


def _exit_with_parent(parent_pid: int) -> None:
    """Worker initializer: exit when the service process that started the pool is gone."""

    def watch():
        while True:
            time.sleep(1.0)
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(0)
            except PermissionError:  # the pid was reused by another user's process: ours is gone
                os._exit(0)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
