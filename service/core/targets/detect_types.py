"""What blob detection takes and gives: :class:`DetectSettings`, :class:`Blobs`, :class:`Rejections`.

The settings and results of :mod:`service.core.targets.detect`, with the names of the reasons a
blob is rejected (:data:`REASONS`, and their codes), in a module of their own so that every stage
of the detection (background, candidates, window measurement) can use them below
:mod:`~service.core.targets.detect`, which puts the stages together. Callers import these names
from :mod:`~service.core.targets.detect`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Image = NDArray[np.uint8] | NDArray[np.uint16]  # a frame, once detect's image check has accepted it
DTYPE_MAX = {np.dtype(t).char: float(np.iinfo(t).max) for t in (np.uint8, np.uint16)}  # np.iinfo is slow per call

CENTRES = ("centroid", "edge")  # what a target's centre is measured as (DetectSettings.centre)
REASONS = ("saturated", "cut_off", "merged_or_misshapen", "too_small", "too_big", "low_contrast", "ring", "too_many")
SATURATED, CUT_OFF, MISSHAPEN, TOO_SMALL, TOO_BIG, LOW_CONTRAST, RING, TOO_MANY = range(len(REASONS))


@dataclass(frozen=True)
class DetectSettings:
    """Filters and options of blob detection; levels in 8-bit DN (see :mod:`service.core.targets.detect`)."""

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
    # what a target's centre is measured as: "edge" (the disk's ellipse fitted to its half-level edge:
    # service.core.targets.edge_centre) or "centroid" (intensity-weighted, in the window)
    centre: str = "edge"
    # None: disks with clipped pixels are measured and flagged saturated (see detect_windows);
    # a number: a disk with more pixels at the saturation level than this is rejected as saturated
    max_saturated_px: int | None = None

    def __post_init__(self) -> None:
        if self.max_saturated_px is not None and self.max_saturated_px < 0:
            raise ValueError(f"max_saturated_px must be 0 or more, not {self.max_saturated_px}")
        if self.centre not in CENTRES:
            raise ValueError(f"centre must be one of {', '.join(CENTRES)}, not {self.centre!r}")


@dataclass(frozen=True)
class Blobs:
    """Measured targets (N of them), in no particular order.

    uv : (N, 2) float, px -- background-corrected intensity-weighted centroid, or with
        ``DetectSettings.centre`` "edge" the centre of the ellipse fitted to the half-level edge
        (where that fit holds; else the centroid)
    ellipse : (N, 5) float -- u_c px, v_c px, a_px (semi-major), b_px (semi-minor), angle rad of the
        major axis from +u towards +v in (-pi/2, pi/2]: the disk's edge, blur removed
    sigma_px : (N,) float, px -- predicted standard deviation of each coordinate of ``uv``
    area_px : (N,) float, px^2 -- flux over plateau level: the area of the disk's image
    peak_dn, background_dn : (N,) float, DN -- brightest pixel; local background at the centre
    fill : (N,) float -- soft overlap of the blob with its ellipse (1: a perfect ellipse)
    has_ring : (N,) bool -- pieces of a coded target's ring were found around it (only these
        can be coded; :func:`~service.core.targets.detect.measure_windows` does not look and says False)
    saturated : (N,) bool -- its flat top is clipped at the saturation level (more than
        ``CLIPPED_PX`` pixels there): measured all the same, a sign that the exposure is too long
    light_gradient : (N, 2) float, 1/px -- the light's relative gradient across the disk (d ln L / du,
        d ln L / dv), fitted to every plateau of the frame, which the edge's half level followed;
        zeros with intensity centroids or where fewer than ``MIN_DISKS`` plateaus were seen
        (:mod:`service.core._kernels.illumination_kernel`)
    blur_px : (N,) float, px -- the blur's sigma the disk's second moments show beyond its own
        (optics, focus, the pixel's width: ~0.3 px for a sharp image)
    """

    uv: Array
    ellipse: Array
    sigma_px: Array
    area_px: Array
    peak_dn: Array
    background_dn: Array
    fill: Array
    has_ring: NDArray[np.bool_]
    saturated: NDArray[np.bool_]
    light_gradient: Array
    blur_px: Array

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def take(self, index: NDArray[np.intp]) -> Blobs:
        """The blobs at ``index`` (any numpy index), in that order."""
        return Blobs(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def join(self, other: Blobs) -> Blobs:
        """These blobs, then ``other``'s."""
        return Blobs(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)})


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
