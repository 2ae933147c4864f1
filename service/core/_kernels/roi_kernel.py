"""ROI tracking's per-target bookkeeping, compiled (numba).

The window sizes about the predicted targets, their measurement and assessment in
one call, and the gathering of the targets found in them
(:class:`service.pipeline.measure.FrameMeasurer`): as numpy expressions some forty
array passes over ~230 targets per frame, each costing more in call overhead than
in arithmetic, together a sixth of an ROI frame.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import warm_images
from service.core._kernels.detect_kernel import NF, assess_kernel, measure_windows_kernel


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


@njit(cache=True, nogil=True, error_model="numpy")
def measure_predicted_kernel(img, uv, half, seg, contrast, full, limits, codes):
    """Measure and assess the disk in the window of half size ``half`` (n,) px about each rounded
    prediction ``uv`` (n, 2) px (:func:`service.core.targets.detect.measure_windows`): ``seg`` and
    ``contrast`` DN are every window's segmentation and contrast levels, ``limits`` and ``codes``
    :func:`~service.core._kernels.detect_kernel.assess_kernel`'s.

    Returns the measurement table (NF, k) of the k accepted disks (their rim not crossed, the
    window inside the image), their sigma_px (k,) and fill (k,), and per window the index of its
    disk among them, or -1."""
    n = uv.shape[0]
    height, width = img.shape
    cu, cv = np.empty(n, dtype=np.intp), np.empty(n, dtype=np.intp)
    radius, placed = np.zeros(n, dtype=np.intp), np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if np.isfinite(uv[i, 0]) and np.isfinite(uv[i, 1]):
            cu[i], cv[i], radius[i] = int(np.rint(uv[i, 0])), int(np.rint(uv[i, 1])), half[i]
        else:  # far outside, as the numpy path puts it
            cu[i] = cv[i] = -1000000
        r = radius[i]
        placed[i] = cu[i] >= r and cu[i] + r < width and cv[i] >= r and cv[i] + r < height and r >= 2
    seg_n, contrast_n = np.full(n, seg), np.full(n, contrast)
    out, n_sat, edge = measure_windows_kernel(
        img, cu, cv, radius, placed, seg_n, full, np.zeros(1, np.float32), np.full(n, -1, dtype=np.intp)
    )
    reason, sigma, fill = assess_kernel(out, n_sat, edge, placed, contrast_n, limits, codes)
    found = np.full(n, -1, dtype=np.intp)
    k = 0
    for i in range(n):
        if reason[i] < 0 and not edge[i] and placed[i]:
            found[i] = k
            k += 1
    table, sigma_ok, fill_ok = np.empty((NF, k)), np.empty(k), np.empty(k)
    for i in range(n):
        j = found[i]
        if j >= 0:
            table[:, j] = out[:, i]
            sigma_ok[j], fill_ok[j] = sigma[i], fill[i]
    return table, sigma_ok, fill_ok, found


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the types the pipeline passes."""
    rows = np.arange(3, dtype=np.int64)
    window_half_size_kernel(np.full(3, 60.0), np.zeros(3, dtype=np.bool_), rows, np.full(3, 1000.0), 0.0067, 1.0)
    # the disks' pixels come as a view of measure_predicted_kernel's table: (2, k) transposed
    gather_found_kernel(np.array([0, -1, 1], dtype=np.int64), np.zeros((2, 2)).T, rows, np.zeros((3, 2)))
    limits = np.array([6, 5000, 4, 0.6, 2, 2.5, 0.4, 3, 4, 0.015, 0.05, 1.3, 2.5])
    uv, half, codes = np.full((2, 2), 16.0), np.full(2, 6, dtype=np.intp), np.arange(5, dtype=np.intp)
    for img in warm_images((np.uint8, np.uint16)):
        measure_predicted_kernel(img, uv, half, 5.0, 10.0, float(np.iinfo(img.dtype).max), limits, codes)
