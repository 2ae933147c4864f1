"""ROI tracking's per-target bookkeeping, compiled (numba).

The window sizes about the predicted targets and the gathering of the targets found
in them (:class:`service.pipeline.measure.FrameMeasurer`; their measurement in one
call is :func:`service.core._kernels.detect_kernel.measure_predicted_kernel`): as
numpy expressions some twenty array passes over ~230 targets per frame, each costing
more in call overhead than in arithmetic, together ~3 % of an ROI frame.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def window_half_size_kernel(radius_c, coded, rows, depth, pixel_mm, allowance_px):
    """Half window (n,) px per target ``rows`` (n,) of the field at ``depth`` (n,) mm: the disk's image
    radius ``radius_c / max(depth, 1) / pixel_mm`` (``radius_c``: radius mm times c mm, per field row),
    3 px of blur and ``allowance_px`` for the prediction error; a ``coded`` (per field row) target's
    window ends 4 px inside its ring (which starts at twice the disk's radius); at least 3 px."""
    n = rows.size
    half = np.empty(n, dtype=np.int64)
    for i in range(n):
        r_px = radius_c[rows[i]] / max(depth[i], 1.0) / pixel_mm
        h = np.ceil(r_px + 3.0 + allowance_px)
        if coded[rows[i]]:
            h = min(h, np.floor(2.0 * r_px - 4.0))
        half[i] = int(max(h, 3.0))
    return half


@njit(cache=True, nogil=True, error_model="numpy")
def gather_found_kernel(found, blob_uv, rows, uv_pred):
    """The field rows (k,) and measured pixels (k, 2) px of the targets whose window found a blob
    (``found`` (n,) >= 0, index into ``blob_uv`` (m, 2) px), and the largest squared distance px^2
    of such a blob from its window's centre (the rounded prediction ``uv_pred`` (n, 2) px)."""
    k = 0
    for i in range(found.size):
        if found[i] >= 0:
            k += 1
    rows_ok = np.empty(k, dtype=np.int64)
    uv = np.empty((k, 2))
    worst = -np.inf
    j = 0
    for i in range(found.size):
        b = found[i]
        if b < 0:
            continue
        rows_ok[j] = rows[i]
        u, v = blob_uv[b, 0], blob_uv[b, 1]
        uv[j, 0], uv[j, 1] = u, v
        du, dv = u - np.rint(uv_pred[i, 0]), v - np.rint(uv_pred[i, 1])
        worst = max(worst, du * du + dv * dv)
        j += 1
    return rows_ok, uv, worst


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the types the pipeline passes."""
    rows = np.arange(3, dtype=np.int64)
    window_half_size_kernel(np.full(3, 60.0), np.zeros(3, dtype=np.bool_), rows, np.full(3, 1000.0), 0.0067, 1.0)
    # the disks' pixels come as a view of measure_predicted_kernel's table, (2, k) transposed, or
    # (edge centres, the default) as an array of their own
    found = np.array([0, -1, 1], dtype=np.int64)
    for blob_uv in (np.zeros((2, 2)).T, np.zeros((2, 2))):
        gather_found_kernel(found, blob_uv, rows, np.zeros((3, 2)))
