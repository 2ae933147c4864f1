"""How fast this host renders the simulated cell: what the 20 Hz no-gap tests can ask of it.

The simulated camera renders each frame (its stand-in for exposure and readout) in a child process.
Where one render takes most of the 50 ms period (40 ms on a slow 2-core VM, against ~25-30 ms on a
faster one), a render that a loaded host delays past its period is a gap in ``seq``: the
simulation's limit, not the service's. The tests allow a late render or two there, and none where
the renderer has room.
"""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np

PERIOD_MS = 50.0  # the simulated cell's 20 Hz
ROOM = 0.6  # of the period: a host that renders within it must show no gap


@lru_cache(maxsize=1)
def sim_render_ms() -> float:
    """The median time of three renders of the simulated cell's frame in this process, ms (the
    first measurement in the process: see :func:`allowed_gaps` for the one taken at the check)."""
    return _render_ms()


def _render_ms() -> float:
    from service.sim.cell import CellConfig, SimCell
    from service.sim.render import RenderSettings

    cell, rng = SimCell(CellConfig()), np.random.default_rng(0)
    cell.render(0.0, rng, RenderSettings(), lit=True)  # the first loads the kernels
    times = []
    for k in range(3):
        t0 = time.perf_counter()
        cell.render(0.05 * (k + 1), rng, RenderSettings(), lit=True)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def allowed_gaps(n_frames: int) -> int:
    """Gaps in ``seq`` a 20 Hz stream of ``n_frames`` of the simulated camera may show on this host:
    0, or a sixth of them (at least 2) where a render takes more than ROOM of the period (4 of 60
    seen under the whole suite on a slow 2-core VM; 5 of 41 on 2026-12-05's slower one, whose
    render takes 40 ms of the 50; rendering under the service's interpreter lock, the regression
    these tests are there for, skips half or more).

    The render is timed when the process first asks and again now, and the slower counts: the same
    VM renders ~1.7x slower for stretches of seconds to minutes (a stream that had no room while the
    first timing said it had: 2 gaps in 44 frames, 18.3 fps)."""
    render_ms = max(sim_render_ms(), _render_ms())
    return 0 if render_ms < ROOM * PERIOD_MS else max(2, n_frames // 6)
