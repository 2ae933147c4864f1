"""Sub-pixel measurement of bright targets in near-IR images (the paper, section 4.2).

:func:`detect_blobs` finds and measures every target in a full frame;
:func:`measure_windows` measures the targets in small windows around predicted
positions (ROI tracking). Both use one primitive over many windows
(:func:`~service.core.targets.detect_windows.measure_all`, a compiled loop in
:mod:`service.core._kernels.detect_kernel`).

Full frame, in three stages of a module each:

1. Background and noise (:mod:`~service.core.targets.detect_background`): the background is the
   image shrunk, blurred and opened; the noise is measured about it per tile. Foreground is
   brighter than the background by ``K_SEG`` noise sigmas, and by at least half of
   ``min_contrast_dn``.
2. Candidates (:mod:`~service.core.targets.detect_candidates`): the foreground's contours, less
   specks, huge, long and cut-off blobs, those not clearly above the noise, the faintest beyond
   ``max_candidates`` and the pieces of coded targets' rings, so the work per frame is bounded
   whatever the image holds.
3. Measurement in circular windows (:mod:`~service.core.targets.detect_windows`), one batch per
   window radius; a peak ``K_PEAK`` noise sigmas (and ``min_contrast_dn``) above the window's
   background is required. Each window gives a centre, an ellipse, shape tests and a precision
   ``sigma_px``.

This module puts them together and checks the input; the settings and results are in
:mod:`~service.core.targets.detect_types`, and are imported from here (:data:`__all__`).

Pixel convention (DESIGN section 2): the centre of the top-left pixel is (0, 0).
``min_contrast_dn`` is in 8-bit DN, scaled by ``full_scale / 255`` (the
saturation level, by default the dtype's maximum), so the defaults suit 8-,
12- and 16-bit images given their saturation level: a 12-bit camera's uint16 frames end at 4095
(``saturation_dn``; ``MeasureSettings.from_options(bit_depth=12)``, which the service sets from
the camera's pixel format).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core._kernels import kernel_array, kernel_vector
from service.core._kernels.detect_kernel import measure_predicted_kernel
from service.core.results import Reason, SolveError
from service.core.targets.detect_background import COARSE_STEP, K_SEG, estimate_background, foreground_mask
from service.core.targets.detect_candidates import find_candidates, misfits, window_radii
from service.core.targets.detect_types import (
    CUT_OFF,
    DTYPE_MAX,
    MISSHAPEN,
    REASONS,
    TOO_BIG,
    Blobs,
    DetectSettings,
    DetectWork,
    Image,
    Rejections,
)
from service.core.targets.detect_windows import (
    K_PEAK,
    assess,
    assess_constants,
    blobs_from,
    blobs_from_table,
    measure_all,
)

# the names callers import from here (the types are defined in detect_types)
__all__ = ["REASONS", "Blobs", "DetectSettings", "DetectWork", "Rejections", "detect_blobs", "measure_windows"]

f64 = np.float64
_DEFAULTS = DetectSettings()  # frozen: one instance is every call's default


def _check_image(image: NDArray[np.generic]) -> Image:
    img: Any = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise SolveError(
            Reason.bad_image, f"Expected a 2-D uint8 or uint16 image, got {img.dtype} of shape {img.shape}."
        )
    if min(img.shape) < 2 * COARSE_STEP:
        raise SolveError(Reason.bad_image, f"The image ({img.shape[1]} x {img.shape[0]} px) is too small.")
    return np.ascontiguousarray(img)


def _median(x: NDArray[np.float64]) -> float:
    """``np.median`` of ``x`` (no NaN), the same value without its overhead (~20 us a frame)."""
    srt = np.sort(x, axis=None)
    k = srt.size // 2
    return float(srt[k]) if srt.size % 2 else float(0.5 * (srt[k - 1] + srt[k]))


def _levels(img: Image, settings: DetectSettings) -> tuple[float, float, float]:
    """(saturation level, contrast threshold, segmentation level) in the image's DN."""
    full = float(DTYPE_MAX[img.dtype.char] if settings.saturation_dn is None else settings.saturation_dn)
    if not full > 0:
        raise ValueError(f"saturation_dn must be positive, got {settings.saturation_dn}")
    contrast = settings.min_contrast_dn * full / 255.0
    return full, contrast, 0.5 * contrast


def detect_blobs(
    image: NDArray[np.generic],
    settings: DetectSettings = _DEFAULTS,
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
    full, contrast, seg = _levels(img, settings)
    if mask_buffer is not None and (
        mask_buffer.shape != img.shape
        or mask_buffer.dtype != np.uint8
        or not mask_buffer.flags.c_contiguous
        or not mask_buffer.flags.writeable
    ):
        mask_buffer = None
    back = estimate_background(img, full, seg)
    cand = find_candidates(img, foreground_mask(img, back, mask_buffer), back, settings, contrast)
    ct, reason = cand.contours, cand.reason
    todo = (reason < 0).nonzero()[0]
    radius, own, limited = window_radii(ct, todo, cand.near, img.shape, settings.window_px)
    # blobs of no disk's shape are not measured; their windows' sizes still set those of their step
    fit = ~misfits(ct, todo)
    if not fit.all():
        reason[todo[~fit]] = MISSHAPEN
        todo, radius, own, limited = todo[fit], radius[fit], own[fit], limited[fit]
    tu, tv = ct.box_centre[todo, 0], ct.box_centre[todo, 1]
    meas, placed = measure_all(img, tu, tv, radius, back.at(back.seg, tu, tv), full, own, settings.centre == "edge")
    wr, sigma, fill = assess(meas, placed, settings, np.maximum(contrast, K_PEAK * back.at(back.noise, tu, tv)))
    # a blob reaching the window's rim is bigger than its window, or cut off where the border limits it
    wr = np.where(meas.edge | ~placed, np.where(limited, CUT_OFF, np.where(wr < 0, TOO_BIG, wr)), wr)
    reason[todo], centre = wr, ct.centre.copy()
    centre[todo] = np.where(np.isfinite(meas.uv), meas.uv, centre[todo])
    rej = (reason >= 0).nonzero()[0]
    ringed = np.zeros(reason.size, dtype=bool)
    ringed[cand.host_of[cand.host_of >= 0]] = True
    work = DetectWork(
        ct.area_px.size,
        cand.n_query,
        int(todo.size),
        cand.n_pairs,
        cand.n_visits,
        _median(back.tiles),
        float(back.tiles.max()),
    )
    blobs = blobs_from(meas, (wr < 0).nonzero()[0], sigma, fill, ringed[todo])
    return blobs, Rejections(reason[rej], ct.box[rej], centre[rej], work)


def measure_windows(
    image: NDArray[np.generic],
    uv_predicted: NDArray[np.float64],
    half_size_px: int | NDArray[np.intp],
    settings: DetectSettings = _DEFAULTS,
    own: NDArray[np.float64] | None = None,
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
        stay inside the ring's gap (below about twice the disk's minor semi-axis less 3 px), or
        the ring must be masked (``own``).
    settings : DetectSettings
        ``window_px``, ``border_px`` and ``max_candidates`` are not used. With ``noise_dn`` (e.g.
        the last full frame's), the segmentation and contrast levels follow it as in
        :func:`detect_blobs`; without, they are ``min_contrast_dn``'s alone.
    own : (M, 5) float, optional
        Per window, the disk's own region ``(x0, y0, Q_uu, Q_uv, Q_vv)``: ``x' Q x <= 1`` about
        (x0, y0) px from the window's centre; bright pixels outside it (a coded target's ring in an
        oblique view) are masked as the full frame masks a crowded window's neighbours
        (:func:`~service.core.targets.detect_windows.measure_all`). NaN rows: nothing masked.

    Returns
    -------
    Blobs
        The measured disks.
    (M,) int
        Per window, the index of its disk in the blobs, or -1 when it holds no bright blob, when
        the blob touches the window's edge (the prediction was off: tell the caller; a disk the
        image border cuts), or when the blob is saturated, too faint, too small or big, or
        misshapen (merged, notched, occluded). A window that would leave the image is made as
        large as the image allows (a whole disk near the border is measured, as in the full frame).
    """
    img = _check_image(image)
    full, contrast, seg = _levels(img, settings)
    uv = kernel_array(uv_predicted).reshape(-1, 2)
    half = kernel_vector(half_size_px, uv.shape[0], np.intp)
    if half.size and np.minimum.reduce(half) < 2:  # the ufunc's own reduce: np.min's wrapper cost ~3 us
        raise ValueError("half_size_px must be at least 2")
    noise_dn = settings.noise_dn
    if noise_dn is not None and noise_dn > 0:
        seg, contrast = max(seg, K_SEG * noise_dn), max(contrast, K_PEAK * noise_dn)
    # one compiled call (windows, assessment, the accepted ones' rows): ROI tracking's every frame
    masks = np.full((uv.shape[0], 5), np.nan) if own is None else kernel_array(np.reshape(own, (-1, 5)))
    if masks.shape[0] != uv.shape[0]:
        raise ValueError(f"own has {masks.shape[0]} rows for {uv.shape[0]} predictions")
    table, sigma, fill, found = measure_predicted_kernel(
        img, uv, half, seg, contrast, full, *assess_constants(settings), settings.centre == "edge", masks
    )
    return blobs_from_table(table, sigma, fill), found
