"""The full frame's candidate targets: the second stage of :mod:`~service.core.targets.detect`.

External contours of the foreground (OpenCV's ``findContours`` border following, compiled in
:mod:`service.core._kernels.trace_kernel`; 3x faster than labelling with statistics) and their
polygon moments (Green's theorem) reject specks, huge blobs, long ones and blobs at the image
border; then, before any window is measured, those whose brightest pixel is not clearly above the
noise, and, beyond ``max_candidates``, the faintest. Only then are the pieces of coded targets'
rings looked for (:func:`neighbours`), each candidate within its own radius. So the work per frame
is bounded whatever the image holds: a frame of pure noise gives next to no foreground, a textured
one many specks that cost one pass each. The work per contour, pair and crowded window is compiled
(:mod:`service.core._kernels.contour_kernel`, :mod:`service.core._kernels.crowd_kernel`).

What it gives (:class:`Candidates`) is every thresholded blob with the reason it was dropped, or
-1 for the ones to measure, and :func:`window_radii` the windows they are measured in: the
measurement itself (:mod:`~service.core.targets.detect_windows`) knows nothing of contours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core._kernels.contour_kernel import classify_kernel, contour_stats_kernel, windows_kernel
from service.core._kernels.crowd_kernel import neighbours_kernel
from service.core._kernels.noise_kernel import box_peak_kernel
from service.core._kernels.trace_kernel import external_contours_kernel, words_of
from service.core.targets.codes import RING_INNER, RING_OUTER
from service.core.targets.detect_background import Background
from service.core.targets.detect_types import (
    CUT_OFF,
    LOW_CONTRAST,
    MISSHAPEN,
    RING,
    TOO_BIG,
    TOO_MANY,
    TOO_SMALL,
    Array,
    DetectSettings,
    Image,
)
from service.core.targets.detect_windows import K_PEAK

# Before measuring, EARLY_CONTRAST of the measurement's K_PEAK noise sigmas against the box's
# brightest pixel, so that no candidate the measurement would keep is dropped.
EARLY_CONTRAST = 0.8
HOSTS_PER_CANDIDATE = 4  # a host's search for its ring costs a small part of a measured window
MIN_PIECE_HALF = 0.4  # a disk-like ring piece's radial half extent, host radii (a ring 1 radius wide: 0.58)
MIN_POLYGON_FILL = 0.9  # contour area over its moments' ellipse area; below: a long arc or merged blob
# Below this fill a blob is not measured at all (misshapen): no disk at any view angle, blurred or
# noisy, fills so little (rendered targets in every bench condition: 0.96 and more). Printed text's
# glyphs are the blobs it spares measuring, and masking their crowded windows: 0.24 of 1.3 ms there.
MIN_MEASURED_FILL = 0.5
# A blob of LARGE_BLOB_PX or more has a polygon smooth enough to ask more of it (a small one's is
# coarse: a 3 px dot's is a diamond). Of such blobs filling 0.5-0.85 the measurement accepted none in
# 33 rendered frames of every bench condition, nor in the 20 real panel images save one speck that
# named no target (they are glyphs, stickers' edges, targets half hidden: 6-12 a real image, 20-30 a
# frame with printed labels); skipping them saves ~0.2 ms of windows on both. A target run into
# printed text (once 0.74) is left out with them: its centroid would carry the text.
LARGE_BLOB_PX = 40
MIN_MEASURED_FILL_LARGE = 0.85
WINDOW_MARGIN_PX = 2  # window radius beyond the thresholded blob, so the rim clears its blur tail
# Steps of window radius: the windows within one step are measured together, at its largest radius.
WINDOW_RADII = (4, 6, 8, 10, 12, 15, 18, 22, 27, 33, 40, 48, 58, 70, 84, 100, 120, 150)
_RADII = np.array(WINDOW_RADII, dtype=np.intp)


@dataclass(frozen=True)
class Contours:
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


def contours(mask: NDArray[np.uint8]) -> Contours:
    """Boxes, areas and polygon moments of the external contours of the 0/255 ``mask`` (compiled:
    OpenCV's ``findContours`` with ``RETR_EXTERNAL`` and ``CHAIN_APPROX_SIMPLE``, written out in
    :func:`~service.core._kernels.trace_kernel.external_contours_kernel`, then Green's theorem over
    each closed polygon, relative to its first vertex, in one pass over the vertices).

    ``mask`` is consumed: the tracing marks the borders in it (a C-contiguous, writeable uint8
    mask is traced in place; any other is converted to a 0/255 copy first, nonzero as foreground)."""
    if not (mask.flags.c_contiguous and mask.flags.writeable and mask.dtype == np.uint8):
        mask = np.where(np.asarray(mask) != 0, np.uint8(255), np.uint8(0))
    pts, starts, lengths = external_contours_kernel(mask, words_of(mask))
    if not lengths.size:
        z2, z = np.zeros((0, 2), np.intp), np.zeros(0)
        return Contours(np.zeros((0, 4), np.intp), z, z, np.zeros((0, 2)), np.zeros((0, 3)), z2, np.zeros(0, np.intp))
    return Contours(*contour_stats_kernel(pts, starts, lengths))


def neighbours(
    ct: Contours,
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


def brightest(which: NDArray[np.bool_], bright: Array, k: int) -> NDArray[np.bool_]:
    """``which`` less all but the ``k`` brightest of it."""
    idx = which.nonzero()[0]
    if idx.size <= k:
        return which
    out = np.zeros_like(which)
    out[idx[np.argsort(-bright[idx], kind="stable")[:k]]] = True
    return out


@dataclass(frozen=True)
class Candidates:
    """The full frame's thresholded blobs (C of them) and what became of them before measurement.

    contours : Contours -- their boxes, areas and moments
    reason : (C,) int -- index into :data:`~service.core.targets.detect_types.REASONS` of those
        rejected already, -1 for those to measure (the caller's to fill in with the measurement's)
    host_of : (C,) int -- the host whose coded ring each is a piece of, -1 for none
    near : (C,) float, px -- for the queried candidates, the distance from the box centre to the
        nearest thresholded pixel of another blob (:func:`neighbours`), inf for the others
    n_query -- candidates searched for neighbours; n_pairs, n_visits -- the pair search's work
    """

    contours: Contours
    reason: NDArray[np.intp]
    host_of: NDArray[np.intp]
    near: Array
    n_query: int
    n_pairs: int
    n_visits: int


def find_candidates(
    img: Image, mask: NDArray[np.uint8], back: Background, settings: DetectSettings, contrast_dn: float
) -> Candidates:
    """The blobs of the foreground ``mask`` (H, W) 0/255 of ``img``, each rejected with a reason
    or to be measured (see the module docstring); ``contrast_dn`` is the least peak contrast, DN.
    ``mask`` is consumed (see :func:`contours`)."""
    height, width = img.shape
    ct = contours(mask)
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
    need = np.maximum(contrast_dn, K_PEAK * back.at(back.noise, ct.box_centre[idx, 0], ct.box_centre[idx, 1]))
    look = idx if idx.size > settings.max_candidates else idx[need > contrast_dn]
    bright = np.full(n, np.inf)
    bright[look] = box_peak_kernel(img, box, look) - back.at(back.level, ct.box_centre[look, 0], ct.box_centre[look, 1])
    faint = np.zeros(n, dtype=bool)
    faint[idx] = bright[idx] < EARLY_CONTRAST * need
    # the hosts claim their rings' pieces, then the rest are measured. A bound on the work whatever
    # the image: at most max_candidates measured, the brightest, and HOSTS_PER_CANDIDATE times as many
    # searched for neighbours (short arcs of rings are candidates too, until a host claims them)
    query = brightest(cand & ~faint, bright, HOSTS_PER_CANDIDATE * settings.max_candidates)
    host_of, near, n_pairs, n_visits = neighbours(ct, a, host & query, disk_like, query, img.shape)
    rest = query & ~cut & (host_of < 0)
    measured = brightest(rest, bright, settings.max_candidates)
    # the first reason that holds of: cut off, too small, too big, a ring piece, misshapen, faint,
    # beyond the bound; written last to first, so the first overwrites (np.select's 17 us, in 8)
    reason = np.full(n, -1, dtype=np.intp)
    reason[~query | (rest & ~measured)] = TOO_MANY
    reason[faint] = LOW_CONTRAST
    reason[long] = MISSHAPEN
    reason[host_of >= 0] = RING
    reason[big] = TOO_BIG
    reason[small] = TOO_SMALL
    reason[cut] = CUT_OFF
    return Candidates(ct, reason, host_of, near, int(query.sum()), n_pairs, n_visits)


def misfits(ct: Contours, idx: NDArray[np.intp]) -> NDArray[np.bool_]:
    """Whether each blob ``idx`` fills less than MIN_MEASURED_FILL (MIN_MEASURED_FILL_LARGE from
    LARGE_BLOB_PX on) of the uniform ellipse of its polygon's moments (a glyph, an arc, blobs merged
    into a crooked shape: none is a disk)."""
    mu = ct.mu[idx]
    half_tr, root = 0.5 * (mu[:, 0] + mu[:, 2]), np.sqrt(0.25 * (mu[:, 0] - mu[:, 2]) ** 2 + mu[:, 1] ** 2)
    ab = 4.0 * np.sqrt((half_tr + root) * np.maximum(half_tr - root, 0.0))  # a b of the semi-axes
    least = np.where(ct.area_px[idx] >= LARGE_BLOB_PX, MIN_MEASURED_FILL_LARGE, MIN_MEASURED_FILL)
    return np.asarray(ct.poly_area[idx] < least * np.pi * ab)


def window_radii(
    ct: Contours, todo: NDArray[np.intp], near: Array, shape: tuple[int, int], window_px: int
) -> tuple[NDArray[np.intp], Array, NDArray[np.bool_]]:
    """Window radius of each blob to measure, its own region for
    :func:`~service.core.targets.detect_windows.measure_all` where another blob reaches into the
    window (its thresholded ellipse + 1.5 px; NaN rows elsewhere), and whether the image border
    limits the window. A window holds the thresholded blob plus
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
