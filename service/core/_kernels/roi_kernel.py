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
def window_half_size_kernel(radius_c, rows, depth, pixel_mm, allowance_px, rim_px):
    """Half window (n,) px per target ``rows`` (n,) of the field at ``depth`` (n,) mm: the disk's image
    radius ``radius_c / max(depth, 1) / pixel_mm`` (``radius_c``: radius mm times c mm, per field row),
    ``rim_px`` for its blur and ``allowance_px`` for the prediction error; at least 3 px. A coded target's ring
    may reach into it: :func:`ring_masks_kernel` keeps it out."""
    n = rows.size
    half = np.empty(n, dtype=np.int64)
    for i in range(n):
        r_px = radius_c[rows[i]] / max(depth[i], 1.0) / pixel_mm
        half[i] = int(max(np.ceil(r_px + rim_px + allowance_px), 3.0))
    return half


# A coded target's own region in its window: its disk's predicted ellipse grown to the middle of the
# dark gap between the disk (1 radius) and the ring (2 radii); the ring outside it is masked
OWN_RADII = 1.5


@njit(cache=True, nogil=True, error_model="numpy")
def ring_masks_kernel(R_cf, t_cf, xyz, ex, ey, radius_mm, coded, rows, uv_pred, f_px, half, ring_inner):
    """Per target ``rows`` (n,) of the field, the own region (n, 5) ``(x0, y0, Q_uu, Q_uv, Q_vv)``
    that :func:`~service.core._kernels.crowd_kernel.mask_windows_kernel` keeps of its window: for a
    ``coded`` (per field row) one, its disk's ellipse predicted by the pose ``R_cf``, ``t_cf``
    (camera from field, mm) and grown to OWN_RADII disk radii, about the prediction ``uv_pred``
    (n, 2) px less the window's centre (the rounded prediction); NaN rows for the others. The
    ellipse is the projection's first-order (affine) image of the disk (radius ``radius_mm`` per
    field row, in the plane of its in-plane unit axes ``ex``, ``ey`` (field rows, 3): the field's x
    and y for a field on one plane) through a pinhole of ``f_px`` px; the lens's distortion
    changes it by far less than the gap it has to fit in. In an oblique view the ring comes within
    twice the disk's foreshortened radius of its centre, inside any window that holds the disk; a
    ring (from ``ring_inner`` disk radii) that stays 2 px (its blur) beyond the window of half size
    ``half`` (n,) px costs no masking and is not given a region."""
    n = rows.size
    own = np.full((n, 5), np.nan)
    for i in range(n):
        j = rows[i]
        if not coded[j]:
            continue
        X = R_cf[0, 0] * xyz[j, 0] + R_cf[0, 1] * xyz[j, 1] + R_cf[0, 2] * xyz[j, 2] + t_cf[0]
        Y = R_cf[1, 0] * xyz[j, 0] + R_cf[1, 1] * xyz[j, 1] + R_cf[1, 2] * xyz[j, 2] + t_cf[1]
        Z = R_cf[2, 0] * xyz[j, 0] + R_cf[2, 1] * xyz[j, 1] + R_cf[2, 2] * xyz[j, 2] + t_cf[2]
        if not Z > 0:
            continue
        x, y, g = X / Z, Y / Z, f_px / Z * radius_mm[j] * OWN_RADII
        # the disk's in-plane axes in the camera, and their image, px: A maps the unit circle onto it
        c0 = R_cf[0, 0] * ex[j, 0] + R_cf[0, 1] * ex[j, 1] + R_cf[0, 2] * ex[j, 2]
        c1 = R_cf[1, 0] * ex[j, 0] + R_cf[1, 1] * ex[j, 1] + R_cf[1, 2] * ex[j, 2]
        c2 = R_cf[2, 0] * ex[j, 0] + R_cf[2, 1] * ex[j, 1] + R_cf[2, 2] * ex[j, 2]
        d0 = R_cf[0, 0] * ey[j, 0] + R_cf[0, 1] * ey[j, 1] + R_cf[0, 2] * ey[j, 2]
        d1 = R_cf[1, 0] * ey[j, 0] + R_cf[1, 1] * ey[j, 1] + R_cf[1, 2] * ey[j, 2]
        d2 = R_cf[2, 0] * ey[j, 0] + R_cf[2, 1] * ey[j, 1] + R_cf[2, 2] * ey[j, 2]
        a00, a01 = g * (c0 - x * c2), g * (d0 - x * d2)
        a10, a11 = g * (c1 - y * c2), g * (d1 - y * d2)
        # x' (A A')^-1 x <= 1: (A A')^-1 = (A^-1)' A^-1
        det = a00 * a11 - a01 * a10
        if not abs(det) > 1e-12:
            continue
        # the ellipse's minor semi-axis: the smaller singular value of A, over OWN_RADII
        p, q = a00 * a00 + a01 * a01 + a10 * a10 + a11 * a11, abs(det)
        b_disk = np.sqrt(max(0.5 * (p - np.sqrt(max(p * p - 4.0 * q * q, 0.0))), 0.0)) / OWN_RADII
        if ring_inner * b_disk - 2.0 > half[i] + 1.0:  # the ring stays clear of the window
            continue
        b00, b01, b10, b11 = a11 / det, -a01 / det, -a10 / det, a00 / det  # A^-1
        own[i, 0] = uv_pred[i, 0] - np.rint(uv_pred[i, 0])
        own[i, 1] = uv_pred[i, 1] - np.rint(uv_pred[i, 1])
        own[i, 2] = b00 * b00 + b10 * b10
        own[i, 3] = b00 * b01 + b10 * b11
        own[i, 4] = b01 * b01 + b11 * b11
    return own


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
    window_half_size_kernel(np.full(3, 60.0), rows, np.full(3, 1000.0), 0.0067, 1.0, 3.0)
    ring_masks_kernel(
        np.eye(3),
        np.array([0.0, 0.0, 1000.0]),
        np.zeros((3, 3)),
        np.eye(3),
        np.eye(3),
        np.full(3, 5.0),
        np.ones(3, dtype=np.bool_),
        rows,
        np.zeros((3, 2)),
        1800.0,
        np.full(3, 10, dtype=np.int64),
        2.0,
    )
    # the disks' pixels come as a view of measure_predicted_kernel's table, (2, k) transposed, or
    # (edge centres, the default) as an array of their own
    found = np.array([0, -1, 1], dtype=np.int64)
    for blob_uv in (np.zeros((2, 2)).T, np.zeros((2, 2))):
        gather_found_kernel(found, blob_uv, rows, np.zeros((3, 2)))
