"""The full frame's candidate blobs (:mod:`service.core.targets.detect`), compiled (numba).

From the external contours' vertices to each blob's box, areas, polygon moments
and reach (:func:`contour_stats_kernel`), the shape classes (:func:`classify_kernel`)
and the measuring windows (:func:`windows_kernel`). Written as loops: as array
expressions over the ~300 contours of a frame they were ~40 numpy passes, 0.4 ms
of a frame. The formulas are those the docstrings of :mod:`service.core.targets.detect`
describe, in the same order of operations (the results are bit for bit the same).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import trace_kernel


@njit(cache=True, nogil=True, inline="always")
def _maximum(a: float, b: float) -> float:  # np.maximum: NaN-propagating
    if a != a or a > b:
        return a
    return b


@njit(cache=True, nogil=True, error_model="numpy")
def _contour_sums(pts, starts, lengths):
    """Per closed polygon (C) of the vertices ``pts`` (M, 2) int, px, from ``starts`` with
    ``lengths``: its box (C, 4) u0 v0 u1 v1 inclusive, the Green's-theorem sums (7, C) relative to
    its first vertex (2A, boundary steps, 6A c_u, 6A c_v, 12A m_uu, 12A m_vv, 24A m_uv; see
    ``detect._contours``) and its reach (C,): the farthest vertex from the box centre, rounded up."""
    nc = starts.size
    box = np.empty((nc, 4), dtype=np.intp)
    sums = np.zeros((7, nc))
    reach = np.empty(nc, dtype=np.intp)
    for c in range(nc):
        s0, L = starts[c], lengths[c]
        fx, fy = pts[s0, 0], pts[s0, 1]
        u0, v0, u1, v1 = fx, fy, fx, fy
        t0 = t1 = t2 = t3 = t4 = t5 = t6 = 0.0
        for k in range(L):
            j = s0 + k
            jn = j + 1 if k + 1 < L else s0  # no modulo: an integer division per vertex costs more than the sums
            u0, u1 = min(u0, pts[j, 0]), max(u1, pts[j, 0])
            v0, v1 = min(v0, pts[j, 1]), max(v1, pts[j, 1])
            x, y = float(pts[j, 0] - fx), float(pts[j, 1] - fy)
            x1, y1 = float(pts[jn, 0] - fx), float(pts[jn, 1] - fy)
            cross = x * y1 - x1 * y
            sx, sy = x + x1, y + y1
            t0 += cross
            t1 += max(abs(x1 - x), abs(y1 - y))
            t2 += sx * cross
            t3 += sy * cross
            t4 += (x * x + x * x1 + x1 * x1) * cross
            t5 += (y * y + y * y1 + y1 * y1) * cross
            t6 += (sx * sy + x * y + x1 * y1) * cross
        box[c, 0], box[c, 1], box[c, 2], box[c, 3] = u0, v0, u1, v1
        sums[0, c], sums[1, c], sums[2, c], sums[3, c] = t0, t1, t2, t3
        sums[4, c], sums[5, c], sums[6, c] = t4, t5, t6
        cu, cv = (u0 + u1) // 2, (v0 + v1) // 2
        far = 0.0
        for k in range(L):
            du, dv = float(pts[s0 + k, 0] - cu), float(pts[s0 + k, 1] - cv)
            far = max(far, du * du + dv * dv)
        reach[c] = int(np.ceil(np.sqrt(far)))
    return box, sums, reach


@njit(cache=True, nogil=True, error_model="numpy")
def contour_stats_kernel(pts, starts, lengths):
    """Per closed polygon (C) of the vertices ``pts`` (M, 2) int, px, from ``starts`` with ``lengths``:
    box (C, 4) u0 v0 u1 v1 inclusive, pixel area (Pick's theorem), polygon area, centroid (C, 2),
    polygon moments (C, 3) uu uv vv, integer box centre (C, 2) and reach (C,): the farthest vertex
    from the box centre, rounded up. Single pixels and lines (|2A| < 1) get the box's middle and
    zero moments."""
    box, sums, reach = _contour_sums(pts, starts, lengths)
    nc = starts.size
    area_px, poly_area = np.empty(nc), np.empty(nc)
    centre, mu = np.empty((nc, 2)), np.empty((nc, 3))
    box_centre = np.empty((nc, 2), dtype=np.intp)
    for c in range(nc):
        a2 = sums[0, c]
        flat = abs(a2) < 0.5  # a lattice polygon has |2A| >= 1
        fx, fy = float(pts[starts[c], 0]), float(pts[starts[c], 1])
        if flat:
            cx, cy = 0.5 * (box[c, 0] + box[c, 2]) - fx, 0.5 * (box[c, 1] + box[c, 3]) - fy
            mu[c, 0] = mu[c, 1] = mu[c, 2] = 0.0
        else:
            cx, cy = sums[2, c] / (3.0 * a2), sums[3, c] / (3.0 * a2)
            mu[c, 0] = sums[4, c] / (6 * a2) - cx * cx
            mu[c, 1] = sums[6, c] / (12 * a2) - cx * cy
            mu[c, 2] = sums[5, c] / (6 * a2) - cy * cy
        centre[c, 0], centre[c, 1] = cx + fx, cy + fy
        poly_area[c] = 0.5 * abs(a2)
        area_px[c] = 0.5 * abs(a2) + 0.5 * sums[1, c] + 1.0
        box_centre[c, 0], box_centre[c, 1] = (box[c, 0] + box[c, 2]) // 2, (box[c, 1] + box[c, 3]) // 2
    return box, area_px, poly_area, centre, mu, box_centre, reach


@njit(cache=True, nogil=True, inline="always")
def _axes(uu, uv, vv):
    """Semi-axes a >= b of the uniform ellipse with second moments uu, uv, vv."""
    half_tr, root = 0.5 * (uu + vv), np.sqrt(0.25 * (uu - vv) ** 2 + uv * uv)
    return 2 * np.sqrt(half_tr + root), 2 * np.sqrt(_maximum(half_tr - root, 0.0))


@njit(cache=True, nogil=True, error_model="numpy")
def classify_kernel(
    box, area_px, poly_area, mu, width, height, border, min_area, max_area, max_aspect, min_polygon_fill
):
    """Per contour (C): semi-major axis a (px) and the classes cut (by the image border), small, big,
    long (b < a / max_aspect), disk_like (not long, and its polygon fills its moments' ellipse) and
    host (a disk-like candidate whose coded ring may be around it)."""
    nc = area_px.size
    a = np.empty(nc)
    cut, small, big = np.empty(nc, np.bool_), np.empty(nc, np.bool_), np.empty(nc, np.bool_)
    long, disk_like, host = np.empty(nc, np.bool_), np.empty(nc, np.bool_), np.empty(nc, np.bool_)
    for c in range(nc):
        ac, bc = _axes(mu[c, 0], mu[c, 1], mu[c, 2])
        a[c] = ac
        cut[c] = (
            box[c, 0] < border
            or box[c, 1] < border
            or box[c, 2] > width - 1 - border
            or box[c, 3] > height - 1 - border
        )
        small[c], big[c] = area_px[c] < min_area, area_px[c] > max_area
        long[c] = not (bc * max_aspect >= ac)
        # a polygon of no area (a 1 px line: zero moments) is no disk, whatever 0 >= 0 says
        disk_like[c] = not long[c] and poly_area[c] > 0 and poly_area[c] >= min_polygon_fill * np.pi * ac * bc
        host[c] = disk_like[c] and not small[c] and not big[c]  # a disk cut by the border still marks its ring
    return a, cut, small, big, long, disk_like, host


@njit(cache=True, nogil=True, error_model="numpy")
def windows_kernel(box_centre, reach, mu, centre, todo, near, width, height, window_px, radii, margin):
    """Window radius (n,) of each contour ``todo`` (n,) to measure, its own region (n, 5) where
    another blob reaches into the window (its thresholded ellipse + 1.5 px, as (x0, y0, Q_uu, Q_uv,
    Q_vv) about the window centre; NaN elsewhere) and whether the image border limits the window
    (``detect._windows``)."""
    n = todo.size
    need = np.empty(n, dtype=np.intp)
    radius = np.empty(n, dtype=np.intp)
    for k in range(n):
        need[k] = reach[todo[k]] + margin
    if window_px > 0:
        radius[:] = window_px // 2
    else:  # the windows within one step of radii share the largest need among them
        top = np.zeros(radii.size, dtype=np.intp)
        step = np.empty(n, dtype=np.intp)
        for k in range(n):
            s = np.searchsorted(radii, need[k])
            step[k] = min(s, radii.size - 1)
            top[step[k]] = max(top[step[k]], need[k])
        for k in range(n):
            radius[k] = max(top[step[k]], need[k])
    own = np.full((n, 5), np.nan)
    limited = np.empty(n, dtype=np.bool_)
    for k in range(n):
        c = todo[k]
        cu, cv = box_centre[c, 0], box_centre[c, 1]
        radius[k] = min(radius[k], min(min(cu, cv), min(width - 1 - cu, height - 1 - cv)))
        limited[k] = radius[k] < need[k]
        if radius[k] + margin + 0.5 > near[c]:
            uu, uv, vv = mu[c, 0], mu[c, 1], mu[c, 2]
            b = _axes(uu, uv, vv)[1]
            g = 1 + 1.5 / _maximum(b, 0.5)
            det4 = 4 * _maximum(uu * vv - uv * uv, 1e-12) * (g * g)
            own[k, 0], own[k, 1] = centre[c, 0] - cu, centre[c, 1] - cv
            own[k, 2], own[k, 3], own[k, 4] = vv / det4, -uv / det4, uu / det4
    return radius, own, limited


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the types :mod:`service.core.targets.detect` passes
    (and the contour tracing's, :mod:`service.core._kernels.trace_kernel`)."""
    trace_kernel.warm_up()
    pts = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], dtype=np.int32)
    box, area_px, poly_area, centre, mu, box_centre, reach = contour_stats_kernel(
        pts, np.array([0], dtype=np.intp), np.array([4], dtype=np.intp)
    )
    classify_kernel(box, area_px, poly_area, mu, 10, 10, 2, 6.0, 5000.0, 4.0, 0.9)
    windows_kernel(
        box_centre,
        reach,
        mu,
        centre,
        np.array([0], dtype=np.intp),
        np.array([np.inf]),
        10,
        10,
        0,
        np.array([4, 6], dtype=np.intp),
        2,
    )
