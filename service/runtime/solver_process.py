"""Solves that take seconds run in a child process, so that measurement keeps its pace.

A hand-eye or camera self-calibration over the API is seconds of NumPy and SciPy under
the interpreter lock; in the service's own process it starved acquisition (a 2.4 s gap
in the frames, reported as a stalled camera). One spawned child (not forked: the service
has threads) does them one at a time; it starts with the worker, so the first solve does
not pay for its imports. A child that dies is replaced on the next solve.
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


class SolverCrashed(RuntimeError):
    """The child process died during a solve (out of memory, killed)."""


def _warm_up() -> None:
    """Imported in the child at start, so that the first solve is as fast as the next."""
    import service.core.calib.bundle
    import service.core.calib.handeye_images
    import service.runtime.handeye_session
    import service.runtime.robot_solve  # noqa: F401


class SolverProcess:
    """One child process for long solves: ``run(fn, *args)`` blocks the calling thread (not the
    interpreter) until ``fn(*args)`` has run in the child; its exceptions are raised here."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = None

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
            return self._pool

    def start(self) -> Future[None]:
        """Start the child and import the solvers in it."""
        return self._executor().submit(_warm_up)

    def run(self, fn: Callable[..., T], *args: Any) -> T:
        pool, name = self._executor(), getattr(fn, "__name__", None) or repr(fn)
        try:
            return pool.submit(fn, *args).result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False)
            log.error("the solver process died during %s; a new one starts with the next solve", name)
            raise SolverCrashed(f"the solver process died during {name}") from None

    def stop(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
