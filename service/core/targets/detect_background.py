"""The full frame's background, noise and foreground: the first stage of :mod:`~service.core.targets.detect`.

The background is the image shrunk 8x, blurred, opened over 120 px (which removes the targets but
keeps hot spots and gradients of the ring light) and blurred again. The noise is measured about it
per 64 px tile (:mod:`service.core._kernels.noise_kernel`: a clipped interquartile range, so read
noise, shot noise and a textured background all count, and the targets do not). Foreground is
brighter than the background by ``K_SEG`` noise sigmas, and by at least half of
``min_contrast_dn`` (a scalar threshold where all of that is flat).

A stage of its own because it is the one part that looks at every pixel of the frame; what it
gives (:class:`Background`) sets the levels the candidates and the windows are judged by.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from service.core._kernels.noise_kernel import cell_threshold_kernel, tile_noise_kernel
from service.core.targets.detect_types import DTYPE_MAX, Array, Image

f32, f64 = np.float32, np.float64

COARSE_STEP = 8  # px per coarse background sample
COARSE_OPENING = 15  # coarse samples across the background's opening (120 px): wider than any target
FLAT_BACKGROUND_FRACTION = 0.25  # of the segmentation level: a flatter background gets a scalar threshold
NOISE_TILE_PX = 64  # side of the tiles the noise is measured in (8 coarse cells)
NOISE_ROWS = 4  # the noise is measured on every 2nd pixel of every 4th row: 512 a tile (sigma to 7 %)
NOISE_HALF_DN = 64  # residuals beyond 64 8-bit DN count as 64: quartiles of noise up to ~90 DN are not moved
# Foreground: K_SEG noise sigmas above the background (white noise passes 5 sigma at 3e-7 of the
# pixels: a stray pixel or two per frame, never a blob of several).
K_SEG = 5.0


@dataclass(frozen=True)
class Background:
    """The coarse grid (one cell per COARSE_STEP x COARSE_STEP px): background level, noise sigma
    and segmentation level above the background, all float32 DN; and the tiles' noise (float64)."""

    level: NDArray[np.float32]
    noise: NDArray[np.float32]
    seg: NDArray[np.float32]
    tiles: Array

    def at(self, grid: NDArray[np.float32], u: NDArray[np.intp], v: NDArray[np.intp]) -> Array:
        """Values of ``grid`` (one of the fields) at the integer pixels (u, v)."""
        hs, ws = grid.shape
        return grid[np.minimum(v // COARSE_STEP, hs - 1), np.minimum(u // COARSE_STEP, ws - 1)].astype(f64)


def estimate_background(img: Image, full_dn: float, seg_dn: float) -> Background:
    """Background, noise and segmentation level of a full frame (see the module docstring)."""
    h, w = img.shape
    small = cv2.resize(img, (w // COARSE_STEP, h // COARSE_STEP), interpolation=cv2.INTER_LINEAR)
    # blur first: an opening of noisy samples would sit below the mean background
    small = cv2.blur(small.astype(f32), (5, 5), borderType=cv2.BORDER_REPLICATE)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (COARSE_OPENING, COARSE_OPENING))
    bg = cv2.morphologyEx(small, cv2.MORPH_OPEN, k, borderType=cv2.BORDER_REPLICATE)
    bg = cv2.blur(bg, (5, 5), borderType=cv2.BORDER_REPLICATE)  # smooths the opening's steps
    # residuals binned 1 DN wide for 8 bits, deeper a quarter of an 8-bit DN or less (16: 64 DN),
    # over +-NOISE_HALF_DN 8-bit DN
    shift = max(0, int(np.floor(np.log2(full_dn / 1020.0)))) if full_dn > 1020.0 else 0
    half = min(512, int(np.ceil(NOISE_HALF_DN * full_dn / 255.0 / 2**shift)))
    tiles = tile_noise_kernel(img, bg, COARSE_STEP, NOISE_TILE_PX, NOISE_ROWS, shift, half)
    per = NOISE_TILE_PX // COARSE_STEP  # the tiles are whole coarse cells from the origin: aligned
    noise = cv2.resize(tiles.astype(f32), (tiles.shape[1] * per, tiles.shape[0] * per), interpolation=cv2.INTER_LINEAR)[
        : bg.shape[0], : bg.shape[1]
    ]
    seg = np.maximum(f32(K_SEG) * noise, f32(seg_dn))
    return Background(cast(NDArray[np.float32], bg), noise, seg, tiles)


def foreground_mask(img: Image, back: Background, out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
    """0/255 mask of the pixels brighter than their coarse cell's background plus its segmentation
    level (one threshold for all where the background is flat), in ``out`` if given."""
    h, w = img.shape
    thr_c = back.level + back.seg
    lo, hi = float(thr_c.min()), float(thr_c.max())
    if hi - lo <= FLAT_BACKGROUND_FRACTION * float(back.seg.min()):
        mask: Any = cv2.compare(img, hi, cv2.CMP_GT, dst=out)  # type: ignore[call-overload]  # dst may be None
        return cast(NDArray[np.uint8], mask)
    # each pixel against its own cell's threshold, not one interpolated between cells: the mask only
    # finds the candidates (the windows measure on the image, against the cell's level as here), and
    # between neighbouring cells of a smooth background the threshold moves by a few DN (at most 3
    # in the hot spot of `posecell bench speed`, over a threshold 20-80 DN above black)
    thr = np.minimum(np.rint(thr_c), DTYPE_MAX[img.dtype.char]).astype(img.dtype)
    if out is None:
        out = np.empty((h, w), dtype=np.uint8)
    return cast(NDArray[np.uint8], cell_threshold_kernel(img, thr, COARSE_STEP, out))
