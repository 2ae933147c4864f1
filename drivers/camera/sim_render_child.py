"""The simulated camera's render process (the child side of ``sim_render``) and what both sides share.

:func:`serve_renders` runs in a process of its own (multiprocessing ``spawn``): it
maps the frame slots the parent created in shared memory, removes their file's
name (both sides have them mapped: nothing is left behind), warms up, and then
renders the parent's jobs in order into their slots until told to stop or until
the parent is gone (its pipe closes). :func:`render_job` is the one function both
processes render with, so that a job gives the same image in either.
"""

from __future__ import annotations

import collections
import os
import shutil
import signal
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray


def shm_dir() -> str | None:
    """``/dev/shm`` (shared memory) where it is writable, else None (the system's temporary folder)."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


@dataclass(frozen=True)
class RenderJob:
    """One frame to render: ``render_frame(camera, field, T_field_camera, settings, default_rng(noise_key))``.

    ``T_field_camera`` (4, 4) float, mm; ``settings`` a ``RenderSettings`` (with the ring light's
    state); ``noise_key`` the entropy of the frame's own noise generator.
    """

    T_field_camera: NDArray[np.float64]
    settings: Any
    noise_key: tuple[int, ...]


def render_job(camera: Any, field: Any, job: RenderJob) -> NDArray[Any]:
    """The image of ``job``: the one function both processes render with."""
    from service.sim.render import render_frame

    rng = np.random.default_rng(list(job.noise_key))
    return render_frame(camera, field, job.T_field_camera, job.settings, rng).image


def child_main(*args: Any) -> None:
    """The render process's target: :func:`serve_renders`, then out at once (the slots are the parent's,
    so there is nothing to clean up, and a full interpreter shutdown would take ~0.3 s of ``close()``)."""
    try:
        serve_renders(*args)
    finally:
        os._exit(0)


def serve_renders(
    conn: Connection,
    path: str,
    n_slots: int,
    slot_bytes: int,
    camera: Any,
    field: Any,
    warmup_T_field_camera: NDArray[np.float64],
) -> None:
    """The child: render jobs into their slots of ``path`` in order until told to stop or the parent is gone.

    Sends ``("ready", render_s)`` once warmed up (or ``("fatal", sentence)``), then per job
    ``("done", ticket, dtype, shape, render_s)``, ``("failed", ticket, sentence)`` or, for a job
    cancelled before it was rendered, ``("skipped", ticket)``.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C of the service is the service's to handle
    try:
        import cv2

        cv2.setNumThreads(1)  # one core for the renders, the other for the service (and no faster with two)
        slots = np.memmap(path, dtype=np.uint8, mode="r+", shape=(n_slots, slot_bytes))
        shutil.rmtree(os.path.dirname(path), ignore_errors=True)  # both sides have it mapped: no name left
        from service.sim.render import RenderSettings

        warm = RenderJob(warmup_T_field_camera, RenderSettings(), (0,))  # a fresh process's first frames are slow
        render_job(camera, field, warm)
        t0 = time.perf_counter()
        render_job(camera, field, warm)
        conn.send(("ready", time.perf_counter() - t0))
    except Exception as e:
        try:
            conn.send(("fatal", f"{type(e).__name__}: {e}"))
        finally:
            conn.close()
        return
    pending: collections.deque[tuple[int, int, RenderJob]] = collections.deque()
    cancelled: set[int] = set()
    try:
        while True:
            while not pending or conn.poll(0):  # read every waiting message before rendering the next
                msg = conn.recv()
                if msg[0] == "stop":
                    return
                if msg[0] == "cancel":
                    if any(p[0] == msg[1] for p in pending):  # else it was rendered already
                        cancelled.add(msg[1])
                else:
                    pending.append(msg[1:])
            ticket, slot, job = pending.popleft()
            if ticket in cancelled:
                cancelled.discard(ticket)
                conn.send(("skipped", ticket))
                continue
            try:
                t0 = time.perf_counter()
                image = render_job(camera, field, job)
                if image.nbytes > slot_bytes:
                    raise ValueError(f"a {image.shape} {image.dtype} frame does not fit a {slot_bytes} byte slot")
                slots[slot, : image.nbytes].view(image.dtype).reshape(image.shape)[...] = image
                conn.send(("done", ticket, image.dtype.str, image.shape, time.perf_counter() - t0))
            except Exception as e:  # the parent renders it in-process and logs why
                conn.send(("failed", ticket, f"{type(e).__name__}: {e}"))
    except (EOFError, OSError):  # the parent is gone
        return
    finally:
        conn.close()
