"""The per-window measurement of :mod:`service.core.targets.detect`, compiled (numba).

One loop over the windows does what :mod:`~service.core.targets.detect` describes for a
window: the background plane through the rim, the moments up to the fourth, the
plateau, the ellipse, the shape statistics and the fill's mismatch. Written by
hand as a loop because a vectorised form needs a stack of equal windows (one
batch per radius) and a hundred array passes per batch, which cost more than
the arithmetic on a few hundred small windows (ROI tracking at >= 1 kHz).

:func:`measure_windows_kernel` returns the measurements as the rows of one
(NF, n) array, named by the constants below (``detect._Measured`` holds them
as fields); :func:`assess_kernel` turns them into reasons, sigma_px and fill;
:mod:`service.core._kernels.contour_kernel` does the full frame's contours and
:mod:`service.core._kernels.crowd_kernel` the work on blobs near each other.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import (
    contour_kernel,
    crowd_kernel,
    edge_kernel,
    illumination_kernel,
    noise_kernel,
    warm_images,
)

# rows of the float output
UV, ELLIPSE, FLUX, LEVEL, PEAK, BACKGROUND, SB2, K_SHOT, VAR_BASE, VAR_PER_K = 0, 0, 5, 6, 7, 8, 9, 10, 11, 12
MISMATCH, NOISE_BG, M3SQ, KURT, KURT_MODEL, FLAT_TOP, VAR_MAJOR, SUMS = 13, 14, 15, 16, 17, 18, 19, 20
EDGE_UV, EDGE_SIGMA = 27, 29  # the edge fit's centre (2 rows) and sigma; NaN where not asked or not held
N_SAT = 30  # the window's pixels at the saturation level (also returned as ``n_sat``)
LIGHT = 31  # the light's relative gradient per px at the window (2 rows) the edge fit followed; 0 without
BLUR = 33  # the blur's variance px^2 the second moments show beyond the disk's own (optics, focus, pixel)
NF = 34
# A disk with more pixels at the saturation level than this is clipped: measured on its flat top (its
# plateau says nothing of the shot noise, see assess_kernel) and counted as saturated for the exposure
CLIPPED_PX = 2

# reassociation lets the pixel sums vectorise; NaN and inf keep their meaning (no nnan/ninf)
_FAST = {"reassoc", "contract", "arcp"}


@njit(cache=True, nogil=True, inline="always")
def _fmin(a: float, b: float) -> float:  # np.fmin: NaN-ignoring
    if a != a:
        return b
    if b != b:
        return a
    return a if a < b else b


@njit(cache=True, nogil=True, inline="always")
def _fmax(a: float, b: float) -> float:  # np.fmax: NaN-ignoring
    if a != a:
        return b
    if b != b:
        return a
    return a if a > b else b


@njit(cache=True, nogil=True, inline="always")
def _maximum(a: float, b: float) -> float:  # np.maximum: NaN-propagating
    if a != a or a > b:
        return a
    return b


# A target smeared by the camera's motion during the exposure: its image is the disk's ellipse
# convolved with a line segment (and the blur), a uniform distribution along the motion, whose
# excess kurtosis is -1.2 (the ellipse's own along an axis: -1, a semicircle; the blur's: 0)
SMEAR_EXCESS_KURTOSIS = 1.2


@njit(cache=True, nogil=True)
def _kurtosis_range(qa4, qb4, var_major):
    """(lowest, highest) kurtosis along the major axis of a disk's ellipse smeared along that axis
    by any length that keeps its own ellipse no narrower than the blob's minor axis. ``qa4`` and
    ``qb4``: the blob's semi-axes squared over 4 (blur removed), px^2; ``var_major``: its variance
    along the major axis, blur included. The ellipse's own major variance ``qa4 - s`` and the
    smear's ``s`` (0 <= s <= qa4 - qb4) add; so do their fourth cumulants, ``-(qa4 - s)^2 - 1.2
    s^2``, a convex function of ``s``. Without room for a smear (a round blob) the range is the
    unsmeared disk's one kurtosis, ``3 - qa4^2 / var_major^2``."""
    s_max = _fmax(qa4 - qb4, 0.0)
    s_min_k = min(max(qa4 / (1.0 + SMEAR_EXCESS_KURTOSIS), 0.0), s_max)  # where -kappa4 is least
    k4_least = (qa4 - s_min_k) ** 2 + SMEAR_EXCESS_KURTOSIS * s_min_k * s_min_k
    k4_most = max(qa4 * qa4, (qa4 - s_max) ** 2 + SMEAR_EXCESS_KURTOSIS * s_max * s_max)
    v2 = var_major * var_major
    return 3.0 - k4_most / v2, 3.0 - k4_least / v2


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST)
def _rows(h, w, wi, sums):
    """Per row dv = a - h of the circle of radius h + 1/2: its half width ``w`` and the half
    width ``wi`` of the disk inside the rim (distance <= h - 1; -1 where the row misses it); the
    circle's sums of du^0, du^2, du^4, du^2 dv^2, du^6, du^4 dv^2, du^8."""
    r2, ri2 = (h + 0.5) ** 2, (h - 1.0) ** 2
    sums[:] = 0.0
    for a in range(2 * h + 1):
        dv2 = (a - h) * (a - h)
        w[a] = int(np.sqrt(r2 - dv2))
        q = ri2 - dv2
        if q < 0:
            wi[a] = -1
        else:
            k = int(np.sqrt(q))
            while (k + 1) * (k + 1) <= q:
                k += 1
            while k * k > q:
                k -= 1
            wi[a] = k
        e2 = e4 = e6 = e8 = 0.0
        for d in range(1, w[a] + 1):
            d2 = float(d * d)
            e2 += 2.0 * d2
            e4 += 2.0 * d2 * d2
            e6 += 2.0 * d2 * d2 * d2
            e8 += 2.0 * d2 * d2 * d2 * d2
        sums[0] += 2 * w[a] + 1
        sums[1] += e2
        sums[2] += e4
        sums[3] += e2 * dv2
        sums[4] += e6
        sums[5] += e4 * dv2
        sums[6] += e8


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST)
def measure_windows_kernel(img, cu, cv, half, placed, seg, full, buf, boff, edge_fit):
    """Measure the blob in the circle of radius ``half + 1/2`` about each (cu, cv).

    Parameters
    ----------
    img : (H, W) uint8 or uint16
    cu, cv, half : (n,) int, px
    placed : (n,) bool -- the window lies inside the image (others give zeros and a crossed rim)
    seg : (n,) float, DN -- each window's segmentation level above its background (the noise's)
    full : float, DN -- saturation level
    buf : (K,) float32 -- pixel values replacing the image's in crowded windows (others masked)
    boff : (n,) int -- each window's s*s values' offset into ``buf``, -1: read the image
    edge_fit : bool -- also fit each disk's half-level edge (:func:`~service.core._kernels.edge_kernel.edge_fit`,
        on the image), its level following the light the windows' plateaus show across the frame
        (:func:`~service.core._kernels.illumination_kernel.fit_light`): rows EDGE_UV, EDGE_SIGMA, LIGHT

    Returns
    -------
    out : (NF, n) float -- the rows named at the top of the module
    n_sat : (n,) int
    edge : (n,) bool
    """
    n = cu.size
    out = np.zeros((NF, n))
    out[EDGE_UV : EDGE_SIGMA + 1] = np.nan
    n_sat = np.zeros(n, dtype=np.intp)
    edge = np.ones(n, dtype=np.bool_)
    hmax = 0
    for i in range(n):
        if placed[i] and half[i] > hmax:
            hmax = half[i]
    s_max = 2 * hmax + 1
    # per window radius, once: the rows' half widths and the circle's sums
    wtab, witab = np.zeros((hmax + 1, s_max), dtype=np.intp), np.zeros((hmax + 1, s_max), dtype=np.intp)
    stab, have = np.zeros((hmax + 1, 7)), np.zeros(hmax + 1, dtype=np.bool_)
    rb = np.empty(8 * s_max + 8)  # rim values and their du, dv
    ru = np.empty(8 * s_max + 8)
    rv = np.empty(8 * s_max + 8)
    # a disk held in its window is no wider than it (a wider blob crosses the rim and is rejected)
    px, py, G, g, core, G0, g0 = edge_kernel.edge_scratch(hmax + 2.0)
    for i in range(n):
        if not placed[i]:
            continue
        h = half[i]
        w, wi, sums = wtab[h], witab[h], stab[h]
        if not have[h]:
            _rows(h, w, wi, sums)
            have[h] = True
        s = 2 * h + 1
        u0, v0 = cu[i] - h, cv[i] - h
        o = boff[i]
        if o < 0:
            n_sat[i], edge[i] = _window(img, v0, u0, img, v0, u0, h, seg[i], full, w, wi, sums, rb, ru, rv, out, i)
        else:
            P = buf[o : o + s * s].reshape(s, s)
            n_sat[i], edge[i] = _window(P, 0, 0, img, v0, u0, h, seg[i], full, w, wi, sums, rb, ru, rv, out, i)
        out[N_SAT, i] = n_sat[i]
    if not edge_fit:
        return out, n_sat, edge
    # the edges once every plateau is known: the light across the frame, then each disk's edge
    height, width = img.shape
    usable = placed & ~edge
    light = illumination_kernel.fit_light(out[0], out[1], out[LEVEL], out[3], n_sat, usable, width, height, CLIPPED_PX)
    for i in range(n):
        if not placed[i]:
            continue
        e = out[:, i]
        gu, gv = illumination_kernel.light_gradient(light, e[0], e[1], width, height)
        e[LIGHT], e[LIGHT + 1] = gu, gv
        u, v, sigma = edge_kernel.edge_fit(
            img, e[0], e[1], e[2], e[3], e[4], e[BACKGROUND], gu, gv, px, py, G, g, core, G0, g0
        )
        if sigma == sigma:
            e[EDGE_UV], e[EDGE_UV + 1], e[EDGE_SIGMA] = u, v, sigma
    return out, n_sat, edge


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST)
def _window(P, pv, ph, img, v0, u0, h, seg, full, w, wi, sums, rb, ru, rv, out, i):
    """One window: the values to measure are ``P[pv:pv + s, ph:ph + s]``, the image's (for the
    peak and saturation) ``img[v0:v0 + s, u0:u0 + s]``, both within the circle. Rows are taken one
    at a time: a 1-D row of a C array is contiguous, which lets the sums vectorise. Writes column
    ``i`` of ``out`` and returns (saturated pixels, rim crossed)."""
    s = 2 * h + 1
    r2 = (h + 0.5) ** 2
    # -- one pass over the circle's rows (each pass's loop over the rows cost more than its arithmetic
    # on these short rows: the peak's own pass over the square was 11 % of a window's time, one pass
    # for all 7 %), giving:
    # - the sums of the rim (the outer 1.5 px) for the background plane, fitted to its pixels that
    #   are not bright. A rim with nothing bright on it is symmetric, so its normal equations are
    #   diagonal: these sums and the rim's brightest pixel decide it (no copy of the rim: that and
    #   its second pass were half of a window's time). Only a rim crossed by something bright is
    #   gathered for a solve, and it counts as crossed when >= 2 pixels are bright;
    # - the moments up to the fourth of the raw values: the plane is removed from them afterwards
    #   (the circle's sums of du^k dv^l are known);
    # - the peak and the saturated pixels, of the image's values.
    s0 = s1 = s2 = sbb = ruu = 0.0
    k, rim_max = 0, -np.inf
    m00 = m10 = m01 = m20 = m11 = m02 = m30 = m21 = m12 = m03 = m40 = m31 = m22 = m13 = m04 = 0.0
    pk = img[v0 + h, u0 + h]
    for a in range(s):
        dv = a - h
        wa, wia, row = w[a], wi[a], P[pv + a]
        row_sum = 0.0
        for ku in range(-wa, -wia):
            pix = np.float64(row[ph + h + ku])  # float() would keep a float32 buffer's precision
            row_sum += pix
            s1 += pix * ku
            sbb += pix * pix
            rim_max = max(rim_max, pix)
        for ku in range(max(wia + 1, -wia), wa + 1):
            pix = np.float64(row[ph + h + ku])  # float() would keep a float32 buffer's precision
            row_sum += pix
            s1 += pix * ku
            sbb += pix * pix
            rim_max = max(rim_max, pix)
        s0 += row_sum
        s2 += row_sum * dv
        n_row = 2 * (wa - wia) if wia >= 0 else 2 * wa + 1
        k += n_row
        ruu += dv * dv * n_row  # the rim is symmetric: its sum of du^2 is its sum of dv^2
        fdv = float(dv)
        q0 = q1 = q2 = q3 = q4 = 0.0
        # a slice indexed from 0: the compiler then knows the indices are not negative and vectorises
        seg_row = P[pv + a, ph + h - wa : ph + h + wa + 1]
        img_row = img[v0 + a, u0 + h - wa : u0 + h + wa + 1]
        for t in range(2 * wa + 1):
            du = float(t - wa)
            p = np.float64(seg_row[t])
            pk = max(pk, img_row[t])
            pu = p * du
            pu2 = pu * du
            q0 += p
            q1 += pu
            q2 += pu2
            q3 += pu2 * du
            q4 += pu2 * du * du
        dv2 = fdv * fdv
        m00 += q0
        m10 += q1
        m01 += q0 * fdv
        m20 += q2
        m11 += q1 * fdv
        m02 += q0 * dv2
        m30 += q3
        m21 += q2 * fdv
        m12 += q1 * dv2
        m03 += q0 * dv2 * fdv
        m40 += q4
        m31 += q3 * fdv
        m22 += q2 * dv2
        m13 += q1 * dv2 * fdv
        m04 += q0 * dv2 * dv2
    peak = float(pk)
    ns = 0
    if peak >= full:
        for a in range(s):
            for b in range(h - w[a], h + w[a] + 1):
                if img[v0 + a, u0 + b] >= full:
                    ns += 1
    mean_thr = s0 / k + seg
    b0, b1, b2 = s0 / k, s1 / ruu, s2 / ruu
    rss = sbb - (b0 * s0 + b1 * s1 + b2 * s2)
    m_used, ruu_used, crossed = float(k), ruu, False
    if rim_max > mean_thr:  # the level of what is not bright, then a plane through what is below it + seg
        k = 0
        for a in range(s):
            dv = a - h
            wa, wia, row = w[a], wi[a], P[pv + a]
            for ku in range(-wa, -wia):
                rb[k], ru[k], rv[k] = row[ph + h + ku], ku, dv
                k += 1
            for ku in range(max(wia + 1, -wia), wa + 1):
                rb[k], ru[k], rv[k] = row[ph + h + ku], ku, dv
                k += 1
        kk, sk = 0, 0.0
        for j in range(k):
            if not rb[j] > mean_thr:
                kk += 1
                sk += rb[j]
        thr = sk / max(kk, 1) + seg
        n00 = n01 = n02 = n11 = n12 = n22 = r0 = r1 = r2_ = dbb = 0.0
        for j in range(k):
            if rb[j] <= thr:
                x, du, dv = rb[j], ru[j], rv[j]
                n00 += 1.0
                n01 += du
                n02 += dv
                n11 += du * du
                n12 += du * dv
                n22 += dv * dv
                r0 += x
                r1 += x * du
                r2_ += x * dv
                dbb += x * x
        crossed = n00 <= k - 2
        if n00 < 6:
            n00, n01, n02, n11, n12, n22, crossed = 1.0, 0.0, 0.0, 1.0, 0.0, 1.0, True
        # the 3 x 3 symmetric solve by cofactors
        c00, c01, c02 = n11 * n22 - n12 * n12, n02 * n12 - n01 * n22, n01 * n12 - n02 * n11
        c11, c12, c22 = n00 * n22 - n02 * n02, n01 * n02 - n00 * n12, n00 * n11 - n01 * n01
        det = n00 * c00 + n01 * c01 + n02 * c02
        b0 = (c00 * r0 + c01 * r1 + c02 * r2_) / det
        b1 = (c01 * r0 + c11 * r1 + c12 * r2_) / det
        b2 = (c02 * r0 + c12 * r1 + c22 * r2_) / det
        rss = dbb - (b0 * r0 + b1 * r1 + b2 * r2_)
        m_used, ruu_used = n00, 0.5 * (n11 + n22)
    sb2 = max(rss, 0.0) / max(m_used - 3.0, 1.0)
    a0, a2, a4, a22 = sums[0], sums[1], sums[2], sums[3]
    # the plane's offset b0 out of the raw moments: the circle's sums of du^0, du^2 (= dv^2), du^4
    # (= dv^4) and du^2 dv^2; its odd sums are zero
    m00 -= b0 * a0
    m20 -= b0 * a2
    m02 -= b0 * a2
    m40 -= b0 * a4
    m04 -= b0 * a4
    m22 -= b0 * a22
    S = m00
    # raw moments about the window centre, over the flux; the slopes' odd moments removed
    m10 -= b1 * a2
    m01 -= b2 * a2
    m30 -= b1 * a4
    m21 -= b2 * a22
    m12 -= b1 * a22
    m03 -= b2 * a4
    uc, vc, m20, m11, m02 = m10 / S, m01 / S, m20 / S, m11 / S, m02 / S
    m30, m21, m12, m03 = m30 / S, m21 / S, m12 / S, m03 / S
    m40, m31, m22, m13, m04 = m40 / S, m31 / S, m22 / S, m13 / S, m04 / S
    mu_uu, mu_uv, mu_vv = m20 - uc * uc, m11 - uc * vc, m02 - vc * vc
    finite = np.isfinite(uc) and np.isfinite(vc)
    # -- the plateau: the 3 x 3 pixels about the rounded centroid
    ci = min(max(int(np.rint(uc)) if finite else 0, 1 - h), h - 1) + h
    cj = min(max(int(np.rint(vc)) if finite else 0, 1 - h), h - 1) + h
    c1 = cc2 = 0.0
    for a in range(cj - 1, cj + 2):
        for b in range(ci - 1, ci + 2):
            x = 0.0
            if (a - h) ** 2 + (b - h) ** 2 <= r2:
                x = P[pv + a, ph + b] - b0
            c1 += x
            cc2 += x * x
    slope_c = b1 * uc + b2 * vc
    level, core_var = c1 / 9.0 - slope_c, (cc2 - c1 * c1 / 9.0) / 8.0
    # -- the disk's edge: second moments less the blur variance
    half_tr, root = 0.5 * (mu_uu + mu_vv), np.sqrt(0.25 * (mu_uu - mu_vv) ** 2 + mu_uv * mu_uv)
    dq = S / (4.0 * np.pi * level)  # a b / 4
    blur = _fmax(_fmin(half_tr - np.sqrt(root * root + dq * dq), 0.9 * (half_tr - root)), 0.0)
    a_ax, b_ax = 2.0 * np.sqrt(half_tr + root - blur), 2.0 * np.sqrt(half_tr - root - blur)
    ang = 0.5 * np.arctan2(2.0 * mu_uv, mu_uu - mu_vv)
    good = finite and S > 0 and level > 0 and b_ax > 0
    # -- third central moments (zero for a centrally symmetric blob), as complex moments:
    # |mu3|^2 = (|E[z^3]|^2 + 3 |E[z^2 z*]|^2) / 4, z = x + i y about the centroid
    z, z2, zz = complex(uc, vc), complex(m20 - m02, 2.0 * m11), m20 + m02
    a3 = complex(m30 - 3 * m12, 3 * m21 - m03) - 3 * z * z2 + 2 * z * z * z
    b3 = complex(m30 + m12, m21 + m03) - 2 * z * zz - z.conjugate() * z2 + 2 * z * z * z.conjugate()
    m3sq = 0.25 * (abs(a3) ** 2 + 3 * abs(b3) ** 2)
    # -- fourth central moment along the major axis
    c, sn = np.cos(ang), np.sin(ang)
    cc, cs, ss2 = c * c, c * sn, sn * sn
    p0, e2 = c * uc + sn * vc, cc * m20 + 2 * cs * m11 + ss2 * m02
    e3 = c * cc * m30 + 3 * cc * sn * m21 + 3 * c * ss2 * m12 + sn * ss2 * m03
    e4 = cc * cc * m40 + 4 * cc * cs * m31 + 6 * cc * ss2 * m22 + 4 * cs * ss2 * m13 + ss2 * ss2 * m04
    var_major, qa4 = e2 - p0 * p0, a_ax * a_ax / 4.0
    kurt = (e4 - 4 * p0 * e3 + 6 * p0 * p0 * e2 - 3 * p0**4) / (var_major * var_major)
    kurt_model = (2 * qa4 * qa4 + 6.0 * blur * qa4 + 3.0 * blur * blur) / (qa4 + blur) ** 2
    # -- fill: the ellipse drawn as clip(level / 2 + k (1 - rho^2), 0, level), rho = 1 on its edge,
    # a ramp of the blur's width; rho^2 is quadratic in (du, dv); the mismatch is sum |pixels - it|
    mismatch = np.inf
    if good:
        g_uu, g_vv = mu_uu - blur, mu_vv - blur
        det4 = 4.0 * (g_uu * g_vv - mu_uv * mu_uv)
        kq = 0.5 * level * np.sqrt(a_ax * b_ax) / _fmin(_fmax(np.sqrt(2.0 * np.pi * blur), 0.5), 4.0) / det4
        qa, qb, qc = kq * g_vv, -kq * mu_uv, kq * g_uu
        k0 = 0.5 * level + kq * det4 - qa * uc * uc - 2 * qb * uc * vc - qc * vc * vc
        k1, k2, k3, k4, k5 = 2 * (qa * uc + qb * vc), 2 * (qb * uc + qc * vc), -qa, -2 * qb, -qc
        mis = 0.0
        for a in range(s):
            dv = float(a - h)
            row0, row1 = k0 + k2 * dv + k5 * dv * dv, k1 + k4 * dv
            lo, hi = h - w[a], h + w[a]
            seg_row = P[pv + a, ph + lo : ph + hi + 1]
            # outside the circle the pixels count as zero and the drawn ellipse is mostly zero too: the
            # row's model is a concave parabola, so where it is <= 0 at the circle's edge on the side
            # away from its vertex it is zero all the way out (the corners were a fifth of the pixels)
            edge_u = float(w[a] + 1)
            vertex = -row1 / (2.0 * k3) if k3 < 0 else 0.0
            if not (k3 < 0 and vertex >= -edge_u and row0 - edge_u * (row1 - k3 * edge_u) <= 0.0):
                for b in range(lo):
                    du = float(b - h)
                    mis += min(max(row0 + du * (row1 + k3 * du), 0.0), level)
            for t in range(hi + 1 - lo):
                du = float(t + lo - h)
                mis += abs(min(max(row0 + du * (row1 + k3 * du), 0.0), level) - (seg_row[t] - b0))
            if not (k3 < 0 and vertex <= edge_u and row0 + edge_u * (row1 + k3 * edge_u) <= 0.0):
                for b in range(hi + 1, s):
                    du = float(b - h)
                    mis += min(max(row0 + du * (row1 + k3 * du), 0.0), level)
        mismatch = mis / level
    area = S / level
    out[0, i], out[1, i] = uc + (u0 + h), vc + (v0 + h)
    out[2, i], out[3, i], out[4, i] = a_ax, b_ax, ang
    out[FLUX, i], out[LEVEL, i], out[PEAK, i] = S, level, peak
    out[BACKGROUND, i], out[SB2, i] = b0 + slope_c, sb2
    out[K_SHOT, i] = _maximum(core_var - sb2, 0.0) / level
    out[VAR_BASE, i] = (
        0.5 * sb2 * (2.0 * (a2 * a2 / ruu_used - a2) + (uc * uc + vc * vc) * (a0 * a0 / m_used - a0)) / (S * S)
    )
    out[VAR_PER_K, i], out[MISMATCH, i] = half_tr / S, mismatch
    out[NOISE_BG, i] = np.sqrt(2.0 / np.pi * sb2) * _maximum(a0 - area, 0.0) / level
    out[M3SQ, i], out[KURT, i], out[KURT_MODEL, i] = m3sq, kurt, kurt_model
    out[FLAT_TOP, i], out[VAR_MAJOR, i], out[BLUR, i] = 1.0 - blur / (half_tr - root), var_major, blur
    for j in range(7):
        out[SUMS + j, i] = sums[j]
    return ns, crossed


@njit(cache=True, nogil=True, inline="always")
def _nan_to_num(x: float) -> float:
    if x != x:
        return 0.0
    if x == np.inf:
        return np.finfo(np.float64).max
    if x == -np.inf:
        return -np.finfo(np.float64).max
    return x


@njit(cache=True, nogil=True, error_model="numpy")
def assess_kernel(out, n_sat, edge, usable, contrast, limits, codes):
    """Reason (-1: accepted), sigma_px and fill of each window of :func:`measure_windows_kernel`'s
    ``out`` (see ``detect._assess`` for the statistics); ``contrast`` (n,) DN: each window's
    least peak above its background.

    ``limits``: min_area, max_area, max_aspect, min_fill, max_saturated, min_plateau_b,
    min_flat_top, shape sigma (2), shape floor (2), the largest flux-over-plateau area per moments'
    ellipse area (for b >= min_plateau_b, and below); ``codes``: the reasons saturated, low
    contrast, too small, too big, misshapen.
    """
    n = out.shape[1]
    min_area, max_area, max_aspect, min_fill, max_sat, min_b, min_flat = limits[:7]
    sig0, sig1, floor0, floor1, ratio_flat, ratio_small = limits[7:13]
    levels = np.full(n, -1, dtype=np.intp)
    plateau = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        S, level = out[FLUX, i], out[LEVEL, i]
        area = S / level
        if n_sat[i] > max_sat:
            levels[i] = codes[0]
        elif not (out[PEAK, i] - out[BACKGROUND, i] >= contrast[i] and level > 0):
            levels[i] = codes[1]
        elif not area >= min_area:
            levels[i] = codes[2]
        elif not area <= max_area:
            levels[i] = codes[3]
        # a clipped plateau has no shot noise: such disks would bias the coefficient low
        plateau[i] = levels[i] < 0 and usable[i] and not edge[i] and out[3, i] >= min_b and n_sat[i] <= CLIPPED_PX
    k = np.median(out[K_SHOT][plateau]) / 0.918 if plateau.any() else 0.0
    reason, sigma, fill = np.empty(n, dtype=np.intp), np.empty(n), np.empty(n)
    for i in range(n):
        a, b = out[2, i], out[3, i]
        S, level, sb2 = out[FLUX, i], out[LEVEL, i], out[SB2, i]
        area = S / level
        sigma[i] = np.sqrt(out[VAR_BASE, i] + k * out[VAR_PER_K, i])
        tr, area_e = 2.0 * out[VAR_PER_K, i] * S, np.pi * a * b
        mis = _maximum(
            out[MISMATCH, i] - out[NOISE_BG, i] - np.sqrt(2.0 / np.pi * (sb2 + k * level)) * area / level, 0.0
        )
        fill[i] = f = _nan_to_num((area + area_e - mis) / (area + area_e + mis))
        # pixel noise through the centred monomials (c0..c8 the window's sums, m the variance per axis)
        c0, c2, c4, c22 = out[SUMS, i], out[SUMS + 1, i], out[SUMS + 2, i], out[SUMS + 3, i]
        c6, c42, c8 = out[SUMS + 4, i], out[SUMS + 5, i], out[SUMS + 6, i]
        m = 0.5 * tr
        bg3 = 2 * (c6 - 6 * m * c4 + 9 * m * m * c2) + 6 * (c42 - 2 * m * c22 + m * m * c2)
        asym_noise = np.sqrt(sb2 * bg3 + k * S * (4.0 * m) ** 3 / 8.0) / S / (2.0 * tr)
        m2, kap = out[VAR_MAJOR, i], out[KURT_MODEL, i]
        al, be = 2 * kap * m2, kap * m2 * m2
        bg4 = c8 - 2 * al * c6 + (al * al + 2 * be) * c4 - 2 * al * be * c2 + be * be * c0
        q = a * a / 4.0
        shot4 = 14 * q**4 - 2 * al * 5 * q**3 + (al * al + 2 * be) * 2 * q * q - 2 * al * be * q + be * be
        kurt_noise = np.sqrt(sb2 * bg4 + k * S * _maximum(shot4, 0.0)) / (S * m2 * m2)
        # the kurtosis of the disk (kap), or of the disk smeared by motion along its major axis
        tol_k = sig1 * kurt_noise + floor1
        k_lo, k_hi = _kurtosis_range(q, b * b / 4.0, m2)
        k_lo, k_hi = min(k_lo, kap), max(k_hi, kap)
        # a disk's flux over its plateau is its ellipse's area; a ring, a glyph or a hollow blob has
        # a dim centre, so its "area" is many times the moments' (the blur estimate stops at 0)
        ratio_max = ratio_flat if b >= min_b else ratio_small
        shape_ok = (
            b * max_aspect >= a
            and f >= min_fill
            and out[FLAT_TOP, i] >= min_flat
            and area <= ratio_max * np.pi * a * b
            and np.sqrt(out[M3SQ, i]) / (2.0 * tr) <= sig0 * asym_noise + floor0
            and k_lo - tol_k <= out[KURT, i] <= k_hi + tol_k
            and np.isfinite(out[0, i])
            and np.isfinite(out[1, i])
        )
        reason[i] = levels[i] if levels[i] >= 0 else (-1 if shape_ok else codes[4])
    return reason, sigma, fill


@njit(cache=True, nogil=True, error_model="numpy")
def measure_predicted_kernel(img, uv, half, seg, contrast, full, limits, codes, edge_fit, own):
    """Measure and assess the disk in the window of half size ``half`` (n,) px about each rounded
    prediction ``uv`` (n, 2) px (:func:`service.core.targets.detect.measure_windows`): ``seg`` and
    ``contrast`` DN are every window's segmentation and contrast levels, ``limits`` and ``codes``
    :func:`assess_kernel`'s; with ``edge_fit`` a disk's centre (and its ellipse's) and sigma_px are
    its edge fit's where that holds (:func:`measure_windows_kernel`). ``own`` (n, 5): a window's own
    region where other bright things (a coded target's ring) are masked
    (:func:`~service.core._kernels.crowd_kernel.mask_windows_kernel`), NaN rows for the others.

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
        # a window at the image border is made as large as the image allows: a disk that no longer
        # fits (or lies partly outside) crosses its rim and is refused below, as an off prediction is
        r = min(radius[i], cu[i], width - 1 - cu[i], cv[i], height - 1 - cv[i])
        radius[i] = max(r, 0)
        placed[i] = r >= 2
    seg_n, contrast_n = np.full(n, seg), np.full(n, contrast)
    k = 0
    for i in range(n):
        k += placed[i] and own[i, 0] == own[i, 0]
    masked = np.empty(k, dtype=np.intp)
    k = 0
    for i in range(n):
        if placed[i] and own[i, 0] == own[i, 0]:
            masked[k] = i
            k += 1
    buf, boff = crowd_kernel.mask_windows_kernel(img, cu, cv, radius, masked, own, seg_n)
    out, n_sat, edge = measure_windows_kernel(img, cu, cv, radius, placed, seg_n, full, buf, boff, edge_fit)
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
            if out[EDGE_SIGMA, i] == out[EDGE_SIGMA, i]:
                table[UV, j], table[UV + 1, j], sigma_ok[j] = out[EDGE_UV, i], out[EDGE_UV + 1, i], out[EDGE_SIGMA, i]
    return table, sigma_ok, fill_ok, found


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for 8- and 16-bit images, writeable or not,
    the image and the masked buffer paths, so that no frame pays for it (a Mono12/16 camera's first
    frame waited ~13 s for its own). Cheap after the first call in a process."""
    c, half = np.array([16, 16], dtype=np.intp), np.array([6, 6], dtype=np.intp)
    placed = np.ones(2, dtype=np.bool_)
    seg = np.full(2, 10.0)
    own = np.array([[0.0, 0.0, 0.1, 0.0, 0.1], [np.nan] * 5])
    for img in warm_images((np.uint8, np.uint16)):
        full = float(np.iinfo(img.dtype).max)
        buf = np.full(13 * 13, 200.0, dtype=np.float32)
        for fit in (False, True):
            out, n_sat, edge = measure_windows_kernel(
                img, c, c, half, placed, seg, full, buf, np.array([-1, 0], dtype=np.intp), fit
            )
        crowd_kernel.mask_windows_kernel(img, c, c, half, np.array([0], dtype=np.intp), own, seg)
    limits = np.array([6, 5000, 4, 0.6, 2, 2.5, 0.4, 3, 4, 0.015, 0.05, 1.3, 2.5])
    assess_kernel(out, n_sat, edge, placed, 2 * seg, limits, np.arange(5, dtype=np.intp))
    uv, codes = np.full((2, 2), 16.0), np.arange(5, dtype=np.intp)
    for img in warm_images((np.uint8, np.uint16)):
        for fit in (False, True):
            for masks in (np.full((2, 5), np.nan), np.array([[0.0, 0.0, 0.1, 0.0, 0.1], [np.nan] * 5])):
                measure_predicted_kernel(
                    img, uv, half, 5.0, 10.0, float(np.iinfo(img.dtype).max), limits, codes, fit, masks
                )
    contour_kernel.warm_up()
    noise_kernel.warm_up()
    centre, flags = np.array([[1.0, 1.0], [9.0, 1.0]]), np.ones(2, dtype=np.bool_)
    box = np.array([[0, 0, 2, 2], [8, 0, 10, 2]], dtype=np.intp)
    crowd_kernel.neighbours_kernel(
        box,
        centre,
        np.ones((2, 3)),
        np.ones((2, 2), dtype=np.intp),
        np.ones(2, dtype=np.intp),
        np.ones(2),
        flags,
        flags,
        flags,
        2.0,
        3.2,
        0.4,
        16,
        16,
    )
