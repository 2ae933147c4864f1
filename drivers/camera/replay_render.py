"""The replay camera's ``"sim"`` source: the simulated cell's frames rendered once, in a child process.

:func:`render_in_child` (the serving process) starts :func:`render_frames` in a
process of its own with multiprocessing ``spawn`` (a fresh interpreter: no fork
of the service's threads and locks), so that rendering (~30 ms a moving 1300 x 1030
frame) runs on a core of its own and never under the service's GIL. The child
writes the frames into a file-backed ``np.memmap`` in ``/dev/shm`` (shared
memory; the system's temporary folder where there is none) and sends the truth
back over a pipe. The parent maps the file read-only and removes its name at
once: the mapping stays valid, and nothing is left behind, however the service
ends later.

The child rebuilds the cell from its ``CellConfig``: a custom trajectory or the
commanded moves of the parent's ``SimCell`` are not carried over. Frame ``k``
shows the cell at ``t_start_s + k * period_s`` with the ring light lit.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import tempfile
import threading
import time
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.base import DriverDisconnected, DriverInitError
from drivers.camera.sim_render_child import shm_dir

POLL_S = 0.2  # how soon a cancel (the camera closed) or a dead child is noticed


def render_in_child(
    cell_config: dict[str, Any],
    shape: tuple[int, int, int],
    bit_depth: int,
    period_s: float,
    exposure_scale: float,
    seed: int,
    cancel: threading.Event,
    timeout_s: float,
    t_start_s: float = 0.0,
) -> tuple[NDArray[Any], NDArray[np.float64], NDArray[np.float64]]:
    """``shape[0]`` frames of the cell, rendered by a child process.

    Returns
    -------
    frames : (N, H, W) uint8 (``bit_depth`` 8) or uint16, a read-only memmap
    T_field_camera : (N, 4, 4) float, mm — each frame's true camera pose
    t_cell_s : (N,) float, s — each frame's cell time

    Raises ``DriverInitError`` when the child fails or takes longer than
    ``timeout_s``, ``DriverDisconnected`` when ``cancel`` is set meanwhile.
    """
    dtype = np.dtype(np.uint8 if bit_depth == 8 else np.uint16)
    ctx = multiprocessing.get_context("spawn")
    tmp = tempfile.mkdtemp(prefix="posecell-replay-", dir=shm_dir())
    path = os.path.join(tmp, "frames.raw")
    conn, child_conn = ctx.Pipe(duplex=False)
    child, answered = None, False
    try:
        np.memmap(path, dtype=dtype, mode="w+", shape=shape).flush()  # the file, at its full size
        args = (child_conn, path, shape, dtype.str, cell_config, period_s, t_start_s, exposure_scale, bit_depth, seed)
        child = ctx.Process(target=render_frames, args=args, name="replay-render", daemon=True)
        child.start()
        child_conn.close()
        msg = _wait_for(conn, child, cancel, timeout_s, shape[0])
        answered = True
        frames = np.memmap(path, dtype=dtype, mode="r", shape=shape)  # mapped: its name may go now
    finally:
        conn.close()
        child_conn.close()
        if child is not None:
            child.join(timeout=5.0 if answered else 0.0)  # an answered child is ending by itself
            if child.is_alive():  # cancelled, too slow, or stuck: stop it now
                child.kill()
                child.join(timeout=5.0)
        shutil.rmtree(tmp, ignore_errors=True)
    return frames, np.asarray(msg[1], dtype=np.float64), np.asarray(msg[2], dtype=np.float64)


def _wait_for(conn: Connection, child: Any, cancel: threading.Event, timeout_s: float, n: int) -> tuple[Any, ...]:
    deadline = time.monotonic() + timeout_s
    died = "the replay's render process ended (exit code {}) without sending its frames"
    while not conn.poll(POLL_S):
        if cancel.is_set():
            raise DriverDisconnected("the replay camera was closed while its frames were being rendered")
        if not child.is_alive() and not conn.poll(POLL_S):
            raise DriverInitError(died.format(child.exitcode))
        if time.monotonic() > deadline:
            raise DriverInitError(f"the replay did not render its {n} frames within {timeout_s:g} s")
    try:
        msg: tuple[Any, ...] = conn.recv()
    except EOFError:
        child.join(timeout=1.0)
        raise DriverInitError(died.format(child.exitcode)) from None
    if msg[0] != "ok":
        raise DriverInitError(f"the replay could not render the simulated cell's frames: {msg[1]}")
    return msg


def render_frames(
    conn: Connection,
    path: str,
    shape: tuple[int, int, int],
    dtype: str,
    cell_config: dict[str, Any],
    period_s: float,
    t_start_s: float,
    exposure_scale: float,
    bit_depth: int,
    seed: int,
) -> None:
    """The child: render into ``path``, answer ``("ok", T_field_camera, t_cell_s)`` or ``("error", sentence)``."""
    try:
        from service.sim.cell import CellConfig, SimCell
        from service.sim.render import RenderSettings

        cell = SimCell(CellConfig.from_dict(cell_config))
        settings = replace(RenderSettings(), exposure_scale=exposure_scale, bit_depth=bit_depth)
        rng = np.random.default_rng(seed)
        out = np.memmap(path, dtype=np.dtype(dtype), mode="r+", shape=shape)
        t_cell_s = t_start_s + period_s * np.arange(shape[0])
        truths = np.empty((shape[0], 4, 4))
        for k, t in enumerate(t_cell_s):
            frame = cell.render(float(t), rng, settings, lit=True)
            if frame.image.shape != shape[1:]:
                raise ValueError(f"the cell's camera renders {frame.image.shape} px frames, not {shape[1:]}")
            out[k] = frame.image
            truths[k] = frame.T_field_camera
        out.flush()
        del out
        conn.send(("ok", truths, t_cell_s))
    except Exception as e:  # the parent turns it into a DriverInitError
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()
