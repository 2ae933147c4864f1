"""Compile the measurement's numba kernels ahead of their first use, two at a time.

On a fresh machine the kernels compile when first called: ~2.7 min on one core of the project's VM
for 8- and 16-bit frames, writeable and read-only (a replayed frame is read-only and numba compiles
once per argument type; the ring reader for each image type ~10 s). numba caches them beside
their modules (``cache=True``) and every later process loads them in well under a second.
``python -m service.pipeline.compile`` compiles them in two processes at once, so the first start
of the service or of the tests waits about half as long; ``deploy/dev.sh`` runs it after installing.
"""

from __future__ import annotations

import importlib
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor

# two groups of about equal compile time; each module's warm_up() compiles its kernels
GROUPS = (
    (
        "service.core._kernels.detect_kernel",
        "service.core._kernels.roi_kernel",
        "service.sim._raster_kernel",
        "service.core._kernels.json_kernel",
    ),
    ("service.core._kernels.geometry_kernels", "service.core._kernels.resection_kernel", "service.core.targets.decode"),
)


def _compile(modules: tuple[str, ...]) -> float:
    t0 = time.perf_counter()
    for name in modules:
        importlib.import_module(name).warm_up()
    return time.perf_counter() - t0


def compile_kernels(processes: int = 2) -> list[float]:
    """Compile (or load) every kernel; the seconds each group took."""
    # spawned, not forked: a fresh interpreter per group, whatever the caller holds
    with ProcessPoolExecutor(max_workers=processes, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(_compile, GROUPS))


def main() -> int:
    t0 = time.perf_counter()
    took = compile_kernels()
    groups = ", ".join(f"{s:.0f} s" for s in took)
    sys.stderr.write(f"posecell: numba kernels ready in {time.perf_counter() - t0:.0f} s ({groups})\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
