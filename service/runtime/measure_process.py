"""One camera's frames measured in a process of its own.

In the service's process the measurement shares the interpreter lock with acquisition,
the robot's reader, storage and the WebSocket fan-out. Measured in the running service at
500 Hz a ROI frame took ~3 ms where ``posecell bench speed`` measures ~0.7 ms: most of it
waiting for the lock after each compiled kernel. Here the :class:`FrameMeasurer` (with its
ROI tracking state) lives in a child process:

- the child is forked from a fork server that has imported the measurement and loaded the
  compiled kernels (:mod:`service.runtime._measure_child`), so it starts in tens of ms,
  not the ~2 s of a fresh interpreter, and not by forking a process that runs threads;
- the frame goes by shared memory (one copy, made while the lock is free); the request
  and the :class:`Outcome` (a few kB) go by a pipe;
- the calling thread waits on the pipe without the interpreter lock.

``MeasureProcess.measure`` has the measurer's signature, so the processor uses either.
A child that dies or hangs is replaced at the next frame (the ROI tracking starts again
with a full frame); the frame it had is reported as failed, with a sentence.
"""

from __future__ import annotations

import logging
import mmap
import multiprocessing
import os
import signal
import tempfile
import threading
import traceback
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, NoReturn, Protocol

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.results import PoseResult, TargetTable
from service.core.targets.field import Field
from service.pipeline.measure import FrameMeasurer, MeasureSettings, Outcome

log = logging.getLogger(__name__)

SETUP_TIMEOUT_S = 300.0  # a child on a machine whose kernel cache went stale compiles them (~2 min)
MEASURE_TIMEOUT_S = 10.0  # a frame takes milliseconds; a child silent this long is hung and replaced
_SHM_DIR = "/dev/shm" if os.path.isdir("/dev/shm") else None  # memory-backed; else the temp dir

_context_lock = threading.Lock()
_context: Any = None


class Measurer(Protocol):
    def measure(self, image: NDArray[np.generic], t_s: float | None = None) -> Outcome: ...


class MeasureProcessError(RuntimeError):
    """The child died, hung or could not measure; the message says which and what happens next."""


def _fork_server() -> Any:
    """The fork-server context, its server preloading the measurement (started on first use)."""
    global _context
    with _context_lock:
        if _context is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(["service.runtime._measure_child"])
            _context = ctx
        return _context


class MeasureProcess:
    """A child process measuring one camera's frames (see the module docstring); one calling thread."""

    def __init__(self, camera_name: str) -> None:
        self.camera_name = camera_name
        self._setup: tuple[BrownFraser, Field, MeasureSettings] | None = None
        self._proc: Any = None
        self._conn: Connection | None = None
        self._buffer: mmap.mmap | None = None
        self._capacity = 0
        self._in_flight = False
        self.restarts = 0  # children replaced after dying or hanging
        self.measure_timeout_s = MEASURE_TIMEOUT_S

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    def configure(self, camera: BrownFraser, field: Field, settings: MeasureSettings) -> None:
        """Measure with these from the next frame on (the tracking starts again); starts the child."""
        self._setup = (camera, field, settings)
        if self._in_flight:  # not done by the processor (it collects before the next frame); kept safe
            self.collect()
        if self._conn is None:
            self._start()
        else:
            self._call(("setup", *self._setup), SETUP_TIMEOUT_S)

    def measure(self, image: NDArray[np.generic], t_s: float | None = None) -> Outcome:
        self.submit(image, t_s)
        return self.collect()

    def submit(self, image: NDArray[np.generic], t_s: float | None = None) -> None:
        """Hand a frame to the child (its outcome is :meth:`collect`'s); one frame at a time."""
        if self._setup is None:
            raise MeasureProcessError("the measurement process has no camera and field yet")
        if self._in_flight:
            raise MeasureProcessError("a frame is already being measured: collect its outcome first")
        if self._conn is None:
            self._start()
        image = np.asarray(image)
        if image.nbytes > self._capacity:
            self._map_buffer(image.nbytes)
        assert self._buffer is not None and self._conn is not None
        np.copyto(np.ndarray(image.shape, image.dtype, buffer=self._buffer), image)
        try:
            self._conn.send(("measure", image.shape, image.dtype.str, t_s))
        except OSError:
            self._lost("died")
        self._in_flight = True

    def collect(self) -> Outcome:
        """The outcome of the submitted frame (waits for it, without the interpreter lock)."""
        if not self._in_flight:
            raise MeasureProcessError("no frame was submitted")
        self._in_flight = False
        outcome = self._reply(self.measure_timeout_s)
        assert isinstance(outcome, Outcome)
        return outcome

    def close(self) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        self._in_flight = False
        if conn is not None:
            try:
                conn.send(("stop",))
            except OSError:
                pass
            conn.close()
        if proc is not None:
            proc.join(timeout=2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)
        if self._buffer is not None:
            self._buffer.close()
        self._buffer, self._capacity = None, 0

    # --- internals ----------------------------------------------------------------------------

    def _start(self) -> None:
        assert self._setup is not None
        ctx = _fork_server()
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=serve, args=(child,), name=f"posecell-measure-{self.camera_name}", daemon=True)
        proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        self._capacity = 0  # the new child maps the buffer afresh
        self._call(("setup", *self._setup), SETUP_TIMEOUT_S)

    def _map_buffer(self, nbytes: int) -> None:
        """A new shared buffer of at least ``nbytes``, mapped here and in the child."""
        capacity = max(nbytes, 2 * self._capacity, 1 << 20)
        fd, path = tempfile.mkstemp(prefix="posecell-frames-", dir=_SHM_DIR)
        try:
            os.ftruncate(fd, capacity)
            buffer = mmap.mmap(fd, capacity)
        finally:
            os.close(fd)
        try:
            self._call(("buffer", path, capacity), self.measure_timeout_s)
        finally:
            os.unlink(path)  # both have it mapped: nothing is left behind whatever happens to either
        if self._buffer is not None:
            self._buffer.close()
        self._buffer, self._capacity = buffer, capacity

    def _call(self, message: tuple[Any, ...], timeout_s: float) -> Any:
        assert self._conn is not None
        try:
            self._conn.send(message)
        except OSError:
            self._lost("died")
        return self._reply(timeout_s)

    def _reply(self, timeout_s: float) -> Any:
        conn, proc = self._conn, self._proc
        assert conn is not None and proc is not None
        try:
            if not conn.poll(timeout_s):
                self._lost(f"did not answer within {timeout_s:.0f} s")
            status, payload = conn.recv()
        except (EOFError, OSError):
            self._lost("died")
        if status != "ok":
            raise MeasureProcessError(f"the measurement process of camera {self.camera_name} failed: {payload}")
        return payload

    def _lost(self, what: str) -> NoReturn:
        """The child died or hung: stop it, say so; the next frame starts a new one."""
        proc = self._proc
        if proc is not None:
            proc.join(timeout=0.2)
            if proc.exitcode is not None:
                what = f"{what} (exit code {proc.exitcode})"
        self._replace(what)

    def _replace(self, what: str) -> NoReturn:
        self.close()
        self.restarts += 1
        log.error(
            "the measurement process of camera %s %s; a new one starts with the next frame", self.camera_name, what
        )
        raise MeasureProcessError(
            f"the measurement process of camera {self.camera_name} {what}; a new one starts with the next frame"
        )


# --- the child ------------------------------------------------------------------------------------


def serve(conn: Connection) -> None:
    """The child's loop: set-up, buffer and measure requests until ``stop`` or the parent goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in a terminal is the service's to handle
    measurer: FrameMeasurer | None = None
    buffer: mmap.mmap | None = None
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        kind = message[0]
        if kind == "stop":
            return
        try:
            if kind == "setup":
                _, camera, field, settings = message
                measurer, reply = FrameMeasurer(camera, field, settings), None
            elif kind == "buffer":
                _, path, capacity = message
                with Path(path).open("r+b") as f:
                    new = mmap.mmap(f.fileno(), capacity)
                if buffer is not None:
                    buffer.close()
                buffer, reply = new, None
            elif kind == "measure":
                assert measurer is not None and buffer is not None, "measure before setup and buffer"
                _, shape, dtype, t_s = message
                reply = measurer.measure(np.ndarray(shape, np.dtype(dtype), buffer=buffer), t_s)
                if isinstance(reply.result, PoseResult) and isinstance(reply.result.targets, TargetTable):
                    reply.result.targets.to_json()  # encoded here, sent with the table: not in the parent
            else:
                raise ValueError(f"unknown request {kind!r}")
        except Exception as e:  # the parent reports it as the frame's failure; the child stays
            conn.send(("error", f"{e!r}\n{traceback.format_exc(limit=8)}"))
            continue
        conn.send(("ok", reply))
