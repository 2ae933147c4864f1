"""The edge centres of :mod:`service.core.targets.edge_centre`, compiled (numba).

Each disk's edge is found where its rows and its columns cross the half level between its
background and its core, a level that follows the light across the disk where it falls (the ring
light's beam, the lens's vignetting: :mod:`service.core._kernels.illumination_kernel`; at one
level the centre moved towards the light), by linear interpolation between the two pixels either
side, only where the row or column crosses the edge steeply (within 0.75 of the disk's half extent
from its centre across them); a direct least-squares conic through those points gives the centre. Pixels, not
bilinear samples along rays (the code reader's re-fit, :func:`~service.core._kernels.decode_kernel._refine`):
as precise on rendered and real images and ~9x cheaper (~0.6-0.9 us a disk of the reference scene).
The blur moves a curved edge inwards point-symmetrically, which leaves the centre where it is.

:func:`edge_fit` fits one disk; the window kernel
(:func:`~service.core._kernels.detect_kernel.measure_windows_kernel`) calls it for each window once
the light is fitted to all of their plateaus, :func:`edge_centres_kernel` for disks given
(:func:`service.core.targets.edge_centre.edge_centres`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import warm_images
from service.core._kernels.contour_kernel import _maximum
from service.core._kernels.geometry_kernels import solve_in_place

STEEP = 0.75  # rows (columns) used: within this fraction of the disk's half height (width) of its centre
MIN_POINTS = 10  # edge points a fit needs (5 unknowns)
MARGIN_PX = 3  # the window reaches this far beyond the disk's semi-major axis


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _run_ends(line, centre, lo, hi, half, slope, at):
    """The linear crossings at both ends of the run of ``line`` through index ``centre`` above the
    level ``half + slope (i - at)`` (the half level following the light across the disk; ``slope``
    0: one level), within (lo, hi); (NaN, NaN) when there is no such run or it reaches lo or hi."""
    if not line[centre] > half + slope * (centre - at):
        return np.nan, np.nan
    i = centre
    while i > lo and line[i - 1] > half + slope * (i - 1 - at):
        i -= 1
    j = centre
    while j < hi and line[j + 1] > half + slope * (j + 1 - at):
        j += 1
    if i == lo or j == hi:  # the disk reaches the window's edge: no crossing there
        return np.nan, np.nan
    a0, a1, b0, b1 = float(line[i - 1]), float(line[i]), float(line[j]), float(line[j + 1])
    # where the line between the two pixels meets the sloped level
    x0 = (i - 1) + (half + slope * (i - 1 - at) - a0) / (a1 - a0 - slope)
    return x0, j + (b0 - half - slope * (j - at)) / (b0 - b1 + slope)


@njit(cache=True, nogil=True, inline="always")
def _median9(p):
    """The median of the 9 values ``p`` (reordered): the exchange network of Paeth (Graphics Gems)."""
    for i, j in (
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 1),
        (3, 4),
        (6, 7),
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 3),
        (5, 8),
        (4, 7),
        (3, 6),
        (1, 4),
        (2, 5),
        (4, 7),
        (4, 2),
        (6, 4),
        (4, 2),
    ):
        if p[i] > p[j]:
            p[i], p[j] = p[j], p[i]
    return p[4]


@njit(cache=True, nogil=True)
def edge_scratch(a_max):
    """Scratch for :func:`edge_fit` of disks up to ``a_max`` px: the points (x, y) and the solve's."""
    cap = 4 * (2 * (int(np.ceil(a_max)) + MARGIN_PX) + 1)  # two crossings a row and a column
    return np.empty(cap), np.empty(cap), np.empty((5, 5)), np.empty(5), np.empty(9), np.empty((5, 5)), np.empty(5)


@njit(cache=True, nogil=True, error_model="numpy")
def edge_fit(img, cu, cv, a, b, ang, background, gu, gv, px, py, G, g, core, G0, g0):
    """The centre (u, v) px of the disk whose centroid is (``cu``, ``cv``), ellipse semi-axes ``a``,
    ``b`` px at ``ang`` rad and background ``background`` DN, fitted to its half-level edge, and its
    standard deviation px per coordinate, from the edge points' scatter about the conic (their
    algebraic residuals over the conic's RMS gradient, ``n - 5`` degrees of freedom) times
    ``sqrt(2 / n)``; NaN where the fit does not hold (the centre is then the centroid). It holds
    with MIN_POINTS edge points or more, a real ellipse, and a centre within half the disk's minor
    semi-axis (+ 0.5 px) of the centroid. The half level follows the light across the disk: ``gu``,
    ``gv`` its relative gradient per px (:func:`~service.core._kernels.illumination_kernel.light_gradient`;
    0, 0: one level). The rest are :func:`edge_scratch`'s, for a disk this big."""
    h, w = img.shape
    if not (np.isfinite(cu) and np.isfinite(cv) and a > 0 and b > 0):
        return cu, cv, np.nan
    R = int(np.ceil(a)) + MARGIN_PX
    ur, vr = int(np.rint(cu)), int(np.rint(cv))
    if ur - R < 0 or vr - R < 0 or ur + R >= w or vr + R >= h or 4 * (2 * R + 1) > px.size:
        return cu, cv, np.nan
    m = 0
    for dv in range(-1, 2):
        for du in range(-1, 2):
            core[m] = float(img[vr + dv, ur + du])
            m += 1
    level = _median9(core)
    half = 0.5 * (background + level)
    if not level > background:
        return cu, cv, np.nan
    # the half level at (u, v): half + su (u - cu) + sv (v - cv), the core's signal scaled by the light
    su, sv = 0.5 * (level - background) * gu, 0.5 * (level - background) * gv
    ca, sa = np.cos(ang), np.sin(ang)
    ext_u, ext_v = np.hypot(a * ca, b * sa), np.hypot(a * sa, b * ca)
    npts, inv_a = 0, 1.0 / a  # the points in units of a (well-conditioned)
    for v in range(vr - R, vr + R + 1):  # rows: left and right edges
        if abs(v - cv) <= STEEP * ext_v:
            x0, x1 = _run_ends(img[v], ur, ur - R, ur + R, half + sv * (v - cv), su, cu)
            if x0 == x0:
                y = (v - cv) * inv_a
                px[npts], py[npts], px[npts + 1], py[npts + 1] = (x0 - cu) * inv_a, y, (x1 - cu) * inv_a, y
                npts += 2
    for u in range(ur - R, ur + R + 1):  # columns: top and bottom edges
        if abs(u - cu) <= STEEP * ext_u:
            y0, y1 = _run_ends(img[:, u], vr, vr - R, vr + R, half + su * (u - cu), sv, cv)
            if y0 == y0:
                x = (u - cu) * inv_a
                px[npts], py[npts], px[npts + 1], py[npts + 1] = x, (y0 - cv) * inv_a, x, (y1 - cv) * inv_a
                npts += 2
    if npts < MIN_POINTS:
        return cu, cv, np.nan
    # direct conic A x^2 + B xy + C y^2 + D x + E y = 1: the normal equations' entries are the
    # points' moments up to the fourth, summed once
    m40 = m31 = m22 = m13 = m04 = m30 = m21 = m12 = m03 = m20 = m11 = m02 = m10 = m01 = 0.0
    for i in range(npts):
        x, y = px[i], py[i]
        xx, xy, yy = x * x, x * y, y * y
        m40 += xx * xx
        m31 += xx * xy
        m22 += xx * yy
        m13 += xy * yy
        m04 += yy * yy
        m30 += xx * x
        m21 += xx * y
        m12 += x * yy
        m03 += yy * y
        m20 += xx
        m11 += xy
        m02 += yy
        m10 += x
        m01 += y
    G[0, 0], G[0, 1], G[0, 2], G[0, 3], G[0, 4] = m40, m31, m22, m30, m21
    G[1, 1], G[1, 2], G[1, 3], G[1, 4] = m22, m13, m21, m12
    G[2, 2], G[2, 3], G[2, 4] = m04, m12, m03
    G[3, 3], G[3, 4], G[4, 4] = m20, m11, m02
    for p in range(5):
        for q in range(p):
            G[p, q] = G[q, p]
    g[0], g[1], g[2], g[3], g[4] = m20, m11, m02, m10, m01
    G0[:, :] = G  # unregularised: the residuals' sum below
    g0[:] = g
    tr = G[0, 0] + G[1, 1] + G[2, 2] + G[3, 3] + G[4, 4]
    for p in range(5):
        G[p, p] += 1e-9 * tr + 1e-12
    c = solve_in_place(G, g)
    det = c[0] * c[2] - c[1] * c[1] / 4.0
    if not det > 0:
        return cu, cv, np.nan
    x0 = -0.5 * (c[2] * c[3] - 0.5 * c[1] * c[4]) / det
    y0 = -0.5 * (c[0] * c[4] - 0.5 * c[1] * c[3]) / det
    if not (np.hypot(x0, y0) * a < 0.5 * b + 0.5 and 1.0 + 0.5 * (c[3] * x0 + c[4] * y0) > 0):
        return cu, cv, np.nan
    # the points' scatter about the conic from the same moments, without a second pass over them:
    # the squared algebraic residuals f = c . (x^2, xy, y^2, x, y) - 1 summed (c' G c - 2 c' g + n),
    # over the mean squared gradient of f (the conic's own, from the moments up to the second)
    ff = float(npts)
    for p in range(5):
        ff -= 2.0 * c[p] * g0[p]
        for q in range(5):
            ff += c[p] * G0[p, q] * c[q]
    c0, c1, c2, c3, c4 = c[0], c[1], c[2], c[3], c[4]
    gg = (
        (4 * c0 * c0 + c1 * c1) * m20
        + (c1 * c1 + 4 * c2 * c2) * m02
        + 4 * c1 * (c0 + c2) * m11
        + 2 * (2 * c0 * c3 + c1 * c4) * m10
        + 2 * (c1 * c3 + 2 * c2 * c4) * m01
        + npts * (c3 * c3 + c4 * c4)
    )
    ss = _maximum(ff, 0.0) / (gg / npts) * a * a
    return cu + x0 * a, cv + y0 * a, np.sqrt(ss / (npts - 5) * 2.0 / npts)


@njit(cache=True, nogil=True, error_model="numpy")
def edge_centres_kernel(img, uv, e, background, gradient):
    """Centres (N, 2) px of the disks whose centroids ``uv`` (N, 2), ellipses ``e`` (N, 5) ``(u_c,
    v_c, a_px, b_px, angle_rad)``, backgrounds (N,) DN and light's relative gradients ``gradient``
    (N, 2) per px are given (:func:`edge_fit` each), each
    centre's standard deviation (N,) px per coordinate, and whether the fit held (where not: the
    centroid, NaN)."""
    n = uv.shape[0]
    out = uv.copy()
    sigma = np.full(n, np.nan)
    a_max = 0.0
    for k in range(n):
        if np.isfinite(e[k, 2]) and e[k, 2] > a_max:
            a_max = e[k, 2]
    px, py, G, g, core, G0, g0 = edge_scratch(a_max)
    for k in range(n):
        out[k, 0], out[k, 1], sigma[k] = edge_fit(
            img,
            uv[k, 0],
            uv[k, 1],
            e[k, 2],
            e[k, 3],
            e[k, 4],
            background[k],
            gradient[k, 0],
            gradient[k, 1],
            px,
            py,
            G,
            g,
            core,
            G0,
            g0,
        )
    return out, sigma, np.isfinite(sigma)


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for 8- and 16-bit images, writeable or not."""
    for img in warm_images((np.uint8, np.uint16), (48, 48)):
        if img.flags.writeable:  # its read-only view, next, shares the disk
            img[20:28, 20:28] = 200
        e = np.array([[23.5, 23.5, 4.0, 4.0, 0.0]])
        edge_centres_kernel(img, np.array([[23.5, 23.5]]), e, np.array([0.0]), np.zeros((1, 2)))
