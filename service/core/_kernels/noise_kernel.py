"""The full frame's background noise, tile by tile, and its foreground (:mod:`service.core.targets.detect`), compiled.

:func:`tile_noise_kernel` estimates, per square tile, the standard deviation of the
pixels about the coarse background: read and shot noise, and whatever texture the
background has (a carbon weave, paper grain), since for a threshold they are all
noise. It is the interquartile range of the residuals (as efficient as the MAD for
normal noise, and without its search), from a histogram, with the targets clipped
away: first from the lower quartile and the median alone, then the interquartile range
of the residuals within 3.5 such sigmas of the median, so a tile 40 % covered by bright
disks and rings (close up, or a dense coded plate) gives the noise of its background,
not of its targets; a tile covered beyond its median is judged by the samples below its
background, where that gives a noise like the frame's (``_iqr_sigma``). Quantiles are
interpolated inside the histogram's bins, so an 8-bit image's integer levels give a
continuous estimate (sigma 0.5 DN does not come out as 0, nor 1.2 DN as 1.48).

Written as one loop over a sample of the pixels (every 4th row, every 2nd column: 512
samples a tile, a 7 % error of sigma): a median per tile by sorting would cost more than
the whole detection; this costs ~0.3 ms of a 1300 x 1030 frame.

:func:`cell_threshold_kernel` compares each pixel with its coarse cell's threshold (an uneven
background: a hot spot, a gradient).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels import warm_images

#: 1 / (2 Phi^-1(3/4)): a normal distribution's interquartile range is this many times its sigma
IQR_TO_SIGMA = 0.7413011092528009
CLIP_SIGMA = 3.5  # the second round keeps the residuals within this many first-round sigmas
MIN_BELOW = 16.0  # samples below the background that a tile covered beyond its median is judged by
COVERED_LIKE = 2.0  # a covered tile's own estimate stands where it is within this many times the frame's


@njit(cache=True, nogil=True, inline="always")
def _cdf(cum, hist, x, half):
    """Samples below ``x`` (bin units from the centre), bins uniform over [k - 1/2, k + 1/2)."""
    t = x + half + 0.5
    if t <= 0.0:
        return 0.0
    if t >= hist.size:
        return float(cum[hist.size])
    k = int(t)
    return cum[k] + (t - k) * hist[k]


@njit(cache=True, nogil=True, inline="always")
def _quantile(cum, hist, target, half):
    """The x whose _cdf is ``target`` (counts): the bin by bisection of ``cum``, then inside it."""
    k = np.searchsorted(cum, target) - 1  # cum[k] < target <= cum[k + 1]
    k = min(max(k, 0), hist.size - 1)
    inside = target - cum[k]
    return (k - half) - 0.5 + (inside / hist[k] if hist[k] > 0 else 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _clipped_iqr(hist, cum, half, centre, sigma):
    """The interquartile sigma (bins) of the samples within CLIP_SIGMA ``sigma`` of ``centre`` (bins),
    ``sigma`` itself when fewer than 8 are."""
    clip = CLIP_SIGMA * max(sigma, 0.5)
    f_lo, f_hi = _cdf(cum, hist, centre - clip, half), _cdf(cum, hist, centre + clip, half)
    m = f_hi - f_lo
    if m < 8.0:
        return sigma
    q1, q3 = _quantile(cum, hist, f_lo + 0.25 * m, half), _quantile(cum, hist, f_lo + 0.75 * m, half)
    return IQR_TO_SIGMA * (q3 - q1)


@njit(cache=True, nogil=True, error_model="numpy")
def _iqr_sigma(hist, cum, half):
    """Clipped interquartile sigma (bins) of one tile's histogram (``cum[k]``: samples in bins < k),
    and the estimate of a tile covered beyond its median (NaN where it is not).

    First from the lower half alone (median less lower quartile): the targets are bright, and a tile
    nearly half covered by them still has its median in the background, while its upper quartile
    would lie on the targets. Then the full interquartile range of what lies within CLIP_SIGMA of the
    median: a textured background's upper tail counts.

    A tile covered more than half (a coded target at close range fills it) has its median on the
    targets, far above the background its residuals centre on (0): its sigma came out at up to 30
    times its noise (seen: 31 DN for 1.5, and a 0.5 m view's big coded disks refused as faint), or as
    the flat top's (0.4 DN for 2-10). Then the samples below 0, the background's lower half, give
    the estimate about 0 (:func:`tile_noise_kernel` takes it where it is like the frame's)."""
    n = cum[hist.size]
    if n < 16:
        return 0.0, np.nan
    med = _quantile(cum, hist, 0.5 * n, half)
    sigma = _clipped_iqr(hist, cum, half, med, 2.0 * IQR_TO_SIGMA * (med - _quantile(cum, hist, 0.25 * n, half)))
    below = _cdf(cum, hist, 0.0, half)  # the background's lower half, whatever covers the rest
    if below < MIN_BELOW:
        return sigma, np.nan
    low = -2.0 * IQR_TO_SIGMA * _quantile(cum, hist, 0.5 * below, half)
    w = 2.0 * max(low, 0.5)
    # the median far above (or near the clipped top, for a noisy tile), and about 0 as many samples
    # above as below (a background centred on 0: residuals that sit a sigma or two above 0 have far
    # more above)
    if med > min(2.0 * CLIP_SIGMA * max(low, 0.5), 0.75 * half) and (
        _cdf(cum, hist, w, half) - below <= 2.0 * (below - _cdf(cum, hist, -w, half)) + 4.0
    ):
        return sigma, _clipped_iqr(hist, cum, half, 0.0, low)
    return sigma, np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def tile_noise_kernel(img, bg, step, tile, sub_v, shift, half):
    """Noise sigma (DN) of each ``tile`` x ``tile`` px tile of ``img`` (H, W) about the coarse
    background ``bg`` (hs, ws): one value per ``step`` (8) x ``step`` px cell, taken as constant over
    it (``tile`` a multiple of ``step``, pixels beyond the last whole cell not sampled). Samples: the
    odd columns of every ``sub_v``-th row. Residuals are binned ``2 ** shift`` DN wide, clipped to
    +-``half`` bins (sigma then saturates at about ``half`` bins). Returns (ceil(hs * step / tile),
    ceil(ws * step / tile)) float."""
    hs, ws = bg.shape
    assert step == 8  # the samples of a cell are unrolled
    per = tile // step
    th, tw = (hs + per - 1) // per, (ws + per - 1) // per
    sigma = np.zeros((th, tw))
    covered = np.full((th, tw), np.nan)
    nb = 2 * half + 1
    cum = np.zeros(nb + 1)
    hist = np.zeros(nb)
    bin_dn = float(1 << shift)
    # each cell's background in bins, rounded (a +-1/2 bin error per cell: 2 % of a 1.5 DN sigma),
    # so that the samples are binned by integer arithmetic
    off = np.empty((hs, ws), dtype=np.intp)
    for a in range(hs):
        for b in range(ws):
            off[a, b] = half - int(bg[a, b] / bin_dn + 0.5)  # bg >= 0: truncation rounds
    # four histograms filled in turn, small enough for the L1 cache: consecutive samples mostly fall
    # in the same few bins, and one histogram's increments would each wait for the last (a
    # store-to-load stall per sample); as floats rounded one by one, or in a histogram per tile row
    # (L2), the samples cost 3 and 0.7 ms of a frame, now 0.25 ms
    hist4 = np.zeros((4, nb), dtype=np.int32)
    top = nb - 1
    for ti in range(th):
        for tj in range(tw):
            hist4[:] = 0
            for v in range(ti * tile + sub_v // 2, min((ti + 1) * tile, hs * step), sub_v):
                orow, row = off[v // step], img[v]
                for cb in range(tj * per, min((tj + 1) * per, ws)):
                    o, u = orow[cb], cb * step + 1  # step 8: the odd columns, unrolled
                    hist4[0, min(max((int(row[u]) >> shift) + o, 0), top)] += 1
                    hist4[1, min(max((int(row[u + 2]) >> shift) + o, 0), top)] += 1
                    hist4[2, min(max((int(row[u + 4]) >> shift) + o, 0), top)] += 1
                    hist4[3, min(max((int(row[u + 6]) >> shift) + o, 0), top)] += 1
            c = 0.0
            for k in range(nb):
                hist[k] = hist4[0, k] + hist4[1, k] + hist4[2, k] + hist4[3, k]
                cum[k] = c
                c += hist[k]
            cum[nb] = c
            sigma[ti, tj], covered[ti, tj] = _iqr_sigma(hist, cum, half)
    # a covered tile's estimate about 0 where it is like the frame's background (at most
    # COVERED_LIKE times the tiles' median): a ramp or a shadow under a cover is not a background
    like = COVERED_LIKE * np.median(sigma) if sigma.size else 0.0
    for ti in range(th):
        for tj in range(tw):
            if covered[ti, tj] <= like:
                sigma[ti, tj] = covered[ti, tj]
    return sigma * bin_dn


@njit(cache=True, nogil=True, error_model="numpy")
def cell_threshold_kernel(img, thr, step, out):
    """``out`` (H, W) uint8 = 255 where ``img`` (H, W) is above its ``step`` x ``step`` px cell's
    threshold ``thr`` (hs, ws) of the image's dtype, else 0; pixels beyond the last whole cell take
    the last cell's. Each row's thresholds are spread out once per cell row, so the compare is one
    vectorised pass: 0.14 ms a 1300 x 1030 frame, where OpenCV's bilinear resize of the thresholds
    to the full frame and the compare took 0.45 ms."""
    assert step == 8  # shifts: with divisions by a variable step the pass took 0.21 ms
    h, w = img.shape
    hs, ws = thr.shape
    row_thr = np.empty(w, dtype=img.dtype)
    for v in range(h):
        if v & 7 == 0 and v >> 3 < hs:  # a new row of cells
            cells = thr[v >> 3]
            for u in range(w):
                row_thr[u] = cells[min(u >> 3, ws - 1)]
        row, mask = img[v], out[v]
        for u in range(w):
            mask[u] = 255 if row[u] > row_thr[u] else 0
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def box_peak_kernel(img, box, which):
    """Brightest pixel (DN) inside the inclusive box (u0, v0, u1, v1) of each contour ``which``."""
    out = np.empty(which.size)
    for k in range(which.size):
        c = which[k]
        pk = img[box[c, 1], box[c, 0]]
        for v in range(box[c, 1], box[c, 3] + 1):
            row = img[v]
            for u in range(box[c, 0], box[c, 2] + 1):
                pk = max(pk, row[u])
        out[k] = float(pk)
    return out


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for 8- and 16-bit images, writeable or not."""
    for img in warm_images((np.uint8, np.uint16)):
        tile_noise_kernel(img, np.zeros((4, 4), dtype=np.float32), 8, 16, 4, 0, 8)
        box_peak_kernel(img, np.array([[0, 0, 3, 3]], dtype=np.intp), np.array([0], dtype=np.intp))
        cell_threshold_kernel(img, np.zeros((1, 1), dtype=img.dtype), 8, np.empty(img.shape, dtype=np.uint8))
