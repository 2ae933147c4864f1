"""The simulated camera's renderer: frames rendered in a child process, ahead of their exposure.

Why: rendering a 1300 x 1030 frame of the simulated cell takes ~30 ms (compiled
coverage and noise, the rest NumPy). Done in the camera's acquisition thread it competes for the service's
GIL with the measurement thread, and the camera delivers about half the frames
it is configured for. :class:`FrameRenderer` moves that work to a process of its
own, started with multiprocessing ``spawn`` (a fresh interpreter: no fork of the
service's threads and locks, as ``replay_render`` does), so that it runs on a
core of its own.

How:

- the camera submits a :class:`RenderJob` as soon as it knows a frame's exposure
  instant, a few frames ahead; the child renders the jobs in order into a ring
  of ``N_SLOTS`` frame slots in a file-backed shared memory map (``/dev/shm``;
  the child removes the file's name once both sides have it mapped, so nothing
  is left behind however the service ends later) and answers over a pipe;
  ``take()`` copies the finished image (its ROI) out of its slot;
- the child holds no cell: the camera computes each frame's pose from the shared
  ``SimCell`` (its program and the commanded moves) and sends it with the job;
  the child needs only the camera model and the field, pickled once at its start;
- each frame's noise comes from a generator of its own, ``default_rng(noise_key)``,
  so a frame is the same image whichever process renders it;
- jobs are rendered in-process (at ``take()``) while the child starts (1-2 s),
  when it cannot start (logged; in-process from then on), and when it died or
  hung with jobs outstanding; a dead child is restarted after ``RESTART_BACKOFF_S``,
  at most ``MAX_RESTARTS`` times (each logged), then the renderer stays in-process.

``close()`` asks the child to stop and kills it if it has not within
``STOP_TIMEOUT_S``; a child whose parent died sees the pipe close and ends.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.base import DriverDisconnected
from drivers.camera.sim_render_child import RenderJob, child_main, render_job, shm_dir

log = logging.getLogger(__name__)

N_SLOTS = 4  # frames in the child's hands at once (the camera asks for 3 ahead at most)
START_TIMEOUT_S = 60.0  # a child that has not said "ready" by then is given up (in-process from then on)
HUNG_S = 5.0  # a job outstanding this long means a stuck child: it is killed and restarted
RESTART_BACKOFF_S = 1.0
MAX_RESTARTS = 3
STOP_TIMEOUT_S = 0.5
POLL_S = 0.02  # the longest a waiting take() holds the lock (close() waits at most this long)


@dataclass
class _Ticket:
    job: RenderJob
    for_child: bool  # False: rendered in-process at take()
    slot: int | None = None  # None (for the child): waiting for a free slot
    slots: NDArray[np.uint8] | None = None  # the mapping the slot is in (a restarted child has its own)
    sent_s: float = 0.0
    done: tuple[str, tuple[int, ...]] | None = None  # (dtype, shape) once rendered
    error: str | None = None


class FrameRenderer:
    """Renders a camera's frames, in a child process when it can (see the module docstring).

    ``mode`` "process" (the default: a child, in-process until it is ready) or "inline" (always
    in-process). Not thread-safe towards several fetching threads; ``close()`` may come from any.
    """

    def __init__(
        self,
        camera: Any,
        field: Any,
        mode: str = "process",
        name: str = "sim camera",
        warmup_T_field_camera: NDArray[np.float64] | None = None,
    ) -> None:
        if mode not in ("process", "inline"):
            raise ValueError(f"render mode must be 'process' or 'inline', got {mode!r}")
        self.camera, self.field, self.mode, self.name = camera, field, mode, name
        self._warmup_T = np.eye(4) if warmup_T_field_camera is None else np.asarray(warmup_T_field_camera)
        self.render_s = 0.03  # running estimate of one frame's render time
        self.restarts = 0
        self._lock = threading.Lock()
        self._tickets: dict[int, _Ticket] = {}
        self._cancelled: dict[int, _Ticket] = {}  # sent to the child, then cancelled: kept until its answer
        self._next_ticket = 0
        self._closed = True
        self._given_up = mode == "inline"
        self._proc: Any = None
        self._conn: Connection | None = None
        self._slots: NDArray[np.uint8] | None = None
        self._free: list[int] = []
        self._tmp: str | None = None
        self._ready = False
        self._started_s = 0.0
        self._restart_at_s: float | None = None

    # --- the camera's side --------------------------------------------------------------------------

    @property
    def status(self) -> dict[str, Any]:
        """``state`` "child" | "starting" | "inline" | "closed", the child's ``pid``, ``restarts``, ``render_ms``."""
        with self._lock:
            state = "closed" if self._closed else "child" if self._ready else "starting" if self._proc else "inline"
            pid = self._proc.pid if self._proc is not None else None
            return {"state": state, "pid": pid, "restarts": self.restarts, "render_ms": round(self.render_s * 1e3, 2)}

    def start(self) -> None:
        """Start the child (if ``mode`` is "process"); returns at once: jobs render in-process until it is ready."""
        with self._lock:
            if not self._closed:
                return
            self._closed = False
            if not self._given_up:
                self._spawn()

    def wait_ready(self, timeout_s: float) -> bool:
        """True once jobs go to the child; False when it is not ready within ``timeout_s`` (or never will be)."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                self._pump(0.0)
                if self._ready or self._closed or (self._proc is None and self._restart_at_s is None):
                    return self._ready
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)

    def submit(self, job: RenderJob) -> int:
        """Hand over a job; returns its ticket for ``take()`` (or ``cancel()``)."""
        with self._lock:
            self._pump(0.0)
            ticket, self._next_ticket = self._next_ticket, self._next_ticket + 1
            self._tickets[ticket] = _Ticket(job, self._ready)
            self._send_waiting()
            return ticket

    @property
    def child_ready(self) -> bool:
        """True while jobs go to the child (it started and is alive, as far as its pipe says)."""
        with self._lock:
            self._pump(0.0)
            return self._ready

    def in_child(self, ticket: int) -> bool:
        """True when the child renders (or rendered) this job; False when ``take()`` will render it here."""
        with self._lock:
            t = self._tickets.get(ticket)
            return t is not None and t.for_child

    def backlog(self) -> int:
        """Jobs the child has yet to finish."""
        with self._lock:
            self._pump(0.0)
            return sum(1 for t in self._tickets.values() if t.for_child and t.done is None and t.error is None)

    def cancel(self, ticket: int) -> None:
        """Forget a job (its result, if it comes, frees its slot)."""
        with self._lock:
            t = self._tickets.pop(ticket, None)
            if t is None or t.slot is None:
                return
            if t.done is not None or t.error is not None:
                self._release(t)
                return
            self._cancelled[ticket] = t  # its answer frees the slot
            if self._conn is not None:
                try:
                    self._conn.send(("cancel", ticket))
                except (OSError, ValueError):
                    self._child_gone("could not be sent a cancel")

    def take(self, ticket: int, deadline_ns: int, roi: tuple[int, int, int, int] | None = None) -> NDArray[Any] | None:
        """The job's image (an owned copy of its ``roi`` (x, y, w, h)), or None when not rendered by ``deadline_ns``.

        A job for the child waits for it (the GIL released); any other is rendered now, whatever
        the deadline. A job not taken stays (take it again later). Raises ``DriverDisconnected``
        when the renderer is closed.
        """
        while True:
            with self._lock:
                if self._closed:
                    raise DriverDisconnected(f"the {self.name} is closed")
                t = self._tickets[ticket]
                if t.for_child and t.error is None:
                    if t.done is not None:
                        del self._tickets[ticket]
                        return self._copy_out(t, roi)
                    if t.slot is not None and time.monotonic() - t.sent_s > HUNG_S:
                        self._child_gone(f"has not rendered a frame in {HUNG_S:g} s", kill=True)
                        continue
                    wait_s = (deadline_ns - time.monotonic_ns()) * 1e-9
                    if wait_s <= 0:
                        return None
                    self._pump(min(wait_s, POLL_S))
                    continue
                if t.error is not None:
                    log.warning(
                        "%s: the render process failed a frame (%s); rendering it in-process", self.name, t.error
                    )
                    self._release(t)
                del self._tickets[ticket]
                t0 = time.perf_counter()
                image = render_job(self.camera, self.field, t.job)
                self._estimate(time.perf_counter() - t0)
                return _roi_copy(image, roi)

    def close(self) -> None:
        """Stop the child (killed if it has not ended within ``STOP_TIMEOUT_S``); idempotent."""
        with self._lock:
            self._closed = True
            self._tickets.clear()
            self._cancelled.clear()
            self._restart_at_s = None
            self._stop_child()

    # --- the child's lifecycle (the lock held) --------------------------------------------------------

    def _spawn(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        slot_bytes = int(self.camera.width) * int(self.camera.height) * 2  # up to 16 bits a pixel
        try:
            self._tmp = tempfile.mkdtemp(prefix="posecell-sim-render-", dir=shm_dir())
            path = os.path.join(self._tmp, "slots.raw")
            self._slots = np.memmap(path, dtype=np.uint8, mode="w+", shape=(N_SLOTS, slot_bytes))
            self._conn, child_conn = ctx.Pipe(duplex=True)
            args = (child_conn, path, N_SLOTS, slot_bytes, self.camera, self.field, self._warmup_T)
            self._proc = ctx.Process(target=child_main, args=args, name="sim-camera-render", daemon=True)
            self._proc.start()
            child_conn.close()
        except Exception as e:  # no process, no shared memory: the frames are rendered in-process
            log.warning(
                "%s: the render process could not start (%s: %s); rendering in-process", self.name, type(e).__name__, e
            )
            self._stop_child()
            self._given_up = True
            return
        self._free, self._ready, self._started_s = list(range(N_SLOTS)), False, time.monotonic()
        self._restart_at_s = None

    def _pump(self, timeout_s: float) -> None:
        """Read the child's answers (waiting up to ``timeout_s`` for the first); restart a dead child when due."""
        if self._closed:
            return
        if self._proc is None:
            if self._restart_at_s is not None and time.monotonic() >= self._restart_at_s:
                self._spawn()
            return
        if not self._ready and time.monotonic() - self._started_s > START_TIMEOUT_S:
            self._given_up = True
            self._child_gone(f"did not start within {START_TIMEOUT_S:g} s", kill=True)
            return
        conn = self._conn
        assert conn is not None
        try:
            while conn.poll(timeout_s):
                self._answer(conn.recv())
                timeout_s = 0.0
        except (EOFError, OSError):
            self._child_gone("ended")
        self._send_waiting()

    def _send_waiting(self) -> None:
        """Send the jobs waiting for a slot, oldest first, while slots are free."""
        for ticket, t in self._tickets.items():
            if not self._free or self._conn is None:
                return
            if t.for_child and t.slot is None and t.done is None and t.error is None:
                t.slot, t.slots, t.sent_s = self._free.pop(), self._slots, time.monotonic()
                try:
                    self._conn.send(("render", ticket, t.slot, t.job))
                except (OSError, ValueError):
                    self._child_gone("could not be sent a job")
                    return

    def _answer(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "ready":
            self._ready = True
            self._estimate(msg[1])
            log.info("%s: frames are rendered by process %d (%.0f ms a frame)", self.name, self._proc.pid, msg[1] * 1e3)
            return
        if kind == "fatal":
            self._given_up = True
            self._child_gone(f"could not render ({msg[1]})", kill=True)
            return
        ticket = msg[1]
        t = self._cancelled.pop(ticket, None)
        cancelled = t is not None
        t = t or self._tickets.get(ticket)
        if t is None:
            return
        if kind == "done":
            t.done = (msg[2], tuple(msg[3]))
            self._estimate(msg[4])
        elif kind == "failed":
            t.error = msg[2]
        if cancelled or kind == "skipped":
            self._release(t)

    def _child_gone(self, why: str, kill: bool = False) -> None:
        """The child ended (or is ended now): its jobs render in-process; it is restarted unless given up."""
        proc = self._proc
        if kill and proc is not None:
            proc.kill()
        if proc is not None:
            proc.join(timeout=STOP_TIMEOUT_S)
        code = None if proc is None else proc.exitcode
        self._stop_child()
        self._cancelled.clear()
        for t in self._tickets.values():
            if t.done is None:  # not rendered: rendered in-process at take()
                t.for_child, t.slot, t.slots, t.error = False, None, None, None
        if self._given_up or self.restarts >= MAX_RESTARTS:
            self._given_up = True
            log.warning(
                "%s: the render process %s (exit code %s); rendering in-process from now on", self.name, why, code
            )
            return
        self.restarts += 1
        self._restart_at_s = time.monotonic() + RESTART_BACKOFF_S
        msg = "%s: the render process %s (exit code %s); restarting it in %g s (restart %d of %d), in-process meanwhile"
        log.warning(msg, self.name, why, code, RESTART_BACKOFF_S, self.restarts, MAX_RESTARTS)

    def _stop_child(self) -> None:
        proc, conn, ready = self._proc, self._conn, self._ready
        self._proc = self._conn = None
        self._ready = False
        self._free = []
        if conn is not None and ready:
            try:
                conn.send(("stop",))
            except (OSError, ValueError):
                pass
        if proc is not None:
            if ready:  # it reads its pipe between frames; a starting one is still importing
                proc.join(timeout=STOP_TIMEOUT_S)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=STOP_TIMEOUT_S)
        if conn is not None:
            conn.close()
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)  # the child removes it once mapped; this if it never did
            self._tmp = None
        self._slots = None  # done jobs keep their mapping (their ticket holds it) until taken

    # --- helpers -------------------------------------------------------------------------------------

    def _release(self, t: _Ticket) -> None:
        if t.slot is not None and t.slots is self._slots and self._slots is not None:
            self._free.append(t.slot)
        t.slot = None

    def _copy_out(self, t: _Ticket, roi: tuple[int, int, int, int] | None) -> NDArray[Any]:
        assert t.done is not None and t.slots is not None and t.slot is not None
        dtype, shape = np.dtype(t.done[0]), t.done[1]
        n = int(np.prod(shape)) * dtype.itemsize
        image = _roi_copy(t.slots[t.slot, :n].view(dtype).reshape(shape), roi)
        self._release(t)
        return image

    def _estimate(self, render_s: float) -> None:
        self.render_s = min(0.5, 0.8 * self.render_s + 0.2 * float(render_s))


def _roi_copy(image: NDArray[Any], roi: tuple[int, int, int, int] | None) -> NDArray[Any]:
    if roi is None:
        return image.copy()
    x, y, w, h = roi
    return image[y : y + h, x : x + w].copy()
