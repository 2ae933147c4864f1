"""The full frame's noise per tile and the contours' peaks (``service.core._kernels.noise_kernel``).

``tile_noise_kernel`` is compared twice. First with its definition written plainly over the
sampled residuals: each integer residual spread uniformly over its bin, the quantiles the
inverse of that distribution, the two clipped rounds of the module docstring; that agrees to
round-off. Then with what it estimates: on Gaussian noise the robust sigma of all the tile's
pixels by ``np.median`` (1.4826 MAD) and the true sigma, within the sampling error of its 512
samples. ``box_peak_kernel`` is ``ndarray.max`` over each box; ``cell_threshold_kernel`` the
compare with each pixel's cell threshold spread over the frame by ``np.repeat``.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels.noise_kernel import (
    CLIP_SIGMA,
    COVERED_LIKE,
    IQR_TO_SIGMA,
    MIN_BELOW,
    box_peak_kernel,
    cell_threshold_kernel,
    tile_noise_kernel,
)

STEP, TILE, SUB_V = 8, 64, 4  # as detect_background passes them


def _samples(img, bg, ti, tj, shift, half):
    """The residuals (bins, clipped to +-half) the tile (ti, tj) samples: the odd columns of whole
    cells, every SUB_V-th row from SUB_V // 2, less the cell's background rounded to bins."""
    hs, ws = bg.shape
    rows = np.arange(ti * TILE + SUB_V // 2, min((ti + 1) * TILE, hs * STEP), SUB_V)
    cols = np.arange(tj * TILE + 1, min((tj + 1) * TILE, ws * STEP), 2)
    v, u = np.meshgrid(rows, cols, indexing="ij")
    level = np.floor(bg.astype(np.float64)[v // STEP, u // STEP] / 2.0**shift + 0.5)
    return np.clip((img[v, u].astype(np.int64) >> shift) - level, -half, half).ravel()


def _cdf(r, x):
    """Samples below x when each sample r is spread uniformly over [r - 1/2, r + 1/2)."""
    return np.clip(x - (r - 0.5), 0.0, 1.0).sum()


def _quantile(r, target):
    """The least x with _cdf(r, x) = target: the inverse of the piecewise linear distribution."""
    values, counts = np.unique(r, return_counts=True)
    after = np.cumsum(counts)
    k = np.searchsorted(after, target)  # the first value whose bin reaches the target
    return values[k] - 0.5 + (target - (after[k] - counts[k])) / counts[k]


def _sigma_reference(r, half):
    """(sigma, the covered tile's estimate or NaN) of one tile's samples."""
    if r.size < 16:
        return 0.0, np.nan

    def clipped(centre, sigma):
        clip = CLIP_SIGMA * max(sigma, 0.5)
        lo, hi = _cdf(r, centre - clip), _cdf(r, centre + clip)
        m = hi - lo
        return IQR_TO_SIGMA * (_quantile(r, lo + 0.75 * m) - _quantile(r, lo + 0.25 * m)) if m >= 8 else sigma

    n = r.size
    med = _quantile(r, 0.5 * n)
    sigma = clipped(med, 2 * IQR_TO_SIGMA * (med - _quantile(r, 0.25 * n)))
    below = _cdf(r, 0.0)
    if below >= MIN_BELOW:  # covered beyond its median: the background's lower half, about 0
        low = -2 * IQR_TO_SIGMA * _quantile(r, 0.5 * below)
        w = 2 * max(low, 0.5)
        symmetric = _cdf(r, w) - below <= 2 * (below - _cdf(r, -w)) + 4  # as many about 0 above as below
        if med > min(2 * CLIP_SIGMA * max(low, 0.5), 0.75 * half) and symmetric:
            return sigma, clipped(0.0, low)
    return sigma, np.nan


def _tiles_reference(img, bg, shape, shift, half):
    """Every tile's sigma, bins: its own, or where covered its estimate about 0 when that is within
    COVERED_LIKE times the median of the tiles' own."""
    both = np.array(
        [
            [_sigma_reference(_samples(img, bg, i, j, shift, half), half) for j in range(shape[1])]
            for i in range(shape[0])
        ]
    )
    own, covered = both[..., 0], both[..., 1]
    with np.errstate(invalid="ignore"):
        return np.where(covered <= COVERED_LIKE * np.median(own), covered, own)


def _image(rng, shape, dtype, sigma_dn, full):
    """A ramp background, Gaussian noise, bright disks over part of it, some saturated pixels."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    base = 0.2 * full + 0.1 * full * (u / w) + 0.05 * full * np.sin(v / 40.0)
    img = base + rng.normal(0, sigma_dn, shape)
    for _ in range(h * w // 3000):
        cu, cv, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(3, 12)
        img[(u - cu) ** 2 + (v - cv) ** 2 < r * r] = rng.uniform(0.5, 1.2) * full
    return np.clip(np.rint(img), 0, full).astype(dtype), base


@pytest.mark.parametrize(
    "dtype, full, shift, half, sigma_dn",
    [
        (np.uint8, 255, 0, 64, 0.5),  # below a DN: the quantiles interpolate inside bins
        (np.uint8, 255, 0, 64, 3.0),
        (np.uint8, 255, 0, 8, 20.0),  # noise beyond the clipped range: saturates at ~half bins
        (np.uint16, 4095, 2, 256, 12.0),  # 12 bits in 16: binned 4 DN wide
        (np.uint16, 65535, 6, 256, 300.0),
    ],
)
def test_tile_noise_is_its_definition_over_the_sampled_residuals(rng, dtype, full, shift, half, sigma_dn):
    # 300 x 420: partial tiles at the bottom and right; bg has whole cells only (37 x 52), so the
    # last 4 rows and columns are never sampled, and the last tile row has 44 rows, 5 samples each
    img, base = _image(rng, (300, 420), dtype, sigma_dn, full)
    bg = base[4::8, 4::8][:37, :52].astype(np.float32)
    got = tile_noise_kernel(img, bg, STEP, TILE, SUB_V, shift, half)
    assert got.shape == (5, 7)
    ref = _tiles_reference(img, bg, (5, 7), shift, half)
    # the same arithmetic in another order: round-off of quantiles ~100 bins from the origin
    np.testing.assert_allclose(got, ref * 2.0**shift, rtol=1e-12, atol=1e-12)


def test_tile_noise_edge_cases(rng):
    img = np.full((64, 64), 100, np.uint8)
    bg = np.full((8, 8), 100.0, np.float32)
    # a flat image: every residual 0, the quantiles inside the one bin: IQR_TO_SIGMA / 2 bins
    np.testing.assert_allclose(tile_noise_kernel(img, bg, STEP, TILE, SUB_V, 0, 64), [[IQR_TO_SIGMA / 2]])
    # a tile of fewer than 16 samples (one cell: 2 sampled rows x 4 columns) gives 0
    small = tile_noise_kernel(img[:8, :8].copy(), bg[:1, :1].copy(), STEP, TILE, SUB_V, 0, 64)
    assert small.shape == (1, 1) and small[0, 0] == 0.0
    # no cells: no tiles
    assert tile_noise_kernel(img, np.zeros((0, 0), np.float32), STEP, TILE, SUB_V, 0, 64).shape == (0, 0)


@pytest.mark.parametrize("sigma_dn", [2.0, 4.0, 10.0])
def test_tile_noise_estimates_the_true_sigma_of_gaussian_noise(rng, sigma_dn):
    # A sampled IQR of 512 values has a relative standard error of ~5 % (measured: 4-5 %); the
    # per-tile band is 4 of those, two-sided, so a vanished or doubled noise fails. Over 64 tiles
    # the mean is good to 0.6 %; whole-DN rounding biases it up by 1.4 % at 2 DN (5-9 % at 1-1.5
    # DN, measured: not tested here), hence 3 %
    img = np.clip(np.rint(80.0 + rng.normal(0, sigma_dn, (512, 512))), 0, 255).astype(np.uint8)
    got = tile_noise_kernel(img, np.full((64, 64), 80.0, np.float32), STEP, TILE, SUB_V, 0, 64)
    assert np.all(np.abs(got / sigma_dn - 1) < 0.2)
    assert abs(np.mean(got) / sigma_dn - 1) < 0.03
    # targets over 40 % of a tile do not raise it: the clipped rounds keep the background's sigma;
    # nor over 75 % or 90 % (a coded target at 0.5 m fills a tile: 31 DN was estimated for 1.5),
    # where the background's lower half alone is left to judge by
    bg = np.full((64, 64), 80.0, np.float32)
    for j, cover in enumerate((26, 48, 58)):
        covered = img.copy()
        covered[64 * j : 64 * (j + 1), :cover] = 240
        again = tile_noise_kernel(covered, bg, STEP, TILE, SUB_V, 0, 64)
        assert abs(again[j, 0] / sigma_dn - 1) < (0.3 if cover < 58 else 0.4), (cover, again[j, 0])
        ref = _tiles_reference(covered, bg, again.shape, 0, 64)
        np.testing.assert_allclose(again, ref, rtol=1e-12)


def test_tile_noise_agrees_with_the_median_absolute_deviation_of_each_tile(rng):
    # 16-bit noise of 40 DN (no quantisation to speak of): 1.4826 MAD over all 4096 pixels of each
    # tile (np.median, standard error ~2 %) against the kernel's 512 samples (~5 %): within 20 %
    img = np.rint(3000.0 + rng.normal(0, 40.0, (512, 512))).astype(np.uint16)
    got = tile_noise_kernel(img, np.full((64, 64), 3000.0, np.float32), STEP, TILE, SUB_V, 0, 512)
    tiles = img.reshape(8, 64, 8, 64).transpose(0, 2, 1, 3).reshape(8, 8, -1).astype(np.float64)
    mad = 1.4826 * np.median(np.abs(tiles - np.median(tiles, axis=2, keepdims=True)), axis=2)
    assert np.all(np.abs(got / mad - 1) < 0.2)
    assert abs(np.mean(got / mad) - 1) < 0.03


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_box_peak_is_the_maximum_over_each_box(rng, dtype):
    img = rng.integers(0, 250 if dtype == np.uint8 else 60000, (120, 90)).astype(dtype)
    u0, v0 = rng.integers(0, 90, 300), rng.integers(0, 120, 300)
    u1, v1 = np.minimum(u0 + rng.integers(0, 15, 300), 89), np.minimum(v0 + rng.integers(0, 15, 300), 119)
    box = np.column_stack([u0, v0, u1, v1]).astype(np.intp)
    box[:4] = [[0, 0, 0, 0], [89, 119, 89, 119], [0, 0, 89, 119], [5, 7, 5, 30]]  # corners, all, a line
    which = np.ascontiguousarray(rng.permutation(300)[:250], dtype=np.intp)
    which[:4] = [0, 1, 2, 3]
    got = box_peak_kernel(img, box, which)
    ref = [img[box[c, 1] : box[c, 3] + 1, box[c, 0] : box[c, 2] + 1].max() for c in which]
    np.testing.assert_array_equal(got, np.array(ref, dtype=np.float64))
    assert box_peak_kernel(img, box, np.zeros(0, np.intp)).shape == (0,)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(64, 48), (70, 53), (9, 8)])  # whole cells; rows and columns beyond them
def test_cell_threshold_is_the_compare_with_each_pixels_cell(rng, dtype, shape):
    top = 250 if dtype == np.uint8 else 60000
    img = rng.integers(0, top, shape).astype(dtype)
    hs, ws = shape[0] // STEP, shape[1] // STEP
    thr = rng.integers(0, top, (hs, ws)).astype(dtype)
    cells = np.repeat(np.repeat(thr, STEP, 0), STEP, 1)
    cells = np.pad(cells, ((0, shape[0] - cells.shape[0]), (0, shape[1] - cells.shape[1])), mode="edge")
    img[::3] = cells[::3]  # equal to the threshold: not above it
    img.flags.writeable = False  # a replayed frame is read-only
    out = np.full(shape, 7, dtype=np.uint8)
    got = cell_threshold_kernel(img, thr, STEP, out)
    assert got is out
    np.testing.assert_array_equal(got, np.where(img > cells, 255, 0).astype(np.uint8))
