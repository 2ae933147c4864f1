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
- the calling thread waits on the pipe without the interpreter lock;
- up to two frames are in flight (:data:`DEPTH`): when frames come faster than the child
  measures, the next one is already in its pipe as it answers the last, so it does not
  idle while this process wakes up and finishes that one (flange, storage, fan-out).

``MeasureProcess.measure`` has the measurer's signature, so the processor uses either.
A child that dies or hangs is replaced at the next frame (the ROI tracking starts again
with a full frame); the frame it had is reported as failed, with a sentence.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import multiprocessing
import os
import signal
import tempfile
import threading
import time
import traceback
from collections import deque
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, NoReturn, Protocol

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.results import PoseResult, TargetTable
from service.core.targets.defects import DefectMap
from service.core.targets.field import Field
from service.pipeline.measure import FrameMeasurer, MeasureSettings, Outcome
from service.runtime.cpus import pin_process

log = logging.getLogger(__name__)

SETUP_TIMEOUT_S = 300.0  # a child on a machine whose kernel cache went stale compiles them (~2 min)
DEPTH = 2  # frames in flight at most: one measured, the next waiting in the pipe
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
    """A child process measuring one camera's frames (see the module docstring); one calling thread.

    Up to :data:`DEPTH` frames are in flight: the child takes the next request from its pipe the
    moment it has answered the last, so it does not wait for this process to wake up between
    frames when they come faster than it measures. Requests are answered in order.
    """

    def __init__(self, camera_name: str) -> None:
        self.camera_name = camera_name
        self._cpus: frozenset[int] | None = None  # the child's CPUs (None: as it inherits them)
        self._setup: tuple[BrownFraser, Field, MeasureSettings, DefectMap | None] | None = None
        self._proc: Any = None
        self._conn: Connection | None = None
        self._buffer: mmap.mmap | None = None
        self._retired: list[mmap.mmap] = []  # replaced buffers, until their frames are answered
        self._generation = 0  # of the buffer: a slot is freed only into the buffer it belongs to
        self._slot_bytes = 0
        self._free: deque[int] = deque()
        self._in_flight: deque[tuple[int, int]] = deque()  # (buffer generation, slot), in request order
        self._lost_frames = 0  # frames that were in flight when the child was lost
        self._lost_message = ""
        self._paths: list[str] = []  # buffer files whose name the child has not removed yet
        self._start_failed = False
        self.restarts = 0  # children replaced after dying or hanging
        self.measure_timeout_s = MEASURE_TIMEOUT_S

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    def keep_to(self, cpus: frozenset[int] | None) -> None:
        """Run the child on ``cpus`` from now on (and every child started after it)."""
        self._cpus = cpus
        if cpus is not None and self._proc is not None and self._proc.pid is not None:
            pin_process(int(self._proc.pid), cpus)

    def waitable(self) -> Connection | None:
        """The connection the answers arrive on (to wait for one with other files), None without a child."""
        return self._conn if self._in_flight else None

    def can_submit(self) -> bool:
        """True when a frame can be handed over now (fewer than :data:`DEPTH` in flight)."""
        return len(self._in_flight) < DEPTH

    def configure(
        self, camera: BrownFraser, field: Field, settings: MeasureSettings, defects: DefectMap | None = None
    ) -> None:
        """Measure with these from the next frame submitted on (the tracking starts again); starts the child.

        Frames already in flight are measured with the previous set-up.
        """
        self._setup = (camera, field, settings, defects)
        if self._conn is None:
            self._start()
        else:
            self._send(("setup", *self._setup))

    def measure(self, image: NDArray[np.generic], t_s: float | None = None) -> Outcome:
        self.submit(image, t_s)
        return self.collect()

    def submit(self, image: NDArray[np.generic], t_s: float | None = None) -> None:
        """Hand a frame to the child; its outcome is the one :meth:`collect` returns in turn."""
        if self._setup is None:
            raise MeasureProcessError("the measurement process has no camera and field yet")
        if not self.can_submit():
            raise MeasureProcessError(f"{DEPTH} frames are already being measured: collect an outcome first")
        if self._conn is None:
            self._start()
        image = np.asarray(image)
        if image.nbytes > self._slot_bytes:
            self._map_buffer(image.nbytes)
        assert self._buffer is not None
        slot = self._free.popleft()
        at = slot * self._slot_bytes
        np.copyto(np.ndarray(image.shape, image.dtype, buffer=self._buffer, offset=at), image)
        self._send(("measure", at, image.shape, image.dtype.str, t_s))
        self._in_flight.append((self._generation, slot))

    def collect(self) -> Outcome:
        """The outcome of the oldest frame submitted (waits for it, without the interpreter lock)."""
        if not self._in_flight:
            if self._lost_frames:  # it was in flight when the child was lost: the same sentence
                self._lost_frames -= 1
                raise MeasureProcessError(self._lost_message)
            raise MeasureProcessError("no frame was submitted")
        generation, slot = self._in_flight.popleft()
        try:
            outcome = self._reply(self.measure_timeout_s)
        finally:
            if generation == self._generation and self._conn is not None:
                self._free.append(slot)
            if not self._in_flight:
                for old in self._retired:
                    old.close()
                self._retired.clear()
        assert isinstance(outcome, Outcome)
        return outcome

    def close(self) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        self._in_flight.clear()
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
        for buffer in (self._buffer, *self._retired):
            if buffer is not None:
                buffer.close()
        self._buffer, self._retired, self._slot_bytes = None, [], 0
        self._free.clear()
        for path in self._paths:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        self._paths.clear()

    # --- internals ----------------------------------------------------------------------------

    def _start(self) -> None:
        assert self._setup is not None
        try:
            ctx = _fork_server()
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=serve, args=(child,), name=f"posecell-measure-{self.camera_name}", daemon=True)
            proc.start()
        except (OSError, RuntimeError) as e:  # no processes or pipes left, a main module without its guard
            message = f"the measurement process of camera {self.camera_name} could not be started: {e!r}"
            if not self._start_failed:  # said once, not at the frame rate; each frame's result says it too
                log.error("%s", message)
            self._start_failed = True
            raise MeasureProcessError(message) from None
        self._start_failed = False
        if self._cpus is not None:
            pin_process(int(proc.pid), self._cpus)
        child.close()
        self._proc, self._conn = proc, parent
        self._lost_frames = 0
        self._send(("setup", *self._setup))
        self._send(("ping",))  # answered once the set-up is done (or with its error)
        self._reply(SETUP_TIMEOUT_S)

    def _map_buffer(self, nbytes: int) -> None:
        """A new shared buffer of :data:`DEPTH` slots of at least ``nbytes``, mapped here and in the child.

        The child maps it when it comes to the request, after the frames already asked for (which
        it reads from the old buffer: kept here until they are answered), and removes its name.
        """
        slot_bytes = max(nbytes, 2 * self._slot_bytes, 1 << 20)
        try:
            fd, path = tempfile.mkstemp(prefix="posecell-frames-", dir=_SHM_DIR)
        except OSError:  # /dev/shm not writable here (a sandbox): a file in the temp directory maps too
            fd, path = tempfile.mkstemp(prefix="posecell-frames-")
        self._paths.append(path)  # removed by the child once mapped; by close() if it never was
        try:
            os.ftruncate(fd, DEPTH * slot_bytes)
            buffer = mmap.mmap(fd, DEPTH * slot_bytes)
        finally:
            os.close(fd)
        self._send(("buffer", path, DEPTH * slot_bytes))
        if self._buffer is not None:
            self._retired.append(self._buffer)
        self._buffer, self._slot_bytes = buffer, slot_bytes
        self._generation += 1
        self._free = deque(range(DEPTH))

    def _send(self, message: tuple[Any, ...]) -> None:
        assert self._conn is not None
        try:
            self._conn.send(message)
        except OSError:
            self._lost("died")

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

    def _call(self, message: tuple[Any, ...], timeout_s: float) -> Any:
        """Send a request that is answered (with nothing in flight: the answer is its own)."""
        self._send(message)
        return self._reply(timeout_s)

    def _lost(self, what: str) -> NoReturn:
        """The child died or hung: stop it, say so; the next frame starts a new one."""
        proc = self._proc
        if proc is not None:
            proc.join(timeout=0.2)
            if proc.exitcode is not None:
                what = f"{what} (exit code {proc.exitcode})"
        message = f"the measurement process of camera {self.camera_name} {what}; a new one starts with the next frame"
        lost = len(self._in_flight)  # the others still in flight: each told by its collect()
        self.close()
        self._lost_frames, self._lost_message = lost, message
        self.restarts += 1
        log.error("%s", message)
        raise MeasureProcessError(message)


# --- the child ------------------------------------------------------------------------------------


def serve(conn: Connection) -> None:
    """The child's loop, until ``stop`` or the parent goes away.

    ``setup`` and ``buffer`` are not answered (they are ordered with the frames); an error in one
    is the answer to the next ``measure`` or ``ping``. Each ``measure`` and ``ping`` is answered.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in a terminal is the service's to handle
    measurer: FrameMeasurer | None = None
    buffer: mmap.mmap | None = None
    errors: dict[str, str] = {}  # of the unanswered requests that failed, told with every answer
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
                _, camera, field, settings, defects = message
                measurer = None
                measurer = FrameMeasurer(camera, field, settings, defects, frames_owned=True)  # its shared slot
                errors.pop(kind, None)
                continue
            if kind == "buffer":
                _, path, nbytes = message
                with Path(path).open("r+b") as f:
                    new = mmap.mmap(f.fileno(), nbytes)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(path)  # mapped on both sides: nothing is left behind whatever happens to either
                if buffer is not None:
                    buffer.close()
                buffer = new
                errors.pop(kind, None)
                continue
            if errors:
                raise RuntimeError("; ".join(errors.values()))
            if kind == "ping":
                reply: Any = None
            elif kind == "measure":
                if measurer is None or buffer is None:
                    raise RuntimeError("a frame before the set-up and the buffer")
                _, offset, shape, dtype, t_s = message
                t0 = time.perf_counter()
                reply = measurer.measure(np.ndarray(shape, np.dtype(dtype), buffer=buffer, offset=offset), t_s)
                if isinstance(reply.result, PoseResult) and isinstance(reply.result.targets, TargetTable):
                    reply.result.targets.to_json()  # encoded here, sent with the table: not in the parent
                # the child's whole time on the frame: the parent's "measure" minus this is the hand-over
                reply.timings_ms["child"] = (time.perf_counter() - t0) * 1e3
            else:
                raise ValueError(f"unknown request {kind!r}")
        except Exception as e:  # the parent reports it as the frame's failure; the child stays
            if kind in ("setup", "buffer"):
                errors[kind] = f"the {kind} failed: {e!r}"
            else:
                reply = ("error", f"{e!r}\n{traceback.format_exc(limit=8)}")
                if not _answer(conn, reply):
                    return
            continue
        if not _answer(conn, ("ok", reply)):
            return


def _answer(conn: Connection, reply: tuple[str, Any]) -> bool:
    """Send ``reply``; False when the parent has gone (it stopped or died): the child then ends
    quietly instead of printing a broken pipe's traceback at every shutdown."""
    try:
        conn.send(reply)
    except OSError:  # BrokenPipeError, ConnectionResetError: nobody is listening any more
        return False
    return True
