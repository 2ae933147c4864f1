"""The code-ring reading of :mod:`service.core.targets.decode`, compiled (numba).

One loop over the targets does what :mod:`~service.core.targets.decode` describes: the
cheap look for a bright ring, the re-fit of the disk ellipse to its edge, the
reading of the ring with both ellipses and the checks. Written by hand as a
loop because the vectorised form was a hundred array passes over (targets x
samples) arrays: 5.6 ms for a frame's 30 coded targets, against 1.4 ms here
(the full frame's budget is 5 ms). Most of what remains is the ~2100 bilinear
samples per target.

Sampling is bilinear exactly as ``cv2.remap`` (``INTER_LINEAR``, constant
border) does it, so the readings are those of the former vectorised reader:
the position is rounded to 1/32 px; an 8-bit image is interpolated in fixed
point and rounded to whole DN, a 16-bit one in floating point and rounded.
Points outside ``[0, W - 1] x [0, H - 1]`` are NaN.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.core._kernels.crowd_kernel import _kth_smallest
from service.core._kernels.geometry_kernels import _solve6

#: how :func:`_sample` interpolates: 8-bit fixed point, rounded floating point, floating point
FIXED8, ROUNDED, FLOAT = 0, 1, 2
#: columns of :func:`read_rings_kernel`'s float output
ROLL_DEG, CONFIDENCE, DISK_DN, BACKGROUND_DN = 0, 1, 2, 3
_TWO_PI = 2.0 * np.pi
RING_LOOK = 48  # samples per circle of :func:`_may_have_ring`'s look at the ring zone


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _sample(img, mode, e, m00, m01, m10, m11, pts, out):
    """``out[k]`` = the image at the normalised point ``pts[k]`` of the ellipse ``e`` with the affine
    map ``m``; NaN outside. The points are placed in float64 and used as float32, like
    ``cv2.remap``'s maps."""
    h, w = img.shape
    flat = img.reshape(-1)
    cu, cv = e[0], e[1]
    for k in range(pts.shape[0]):
        px, py = pts[k, 0], pts[k, 1]
        u = float(np.float32(cu + m00 * px + m01 * py))
        v = float(np.float32(cv + m10 * px + m11 * py))
        if not (u >= 0.0 and u <= w - 1 and v >= 0.0 and v <= h - 1):
            out[k] = np.nan
            continue
        X, Y = np.int64(np.rint(u * 32.0)), np.int64(np.rint(v * 32.0))  # exact, as in float32
        x0, y0, fx, fy = X >> 5, Y >> 5, X & 31, Y & 31
        i00 = y0 * w + x0
        i01 = i00 + (1 if x0 < w - 1 else 0)  # beyond the border the weight is 0
        dy = w if y0 < h - 1 else 0
        # unsigned indices: no test for negative ones in the hot loop
        p00, p01 = flat[np.uint64(i00)], flat[np.uint64(i01)]
        p10, p11 = flat[np.uint64(i00 + dy)], flat[np.uint64(i01 + dy)]
        if mode == FIXED8:  # weights (32 - fx)(32 - fy) ... summing to 1024, rounded
            top = np.int64(p00) * 32 + (np.int64(p01) - np.int64(p00)) * fx
            bot = np.int64(p10) * 32 + (np.int64(p11) - np.int64(p10)) * fx
            out[k] = float((top * 32 + (bot - top) * fy + 512) >> 10)
        else:
            ax, ay = fx / 32.0, fy / 32.0
            s = (
                (1.0 - ax) * (1.0 - ay) * float(p00)
                + ax * (1.0 - ay) * float(p01)
                + (1.0 - ax) * ay * float(p10)
                + ax * ay * float(p11)
            )
            out[k] = np.rint(s) if mode == ROUNDED else s


@njit(cache=True, nogil=True, error_model="numpy")
def _insertion_sort(x, n):
    for i in range(1, n):
        a, j = x[i], i - 1
        while j >= 0 and x[j] > a:
            x[j + 1] = x[j]
            j -= 1
        x[j + 1] = a


@njit(cache=True, nogil=True, error_model="numpy")
def _middle(work, n):
    """Median of ``work[:n]`` (n >= 1), reordering it: the mean of its two middle values."""
    k = n // 2
    upper = _kth_smallest(work[:n], k)
    if n % 2:
        return upper
    lower = work[0]
    for i in range(1, k):
        lower = max(lower, work[i])
    return 0.5 * (lower + upper)


@njit(cache=True, nogil=True, error_model="numpy")
def _median(x, work):
    """Median of ``x`` (NaN if any is NaN, as ``np.median``); ``work`` is scratch of len(x)."""
    n = x.size
    for i in range(n):
        if x[i] != x[i]:
            return np.nan
        work[i] = x[i]
    return _middle(work, n)


@njit(cache=True, nogil=True, error_model="numpy")
def _finite_median(x, work):
    """Median of the finite values of ``x``; NaN without any."""
    k = 0
    for i in range(x.size):
        if np.isfinite(x[i]):
            work[k] = x[i]
            k += 1
    if k == 0:
        return np.nan
    return _middle(work, k)


@njit(cache=True, nogil=True, error_model="numpy")
def _affine(e):
    """M = Rot(angle) @ diag(a, b): the unit circle onto the ellipse (u_c, v_c, a, b, angle)."""
    ca, sa = np.cos(e[4]), np.sin(e[4])
    return ca * e[2], -sa * e[3], sa * e[2], ca * e[3]


@njit(cache=True, nogil=True, error_model="numpy")
def _ellipse_from_conic(A, B, C, D, E):
    """Centre, semi-axes (major first), major axis angle and validity of ``A x^2 + B xy + C y^2 +
    D x + E y = 1``."""
    ok = A * C - B * B / 4 > 0
    if not ok:
        A, B, C = 1.0, 0.0, 1.0
    det = A * C - B * B / 4
    cx = -0.5 * (C * D - 0.5 * B * E) / det
    cy = -0.5 * (A * E - 0.5 * B * D) / det
    mu = 1.0 + 0.5 * (D * cx + E * cy)
    s = mu if mu > 0 else 1.0
    p, q, r = A / s, 0.5 * B / s, C / s
    m, d = 0.5 * (p + r), np.hypot(0.5 * (p - r), q)
    lam0, lam1 = m - d, m + d
    ok = ok and mu > 0 and lam0 > 0 and lam1 > 0
    a_ax = 1.0 / np.sqrt(lam0 if lam0 > 0 else 1.0)
    b_ax = 1.0 / np.sqrt(lam1 if lam1 > 0 else 1.0)
    # the larger eigenvalue's vector lies at half the angle of (p - r, 2 q); the major axis across it
    angle = 0.5 * np.arctan2(2.0 * q, p - r) + 0.5 * np.pi
    if angle > 0.5 * np.pi:
        angle -= np.pi
    return cx, cy, a_ax, b_ax, angle, ok


@njit(cache=True, nogil=True, error_model="numpy")
def _fit_conic(r, ray, found, size, G, g, row):
    """Direct least-squares conic through the points ``r[d] * ray[d]`` px with ``found[d]``,
    about the ellipse's centre; returns its centre offset, semi-axes, angle and validity.
    ``G`` (5, 5), ``g`` and ``row`` (5,) are scratch."""
    for a in range(5):
        g[a] = 0.0
        for b in range(5):
            G[a, b] = 0.0
    for d in range(r.size):
        if not found[d]:
            continue
        px, py = r[d] * ray[d, 0] / size, r[d] * ray[d, 1] / size
        row[0], row[1], row[2], row[3], row[4] = px * px, px * py, py * py, px, py
        for a in range(5):
            g[a] += row[a]
            for b in range(5):
                G[a, b] += row[a] * row[b]
    tr = G[0, 0] + G[1, 1] + G[2, 2] + G[3, 3] + G[4, 4]
    for a in range(5):  # rows with too few points are judged by the caller; keep them solvable
        G[a, a] += 1e-9 * tr + 1e-12
    coef = _solve6(G, g)
    cx, cy, a_ax, b_ax, angle, ok = _ellipse_from_conic(coef[0], coef[1], coef[2], coef[3], coef[4])
    return cx * size, cy * size, a_ax * size, b_ax * size, angle, ok


@njit(cache=True, nogil=True, error_model="numpy")
def _may_have_ring(img, mode, e, pts, vals, work):
    """Whether anything in the ring zone (``pts[13:]``) is clearly brighter than the gap
    (``pts[1:13]``) round the disk's centre (``pts[0]``). ``vals`` (len(pts),) and ``work`` (12,)
    are scratch.

    The ring zone is sampled a circle (RING_LOOK points) at a time, and the look ends at the first
    circle that holds a bright sample: the answer is that of the brightest sample (``v - gap`` is
    monotonic in ``v``), and a coded ring shows in the first circle (a third of the samples)."""
    m00, m01, m10, m11 = _affine(e)
    _sample(img, mode, e, m00, m01, m10, m11, pts[:13], vals[:13])
    disk, gap = vals[0], _median(vals[1:13], work)
    if not disk > gap:
        return False
    bar = 0.25 * (disk - gap)
    for k0 in range(13, pts.shape[0], RING_LOOK):
        k1 = min(k0 + RING_LOOK, pts.shape[0])
        _sample(img, mode, e, m00, m01, m10, m11, pts[k0:k1], vals[k0:k1])
        for k in range(k0, k1):
            if np.isfinite(vals[k]) and vals[k] - gap > bar:
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _refine(img, mode, e, rho, step, dirs, pts, lo_index, lo_gamma, out, ws, found, ray, G, g, row):
    """Re-fit the disk ellipse ``e`` to the half-level edge along the rays ``dirs`` (D, 2) sampled
    at ``rho`` (R,) (``pts`` = rho x dirs); write it to ``out`` (5,). Step 1 of the
    :mod:`~service.core.targets.decode` docstring. ``ws`` (2 R D + 6 D,), ``found`` (D,) bool,
    ``ray`` (D, 2) and ``G``, ``g``, ``row`` (see :func:`_fit_conic`) are scratch."""
    nr, nd = rho.size, dirs.shape[0]
    m00, m01, m10, m11 = _affine(e)
    vals, work = ws[: nr * nd], ws[nr * nd : 2 * nr * nd]
    o = 2 * nr * nd
    r50, x0s, x1s = ws[o : o + nd], ws[o + nd : o + 2 * nd], ws[o + 2 * nd : o + 3 * nd]
    rim, var, shifted = ws[o + 3 * nd : o + 4 * nd], ws[o + 4 * nd : o + 5 * nd], ws[o + 5 * nd : o + 6 * nd]
    _sample(img, mode, e, m00, m01, m10, m11, pts, vals)
    for k in range(vals.size):
        if vals[k] != vals[k]:
            vals[k] = 0.0
    hi = _median(vals[:nd], work)
    n_out = 0
    for ri in range(nr):
        if rho[ri] > 1.25:
            for d in range(nd):
                work[n_out] = vals[ri * nd + d]
                n_out += 1
    # np.percentile's linear interpolation (index and fraction from the caller, as numpy computes them)
    if lo_index + 1 < n_out:
        above = _kth_smallest(work[:n_out], lo_index + 1)
        below = work[0]
        for i in range(1, lo_index + 1):
            below = max(below, work[i])
    else:
        below = above = _kth_smallest(work[:n_out], lo_index)
    lo = below + (above - below) * lo_gamma
    n_found = 0
    for d in range(nd):
        i1, hit = 0, False
        for ri in range(nr):
            if (vals[ri * nd + d] - lo) / (hi - lo) < 0.5:
                i1, hit = ri, True
                break
        f = hit and i1 > 0
        i1 = min(max(i1, 1), nr - 1)
        x0 = (vals[(i1 - 1) * nd + d] - lo) / (hi - lo)
        x1 = (vals[i1 * nd + d] - lo) / (hi - lo)
        r = rho[i1 - 1] + step * (x0 - 0.5) / (x0 - x1)
        f = f and np.isfinite(r) and hi > lo
        found[d], r50[d], x0s[d], x1s[d] = f, r if f else 1.0, x0, x1
        n_found += f
        ray[d, 0] = dirs[d, 0] * m00 + dirs[d, 1] * m01
        ray[d, 1] = dirs[d, 0] * m10 + dirs[d, 1] * m11
        rim[d] = np.sqrt(ray[d, 0] * ray[d, 0] + ray[d, 1] * ray[d, 1])
    for k in range(5):
        out[k] = e[k]
    size = np.sqrt(e[2] * e[3])
    cx, cy, A, B, angle, ok = _fit_conic(r50, ray, found, size, G, g, row)
    # Blur moves the half-level contour inwards by sigma^2 / 2 times its curvature: sigma from the
    # edge slope, each edge point pushed out by that, and a second fit
    for d in range(nd):
        slope = (x0s[d] - x1s[d]) / step / rim[d]
        var[d] = 1.0 / (2 * np.pi * (slope * slope)) if found[d] and slope > 0 else np.nan
    sigma = np.sqrt(_finite_median(var, work))
    ca, sa = np.cos(angle), np.sin(angle)
    for d in range(nd):
        rx, ry = r50[d] * ray[d, 0] - cx, r50[d] * ray[d, 1] - cy
        t = np.arctan2((-sa * rx + ca * ry) / B, (ca * rx + sa * ry) / A)
        kappa = A * B / (A * A * np.sin(t) ** 2 + B * B * np.cos(t) ** 2) ** 1.5
        shift = 0.5 * sigma * sigma * kappa / rim[d]
        shifted[d] = r50[d] + (min(shift, 0.5) if np.isfinite(shift) and ok else 0.0)
    cx, cy, A, B, angle, ok2 = _fit_conic(shifted, ray, found, size, G, g, row)
    b0 = min(e[2], e[3])
    # trust the fit only near the input: an edge ray that ran into a neighbour must not drag it
    ok = ok and ok2 and n_found >= 16 and np.hypot(cx, cy) < 0.5 * b0 + 0.5
    r_minor, r_major = min(A, B) / b0, max(A, B) / max(e[2], e[3])
    ok = ok and 0.6 < r_minor < 1.6 and 0.75 < r_major < 1.33
    if ok:
        out[0], out[1], out[2], out[3], out[4] = e[0] + cx, e[1] + cy, A, B, angle
    elif n_found >= 8:  # one common size offset (px) from the median edge distance
        for d in range(nd):
            var[d] = (r50[d] - 1.0) * rim[d] if found[d] else np.nan
        delta = _finite_median(var, work)
        delta = delta if abs(delta) < 0.5 * b0 else 0.0
        out[2] += delta
        out[3] += delta


@njit(cache=True, nogil=True)
def read_scratch_size(P, n_disk, n_gap, K, S, run):
    """The length of :func:`_read_ring`'s float scratch."""
    KS = K * S
    return P + max(n_disk, n_gap) + n_gap + 5 * KS + (KS + run) + 4 * K + S


@njit(cache=True, nogil=True, error_model="numpy")
def _read_ring(
    img,
    mode,
    e,
    bg_given,
    pts,
    n_disk,
    n_gap,
    n_radii,
    K,
    S,
    core_a,
    run,
    code_of,
    roll_of,
    floor_dn,
    limits,
    levels_out,
    bits_out,
    ws,
):
    """Read the ring of the ellipse ``e`` (steps 3-4 of the :mod:`~service.core.targets.decode`
    docstring): whether it passes every check of ``decode.read_codes``, its code, roll (sectors),
    margin, roll_deg, disk and background DN. ``levels_out`` and ``bits_out`` (K,) receive the
    sectors as read; ``ws`` (:func:`read_scratch_size`,) is scratch.

    A reading that fails a check is never used (see :func:`read_rings_kernel`), so each check
    returns as soon as what it needs is known: the ellipse's size before any sample, the disk's
    contrast and the gap before the ring's samples, the word and margin before the roll. The
    values of a failed reading are therefore not meaningful."""
    min_conf, min_snr, min_minor, min_diam, min_margin_snr, min_ratio, max_spread, max_level = limits[:8]
    fail = (False, 0, 0, -1.0, np.nan, np.nan, np.nan)
    b_px, a_px = min(e[2], e[3]), max(e[2], e[3])
    if not (b_px >= min_minor and 2 * a_px >= min_diam and b_px >= min_ratio * a_px):
        return fail
    P = pts.shape[0]
    KS = K * S
    n_in = n_disk + n_gap  # disk and gap samples come first
    o = 0
    vals = ws[o : o + P]
    o += P
    work = ws[o : o + max(n_disk, n_gap)]
    o += max(n_disk, n_gap)
    diffs = ws[o : o + n_gap]
    o += n_gap
    profile, prof_in, prof_out = ws[o : o + KS], ws[o + KS : o + 2 * KS], ws[o + 2 * KS : o + 3 * KS]
    run_in, run_out = ws[o + 3 * KS : o + 4 * KS], ws[o + 4 * KS : o + 5 * KS]
    o += 5 * KS
    csum = ws[o : o + KS + run]
    o += KS + run
    lv, srt, pmin, pmax = ws[o : o + K], ws[o + K : o + 2 * K], ws[o + 2 * K : o + 3 * K], ws[o + 3 * K : o + 4 * K]
    o += 4 * K
    edge = ws[o : o + S]
    m00, m01, m10, m11 = _affine(e)
    _sample(img, mode, e, m00, m01, m10, m11, pts[:n_in], vals[:n_in])
    for k in range(n_in):
        if not np.isfinite(vals[k]):
            return fail
    disk_dn = _median(vals[:n_disk], work)
    gap = vals[n_disk:n_in]
    gap_dn = _median(gap, work)
    bg = gap_dn if bg_given != bg_given else bg_given
    # noise from differences of angular neighbours round the gap, robust to the odd bright speck
    ng = n_gap // 2
    spread_lo, spread_hi = np.inf, -np.inf
    for k in range(ng):
        kp = k - 1 if k > 0 else ng - 1
        diffs[k] = abs(gap[k] - gap[kp])
        diffs[ng + k] = abs(gap[ng + k] - gap[ng + kp])
        g = (gap[k] + gap[ng + k]) / 2
        spread_lo, spread_hi = min(spread_lo, g), max(spread_hi, g)
    noise_dn = 1.4826 / np.sqrt(2.0) * _median(diffs, work)
    contrast = disk_dn - bg
    scale = contrast if contrast > 0 else 1.0
    noise = max(noise_dn, floor_dn)
    if not (contrast > min_snr * noise and (spread_hi - spread_lo) / scale <= max_spread):
        return fail
    _sample(img, mode, e, m00, m01, m10, m11, pts[n_in:], vals[n_in:])
    ring = vals[n_in:]
    for k in range(ring.size):
        if not np.isfinite(ring[k]):
            return fail
    # profile (mean over radii) and the inner/outer halves' means, per ring sample
    h = n_radii // 2
    profile[:] = 0.0
    prof_in[:] = 0.0
    prof_out[:] = 0.0
    for ri in range(n_radii):  # radius by radius: the inner loops vectorise
        part = prof_in if ri < h else prof_out
        for j in range(KS):
            x = (ring[ri * KS + j] - bg) / scale
            profile[j] += x
            part[j] += x
    for j in range(KS):
        profile[j], prof_in[j], prof_out[j] = profile[j] / n_radii, prof_in[j] / h, prof_out[j] / (n_radii - h)
    # running means of `run` samples of the mid-sample values, by a cumulative sum (wrapping round)
    for half in range(2):
        prof = prof_in if half == 0 else prof_out
        run_mean = run_in if half == 0 else run_out
        c = 0.0
        csum[0] = 0.0
        for i in range(KS + run - 1):
            ii = i if i < KS else i - KS  # no integer modulo in the hot loops: it costs a division
            c += 0.5 * (prof[ii] + prof[ii + 1 if ii + 1 < KS else 0])
            csum[i + 1] = c
        for i in range(KS):
            run_mean[i] = (csum[i + run] - csum[i]) / run
    # every phase: sector levels in four parts (inner/outer x first/second half of the core); the
    # threshold at the widest gap of the sorted levels; the margin between the worst parts
    best_j, best_margin, best_thr = 0, -np.inf, 0.0
    for j in range(S):
        for k in range(K):
            i0, i1 = j + S * k + core_a, j + S * k + S // 2  # below KS + S: one wrap at most
            i0, i1 = i0 - KS if i0 >= KS else i0, i1 - KS if i1 >= KS else i1
            a, b, c, d = run_in[i0], run_in[i1], run_out[i0], run_out[i1]
            lv[k] = (((a + b) + c) + d) / 4
            srt[k] = lv[k]
            pmin[k], pmax[k] = min(min(a, b), min(c, d)), max(max(a, b), max(c, d))
        _insertion_sort(srt, K)
        gi, gmax = 0, srt[1] - srt[0]
        for k in range(1, K - 1):
            if srt[k + 1] - srt[k] > gmax:
                gi, gmax = k, srt[k + 1] - srt[k]
        thr = 0.5 * (srt[gi] + srt[gi + 1])
        lo_bright, hi_dark = np.inf, -np.inf
        for k in range(K):
            if lv[k] > thr:
                lo_bright = min(lo_bright, pmin[k])
            else:
                hi_dark = max(hi_dark, pmax[k])
        margin = lo_bright - hi_dark
        if not np.isfinite(margin):
            margin = -1.0
        if margin > best_margin:
            best_j, best_margin, best_thr = j, margin, thr
            for k in range(K):
                levels_out[k] = lv[k]
    j = best_j
    word, level_max = 0, -np.inf
    for k in range(K):
        bits_out[k] = levels_out[k] > best_thr
        word |= int(bits_out[k]) << k
        level_max = max(level_max, levels_out[k])
    code, roll = code_of[word], roll_of[word]
    good = (
        best_margin >= min_conf
        and best_margin * contrast >= min_margin_snr * noise
        and best_thr > 0.1
        and best_thr < 0.8
        and level_max <= max_level
        and code > 0
    )
    if not good:
        return fail
    # sub-sample phase, for the roll only: the sector edges folded onto one sector, searched within a
    # quarter sector of the chosen phase, a parabola through the peak
    edge[:] = 0.0
    for k in range(K):
        for s in range(S):
            i = k * S + s
            edge[s] += abs(profile[i + 1 if i + 1 < KS else 0] - profile[i])
    jj, e_best = 0, -np.inf
    for off in range(-(S // 4), S // 4 + 1):
        w = (j + off) % S
        if edge[w] > e_best:
            jj, e_best = w, edge[w]
    em, e0, ep = edge[(jj - 1) % S], edge[jj], edge[(jj + 1) % S]
    denom = em - 2 * e0 + ep
    frac = 0.5 * (em - ep) / denom if denom < 0 else 0.0
    frac = 0.0 if frac != frac else frac
    phase = j + 0.5 + (((jj - j + S // 2) % S) - S // 2) + min(max(frac, -0.5), 0.5)
    phi = -(roll * S + phase) * (_TWO_PI / KS)
    cp, sp = np.cos(phi), np.sin(phi)
    roll_deg = np.degrees(np.arctan2(-(m10 * cp + m11 * sp), m00 * cp + m01 * sp))
    return True, code, roll, best_margin, roll_deg, disk_dn, bg


@njit(cache=True, nogil=True, error_model="numpy")
def _same_samples(e, f, r_max, tol_px):
    """Whether the ellipses ``e`` and ``f`` place every sample point within ``r_max`` disk radii of
    the centre less than ``tol_px`` apart: the centre's offset plus ``r_max`` times the largest
    singular value of the difference of their affine maps bounds every point's offset."""
    a00, a01, a10, a11 = _affine(e)
    b00, b01, b10, b11 = _affine(f)
    p, q, r, s = b00 - a00, b01 - a01, b10 - a10, b11 - a11
    sigma = 0.5 * (np.hypot(p + s, q - r) + np.hypot(p - s, q + r))
    return np.hypot(f[0] - e[0], f[1] - e[1]) + r_max * sigma <= tol_px


@njit(cache=True, nogil=True, error_model="numpy")
def read_rings_kernel(
    img,
    mode,
    e,
    todo,
    bg,
    ring_pts,
    refine_pts,
    rho,
    step,
    dirs,
    lo_index,
    lo_gamma,
    pts,
    n_disk,
    n_gap,
    n_radii,
    n_bits,
    S,
    core_a,
    run,
    code_of,
    roll_of,
    floor_dn,
    limits,
):
    """Read the code rings of the ellipses ``e`` (N, 5) where ``todo`` (N,), as ``decode.read_codes``.

    ``bg`` (N,): the background DN, NaN to measure it in the gap. The pattern arrays are those of
    ``decode``; ``limits``: min_confidence, min_snr, min_minor_px, min_diameter_px, min_margin_snr,
    MIN_AXIS_RATIO, MAX_GAP_SPREAD, MAX_SECTOR_LEVEL, SAME_SAMPLES_PX.

    Returns
    -------
    ok : (N,) bool -- read, every check passed, and the two ellipses do not name different codes
    code : (N,) int
    values : (N, 4) float -- roll_deg, confidence, disk_dn, background_dn (columns named above)
    bits, levels : (N, n_bits) -- the sectors in the target's own order
    ellipse : (N, 5) float -- the ellipse the reading used
    """
    n, K = e.shape[0], n_bits
    ok = np.zeros(n, dtype=np.bool_)
    code = np.zeros(n, dtype=np.int64)
    values = np.full((n, 4), np.nan)
    bits = np.zeros((n, K), dtype=np.bool_)
    levels = np.zeros((n, K))
    ellipse = e.copy()
    same_px = limits[8]
    r_max = 0.0
    for k in range(pts.shape[0]):
        r_max = max(r_max, np.hypot(pts[k, 0], pts[k, 1]))
    # scratch, once for all targets
    scratch, work12 = np.empty(ring_pts.shape[0]), np.empty(12)
    nd = dirs.shape[0]
    refine_ws = np.empty(2 * refine_pts.shape[0] + 6 * nd)
    found, ray = np.zeros(nd, dtype=np.bool_), np.empty((nd, 2))
    G, g, row = np.empty((5, 5)), np.empty(5), np.empty(5)
    read_ws = np.empty(read_scratch_size(pts.shape[0], n_disk, n_gap, K, S, run))
    fit = np.empty(5)
    lv0, lv1 = np.empty(K), np.empty(K)
    b0, b1 = np.zeros(K, dtype=np.bool_), np.zeros(K, dtype=np.bool_)
    for i in range(n):
        if not todo[i] or not _may_have_ring(img, mode, e[i], ring_pts, scratch, work12):
            continue
        # read with the given ellipse and with its re-fit to the disk edge (step 2 of decode's docstring)
        _refine(img, mode, e[i], rho, step, dirs, refine_pts, lo_index, lo_gamma, fit, refine_ws, found, ray, G, g, row)
        g1, c1, r1, m1, d1, disk1, bg1 = _read_ring(
            img,
            mode,
            fit,
            bg[i],
            pts,
            n_disk,
            n_gap,
            n_radii,
            K,
            S,
            core_a,
            run,
            code_of,
            roll_of,
            floor_dn,
            limits,
            lv1,
            b1,
            read_ws,
        )
        if _same_samples(e[i], fit, r_max, same_px):
            # the two readings would sample the same points within a fraction of a pixel
            g0, c0, r0, m0, d0, disk0, bg0 = False, 0, 0, -1.0, np.nan, np.nan, np.nan
        else:
            g0, c0, r0, m0, d0, disk0, bg0 = _read_ring(
                img,
                mode,
                e[i],
                bg[i],
                pts,
                n_disk,
                n_gap,
                n_radii,
                K,
                S,
                core_a,
                run,
                code_of,
                roll_of,
                floor_dn,
                limits,
                lv0,
                b0,
                read_ws,
            )
        if not (g0 or g1) or (g0 and g1 and c0 != c1):
            continue
        # of two agreeing readings, the one with the wider margin
        if g1 and (not g0 or m1 >= m0):
            c, roll, m, d, disk, bgv, lv, b = c1, r1, m1, d1, disk1, bg1, lv1, b1
            for k in range(5):
                ellipse[i, k] = fit[k]
        else:
            c, roll, m, d, disk, bgv, lv, b = c0, r0, m0, d0, disk0, bg0, lv0, b0
        ok[i], code[i] = True, c
        values[i, ROLL_DEG], values[i, CONFIDENCE], values[i, DISK_DN], values[i, BACKGROUND_DN] = d, m, disk, bgv
        for k in range(K):  # target sector k was read as sector k + roll
            bits[i, k], levels[i, k] = b[(k + roll) % K], lv[(k + roll) % K]
    return ok, code, values, bits, levels, ellipse
