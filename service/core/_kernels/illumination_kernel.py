"""The light across a frame, from its disks' plateaus, for the edge fit (compiled, numba).

Why: a disk's edge is found where its rows and columns cross one level, half way between its
background and its core (:mod:`service.core._kernels.edge_kernel`). Where the light falls across
the disk (the ring light's beam, the lens's vignetting: both darken the image towards its corners),
the brighter side's edge crosses that level farther out and the darker side's nearer in, and the
fitted centre moves towards the light by about ``1.25 g r s`` px (``g`` the relative gradient per
px, ``r`` the disk's radius, ``s`` the blur's sigma): towards the image centre. posecell's printed
sheet imaged through cairo and OpenCV with its corners 60 % darker: -0.006 px at the corners
(-0.001 evenly lit), which nearly doubled the pose's error (0.013 -> 0.022 mm); flat-fielded, or
with the level following the light, 0.012-0.013 mm and -0.001 px.

The light is smooth and the same for every target near another, so it is fitted once a frame to
all of the plateaus: ``ln(level)`` as a quadratic in the image coordinates (fitted three times,
each time without the plateaus the fit before missed most: labels, stickers, hot pixels and
half-hidden disks), and each disk's edge level then
follows the fitted light across it (:func:`~service.core._kernels.edge_kernel.edge_fit`). A disk's
own plateau is too noisy for its own gradient (shot noise alone: ~0.001 per px on a 9 px disk, the
size of the effect). Only disks whose core is on their plateau count (semi-minor axis
MIN_PLATEAU_PX or more, not clipped): a small disk's core is lowered by the blur, and the far
side of an oblique sheet would look darker than it is lit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.core._kernels.geometry_kernels import solve_in_place

N_COEF = 6  # ln(level) = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2, (x, y) the normalised image coordinates
MIN_DISKS = 15  # plateaus a fit needs; fewer: no gradient (the light is taken as even)
MIN_PLATEAU_PX = 4.0  # a disk's semi-minor axis from which its core is its plateau (blur sigma up to ~1.5 px)
# Before any fit, plateaus farther than this from their median (ln units: a factor 2.7) are no
# targets' (printed grey text, a sticker's edge: 10 % of the median in posecell's printed sheet);
# a ring light and a lens darken a frame's corners by at most ~60 %
FAR_FROM_MEDIAN = 1.0
TRIM = 3.0  # robust sigmas (1.4826 MAD) beyond which a plateau is left out of the next pass
PASSES = 2  # fits after the first, each without the plateaus the one before fitted worst
MIN_TRIM = 0.02  # ... but never nearer than 2 % (ln units): the shot noise of a bright plateau
RIDGE = 1e-3  # on the non-constant terms, per disk: the quadratic bends little where few disks lie
MAX_GRADIENT = 0.01  # per px: steeper is no light across a frame (a fit thrown by what it was given)


@njit(cache=True, nogil=True, inline="always")
def _terms(u, v, width, height, t):
    s = 2.0 / max(width, height)
    x, y = (u - 0.5 * width) * s, (v - 0.5 * height) * s
    t[0], t[1], t[2], t[3], t[4], t[5] = 1.0, x, y, x * x, x * y, y * y


@njit(cache=True, nogil=True, error_model="numpy")
def _solve(u, v, y, use, width, height, coef):
    """Least squares of ``y`` on the quadratic's terms over ``use``; False if too few or singular."""
    G, t = np.zeros((N_COEF, N_COEF)), np.empty(N_COEF)
    coef[:] = 0.0
    n = 0
    for i in range(u.size):
        if use[i]:
            _terms(u[i], v[i], width, height, t)
            for p in range(N_COEF):
                coef[p] += t[p] * y[i]
                for q in range(N_COEF):
                    G[p, q] += t[p] * t[q]
            n += 1
    if n < MIN_DISKS:
        return False
    for p in range(1, N_COEF):
        G[p, p] += RIDGE * n
    solve_in_place(G, coef)
    return bool(np.all(np.isfinite(coef)))


@njit(cache=True, nogil=True, error_model="numpy")
def fit_light(u, v, level, b, n_sat, usable, width, height, clipped_px):
    """The coefficients (N_COEF,) of ``ln(level)`` over the frame, from the disks at (``u``, ``v``) px
    with plateau ``level`` DN above their background, semi-minor axis ``b`` px, ``n_sat`` pixels at
    full scale and ``usable`` (their window measured); all zero (an even light) when fewer than
    MIN_DISKS disks have a plateau or the fit fails."""
    n = u.size
    y, e, r = np.zeros(n), np.zeros(n), np.empty(n)
    use = np.zeros(n, dtype=np.bool_)
    coef, t = np.zeros(N_COEF), np.empty(N_COEF)
    m = 0
    for i in range(n):
        ok = usable[i] and level[i] > 0 and b[i] >= MIN_PLATEAU_PX and n_sat[i] <= clipped_px
        use[i] = ok and np.isfinite(u[i]) and np.isfinite(v[i])
        if use[i]:
            y[i] = e[i] = r[m] = np.log(level[i])
            m += 1
    if m < MIN_DISKS:
        return coef
    mid, limit = np.median(r[:m]), FAR_FROM_MEDIAN
    for k in range(PASSES + 1):
        for i in range(n):  # residuals about the fit before (the first: the plateaus' median)
            use[i] = use[i] and abs(e[i] - mid) <= limit
        if not _solve(u, v, y, use, width, height, coef):
            return np.zeros(N_COEF)
        if k == PASSES:
            break
        m = 0
        for i in range(n):
            if use[i]:
                _terms(u[i], v[i], width, height, t)
                e[i] = y[i] - (
                    coef[0] + coef[1] * t[1] + coef[2] * t[2] + coef[3] * t[3] + coef[4] * t[4] + coef[5] * t[5]
                )
                r[m] = e[i]
                m += 1
        # about the residuals' median (not 0 where outliers pulled the fit), their spread's
        mid = np.median(r[:m])
        for j in range(m):
            r[j] = abs(r[j] - mid)
        limit = max(TRIM * 1.4826 * np.median(r[:m]), MIN_TRIM)
    coef[0] = 0.0  # the level itself is not used: only how it changes
    return coef


# not inlined: the windows' kernel is compiled with fastmath, which would contract this one's
# arithmetic differently for a read-only frame than for a writeable one
@njit(cache=True, nogil=True)
def light_gradient(coef, u, v, width, height):
    """The relative gradient (d ln L / du, d ln L / dv) per px of the light :func:`fit_light` fitted,
    at (``u``, ``v``) px; each component within +-MAX_GRADIENT."""
    s = 2.0 / max(width, height)
    x, y = (u - 0.5 * width) * s, (v - 0.5 * height) * s
    gu = (coef[1] + 2.0 * coef[3] * x + coef[4] * y) * s
    gv = (coef[2] + coef[4] * x + 2.0 * coef[5] * y) * s
    if not (np.isfinite(gu) and np.isfinite(gv)):
        return 0.0, 0.0
    return min(max(gu, -MAX_GRADIENT), MAX_GRADIENT), min(max(gv, -MAX_GRADIENT), MAX_GRADIENT)
