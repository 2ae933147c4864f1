"""Compile the measurement's numba kernels ahead of their first use, two at a time.

On a fresh machine the kernels compile when first called: ~2.7 min on one core of the project's VM
for 8- and 16-bit frames, writeable and read-only (a replayed frame is read-only and numba compiles
once per argument type; the ring reader for each image type ~10 s). numba caches them beside
their modules (``cache=True``) and every later process loads them in well under a second.
``python -m service.pipeline.compile`` compiles them in two processes at once, so the first start
of the service or of the tests waits about half as long; ``deploy/dev.sh`` runs it after installing.

numba keys a kernel's cache on its own file only: a kernel that calls another module's kernel keeps
that one's old code after it changes (numba's documented limitation; seen here once as a stale ROI
kernel after an edit, and a ``git pull`` or an upgrade that changes one module does the same). So
before the kernels load, :func:`refresh_kernel_caches` compares the kernel modules' contents with
those the caches were made from and empties every cache when they differ: here at set-up, at the
start of every ``posecell`` verb and of the service, and at the start of the tests.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Any

# two groups of about equal compile time; each module's warm_up() compiles its kernels
GROUPS = (
    (
        "service.core._kernels.detect_kernel",
        "service.core._kernels.roi_kernel",
        "service.sim._raster_kernel",
        "service.core._kernels.json_kernel",
        "service.core._kernels.edge_kernel",
        "service.core._kernels.defects_kernel",
    ),
    ("service.core._kernels.geometry_kernels", "service.core._kernels.resection_kernel", "service.core.targets.decode"),
)


#: the packages whose kernels call each other's (a kernel elsewhere calls only its own module's)
KERNEL_PACKAGES = ("service.core._kernels",)


def refresh_stale_caches(directory: Path, package: str) -> bool:
    """Empty the numba caches of every kernel of ``package`` (its modules: the ``*.py`` in
    ``directory``) when the modules' contents differ from those the caches were made from, as
    recorded beside the caches; True when it did. Each cache location (``__pycache__``, a service's
    ``NUMBA_CACHE_DIR``) keeps its own record. Imports every module of the package."""
    from numba.core.dispatcher import Dispatcher

    sources = sorted(directory.glob("*.py"))
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    caches: list[Any] = []
    for path in sources:
        if path.stem == "__init__":
            continue
        for d in vars(importlib.import_module(f"{package}.{path.stem}")).values():
            # numba keeps a dispatcher's cache in _cache; flush() and cache_path are the cache's own API
            cache = getattr(d, "_cache", None) if isinstance(d, Dispatcher) else None
            if hasattr(cache, "cache_path"):
                caches.append(cache)
    if not caches:
        return False
    stamp = Path(caches[0].cache_path) / f"{package}.sources.sha256"
    with contextlib.suppress(OSError):
        if stamp.read_text() == digest.hexdigest():
            return False
    try:
        for cache in caches:
            cache.flush()  # an empty index: the next call compiles, with the current code of every module
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(digest.hexdigest())
        tmp.replace(stamp)
    except OSError:  # a cache that cannot be written is not read either
        return False
    return True


@lru_cache(maxsize=1)  # once per process: before its first kernel loads
def refresh_kernel_caches() -> bool:
    """:func:`refresh_stale_caches` of :data:`KERNEL_PACKAGES`; True when a cache was emptied."""
    refreshed = False
    for package in KERNEL_PACKAGES:
        module = importlib.import_module(package)
        refreshed |= refresh_stale_caches(Path(module.__file__ or "").resolve().parent, package)
    return refreshed


def _compile(modules: tuple[str, ...]) -> float:
    t0 = time.perf_counter()
    refresh_kernel_caches()
    for name in modules:
        importlib.import_module(name).warm_up()
    return time.perf_counter() - t0


def compile_kernels(processes: int = 2) -> list[float]:
    """Compile (or load) every kernel; the seconds each group took."""
    refresh_kernel_caches()  # here, before the two groups start: not both at once
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
