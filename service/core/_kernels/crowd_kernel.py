"""Blobs near each other in the full frame (:mod:`service.core.targets.detect`), compiled (numba).

:func:`neighbours_kernel` finds the pieces of coded targets' rings and how near
each blob's window comes to another blob; :func:`mask_windows_kernel` sets other
blobs to the background in the crowded windows before they are measured. Written
as loops: as array expressions over the pairs and the windows (numpy passes over a
few hundred small items) they took 0.9 ms of a 10 ms frame, now 0.25 ms.

The neighbours are searched from the candidates only (the blobs to be measured and
the hosts of rings), each within its own radius, through a grid of the contours'
boxes: one search radius for all (the largest blob's) made a frame with a bright
sticker, or with thousands of noise specks, cost millions of pairs.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _box_grid(box, cell, width, height):
    """Every contour listed in each ``cell`` x ``cell`` px grid cell its box (C, 4) overlaps
    (counting sort): (nx, ny, start (nx * ny + 1,), members). A contour whose box spans
    several cells is in each of them, so a query finds it from whichever side it comes."""
    nx, ny = max(1, -(-width // cell)), max(1, -(-height // cell))
    n = box.shape[0]
    start = np.zeros(nx * ny + 1, dtype=np.intp)
    for c in range(n):
        for gy in range(min(max(box[c, 1] // cell, 0), ny - 1), min(max(box[c, 3] // cell, 0), ny - 1) + 1):
            for gx in range(min(max(box[c, 0] // cell, 0), nx - 1), min(max(box[c, 2] // cell, 0), nx - 1) + 1):
                start[gy * nx + gx + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    members, fill = np.empty(start[nx * ny], dtype=np.intp), start[:-1].copy()
    for c in range(n):
        for gy in range(min(max(box[c, 1] // cell, 0), ny - 1), min(max(box[c, 3] // cell, 0), ny - 1) + 1):
            for gx in range(min(max(box[c, 0] // cell, 0), nx - 1), min(max(box[c, 2] // cell, 0), nx - 1) + 1):
                k = gy * nx + gx
                members[fill[k]] = c
                fill[k] += 1
    return nx, ny, start, members


@njit(cache=True, nogil=True, error_model="numpy")
def _pairs_near(box, centre, box_centre, reach, a, host, query, ring_outer, width, height):
    """Ordered pairs (i, j): ``i`` a query (a candidate to measure or a host), ``j`` any other
    contour whose box comes within ``R_i`` of i's centre, where ``R_i`` holds i's ring (a host's
    pieces lie within ``(ring_outer + 0.6) a_i``) and i's window (at most 1.25 times the blob's
    reach plus the margins, about the box centre). Through a grid of boxes with cells of the
    median query radius, so the work is the queries times the contours near each, never all
    pairs. Returns (pi, pj, visits): visits counts every contour looked at (the work)."""
    nq = 0
    for c in range(query.size):
        nq += query[c]
    radius = np.zeros(query.size)
    rq = np.empty(max(nq, 1))
    m = 0
    for c in range(query.size):
        if query[c]:
            dx, dy = box_centre[c, 0] - centre[c, 0], box_centre[c, 1] - centre[c, 1]
            r = 1.25 * reach[c] + 6.0 + np.sqrt(dx * dx + dy * dy)
            if host[c]:
                r = max(r, (ring_outer + 0.6) * a[c])
            radius[c] = r
            rq[m] = r
            m += 1
    cell = max(8, int(np.median(rq[: max(nq, 1)]))) if nq > 0 else 8
    nx, ny, start, members = _box_grid(box, cell, width, height)
    stamp = np.full(query.size, -1, dtype=np.intp)
    cap = max(16, 8 * nq)
    pi, pj = np.empty(cap, dtype=np.intp), np.empty(cap, dtype=np.intp)
    m, visits = 0, 0
    for i in range(query.size):
        if not query[i]:
            continue
        r = radius[i]
        x0, x1 = int(np.floor((centre[i, 0] - r) / cell)), int(np.floor((centre[i, 0] + r) / cell))
        y0, y1 = int(np.floor((centre[i, 1] - r) / cell)), int(np.floor((centre[i, 1] + r) / cell))
        for gy in range(max(y0, 0), min(y1, ny - 1) + 1):
            for gx in range(max(x0, 0), min(x1, nx - 1) + 1):
                k = gy * nx + gx
                for q in range(start[k], start[k + 1]):
                    j = members[q]
                    visits += 1
                    if j == i or stamp[j] == i:
                        continue
                    stamp[j] = i
                    # the box within r of the centre (Chebyshev): its pixels may be
                    if (
                        box[j, 0] - r > centre[i, 0]
                        or box[j, 2] + r < centre[i, 0]
                        or box[j, 1] - r > centre[i, 1]
                        or box[j, 3] + r < centre[i, 1]
                    ):
                        continue
                    if m == cap:
                        cap *= 2
                        ni, nj = np.empty(cap, dtype=np.intp), np.empty(cap, dtype=np.intp)
                        ni[:m], nj[:m] = pi[:m], pj[:m]
                        pi, pj = ni, nj
                    pi[m], pj[m] = i, j
                    m += 1
    return pi[:m], pj[:m], visits


@njit(cache=True, nogil=True, error_model="numpy")
def neighbours_kernel(
    box, centre, mu, box_centre, reach, a, host, disk_like, query, ring_inner, ring_outer, min_piece_half, width, height
):
    """``detect._neighbours``: per blob the host whose coded ring it is a piece of (-1: none) and,
    for the queries, the distance from its box centre to the nearest thresholded pixel of another
    blob; and the pairs looked at and the contours visited (the work).

    Of two hosts that could claim one piece (rings that overlap), the nearer one (in its own
    ellipse's radii) takes it. A disk-like piece must be as wide (radially) as a ring can be:
    ``min_piece_half`` host radii for its moments' half extent towards the host (a ring one
    radius wide gives 0.58), so the dots round a bright sticker taken for a host are not its ring.
    """
    n = centre.shape[0]
    host_of = np.full(n, -1, dtype=np.intp)
    near = np.full(n, np.inf)
    if n < 2:
        return host_of, near, 0, 0
    pi, pj, visits = _pairs_near(box, centre, box_centre, reach, a, host, query, ring_outer, width, height)
    m = pi.size
    per = np.zeros(m)
    claim = np.zeros(m, dtype=np.bool_)
    claimed = np.zeros(n, dtype=np.bool_)
    for k in range(m):
        i, j = pi[k], pj[k]
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
            c = (
                rho > ring_inner - 0.6
                and (d - half) * per_px > 1.0
                and (d + half) * per_px < ring_outer + 0.4
                and half * per_px >= min_piece_half
            )
        else:
            c = rho < ring_outer + 0.5
        per[k], claim[k] = per_px, c
        if claim[k]:
            claimed[j] = True
    best = np.full(n, np.inf)
    for k in range(m):
        i, j = pi[k], pj[k]
        if claim[k] and not claimed[i]:  # a claimed host claims nothing
            dx, dy = centre[j, 0] - centre[i, 0], centre[j, 1] - centre[i, 1]
            rho = (np.sqrt(dx * dx + dy * dy) + 1e-9) * per[k]
            if rho < best[j]:
                best[j], host_of[j] = rho, i
    for k in range(m):
        i, j = pi[k], pj[k]
        if host_of[j] == i:
            approach = ring_inner * (1.0 / max(per[k], 1e-9) + 0.5) - 6.0
        else:
            bx, by = centre[j, 0] - box_centre[i, 0], centre[j, 1] - box_centre[i, 1]
            approach = np.sqrt(bx * bx + by * by) - reach[j] - 0.5
        near[i] = min(near[i], approach)
    return host_of, near, m, visits


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
def mask_windows_kernel(img, cu, cv, half, crowd, own, seg):
    """The crowded windows' pixels with other blobs set to the background (``detect._mask_others``).

    For each window ``crowd[k]``: the blob's own region is ``x' Q x <= 1`` about (x0, y0) from
    the window centre, ``own`` (n, 5) rows (x0, y0, Q_uu, Q_uv, Q_vv); pixels outside it that are
    brighter than the rim's lower quartile plus ``seg[i]`` (DN), grown by 3 px (their blur tail), take
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
    one = np.float32(1.0)
    # scratch for the largest window, once: a fresh array per window cost more than its pixels
    s_max = 1
    for k in range(crowd.size):
        s_max = max(s_max, 2 * half[crowd[k]] + 1)
    rim = np.empty(8 * s_max + 8, dtype=np.float32)
    outside = np.empty((s_max, s_max), dtype=np.bool_)
    bright = np.empty((s_max, s_max), dtype=np.bool_)
    hrow = np.empty((s_max, s_max), dtype=np.int32)
    for k in range(crowd.size):
        i = crowd[k]
        h = half[i]
        s = 2 * h + 1
        P = buf[boff[i] : boff[i] + s * s].reshape(s, s)
        for a in range(s):
            row = img[cv[i] - h + a]
            for b in range(s):
                P[a, b] = np.float32(row[cu[i] - h + b])
        # the rim (h - 1 < distance <= h + 1/2): its lower quartile. Per row, the pixels between the
        # disk inside the rim (|du| <= wi) and the circle (|du| <= wo)
        r2, ri2 = (h + 0.5) ** 2, (h - 1.0) ** 2
        m = 0
        for a in range(s):
            dv2 = (a - h) * (a - h)
            wo = int(np.sqrt(r2 - dv2))  # r2 - dv2 >= h + 1/4: never just below a square
            wi = int(np.sqrt(ri2 - dv2)) if ri2 >= dv2 else -1  # an integer's root: exact for a square
            for b in range(h - wo, h - wi if wi >= 0 else h + wo + 1):
                rim[m] = P[a, b]
                m += 1
            if wi >= 0:
                for b in range(h + wi + 1, h + wo + 1):
                    rim[m] = P[a, b]
                    m += 1
        level0 = _kth_smallest(rim[:m], m // 4)
        x0, y0, qa, qb, qc = own[i, 0], own[i, 1], own[i, 2], own[i, 3], own[i, 4]
        q0 = np.float32(qa * x0 * x0 + 2 * qb * x0 * y0 + qc * y0 * y0)
        q1, q2 = np.float32(-2 * (qa * x0 + qb * y0)), np.float32(-2 * (qb * x0 + qc * y0))
        q3, q4, q5 = np.float32(qa), np.float32(2 * qb), np.float32(qc)
        thr = level0 + np.float32(seg[i])
        a_lo, a_hi, b_lo, b_hi = s, -1, s, -1  # the bright pixels' box
        for a in range(s):
            dv = np.float32(a - h)
            n_row = 0
            for b in range(s):
                du = np.float32(b - h)
                val = q0 + q1 * du + q2 * dv + q3 * (du * du) + q4 * (du * dv) + q5 * (dv * dv)
                out_ab = val > one
                br = out_ab & (P[a, b] > thr)
                outside[a, b] = out_ab
                bright[a, b] = br
                n_row += br
            if n_row:
                a_lo, a_hi = min(a_lo, a), a
                for b in range(s):
                    if bright[a, b]:
                        b_lo = min(b_lo, b)
                        break
                for b in range(s - 1, -1, -1):
                    if bright[a, b]:
                        b_hi = max(b_hi, b)
                        break
        if a_hi < 0:
            continue  # nothing bright outside the blob's own region: the window stays as it is
        # a 7 x 7 dilation of the bright pixels, inside the window, within their box grown by 3 px:
        # along rows (running counts over 7), then along columns
        c0, c1 = max(b_lo - 3, 0), min(b_hi + 3, s - 1)
        for a in range(a_lo, a_hi + 1):
            cnt = 0
            for b in range(b_lo, min(b_hi, c0 + 2) + 1):  # the count about column c0 - 1
                cnt += bright[a, b]
            for c in range(c0, c1 + 1):
                if c + 3 <= b_hi:
                    cnt += bright[a, c + 3]
                if c - 4 >= b_lo:
                    cnt -= bright[a, c - 4]
                hrow[a, c] = cnt
        t0, t1 = max(a_lo - 3, 0), min(a_hi + 3, s - 1)
        for c in range(c0, c1 + 1):
            cnt = 0
            for a in range(a_lo, min(a_hi, t0 + 2) + 1):  # the count about row t0 - 1
                cnt += hrow[a, c]
            for t in range(t0, t1 + 1):
                if t + 3 <= a_hi:
                    cnt += hrow[t + 3, c]
                if t - 4 >= a_lo:
                    cnt -= hrow[t - 4, c]
                if cnt > 0 and outside[t, c]:
                    P[t, c] = level0
    return buf, boff
