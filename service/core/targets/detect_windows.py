"""Measurement of the one bright disk in each of many circular windows: the last stage of
:mod:`~service.core.targets.detect`, and all there is to :func:`~service.core.targets.detect.measure_windows`.

Windows are measured in one batch per window radius; a peak ``K_PEAK`` noise sigmas (and
``min_contrast_dn``) above the window's background is required. The work per window is compiled
(:mod:`service.core._kernels.detect_kernel`); here are what it returns (:class:`Measured`), the
limits it is judged by (:func:`assess`) and the :class:`~service.core.targets.detect_types.Blobs`
made of it.

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
- precision ``sigma_px``: pixel noise propagated through the centroid (:func:`measure_all`), with
  the shot noise measured on the targets' plateaus (unclipped ones);
- saturation: a disk whose flat top is clipped at the saturation level is measured all the same
  and flagged (:attr:`~service.core.targets.detect_types.Blobs.saturated`): clipping flattens a
  symmetric plateau symmetrically, so its centre holds (an overexposed sheet, 2-4 times full
  scale: centres 0.01-0.02 px from the truth, ``posecell bench independent``). With
  ``DetectSettings.max_saturated_px`` such disks are rejected instead (a sensor whose charge
  blooms along its columns).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from service.core._kernels import detect_kernel
from service.core._kernels.crowd_kernel import mask_windows_kernel
from service.core._kernels.detect_kernel import CLIPPED_PX, assess_kernel, measure_windows_kernel
from service.core.targets.detect_types import (
    LOW_CONTRAST,
    MISSHAPEN,
    SATURATED,
    TOO_BIG,
    TOO_SMALL,
    Array,
    Blobs,
    DetectSettings,
)

f32, f64 = np.float32, np.float64

# A target: its peak K_PEAK noise sigmas above its window's background (8 sigma: a textured
# background's brightest specks stay below; it is the 40 DN that flash-lit carbon panels needed by hand).
K_PEAK = 8.0
SHAPE_SIGMA = (3.0, 4.0)  # asymmetry and kurtosis may deviate this many times their noise ...
SHAPE_FLOOR = (0.015, 0.05)  # ... plus this (pixel sampling): px, and unitless
MIN_FLAT_TOP = 0.4  # a disk's own minor-axis variance exceeds 0.4 of the blurred blob's (0.7 at 2 px radius)
MIN_PLATEAU_B_PX = 2.5  # blobs narrower than this have no flat 3 x 3 centre for the shot noise
# A disk's flux over its plateau level is its ellipse's area (rendered and drawn disks: within 6 %;
# narrower than MIN_PLATEAU_B_PX, whose 3 x 3 centre is not flat, up to 1.7 times); printed glyphs and
# rings have dim centres and 9-60 times
MAX_AREA_RATIO = (1.3, 2.5)


@dataclass(frozen=True)
class Measured:
    """Per window (n), see :func:`measure_all`: centre (n, 2) px, ellipse (n, 5), flux S, plateau
    level and peak and background (DN), background noise variance sb2 (rim plane residual), shot
    noise per DN of level, centroid variance from background noise and per unit shot coefficient,
    the fill's mismatch (sum |blob - ellipse model| / level) and what background noise adds to it
    (px^2), the third central moments' squared norm, the kurtosis along the major axis and the
    blurred ellipse's, the disk's share of the minor-axis variance (the rest is blur), the
    variance along the major axis, the window's sums (n, 7), the edge fit's centre and sigma
    (:mod:`~service.core.targets.edge_centre`), saturated pixels, rim crossed."""

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
    edge_uv: Array  # (n, 2) px: the centre fitted to the disk's edge, NaN where not asked or not held
    edge_sigma: Array
    light_gradient: Array  # (n, 2) 1/px: the light's relative gradient the edge's level followed; 0 without
    blur: Array  # px^2: the blur's variance beyond the disk's own
    n_sat: NDArray[np.intp]  # pixels at the saturation level
    edge: NDArray[np.bool_]
    table: Array  # (NF, n): the kernel's output, whose rows the fields above are


def measure_all(
    img: NDArray[np.generic],
    cu: NDArray[np.intp],
    cv: NDArray[np.intp],
    radius: NDArray[np.intp],
    seg_dn: Array,
    full_dn: float,
    own: Array | None,
    edge_fit: bool = False,
) -> tuple[Measured, NDArray[np.bool_]]:
    """Measure the blob in the circle of radius ``radius + 1/2`` px about each (cu, cv), with the
    segmentation level ``seg_dn`` (n,) DN above the background of each window. ``own`` (n, 5):
    rows (x0, y0, Q_uu, Q_uv, Q_vv), the blob's own region ``x' Q x <= 1`` about (x0, y0) from the
    window centre, NaN where nothing else is near. In those crowded windows, bright pixels outside
    the region and a 3 px band around them (their blur tail) take the rim's lower quartile (the
    rim may cross the other blob): :func:`~service.core._kernels.crowd_kernel.mask_windows_kernel`. The
    work per window is :func:`~service.core._kernels.detect_kernel.measure_windows_kernel`; with
    ``edge_fit`` it also fits each disk's edge, on the image (unmasked).

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
    out, n_sat, edge = measure_windows_kernel(img, cu, cv, radius, placed, seg_dn, float(full_dn), buf, boff, edge_fit)
    K = detect_kernel
    return Measured(
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
        edge_uv=out[K.EDGE_UV : K.EDGE_UV + 2].T,
        edge_sigma=out[K.EDGE_SIGMA],
        light_gradient=out[K.LIGHT : K.LIGHT + 2].T,
        blur=out[K.BLUR],
        n_sat=n_sat,
        edge=edge,
        table=out,
    ), placed


def assess(
    meas: Measured, usable: NDArray[np.bool_], settings: DetectSettings, contrast_dn: Array
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
        *assess_constants(settings),
    )


@lru_cache(maxsize=8)
def assess_constants(settings: DetectSettings) -> tuple[Array, NDArray[np.intp]]:
    """The limits and reason codes :func:`~service.core._kernels.detect_kernel.assess_kernel` takes."""
    limits = np.array(
        [
            settings.min_area_px,
            settings.max_area_px,
            settings.max_aspect,
            settings.min_fill,
            np.inf if settings.max_saturated_px is None else settings.max_saturated_px,
            MIN_PLATEAU_B_PX,
            MIN_FLAT_TOP,
            *SHAPE_SIGMA,
            *SHAPE_FLOOR,
            *MAX_AREA_RATIO,
        ],
        dtype=f64,
    )
    return limits, np.array([SATURATED, LOW_CONTRAST, TOO_SMALL, TOO_BIG, MISSHAPEN], dtype=np.intp)


def blobs_from(
    meas: Measured, index: NDArray[np.intp], sigma: Array, fill: Array, has_ring: NDArray[np.bool_] | None = None
) -> Blobs:
    """The windows at ``index`` as :class:`Blobs`, with their ``sigma`` and ``fill`` from :func:`assess`;
    the centre (the ellipse's too) and sigma are the edge fit's where it was asked for and held."""
    held = np.isfinite(meas.edge_sigma[index])
    uv = np.where(held[:, None], meas.edge_uv[index], meas.uv[index])
    ellipse = meas.ellipse[index]
    ellipse[:, :2] = uv
    return Blobs(
        uv=uv,
        ellipse=ellipse,
        sigma_px=np.where(held, meas.edge_sigma[index], sigma[index]),
        area_px=meas.flux[index] / meas.level[index],
        peak_dn=meas.peak[index],
        background_dn=meas.background[index],
        fill=fill[index],
        has_ring=np.zeros(index.size, dtype=bool) if has_ring is None else has_ring[index],
        saturated=meas.n_sat[index] > CLIPPED_PX,
        light_gradient=meas.light_gradient[index],
        blur_px=np.sqrt(meas.blur[index]),
    )


def blobs_from_table(table: Array, sigma: Array, fill: Array) -> Blobs:
    """The accepted windows as :class:`Blobs`: their rows (NF, k) of the measurement table (views of
    it, no copies; the centres already the edge fit's where asked for), with their ``sigma`` and ``fill``
    (:func:`~service.core._kernels.roi_kernel.measure_predicted_kernel`)."""
    K = detect_kernel
    return Blobs(
        uv=table[K.UV : K.UV + 2].T,
        ellipse=table[K.ELLIPSE : K.ELLIPSE + 5].T,
        sigma_px=sigma,
        area_px=table[K.FLUX] / table[K.LEVEL],
        peak_dn=table[K.PEAK],
        background_dn=table[K.BACKGROUND],
        fill=fill,
        has_ring=np.zeros(sigma.size, dtype=bool),
        saturated=table[K.N_SAT] > CLIPPED_PX,
        light_gradient=table[K.LIGHT : K.LIGHT + 2].T,
        blur_px=np.sqrt(table[K.BLUR]),
    )
