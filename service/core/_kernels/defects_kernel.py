"""A sensor's defect pixels patched in a frame, compiled (numba): :class:`service.core.targets.defects.DefectMap`.

Why compiled: as array expressions the patch of 670 defects cost an ROI frame 0.12-0.17 ms (gathers,
an argmin and the temporaries of a dozen numpy calls, each touching the scattered pixels again);
one pass here reads each defect's neighbours once.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import warm_images


@njit(cache=True, nogil=True)
def patch_kernel(flat, idx, pair_a, pair_b, pair_good, neighbours, weights, saved):
    """Patch the defects ``idx`` (K,) of the flattened frame ``flat`` in place, their old values into
    ``saved`` (K,). A defect's value: the mean of the pair of opposite good neighbours (``pair_a``,
    ``pair_b``, ``pair_good``: (K, 4)) that differ least, else the ``weights`` (K, 8) mean of its
    ``neighbours`` (K, 8), else its own. Good neighbours are no defects, so the order is free."""
    for k in range(idx.size):
        saved[k] = flat[idx[k]]
    for k in range(idx.size):
        best, value = np.inf, 0.0
        for j in range(4):
            if pair_good[k, j]:
                a, b = float(flat[pair_a[k, j]]), float(flat[pair_b[k, j]])
                if abs(a - b) < best:
                    best, value = abs(a - b), 0.5 * (a + b)
        if best == np.inf:
            total, weight = 0.0, 0.0
            for j in range(8):
                if weights[k, j] > 0:
                    total += weights[k, j] * float(flat[neighbours[k, j]])
                    weight += weights[k, j]
            value = total if weight > 0 else float(saved[k])
        flat[idx[k]] = np.rint(value)


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for 8- and 16-bit frames."""
    idx = np.array([17], dtype=np.intp)
    pairs = np.array([[0, 34, 16, 1]], dtype=np.intp)
    good = np.ones((1, 4), dtype=np.bool_)
    neighbours = np.zeros((1, 8), dtype=np.intp)
    weights = np.full((1, 8), 0.125)
    for img in warm_images((np.uint8, np.uint16), (8, 8)):
        if img.flags.writeable:  # the kernel writes: only a writeable frame is patched in place
            patch_kernel(img.reshape(-1), idx, pairs, pairs, good, neighbours, weights, np.zeros(1, img.dtype))
