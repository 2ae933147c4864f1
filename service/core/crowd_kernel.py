"""Blobs near each other in the full frame (:mod:`service.core.detect`), compiled (numba).

:func:`neighbours_kernel` finds the pieces of coded targets' rings and how near
each blob's window comes to another blob; :func:`mask_windows_kernel` sets other
blobs to the background in the crowded windows before they are measured. Written
as loops: as array expressions over the pairs and the windows (numpy passes over a
few hundred small items) they took 0.9 ms of a 10 ms frame, now 0.25 ms.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _pairs_within(centre, r):
    """All unordered pairs (i < j) of points ``centre`` (n, 2) at most ``r`` apart, through a grid
    of r-sized cells (the full frame's ~300 blobs have a few neighbours each)."""
    n = centre.shape[0]
    cell = max(r, 1.0)
    gx = np.empty(n, dtype=np.intp)
    gy = np.empty(n, dtype=np.intp)
    x0, y0 = np.inf, np.inf
    for i in range(n):
        x0, y0 = min(x0, centre[i, 0]), min(y0, centre[i, 1])
    nx = ny = 1
    for i in range(n):
        gx[i], gy[i] = int((centre[i, 0] - x0) / cell), int((centre[i, 1] - y0) / cell)
        nx, ny = max(nx, gx[i] + 1), max(ny, gy[i] + 1)
    # counting sort of the points by cell
    start = np.zeros(nx * ny + 1, dtype=np.intp)
    for i in range(n):
        start[gy[i] * nx + gx[i] + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    order, fill = np.empty(n, dtype=np.intp), start[:-1].copy()
    for i in range(n):
        k = gy[i] * nx + gx[i]
        order[fill[k]] = i
        fill[k] += 1
    r2 = r * r
    # twice over the cells: count, then fill (growing the arrays in the loop costs more)
    pi, pj = np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp)
    m = 0
    for fill_in in (False, True):
        if fill_in:
            pi, pj = np.empty(m, dtype=np.intp), np.empty(m, dtype=np.intp)
            m = 0
        for i in range(n):
            for cy in range(max(gy[i] - 1, 0), min(gy[i] + 2, ny)):
                for cx in range(max(gx[i] - 1, 0), min(gx[i] + 2, nx)):
                    k = cy * nx + cx
                    for q in range(start[k], start[k + 1]):
                        j = order[q]
                        if j > i:
                            dx, dy = centre[j, 0] - centre[i, 0], centre[j, 1] - centre[i, 1]
                            if dx * dx + dy * dy <= r2:
                                if fill_in:
                                    pi[m], pj[m] = i, j
                                m += 1
    return pi[:m], pj[:m]


@njit(cache=True, error_model="numpy")
def neighbours_kernel(centre, mu, box_centre, reach, host, disk_like, r_px, ring_inner, ring_outer):
    """``detect._neighbours``: per blob the host whose coded ring it is a piece of (-1: none) and
    the distance from its box centre to the nearest thresholded pixel of another blob.

    Of two hosts that could claim one piece (rings that overlap), the nearer one (in its own
    ellipse's radii) takes it.
    """
    n = centre.shape[0]
    host_of = np.full(n, -1, dtype=np.intp)
    near = np.full(n, np.inf)
    if n < 2:
        return host_of, near
    pi, pj = _pairs_within(centre, r_px)
    m = pi.size
    # both directions of every pair: k < m is (i = pi, j = pj), k >= m the reverse
    per = np.zeros(2 * m)
    claim = np.zeros(2 * m, dtype=np.bool_)
    claimed = np.zeros(n, dtype=np.bool_)
    for k in range(2 * m):
        i, j = (pi[k], pj[k]) if k < m else (pj[k - m], pi[k - m])
        if not host[i]:  # only a host claims pieces (per[k] is used only for a claim)
            continue
        dx, dy = centre[j, 0] - centre[i, 0], centre[j, 1] - centre[i, 1]
        d = np.sqrt(dx * dx + dy * dy) + 1e-9
        ex, ey = dx / d, dy / d
        det = max(mu[i, 0] * mu[i, 2] - mu[i, 1] ** 2, 1e-12)
        # rho per px along e in the host's frame, and the piece's moment half-extent towards the host
        per_px = np.sqrt(max(mu[i, 2] * ex * ex - 2 * mu[i, 1] * ex * ey + mu[i, 0] * ey * ey, 0.0) / (4 * det))
        half = 2 * np.sqrt(max(mu[j, 0] * ex * ex + 2 * mu[j, 1] * ex * ey + mu[j, 2] * ey * ey, 0.0))
        rho = d * per_px
        if disk_like[j]:
            c = (rho > ring_inner - 0.6 and (d - half) * per_px > 1.0
                 and (d + half) * per_px < ring_outer + 0.4)
        else:
            c = rho < ring_outer + 0.5
        per[k], claim[k] = per_px, c
        if claim[k]:
            claimed[j] = True
    best = np.full(n, np.inf)
    for k in range(2 * m):
        i, j = (pi[k], pj[k]) if k < m else (pj[k - m], pi[k - m])
        if claim[k] and not claimed[i]:  # a claimed host claims nothing
            dx, dy = centre[j, 0] - centre[i, 0], centre[j, 1] - centre[i, 1]
            rho = (np.sqrt(dx * dx + dy * dy) + 1e-9) * per[k]
            if rho < best[j]:
                best[j], host_of[j] = rho, i
    for k in range(2 * m):
        i, j = (pi[k], pj[k]) if k < m else (pj[k - m], pi[k - m])
        if host_of[j] == i:
            approach = ring_inner * (1.0 / max(per[k], 1e-9) + 0.5) - 6.0
        else:
            bx, by = centre[j, 0] - box_centre[i, 0], centre[j, 1] - box_centre[i, 1]
            approach = np.sqrt(bx * bx + by * by) - reach[j] - 0.5
        near[i] = min(near[i], approach)
    return host_of, near


@njit(cache=True, error_model="numpy")
def _kth_smallest(x, k):
    """The k-th smallest value (0-based) of ``x`` (no NaN), reordering it: Hoare's selection."""
    lo, hi = 0, x.size - 1
    while lo < hi:
        pivot = x[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while x[i] < pivot:
                i += 1
            while x[j] > pivot:
                j -= 1
            if i <= j:
                x[i], x[j] = x[j], x[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return x[k]


@njit(cache=True, error_model="numpy")
def mask_windows_kernel(img, cu, cv, half, crowd, own, seg):
    """The crowded windows' pixels with other blobs set to the background (``detect._mask_others``).

    For each window ``crowd[k]``: the blob's own region is ``x' Q x <= 1`` about (x0, y0) from
    the window centre, ``own`` (n, 5) rows (x0, y0, Q_uu, Q_uv, Q_vv); pixels outside it that are
    brighter than the rim's lower quartile plus ``seg``, grown by 3 px (their blur tail), take
    that quartile. The region's test is done in float32, as the former array expression did.

    Returns the windows' s*s float32 values, one after the other (``buf``), and each window's
    offset into it (``boff`` (n,), -1 for the others): :func:`measure_windows_kernel`'s input.
    """
    n = cu.size
    boff = np.full(n, -1, dtype=np.intp)
    total = 0
    for k in range(crowd.size):
        i = crowd[k]
        s = 2 * half[i] + 1
        boff[i] = total
        total += s * s
    buf = np.empty(max(total, 1), dtype=np.float32)
    one, seg32 = np.float32(1.0), np.float32(seg)
    for k in range(crowd.size):
        i = crowd[k]
        h = half[i]
        s = 2 * h + 1
        P = buf[boff[i]:boff[i] + s * s].reshape(s, s)
        for a in range(s):
            for b in range(s):
                P[a, b] = np.float32(img[cv[i] - h + a, cu[i] - h + b])
        # the rim (h - 1 < distance <= h + 1/2): its lower quartile
        r2, ri2 = (h + 0.5) ** 2, (h - 1.0) ** 2
        rim = np.empty(8 * s + 8, dtype=np.float32)
        m = 0
        for a in range(s):
            dv2 = (a - h) * (a - h)
            for b in range(s):
                d2 = (b - h) * (b - h) + dv2
                if d2 <= r2 and d2 > ri2:
                    rim[m] = P[a, b]
                    m += 1
        level0 = _kth_smallest(rim[:m], m // 4)
        x0, y0, qa, qb, qc = own[i, 0], own[i, 1], own[i, 2], own[i, 3], own[i, 4]
        q0 = np.float32(qa * x0 * x0 + 2 * qb * x0 * y0 + qc * y0 * y0)
        q1, q2 = np.float32(-2 * (qa * x0 + qb * y0)), np.float32(-2 * (qb * x0 + qc * y0))
        q3, q4, q5 = np.float32(qa), np.float32(2 * qb), np.float32(qc)
        outside = np.zeros((s, s), dtype=np.bool_)
        bright = np.zeros((s, s), dtype=np.bool_)
        thr = level0 + seg32
        for a in range(s):
            dv = np.float32(a - h)
            for b in range(s):
                du = np.float32(b - h)
                val = q0 + q1 * du + q2 * dv + q3 * (du * du) + q4 * (du * dv) + q5 * (dv * dv)
                outside[a, b] = val > one
                bright[a, b] = outside[a, b] and P[a, b] > thr
        # a 7 x 7 dilation of the bright pixels, inside the window: along rows, then along columns
        # (running counts over 7)
        hrow = np.zeros((s, s), dtype=np.int32)
        for a in range(s):
            cnt = 0
            for b in range(s + 3):
                if b < s:
                    cnt += bright[a, b]
                if b >= 7:
                    cnt -= bright[a, b - 7]
                if b >= 3:
                    hrow[a, b - 3] = cnt
        for b in range(s):
            cnt = 0
            for a in range(s + 3):
                if a < s:
                    cnt += hrow[a, b]
                if a >= 7:
                    cnt -= hrow[a - 7, b]
                if a >= 3 and cnt > 0 and outside[a - 3, b]:
                    P[a - 3, b] = level0
    return buf, boff
