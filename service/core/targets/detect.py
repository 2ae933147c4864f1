"""Sub-pixel measurement of bright targets in near-IR images (the paper, section 4.2).

:func:`detect_blobs` finds and measures every target in a full frame;
:func:`measure_windows` measures the targets in small windows around predicted
positions (ROI tracking). Both use one primitive over many windows
(:func:`_measure_all`, a compiled loop in :mod:`service.core._kernels.detect_kernel`).

Full frame:

1. Background and noise: the background is the image shrunk 8x, blurred, opened over 120 px
   (which removes the targets but keeps hot spots and gradients of the ring light) and blurred
   again. The noise is measured about it per 64 px tile (:mod:`service.core._kernels.noise_kernel`: a
   clipped interquartile range, so read noise, shot noise and a textured background all count,
   and the targets do not). Foreground is brighter than the background by ``K_SEG`` noise sigmas, and by at least
   half of ``min_contrast_dn`` (a scalar threshold where all of that is flat).
2. Candidates: external contours (``cv2.findContours``, 3x faster than labelling with statistics)
   and their polygon moments (Green's theorem) reject specks, huge blobs, long ones and blobs at
   the image border; then, before any window is measured, those whose brightest pixel is not
   clearly above the noise, and, beyond ``max_candidates``, the faintest. Only then are the
   pieces of coded targets' rings looked for (:func:`_neighbours`), each candidate within its own
   radius. So the work per frame is bounded whatever the image holds: a frame of pure noise
   gives next to no foreground, a textured one many specks that cost one pass each.
   The work per contour, pair and crowded window is compiled (:mod:`service.core._kernels.contour_kernel`,
   :mod:`service.core._kernels.crowd_kernel`).
3. Measurement in circular windows, one batch per window radius; a peak ``K_PEAK`` noise sigmas
   (and ``min_contrast_dn``) above the window's background is required.

Per window (the circle of radius ``h + 1/2``):

- background: a plane through the rim (the outer 1.5 px), fitted to its pixels that are not
  bright, so a ring-light gradient biases no centre;
- centre: the background-corrected intensity-weighted centroid over the circle, unbiased for any
  symmetric blur. All moments up to the fourth come from one matrix product with a table of
  monomials; the plane's slopes are removed from them analytically (the circle is symmetric);
- ellipse (what a coded-ring reader needs): the second moments less the isotropic blur variance
  ``s``. With ``L`` the plateau (mean of the 3 x 3 pixels at the centre) and ``S`` the flux, the
  disk's area is ``S / L = pi a b``, so ``s`` solves ``(l1 - s)(l2 - s) = (S / (4 pi L))**2``;
- shape: a disk seen at any angle is a centrally symmetric, flat-topped ellipse. A notch or an
  occluder makes third moments, two merged disks a fourth moment along the major axis unlike the
  ellipse's, a bright spot a blob that is mostly "blur"; the fill (soft overlap with the ellipse
  drawn with the same edge) catches other misfits. The moment statistics are compared with their
  own predicted noise, so the tests hold for faint and bright targets alike. Notches that move
  the centre by less than about 0.3 px (at the reference noise) are not detected;
- precision ``sigma_px``: pixel noise propagated through the centroid (:func:`_measure_all`), with
  the shot noise measured on the targets' plateaus.

Pixel convention (DESIGN section 2): the centre of the top-left pixel is (0, 0).
``min_contrast_dn`` is in 8-bit DN, scaled by ``full_scale / 255`` (the
saturation level, by default the dtype's maximum), so the defaults suit 8-,
12- and 16-bit images.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from service.core._kernels import detect_kernel
from service.core._kernels.contour_kernel import classify_kernel, contour_stats_kernel, windows_kernel
from service.core._kernels.crowd_kernel import mask_windows_kernel, neighbours_kernel
from service.core._kernels.detect_kernel import assess_kernel, measure_windows_kernel
from service.core._kernels.noise_kernel import box_peak_kernel, tile_noise_kernel
from service.core.results import Reason, SolveError
from service.core.targets.codes import RING_INNER, RING_OUTER

Array = NDArray[np.float64]
Image = NDArray[np.uint8] | NDArray[np.uint16]  # a frame, once _check_image has accepted it
f32, f64 = np.float32, np.float64

REASONS = ("saturated", "cut_off", "merged_or_misshapen", "too_small", "too_big", "low_contrast", "ring", "too_many")
_SATURATED, _CUT_OFF, _MISSHAPEN, _TOO_SMALL, _TOO_BIG, _LOW_CONTRAST, _RING, _TOO_MANY = range(len(REASONS))

COARSE_STEP = 8  # px per coarse background sample
COARSE_OPENING = 15  # coarse samples across the background's opening (120 px): wider than any target
FLAT_BACKGROUND_FRACTION = 0.25  # of the segmentation level: a flatter background gets a scalar threshold
NOISE_TILE_PX = 64  # side of the tiles the noise is measured in (8 coarse cells)
NOISE_ROWS = 4  # the noise is measured on every 2nd pixel of every 4th row: 512 a tile (sigma to 7 %)
NOISE_HALF_DN = 64  # residuals beyond 64 8-bit DN count as 64: quartiles of noise up to ~90 DN are not moved
# Foreground: K_SEG noise sigmas above the background (white noise passes 5 sigma at 3e-7 of the
# pixels: a stray pixel or two per frame, never a blob of several). A target: its peak K_PEAK sigmas
# above its window's background (8 sigma: a textured background's brightest specks stay below; it
# is the 40 DN that flash-lit carbon panels needed by hand). Before measuring, EARLY_CONTRAST of that
# against the box's brightest pixel, so that no candidate the measurement would keep is dropped.
K_SEG, K_PEAK, EARLY_CONTRAST = 5.0, 8.0, 0.8
HOSTS_PER_CANDIDATE = 4  # a host's search for its ring costs a small part of a measured window
MIN_PIECE_HALF = 0.4  # a disk-like ring piece's radial half extent, host radii (a ring 1 radius wide: 0.58)
WINDOW_MARGIN_PX = 2  # window radius beyond the thresholded blob, so the rim clears its blur tail
# Steps of window radius: the windows within one step are measured together, at its largest radius.
WINDOW_RADII = (4, 6, 8, 10, 12, 15, 18, 22, 27, 33, 40, 48, 58, 70, 84, 100, 120, 150)
_RADII = np.array(WINDOW_RADII, dtype=np.intp)
MAX_SATURATED_PX = 2  # more saturated pixels than this reject a blob
MIN_POLYGON_FILL = 0.9  # contour area over its moments' ellipse area; below: a long arc or merged blob
SHAPE_SIGMA = (3.0, 4.0)  # asymmetry and kurtosis may deviate this many times their noise ...
SHAPE_FLOOR = (0.015, 0.05)  # ... plus this (pixel sampling): px, and unitless
MIN_FLAT_TOP = 0.4  # a disk's own minor-axis variance exceeds 0.4 of the blurred blob's (0.7 at 2 px radius)
MIN_PLATEAU_B_PX = 2.5  # blobs narrower than this have no flat 3 x 3 centre for the shot noise
# A disk's flux over its plateau level is its ellipse's area (rendered and drawn disks: within 6 %;
# narrower than MIN_PLATEAU_B_PX, whose 3 x 3 centre is not flat, up to 1.7 times); printed glyphs and
# rings have dim centres and 9-60 times
MAX_AREA_RATIO = (1.3, 2.5)


@dataclass(frozen=True)
class DetectSettings:
    """Filters and options of blob detection; levels in 8-bit DN (see the module docstring)."""

    min_area_px: int = 6
    max_area_px: int = 5000
    min_contrast_dn: float = 20.0  # peak above local background, 8-bit DN
    max_aspect: float = 4.0  # b/a < 1/max_aspect -> rejected (ring sectors, scratches)
    min_fill: float = 0.6  # soft overlap of blob and ellipse; a gross misfit fails
    saturation_dn: float | None = None  # default: the dtype max (255 / 65535)
    border_px: int = 2  # blobs this close to the image border are cut off -> rejected
    window_px: int = 0  # side of the measuring window; 0: automatic from blob size
    max_candidates: int = 1500  # blobs measured per full frame at most (the brightest): bounds the work
    # the image's noise sigma (image DN) for measure_windows, e.g. the last full frame's
    # DetectWork.noise_dn; detect_blobs measures its own. None: min_contrast_dn's levels alone
    noise_dn: float | None = None


@dataclass(frozen=True)
class Blobs:
    """Measured targets (N of them), in no particular order.

    uv : (N, 2) float, px -- background-corrected intensity-weighted centroid
    ellipse : (N, 5) float -- u_c px, v_c px, a_px (semi-major), b_px (semi-minor), angle rad of the
        major axis from +u towards +v in (-pi/2, pi/2]: the disk's edge, blur removed
    sigma_px : (N,) float, px -- predicted standard deviation of each coordinate of ``uv``
    area_px : (N,) float, px^2 -- flux over plateau level: the area of the disk's image
    peak_dn, background_dn : (N,) float, DN -- brightest pixel; local background at the centre
    fill : (N,) float -- soft overlap of the blob with its ellipse (1: a perfect ellipse)
    has_ring : (N,) bool -- pieces of a coded target's ring were found around it (only these
        can be coded; :func:`measure_windows` does not look and says False)
    """

    uv: Array
    ellipse: Array
    sigma_px: Array
    area_px: Array
    peak_dn: Array
    background_dn: Array
    fill: Array
    has_ring: NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def take(self, index: NDArray[np.intp]) -> Blobs:
        """The blobs at ``index`` (any numpy index), in that order."""
        return Blobs(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


@dataclass(frozen=True)
class DetectWork:
    """What one full frame cost and what its background was like (diagnostics, benchmarks).

    n_contours -- thresholded blobs (each costs one pass over its contour)
    n_candidates -- of them, plausible as a target or a ring's host (area, shape, contrast)
    n_measured -- windows measured (at most ``max_candidates``)
    n_pairs -- (candidate, neighbour) pairs examined for ring pieces and crowding
    n_visits -- contours looked at while finding them (the pair search's work)
    noise_dn -- median of the tiles' noise sigma, image DN; noise_max_dn -- the largest tile's
    """

    n_contours: int = 0
    n_candidates: int = 0
    n_measured: int = 0
    n_pairs: int = 0
    n_visits: int = 0
    noise_dn: float = 0.0
    noise_max_dn: float = 0.0


@dataclass(frozen=True)
class Rejections:
    """Blobs found but not measured, and why.

    reason_code : (K,) int -- index into :data:`REASONS`
    box : (K, 4) int, px -- u0, v0, u1, v1 of the thresholded blob, inclusive
    uv : (K, 2) float, px -- its centre (of the measurement where there was one)
    work : DetectWork -- the frame's work and noise
    """

    reason_code: NDArray[np.intp]
    box: NDArray[np.intp]
    uv: Array
    work: DetectWork = DetectWork()

    def __len__(self) -> int:
        return int(self.reason_code.shape[0])

    @property
    def reason(self) -> NDArray[np.str_]:
        """(K,) reason names."""
        return np.asarray(REASONS)[self.reason_code]

    @property
    def counts(self) -> dict[str, int]:
        """Rejected blobs per reason, every reason present."""
        n = np.bincount(self.reason_code, minlength=len(REASONS))
        return {r: int(c) for r, c in zip(REASONS, n, strict=True)}


def _check_image(image: NDArray[np.generic]) -> Image:
    img: Any = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise SolveError(
            Reason.bad_image, f"Expected a 2-D uint8 or uint16 image, got {img.dtype} of shape {img.shape}."
        )
    if min(img.shape) < 2 * COARSE_STEP:
        raise SolveError(Reason.bad_image, f"The image ({img.shape[1]} x {img.shape[0]} px) is too small.")
    return np.ascontiguousarray(img)


_DTYPE_MAX = {np.dtype(t).char: float(np.iinfo(t).max) for t in (np.uint8, np.uint16)}  # np.iinfo is slow per call


def _levels(img: Image, settings: DetectSettings) -> tuple[float, float, float]:
    """(saturation level, contrast threshold, segmentation level) in the image's DN."""
    full = float(_DTYPE_MAX[img.dtype.char] if settings.saturation_dn is None else settings.saturation_dn)
    if not full > 0:
        raise ValueError(f"saturation_dn must be positive, got {settings.saturation_dn}")
    contrast = settings.min_contrast_dn * full / 255.0
    return full, contrast, 0.5 * contrast


@dataclass(frozen=True)
class _Background:
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


def _background(img: Image, full_dn: float, seg_dn: float) -> _Background:
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
    return _Background(cast(NDArray[np.float32], bg), noise, seg, tiles)


def _foreground(img: Image, back: _Background, out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
    """0/255 mask of the pixels brighter than the coarse background plus its segmentation level,
    in ``out`` if given."""
    h, w = img.shape
    thr_c = back.level + back.seg
    lo, hi = float(thr_c.min()), float(thr_c.max())
    mask: Any  # OpenCV's MatLike: the 0/255 uint8 mask
    if hi - lo <= FLAT_BACKGROUND_FRACTION * float(back.seg.min()):
        mask = cv2.compare(img, hi, cv2.CMP_GT, dst=out)  # type: ignore[call-overload]  # dst may be None
        return cast(NDArray[np.uint8], mask)
    thr = np.minimum(np.rint(thr_c), _DTYPE_MAX[img.dtype.char]).astype(img.dtype)
    if out is not None and img.dtype == np.uint8:  # the full-size threshold in ``out``, compared in place
        thr_full = cv2.resize(thr, (w, h), dst=out, interpolation=cv2.INTER_LINEAR)
        mask = cv2.compare(img, thr_full, cv2.CMP_GT, dst=out)
    else:
        thr_full = cv2.resize(thr, (w, h), interpolation=cv2.INTER_LINEAR)
        mask = cv2.compare(img, thr_full, cv2.CMP_GT, dst=out)
    return cast(NDArray[np.uint8], mask)


@dataclass(frozen=True)
class _Contours:
    """Per contour (C): box (C, 4) inclusive, pixel area, polygon area, centroid (C, 2),
    polygon moments (C, 3) uu uv vv, integer box centre (C, 2) and reach: the farthest
    contour pixel from the box centre, px, rounded up."""

    box: NDArray[np.intp]
    area_px: Array
    poly_area: Array
    centre: Array
    mu: Array
    box_centre: NDArray[np.intp]
    reach: NDArray[np.intp]


def _contours(mask: NDArray[np.uint8]) -> _Contours:
    """Boxes, areas and polygon moments of the external contours of ``mask`` (compiled: Green's
    theorem over each closed polygon, relative to its first vertex, in one pass over the vertices)."""
    found, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not found:
        z2, z = np.zeros((0, 2), np.intp), np.zeros(0)
        return _Contours(np.zeros((0, 4), np.intp), z, z, np.zeros((0, 2)), np.zeros((0, 3)), z2, np.zeros(0, np.intp))
    lengths = np.fromiter(map(len, found), dtype=np.intp, count=len(found))
    pts = np.concatenate(found).reshape(-1, 2)
    starts = np.cumsum(lengths) - lengths
    return _Contours(*contour_stats_kernel(np.require(pts, np.int32, ["C", "W"]), starts, lengths))


def _neighbours(
    ct: _Contours,
    a: Array,
    host: NDArray[np.bool_],
    disk_like: NDArray[np.bool_],
    query: NDArray[np.bool_],
    shape: tuple[int, int],
) -> tuple[NDArray[np.intp], Array, int, int]:
    """Per blob: the ``host`` (disk candidate) whose coded ring it is a piece of, or -1, and for
    each ``query`` (the candidates) the distance from its box centre to the nearest thresholded
    pixel of another blob; and the pairs examined and contours visited.

    Distances to a host are measured in its own ellipse (rho = 1 on its edge),
    so the rules hold in oblique views. A disk-like piece (a short arc) lies
    wholly between RING_INNER and RING_OUTER, its ends from its moments, with
    a pixel's slack for the threshold, and is as wide as a ring (MIN_PIECE_HALF);
    any other blob within RING_OUTER is a
    longer arc. From a short arc the real disk is far too large to lie in the
    arc's annulus, so a disk is never a piece of its own ring; a claimed host
    claims nothing. A ring comes nearest at its inner edge, RING_INNER disk
    radii less the threshold's growth, taken as 2 px on disk and ring (so the
    estimate errs towards masking); other blobs at their distance less their reach.
    Of two hosts that could claim one piece (overlapping rings), the nearer takes it. Compiled
    (:func:`~service.core._kernels.crowd_kernel.neighbours_kernel`): as array expressions over the pairs it
    took 0.47 ms of a frame, now 0.06 ms. Each query looks only as far as its own ring and window
    reach, through a grid of the contours' boxes, so the pairs grow with the candidates, not with
    the square of the blobs.
    """
    c = np.ascontiguousarray  # one compiled kernel for every way the arrays come
    host_of, near, n_pairs, visits = neighbours_kernel(
        c(ct.box),
        c(ct.centre),
        c(ct.mu),
        c(ct.box_centre),
        c(ct.reach),
        c(a),
        c(host),
        c(disk_like),
        c(query),
        float(RING_INNER),
        float(RING_OUTER),
        MIN_PIECE_HALF,
        shape[1],
        shape[0],
    )
    return host_of, near, int(n_pairs), int(visits)


def _brightest(which: NDArray[np.bool_], bright: Array, k: int) -> NDArray[np.bool_]:
    """``which`` less all but the ``k`` brightest of it."""
    idx = which.nonzero()[0]
    if idx.size <= k:
        return which
    out = np.zeros_like(which)
    out[idx[np.argsort(-bright[idx], kind="stable")[:k]]] = True
    return out


@dataclass(frozen=True)
class _Measured:
    """Per window (n), see :func:`_measure_all`: centre (n, 2) px, ellipse (n, 5), flux S, plateau
    level and peak and background (DN), background noise variance sb2 (rim plane residual), shot
    noise per DN of level, centroid variance from background noise and per unit shot coefficient,
    the fill's mismatch (sum |blob - ellipse model| / level) and what background noise adds to it
    (px^2), the third central moments' squared norm, the kurtosis along the major axis and the
    blurred ellipse's, the disk's share of the minor-axis variance (the rest is blur), the
    variance along the major axis, the window's sums (n, 7), saturated pixels, rim crossed."""

    uv: Array
    ellipse: Array
    flux: Array
    level: Array
    peak: Array
    background: Array
    sb2: Array
    k_shot: Array
    var_base: Array
    var_per_k: Array
    mismatch: Array
    noise_bg: Array
    m3sq: Array
    kurt: Array
    kurt_model: Array
    flat_top: Array
    var_major: Array
    sums: Array
    n_sat: NDArray[np.intp]
    edge: NDArray[np.bool_]
    table: Array  # (NF, n): the kernel's output, whose rows the fields above are


def _measure_all(
    img: NDArray[np.generic],
    cu: NDArray[np.intp],
    cv: NDArray[np.intp],
    radius: NDArray[np.intp],
    seg_dn: Array,
    full_dn: float,
    own: Array | None,
) -> tuple[_Measured, NDArray[np.bool_]]:
    """Measure the blob in the circle of radius ``radius + 1/2`` px about each (cu, cv), with the
    segmentation level ``seg_dn`` (n,) DN above the background of each window. ``own`` (n, 5):
    rows (x0, y0, Q_uu, Q_uv, Q_vv), the blob's own region ``x' Q x <= 1`` about (x0, y0) from the
    window centre, NaN where nothing else is near. In those crowded windows, bright pixels outside
    the region and a 3 px band around them (their blur tail) take the rim's lower quartile (the
    rim may cross the other blob): :func:`~service.core._kernels.crowd_kernel.mask_windows_kernel`. The
    work per window is :func:`~service.core._kernels.detect_kernel.measure_windows_kernel`.

    Returns the measurements in input order and whether each window fits in the image (the others
    give zeros and a crossed rim).

    Precision: the centre is linear in the pixel values, the rim pixels
    counting twice (in the sums and through the plane fitted to them). With
    the circle's ``A0`` pixels and ``A2 = sum(du^2)``, a rim of ``m`` pixels
    with ``R = sum_rim(du^2)``, the flux ``S``, the background noise ``sb``
    (rms residual of the rim plane) and the shot-noise variance ``k`` per DN of
    signal, the variance of ``u_c`` (relative to the window centre) is::

        [sb^2 (A2^2 / R - A2 + u_c^2 (A0^2 / m - A0)) + k S mu_uu] / S^2

    likewise along v; ``sigma_px`` is the square root of their mean.
    """
    height, width = img.shape
    cu, cv, radius = (np.require(x, np.intp, ["C", "W"]) for x in (cu, cv, radius))
    seg_dn = np.require(seg_dn, f64, ["C", "W"])
    if not img.flags.writeable:  # a read-only frame would need its own compiled kernel
        img = img.copy()
    placed = (cu >= radius) & (cu + radius < width) & (cv >= radius) & (cv + radius < height) & (radius >= 2)
    crowd = (placed & np.isfinite(own[:, 0])).nonzero()[0] if own is not None else np.zeros(0, dtype=np.intp)
    if crowd.size:  # other blobs reach into these windows: mask them
        buf, boff = mask_windows_kernel(img, cu, cv, radius, crowd, np.ascontiguousarray(own, dtype=f64), seg_dn)
    else:
        buf, boff = np.zeros(1, f32), np.full(cu.size, -1, dtype=np.intp)
    out, n_sat, edge = measure_windows_kernel(img, cu, cv, radius, placed, seg_dn, float(full_dn), buf, boff)
    K = detect_kernel
    return _Measured(
        uv=out[K.UV : K.UV + 2].T,
        ellipse=out[K.ELLIPSE : K.ELLIPSE + 5].T,
        flux=out[K.FLUX],
        level=out[K.LEVEL],
        peak=out[K.PEAK],
        background=out[K.BACKGROUND],
        sb2=out[K.SB2],
        k_shot=out[K.K_SHOT],
        var_base=out[K.VAR_BASE],
        var_per_k=out[K.VAR_PER_K],
        mismatch=out[K.MISMATCH],
        noise_bg=out[K.NOISE_BG],
        m3sq=out[K.M3SQ],
        kurt=out[K.KURT],
        kurt_model=out[K.KURT_MODEL],
        flat_top=out[K.FLAT_TOP],
        var_major=out[K.VAR_MAJOR],
        sums=out[K.SUMS : K.SUMS + 7].T,
        n_sat=n_sat,
        edge=edge,
        table=out,
    ), placed


def _assess(
    meas: _Measured, usable: NDArray[np.bool_], settings: DetectSettings, contrast_dn: Array
) -> tuple[NDArray[np.intp], Array, Array]:
    """Reason (-1: accepted; rim contact not included), sigma_px and fill of each window, whose
    peak must be ``contrast_dn`` (n,) DN above its background.

    The shot-noise coefficient ``k`` is the median plateau variance per DN of the usable blobs
    that pass the level tests (8 degrees of freedom each: the median is 0.918 of the mean). The
    shape statistics against their noise (through the window's sums, the blob as a uniform disk
    for shot noise): asymmetry ``|mu3| / (2 tr mu)`` px (a one-sided defect's shift of the
    centre, ``|mu3|^2 = k30^2 + 3 k21^2 + 3 k12^2 + k03^2``); kurtosis along the major axis;
    fill ``(A + Ae - m) / (A + Ae + m)`` of the blob's area ``A``, the ellipse's ``Ae`` and their
    mismatch ``m`` less what noise adds to it (``sqrt(2 / pi)`` sigma per pixel).
    """
    return assess_kernel(
        meas.table,
        meas.n_sat,
        meas.edge,
        usable,
        np.require(contrast_dn, f64, ["C", "W"]),
        *_assess_constants(settings),
    )


@lru_cache(maxsize=8)
def _assess_constants(settings: DetectSettings) -> tuple[Array, NDArray[np.intp]]:
    """The limits and reason codes :func:`~service.core._kernels.detect_kernel.assess_kernel` takes."""
    limits = np.array(
        [
            settings.min_area_px,
            settings.max_area_px,
            settings.max_aspect,
            settings.min_fill,
            MAX_SATURATED_PX,
            MIN_PLATEAU_B_PX,
            MIN_FLAT_TOP,
            *SHAPE_SIGMA,
            *SHAPE_FLOOR,
            *MAX_AREA_RATIO,
        ],
        dtype=f64,
    )
    return limits, np.array([_SATURATED, _LOW_CONTRAST, _TOO_SMALL, _TOO_BIG, _MISSHAPEN], dtype=np.intp)


def _blobs(
    meas: _Measured, index: NDArray[np.intp], sigma: Array, fill: Array, has_ring: NDArray[np.bool_] | None = None
) -> Blobs:
    return Blobs(
        uv=meas.uv[index],
        ellipse=meas.ellipse[index],
        sigma_px=sigma[index],
        area_px=meas.flux[index] / meas.level[index],
        peak_dn=meas.peak[index],
        background_dn=meas.background[index],
        fill=fill[index],
        has_ring=np.zeros(index.size, dtype=bool) if has_ring is None else has_ring[index],
    )


def _windows(
    ct: _Contours, todo: NDArray[np.intp], near: Array, shape: tuple[int, int], window_px: int
) -> tuple[NDArray[np.intp], Array, NDArray[np.bool_]]:
    """Window radius of each blob to measure, its own region for :func:`_measure_all` where
    another blob reaches into the window (its thresholded ellipse + 1.5 px; NaN rows elsewhere), and
    whether the image border limits the window. A window holds the thresholded blob plus
    WINDOW_MARGIN_PX; the windows within one step of WINDOW_RADII share the largest radius among
    them (:func:`~service.core._kernels.contour_kernel.windows_kernel`)."""
    return windows_kernel(
        ct.box_centre,
        ct.reach,
        ct.mu,
        ct.centre,
        np.ascontiguousarray(todo, dtype=np.intp),
        near,
        shape[1],
        shape[0],
        int(window_px),
        _RADII,
        WINDOW_MARGIN_PX,
    )


def detect_blobs(
    image: NDArray[np.generic],
    settings: DetectSettings = DetectSettings(),
    *,
    mask_buffer: NDArray[np.uint8] | None = None,
) -> tuple[Blobs, Rejections]:
    """Find and measure every bright target (disk) in a full frame.

    Parameters
    ----------
    image : (H, W) uint8 or uint16
    settings : DetectSettings
    mask_buffer : (H, W) uint8, optional
        Scratch for the foreground mask. A caller that measures a stream of frames passes the
        same array each time: a fresh frame-sized array (allocated, and cleared by the system)
        cost a fifth of the detection (measured: 0.85 of 4.2 ms on the reference scene).
        Its content is overwritten; an array of another shape or type is not used.

    Returns
    -------
    Blobs
        The measured disks.
    Rejections
        Blobs found but not measured: saturated, cut off by the image border, merged or misshapen
        (notched, occluded), too small, too big, too faint, a piece of a coded target's ring, or
        beyond ``max_candidates``; and the frame's work and noise (:class:`DetectWork`).

    Raises
    ------
    SolveError
        ``bad_image`` if the image is not a 2-D uint8/uint16 array.
    """
    img = _check_image(image)
    (height, width), (full, contrast, seg) = img.shape, _levels(img, settings)
    if mask_buffer is not None and (
        mask_buffer.shape != img.shape
        or mask_buffer.dtype != np.uint8
        or not mask_buffer.flags.c_contiguous
        or not mask_buffer.flags.writeable
    ):
        mask_buffer = None
    back = _background(img, full, seg)
    ct = _contours(_foreground(img, back, mask_buffer))
    box, n = ct.box, ct.area_px.size
    a, cut, small, big, long, disk_like, host = classify_kernel(
        box,
        ct.area_px,
        ct.poly_area,
        ct.mu,
        width,
        height,
        settings.border_px,
        float(settings.min_area_px),
        float(settings.max_area_px),
        float(settings.max_aspect),
        MIN_POLYGON_FILL,
    )
    # candidates: plausible as a target or as a ring's host (a disk cut by the border still marks
    # its ring); before any window is measured, their brightest pixel against the noise there,
    # where the noise sets the bar (elsewhere the measurement's test is as cheap), and all of them
    # when there are more than can be measured: the brightest are kept
    cand = ~small & ~big & ~long
    idx = cand.nonzero()[0]
    need = np.maximum(contrast, K_PEAK * back.at(back.noise, ct.box_centre[idx, 0], ct.box_centre[idx, 1]))
    look = idx if idx.size > settings.max_candidates else idx[need > contrast]
    bright = np.full(n, np.inf)
    bright[look] = box_peak_kernel(img, box, look) - back.at(back.level, ct.box_centre[look, 0], ct.box_centre[look, 1])
    faint = np.zeros(n, dtype=bool)
    faint[idx] = bright[idx] < EARLY_CONTRAST * need
    # the hosts claim their rings' pieces, then the rest are measured. A bound on the work whatever
    # the image: at most max_candidates measured, the brightest, and HOSTS_PER_CANDIDATE times as many
    # searched for neighbours (short arcs of rings are candidates too, until a host claims them)
    query = _brightest(cand & ~faint, bright, HOSTS_PER_CANDIDATE * settings.max_candidates)
    host_of, near, n_pairs, n_visits = _neighbours(ct, a, host & query, disk_like, query, img.shape)
    rest = query & ~cut & (host_of < 0)
    measured = _brightest(rest, bright, settings.max_candidates)
    reason = np.select(
        [cut, small, big, (host_of >= 0), long, faint, ~query | (rest & ~measured)],
        [_CUT_OFF, _TOO_SMALL, _TOO_BIG, _RING, _MISSHAPEN, _LOW_CONTRAST, _TOO_MANY],
        -1,
    )

    todo = (reason < 0).nonzero()[0]
    radius, own, limited = _windows(ct, todo, near, img.shape, settings.window_px)
    tu, tv = ct.box_centre[todo, 0], ct.box_centre[todo, 1]
    meas, placed = _measure_all(img, tu, tv, radius, back.at(back.seg, tu, tv), full, own)
    wr, sigma, fill = _assess(meas, placed, settings, np.maximum(contrast, K_PEAK * back.at(back.noise, tu, tv)))
    # a blob reaching the window's rim is bigger than its window, or cut off where the border limits it
    wr = np.where(meas.edge | ~placed, np.where(limited, _CUT_OFF, np.where(wr < 0, _TOO_BIG, wr)), wr)
    reason[todo], centre = wr, ct.centre.copy()
    centre[todo] = np.where(np.isfinite(meas.uv), meas.uv, centre[todo])
    rej = (reason >= 0).nonzero()[0]
    ringed = np.zeros(reason.size, dtype=bool)
    ringed[host_of[host_of >= 0]] = True
    work = DetectWork(
        n, int(query.sum()), int(todo.size), n_pairs, n_visits, float(np.median(back.tiles)), float(back.tiles.max())
    )
    return (
        _blobs(meas, (wr < 0).nonzero()[0], sigma, fill, ringed[todo]),
        Rejections(reason[rej], box[rej], centre[rej], work),
    )


def measure_windows(
    image: NDArray[np.generic],
    uv_predicted: NDArray[np.float64],
    half_size_px: int | NDArray[np.intp],
    settings: DetectSettings = DetectSettings(),
) -> tuple[Blobs, NDArray[np.intp]]:
    """Measure the one bright disk in a small window around each predicted position.

    The measurement of :func:`detect_blobs` (a window is the circle of radius
    ``half_size_px + 1/2`` about the rounded prediction), vectorised over windows.

    Parameters
    ----------
    image : (H, W) uint8 or uint16
    uv_predicted : (M, 2) float, px
    half_size_px : int or (M,) int
        The disk plus 2 px and the prediction's error must fit in it; for a coded target it must
        stay inside the ring's gap (below about twice the disk radius less 3 px).
    settings : DetectSettings
        ``window_px``, ``border_px`` and ``max_candidates`` are not used. With ``noise_dn`` (e.g.
        the last full frame's), the segmentation and contrast levels follow it as in
        :func:`detect_blobs`; without, they are ``min_contrast_dn``'s alone.

    Returns
    -------
    Blobs
        The measured disks.
    (M,) int
        Per window, the index of its disk in the blobs, or -1 when it holds no bright blob, when
        the blob touches the window's edge (the prediction was off: tell the caller), when the
        window leaves the image, or when the blob is saturated, too faint, too small or big, or
        misshapen (merged, notched, occluded).
    """
    img = _check_image(image)
    full, contrast, seg = _levels(img, settings)
    uv = np.asarray(uv_predicted, dtype=f64).reshape(-1, 2)
    half = np.broadcast_to(np.asarray(half_size_px, dtype=np.intp), (uv.shape[0],))
    if half.size and half.min() < 2:
        raise ValueError("half_size_px must be at least 2")
    finite = np.asarray(np.isfinite(uv).all(axis=1))
    c = np.rint(np.where(finite[:, None], uv, -1e6)).astype(np.intp).T.copy()  # rows cu, cv
    noise_dn = settings.noise_dn
    if noise_dn is not None and noise_dn > 0:
        seg, contrast = max(seg, K_SEG * noise_dn), max(contrast, K_PEAK * noise_dn)
    meas, placed = _measure_all(img, c[0], c[1], np.where(finite, half, 0), np.full(uv.shape[0], seg), full, None)
    wr, sigma, fill = _assess(meas, placed, settings, np.full(uv.shape[0], contrast))
    ok = ((wr < 0) & ~meas.edge & placed).nonzero()[0]
    found = np.full(uv.shape[0], -1, dtype=np.intp)
    found[ok] = np.arange(ok.size)
    return _blobs(meas, ok, sigma, fill), found
