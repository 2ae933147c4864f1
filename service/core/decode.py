"""Reading the code ring of a coded target (see :mod:`service.core.codes`) from a grey image.

The reader takes the code family as a parameter (:class:`~service.core.codes.CodeFamily`):
posecell's own 12-bit ring (2.0-3.2 disk radii, the default) or the 14-bit ring of
AICON-style plates as MicMac MMVII reads them (2.0-3.0 R, :mod:`service.core.codes_micmac`).
Both number their sectors the same way round, so the same reading serves both; the
numbers below are for the 12-bit ring.

Input is the ellipse fitted to the image of the target's central disk. The map
from the target plane to the image is, to first order, the affine map that
takes the unit circle onto that ellipse, up to an unknown rotation (the
target's roll); that holds under perspective because the ring spans only a
few disk radii, so a 60 deg view still reads. With ``M = Rot(angle) @ diag(a, b)``
a target-plane point at radius ``r`` (in disk radii) and angle ``theta`` lands at::

    (u, v) = (u_c, v_c) + r * M @ (cos(phi - theta), sin(phi - theta))

``phi`` is the roll in the disk's normalised frame. The ``phi - theta`` (a
reflection) is there because the target is seen from its front: its local
``+x, +y, +z`` (z out of the face, towards the camera) appear in the image,
whose ``v`` runs down, as a mirror image. So the ring reads counter-clockwise
on a screen, the way the target's sectors are numbered. Reading it the other
way round would turn a non-palindromic code into another valid code.

Steps, for all targets at once (``read_codes``; about 0.18 ms per coded target in a batch of
30, about 6 ms for a reference frame's 200 blobs):

0. Look cheaply for anything bright in the ring zone. Uncoded blobs stop here.
1. Re-fit the disk ellipse to the disk's half-level edge along 24 rays, with a
   direct conic fit. Blur moves that edge inwards in proportion to its
   curvature, so the fit is done twice. The second pass pushes the edge
   points back by ``sigma^2 / 2`` times the curvature, with sigma estimated
   from the edge slope.
2. Read the ring with both ellipses, the given one and the re-fit, because
   each can be the worse one. A contour fit is off by a fraction of a
   pixel; a re-fit of a dim, noisy 8 px disk can turn by 10 deg.
3. Sample the disk, the dark gap (1.4..1.6 R) and the ring at radii
   2.3..2.9 R, clear of the ring's edges at 2.0 and 3.2 R (2.25..2.75 R for the
   14-bit ring's 2.0 and 3.0 R). Sampling uses 16 angles per sector, bilinear.
4. For each of the 16 sector phases, take each sector's level in four parts
   (inner/outer radii x first/second half of the sector's middle half) and
   normalise it to ``(level - background) / (disk - background)``. Split the
   12 (or 14) levels at their widest gap: an adaptive threshold that holds when blur
   dims isolated bright sectors. The margin is the darkest part of any
   bright sector minus the brightest part of any dark one. Keep the phase
   with the widest margin, look the word up in the code table, and get the
   sub-sample phase (for the roll) from the sector edges.

The result is ``None``, never a guess, when:

- the word is no code;
- the margin is below ``min_confidence``, or below ``min_margin_snr`` times the
  pixel noise;
- the gap is not dark all round (the ring is squeezed into it);
- a sector is far brighter than the disk (something else reaches into the ring);
- the disk is smaller than ``min_diameter_px``, or its minor semi-axis is
  smaller than ``min_minor_px``;
- the contrast is not clearly above the noise;
- the ring leaves the image;
- the two ellipses read different codes.

The family's minimum Hamming distance, under any rotation, is 2. A single bit
error gives an odd-weight word, which is no code, so it comes back as
``None`` and is never read as another code. Two bit errors can turn one code
into another; the margin and the geometric checks guard against that.

Measured on rendered images (``service.sim.render``), with 8-12 px disks seen
at 30-62 deg, 0.4-1.2 px of blur and disk contrasts of 10-200 DN: about
45,000 readings gave no wrong code, even with ``min_confidence`` at 0, and
2.6 % ``None``. Smaller disks (down to 6 px) and views up to 80 deg gave more
``None``, and still no wrong code.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.codes import POSECELL12, CodeFamily, family_word_table

Array = NDArray[np.float64]

SAMPLES_PER_SECTOR = 16
GAP_RADII = (1.4, 1.6)  # the dark annulus between disk and ring: the target's own background
DISK_RADII = (0.0, 0.3, 0.5)
# Part of each sector that is averaged: its middle half, well clear of phase and blur errors.
SECTOR_CORE = (0.25, 0.75)
RUN = 5  # samples averaged in each half of a sector's core (its ends included)
# Beyond a ~75 deg view (b/a = cos) the affine model and the ellipse angle become unreliable.
MIN_AXIS_RATIO = 0.25
# Largest brightness range round the gap annulus, in disk contrasts: within a 60 deg view it stays
# below ~0.45 even for 8 px disks; squeezed rings at 70+ deg push it above.
MAX_GAP_SPREAD = 0.5
# Brightest accepted sector, in disk contrasts. The ring is the disk's material, and blur only dims
# it: on MicMac's real AICON panel 1016 correct readings stayed below 1.2, while the one wrong
# reading found there (a bright neighbour reaching into the ring zone) had sectors at 1.86.
MAX_SECTOR_LEVEL = 1.5


@dataclass(frozen=True)
class CodeReading:
    """One decoded coded target.

    code : int, 1..family.n_codes (for the AICON family, the AICON number)
    roll_deg : float, deg
        The direction in the image of the target's local +x axis (the start of
        sector 0), counter-clockwise as displayed (from +u towards -v), in
        (-180, 180].
    confidence : float
        The contrast margin: the darkest part (quarter) of any bright sector
        minus the brightest part of any dark sector, as a fraction of the
        disk-to-background contrast. 1 is a perfect ring, 0 or less means no
        separation.
    bits : (n_bits,) bool
        The sectors as read, in the target's own sector order (equal to
        ``bits_of(code)``).
    levels : (n_bits,) float
        The normalised sector levels in the same order (0 = background, 1 = disk).
    disk_dn, background_dn : float
        The disk and background levels that were used, in image DN.
    ellipse : (5,) float
        The disk ellipse the reading used, ``(u_c, v_c, a_px, b_px, angle_rad)``:
        either the given one or the reader's re-fit to the disk edge.
    """

    code: int
    roll_deg: float
    confidence: float
    bits: NDArray[np.bool_]
    levels: Array
    disk_dn: float
    background_dn: float
    ellipse: Array


def _unit_circle(n: int, sign: float = 1.0) -> Array:
    t = np.arange(n) * (2 * np.pi / n)
    return np.stack([np.cos(sign * t), np.sin(sign * t)], axis=-1)


@lru_cache(maxsize=4)
def _pattern(family: CodeFamily) -> tuple[Array, int, int]:
    """Normalised sample points (P, 2) of disk, gap and ring; the sizes of the first two groups."""
    disk = np.concatenate([r * _unit_circle(8) for r in DISK_RADII])
    gap = np.concatenate([r * _unit_circle(24) for r in GAP_RADII])
    # Ring angle t runs with the target's theta, i.e. psi = -t in the normalised frame.
    ring = np.concatenate([r * _unit_circle(family.n_bits * SAMPLES_PER_SECTOR, -1.0)
                           for r in family.ring_radii])
    return np.concatenate([disk, gap, ring]), len(disk), len(gap)


@lru_cache(maxsize=4)
def _core_index(n_bits: int) -> NDArray[np.intp]:
    """Indices (S * K * 2,) into the 5-sample running means of the profile: the two halves of the
    core of every sector at every phase, ordered (phase, sector, half)."""
    S, K = SAMPLES_PER_SECTOR, n_bits
    a, b = (round(f * S) for f in SECTOR_CORE)
    assert b - S // 2 == S // 2 - a == RUN - 1
    idx = np.arange(S)[:, None, None] + S * np.arange(K)[None, :, None] + np.array([a, S // 2])
    return (idx % (S * K)).ravel()


def _check_ellipses(ellipses: ArrayLike) -> Array:
    e = np.asarray(ellipses, dtype=np.float64)
    if e.ndim == 1:
        e = e[None]
    if e.ndim != 2 or e.shape[1] != 5:
        raise ValueError(
            f"ellipses must be (N, 5) = (u_c, v_c, a_px, b_px, angle_rad), got shape {e.shape}")
    return e


def _affine(e: Array) -> Array:
    """M (N, 2, 2) = Rot(angle) @ diag(a, b): the unit circle onto each ellipse."""
    ca, sa = np.cos(e[:, 4]), np.sin(e[:, 4])
    M = np.empty((len(e), 2, 2))
    M[:, 0, 0], M[:, 0, 1] = ca * e[:, 2], -sa * e[:, 3]
    M[:, 1, 0], M[:, 1, 1] = sa * e[:, 2], ca * e[:, 3]
    return M


def _sample(img: NDArray[np.generic], e: Array, M: Array, pts: Array) -> Array:
    """Bilinear image values (N, P) at normalised points (P, 2) of each ellipse; NaN outside.

    ``cv2.remap`` is used because it is about ten times faster than ``map_coordinates`` here. It
    quantises positions to 1/32 px and rounds integer images to whole DN, which is far below
    what reading a ring needs.
    """
    # by broadcasting: a stack of (P, 2) @ (2, 2) products is slower
    u = (e[:, 0:1] + M[:, 0, 0:1] * pts[:, 0] + M[:, 0, 1:2] * pts[:, 1]).astype(np.float32)  # (N, P)
    v = (e[:, 1:2] + M[:, 1, 0:1] * pts[:, 0] + M[:, 1, 1:2] * pts[:, 1]).astype(np.float32)
    h, w = img.shape
    vals = cv2.remap(img, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    return np.where(inside, vals.astype(np.float64), np.nan)


def _ellipse_from_conic(coef: Array) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """Centre (N, 2), semi-axes (N, 2), axis angle (N,) and a valid mask (N,) of conics (N, 5).

    The conic is ``A x^2 + B xy + C y^2 + D x + E y = 1``.
    """
    A, B, C, D, E = coef.T
    Q = np.stack([np.stack([A, B / 2], -1), np.stack([B / 2, C], -1)], -2)  # (N, 2, 2)
    det = A * C - B * B / 4
    ok = det > 0
    Qs = np.where(ok[:, None, None], Q, np.eye(2))
    c = -0.5 * np.linalg.solve(Qs, np.stack([D, E], -1)[..., None])[..., 0]
    mu = 1.0 + 0.5 * (D * c[:, 0] + E * c[:, 1])  # 1 - c'Qc - b'c with c = -Q^-1 b / 2
    lam, V = np.linalg.eigh(Qs / np.where(mu > 0, mu, 1.0)[:, None, None])
    ok &= (mu > 0) & np.all(lam > 0, axis=1)
    axes = 1.0 / np.sqrt(np.where(lam > 0, lam, 1.0))
    angle = np.arctan2(V[:, 1, 0], V[:, 0, 0])
    return c, axes, angle, ok


def _row_median(x: Array) -> Array:
    """Median of the finite values of each row of ``x`` (N, D); NaN for a row without any."""
    srt = np.sort(np.where(np.isfinite(x), x, np.inf), axis=1)
    k = np.isfinite(x).sum(axis=1)
    rows = np.arange(len(x))
    lo, hi = np.maximum((k - 1) // 2, 0), np.maximum(k // 2, 0)
    with np.errstate(invalid="ignore"):
        med = 0.5 * (srt[rows, lo] + srt[rows, np.minimum(hi, x.shape[1] - 1)])
    return np.where(k > 0, med, np.nan)


def _fit_conic(pts_px: Array, weight: NDArray[np.bool_], size: Array
               ) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """Direct least-squares conic through the weighted points (N, D, 2), px, about a centre.

    Returns the centre offset (N, 2) px, semi-axes (N, 2) px, axis angle (N,) rad and a valid mask.
    """
    pts = pts_px / size[:, None, None]  # conditioning
    px, py = pts[..., 0], pts[..., 1]
    G = np.stack([px * px, px * py, py * py, px, py], -1) * weight[..., None]  # (N, D, 5)
    GtG = G.transpose(0, 2, 1) @ G
    # Rows with too few points are judged by the caller; keep their systems solvable.
    GtG += (1e-9 * np.trace(GtG, axis1=1, axis2=2) + 1e-12)[:, None, None] * np.eye(5)
    coef = np.linalg.solve(GtG, G.transpose(0, 2, 1) @ weight.astype(np.float64)[..., None])[..., 0]
    c, axes, angle, ok = _ellipse_from_conic(coef)
    return c * size[:, None], axes * size[:, None], angle, ok


def _refine_ellipse(img: NDArray[np.generic], e: Array) -> Array:
    """Re-fit each disk ellipse (N, 5) to the disk's half-level edge, found along 24 rays.

    An ellipse fitted to a pixel contour, or thresholded at another level, is
    off by a fraction of a pixel. On an 8 px disk that is 10-25 % of the
    radius, and a few degrees of axis angle on a foreshortened disk. The ring
    sits 2-3 radii out and is read in the disk's de-stretched frame, so both
    errors are magnified there. The edge points come from radial profiles
    normalised between the disk centre and the dark gap; a direct conic fit
    (corrected for blur, see below) goes through them. Where that fit is not
    trustworthy, only a common size offset is applied, or the input is kept.
    """
    n = len(e)
    M = _affine(e)
    step = 0.1
    # Search no further out than mid-gap, so that a ring squeezed against the disk by a steep view
    # cannot be taken for the disk's edge.
    rho = np.arange(0.4, 1.55, step)
    dirs = _unit_circle(24)
    vals = _sample(img, e, M, (rho[:, None, None] * dirs[None]).reshape(-1, 2))
    # A disk too close to the image border cannot be decoded anyway (its ring leaves the image).
    prof = np.nan_to_num(vals, nan=0.0).reshape(n, len(rho), len(dirs))  # (N, radius, direction)
    with np.errstate(invalid="ignore", divide="ignore"):
        hi = np.median(prof[:, 0], axis=1)
        lo = np.percentile(prof[:, rho > 1.25].reshape(n, -1), 20, axis=1)
        x = (prof - lo[:, None, None]) / (hi - lo)[:, None, None]
        below = x < 0.5
        i1 = np.argmax(below, axis=1)  # first sample below half level, per direction
        found = below.any(axis=1) & (i1 > 0)
        i1 = np.clip(i1, 1, len(rho) - 1)
        x0 = np.take_along_axis(x, (i1 - 1)[:, None, :], axis=1)[:, 0]
        x1 = np.take_along_axis(x, i1[:, None, :], axis=1)[:, 0]
        r50 = rho[i1 - 1] + step * (x0 - 0.5) / (x0 - x1)
    found &= np.isfinite(r50) & (hi > lo)[:, None]
    r50 = np.where(found, r50, 1.0)
    out = e.copy()

    # Direct conic fit to the edge points, in coordinates centred on the input ellipse and scaled
    # by its size (for conditioning); rays without an edge get zero weight.
    size = np.sqrt(e[:, 2] * e[:, 3])
    ray_px = dirs @ M.transpose(0, 2, 1)  # (N, D, 2): image offset per unit of rho along each ray
    rim_px = np.linalg.norm(ray_px, axis=2)
    c_px, axes_px, angle, ok = _fit_conic(r50[..., None] * ray_px, found, size)
    # Blur rounds the disk: the half-level contour of a blurred edge moves inwards by about
    # sigma^2 / 2 times its curvature (the heat equation's curvature flow), which shortens a
    # foreshortened disk's long axis. On an 8 px disk at 60 deg with 1 px of blur that is a
    # tenth of the axis, and it turns the ring's sectors. So estimate sigma from the edge slope,
    # push each edge point out by the flow, and fit again.
    with np.errstate(invalid="ignore", divide="ignore"):
        slope_px = (x0 - x1) / step / rim_px  # normalised level per px at the crossing
        var_px = np.where(found & (slope_px > 0), 1.0 / (2 * np.pi * slope_px**2), np.nan)
        sigma_px = np.sqrt(_row_median(var_px))
        rel = r50[..., None] * ray_px - c_px[:, None, :]
        ca, sa = np.cos(angle)[:, None], np.sin(angle)[:, None]
        u = (ca * rel[..., 0] + sa * rel[..., 1]) / axes_px[:, None, 0]
        v = (-sa * rel[..., 0] + ca * rel[..., 1]) / axes_px[:, None, 1]
        t = np.arctan2(v, u)
        A, B = axes_px[:, None, 0], axes_px[:, None, 1]
        kappa = A * B / (A**2 * np.sin(t) ** 2 + B**2 * np.cos(t) ** 2) ** 1.5
        shift = 0.5 * sigma_px[:, None] ** 2 * kappa / rim_px
    shift = np.where(np.isfinite(shift) & ok[:, None], np.minimum(shift, 0.5), 0.0)
    c_px, axes_px, angle, ok2 = _fit_conic((r50 + shift)[..., None] * ray_px, found, size)
    ok &= ok2
    ok &= found.sum(axis=1) >= 16
    b0 = np.minimum(e[:, 2], e[:, 3])
    # Trust the fit only near the input: an edge ray that ran into a neighbour must not drag it.
    ok &= (np.hypot(c_px[:, 0], c_px[:, 1]) < 0.5 * b0 + 0.5)
    ratio = np.sort(axes_px, axis=1) / np.sort(e[:, 2:4], axis=1)  # (minor, major) new / old
    ok &= (ratio[:, 0] > 0.6) & (ratio[:, 0] < 1.6) & (ratio[:, 1] > 0.75) & (ratio[:, 1] < 1.33)
    out[ok, :2] = e[ok, :2] + c_px[ok]
    out[ok, 2], out[ok, 3], out[ok, 4] = axes_px[ok, 0], axes_px[ok, 1], angle[ok]

    # Fallback: one common size offset (px) from the median edge distance.
    fb = ~ok & (found.sum(axis=1) >= 8)
    if np.any(fb):
        offset = np.where(found[fb], (r50[fb] - 1.0) * rim_px[fb], np.nan)
        delta = _row_median(offset)
        delta = np.where(np.abs(delta) < 0.5 * b0[fb], delta, 0.0)
        out[fb, 2] += delta
        out[fb, 3] += delta
    return out


def _measure(img: NDArray[np.generic], e: Array, background_dn: Array | None,
             family: CodeFamily) -> dict[str, Array]:
    """All intermediate arrays of the reading, for (N,) ellipses."""
    n = len(e)
    S, K = SAMPLES_PER_SECTOR, family.n_bits
    n_angles = K * S
    n_radii = len(family.ring_radii)
    M = _affine(e)
    pts, n_disk, n_gap = _pattern(family)
    vals = _sample(img, e, M, pts)
    inside = np.all(np.isfinite(vals), axis=1)
    vals = np.where(inside[:, None], vals, 0.0)
    disk_s = vals[:, :n_disk]
    gap_s = vals[:, n_disk:n_disk + n_gap]
    ring = vals[:, n_disk + n_gap:].reshape(n, n_radii, n_angles)

    disk_dn = np.median(disk_s, axis=1)
    gap_dn = np.median(gap_s, axis=1)
    bg_dn = gap_dn if background_dn is None else background_dn
    # Noise from differences of angular neighbours in the gap: blur leaks the disk and the ring into
    # the gap of a small target, which changes its level radially but hardly between neighbours.
    ring_gap = gap_s.reshape(n, len(GAP_RADII), -1)
    diffs = (ring_gap - np.roll(ring_gap, 1, axis=2)).reshape(n, -1)
    noise_dn = 1.4826 / np.sqrt(2) * np.median(np.abs(diffs), axis=1)
    gap_ang = ring_gap.mean(axis=1)
    contrast = disk_dn - bg_dn
    scale = np.where(contrast > 0, contrast, 1.0)
    profile_r = (ring - bg_dn[:, None, None]) / scale[:, None, None]  # (N, radius, K*S)
    profile = profile_r.mean(axis=1)  # sample j at t = j*dt

    # Sector levels for every phase on the sample grid (sector m of phase j starts at t = j + 0.5 +
    # m*S samples), each in four parts of the sector's core: inner/outer radii x first/second
    # half. A misplaced ring, or a sector smeared into its neighbour, makes the parts disagree.
    # (N, 2, K*S): inner and outer radii
    h = n_radii // 2
    prof2 = np.stack([profile_r[:, :h].mean(axis=1), profile_r[:, h:].mean(axis=1)], axis=1)
    mid = 0.5 * (prof2 + np.roll(prof2, -1, axis=2))  # value at t = i + 0.5 samples
    # Running means of RUN consecutive samples (wrapping round), then one gather for all phases.
    wrapped = np.concatenate([mid, mid[:, :, : RUN - 1]], axis=2)
    csum = np.concatenate([np.zeros((n, 2, 1)), np.cumsum(wrapped, axis=2)], axis=2)
    run_mean = (csum[:, :, RUN:] - csum[:, :, :-RUN]) / RUN  # (N, 2, K*S): mean of mid[i..i+RUN-1]
    part = run_mean[:, :, _core_index(K)].reshape(n, 2, S, K, 2)  # (N, radius, phase, K, half)
    part = part.transpose(0, 2, 3, 1, 4).reshape(n, S, K, 4)
    levels_all = part.mean(axis=3)  # (N, phase, K)

    # Adaptive threshold per phase: split the sorted levels at their widest gap. The margin lies
    # between the worst parts: the darkest part of any bright sector and the brightest part of any
    # dark one. The phase with the widest margin wins. Maximising the margin directly, not the edge
    # energy, keeps a blurred run of two sectors from being read half a sector off.
    srt = np.sort(levels_all, axis=2)
    g = np.argmax(np.diff(srt, axis=2), axis=2)[..., None]
    thr_all = 0.5 * (np.take_along_axis(srt, g, axis=2)
                     + np.take_along_axis(srt, g + 1, axis=2))[..., 0]
    bits_all = levels_all > thr_all[..., None]
    margin_all = (np.where(bits_all, part.min(axis=3), np.inf).min(axis=2)
                  - np.where(bits_all, -np.inf, part.max(axis=3)).max(axis=2))  # (N, phase)
    # A flat ring (all levels equal) puts every sector in one class: no margin at all.
    margin_all = np.where(np.isfinite(margin_all), margin_all, -1.0)
    rows = np.arange(n)
    j = np.argmax(margin_all, axis=1)
    levels, bits = levels_all[rows, j], bits_all[rows, j]
    margin, thr = margin_all[rows, j], thr_all[rows, j]
    # Sub-sample phase, for the roll only. The margin is flat near its best, so take the sector
    # edges instead: the edge between samples i and i+1 (at t = i + 0.5) folded onto one sector,
    # searched within a quarter sector of the chosen phase, then a parabola through the peak.
    edge = np.abs(np.roll(profile, -1, axis=1) - profile).reshape(n, K, S).sum(axis=1)  # (N, S)
    window = (j[:, None] + np.arange(-(S // 4), S // 4 + 1)[None, :]) % S
    best = np.argmax(np.take_along_axis(edge, window, axis=1), axis=1)
    jj = window[rows, best]
    em, e0, ep = edge[rows, (jj - 1) % S], edge[rows, jj], edge[rows, (jj + 1) % S]
    denom = em - 2 * e0 + ep
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(denom < 0, 0.5 * (em - ep) / np.where(denom < 0, denom, -1.0), 0.0)
    phase = j + 0.5 + (((jj - j + S // 2) % S) - S // 2) + np.clip(np.nan_to_num(frac), -0.5, 0.5)
    words = (bits.astype(np.int64) << np.arange(K)).sum(axis=1)
    code_of, roll_of = family_word_table(family)
    codes, rolls = code_of[words], roll_of[words]

    # Read sector m is the target's sector m - roll, whose start theta = (m - roll) * 360/K deg
    # lies at t = phase + m * S samples; theta = phi + t gives phi.
    phi = -(rolls * S + phase) * (2 * np.pi / n_angles)
    d = (M @ np.stack([np.cos(phi), np.sin(phi)], axis=-1)[..., None])[..., 0]
    roll_deg = np.degrees(np.arctan2(-d[:, 1], d[:, 0]))
    return {"inside": inside, "disk_dn": disk_dn, "background_dn": bg_dn, "noise_dn": noise_dn,
            "contrast": contrast, "levels": levels, "margin": margin, "threshold": thr,
            "bits": bits,
            "codes": codes, "rolls": rolls, "roll_deg": roll_deg, "phase": phase,
            "gap_spread": (gap_ang.max(axis=1) - gap_ang.min(axis=1)) / scale}


def read_codes(
    image: NDArray[np.generic],
    ellipses: ArrayLike,
    background_dn: ArrayLike | None = None,
    min_confidence: float = 0.2,
    min_snr: float = 8.0,
    min_minor_px: float = 1.9,
    min_diameter_px: float = 6.5,
    min_margin_snr: float = 4.0,
    family: CodeFamily = POSECELL12,
) -> list[CodeReading | None]:
    """Decode the code rings of many coded targets in one image (vectorised).

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float
        Grey image; targets bright on dark.
    ellipses : (N, 5) float
        The ellipse of each target's central disk, ``(u_c, v_c, a_px, b_px, angle_rad)``.
        ``a_px`` and ``b_px`` are semi-axes. ``a_px`` lies along ``angle_rad``,
        which is measured from +u towards +v, as OpenCV measures it. Which axis
        is called ``a`` does not matter. The reader also re-fits each
        ellipse to the disk's edge and reads the ring with both.
    background_dn : float or (N,) float, optional
        The dark level around each target, in DN. When it is not given, it is
        measured in the gap between the disk and the ring.
    min_confidence : float
        The smallest accepted margin between the darkest part of any bright
        sector and the brightest part of any dark sector, as a fraction of
        the disk-to-background contrast (``CodeReading.confidence``).
    min_snr : float
        The smallest disk-to-background contrast that is accepted, in units of
        the image noise measured in the gap (at least 0.3 DN in an integer image).
    min_minor_px, min_diameter_px : float, px
        The smallest minor semi-axis and long-axis diameter of the disk
        ellipse that are decoded. On smaller, blurred disks (less than 7.5 px
        across, or a minor semi-axis under 2 px) a run of two bright sectors
        can read as one, and the result is another valid code with a clear
        margin. A 60 deg view of an 8 px disk has a 2 px semi-axis. Blur
        shrinks the measured disk a little, hence the allowance.
    min_margin_snr : float
        The margin, in DN, must also be this many times the pixel noise. On a
        dim target, a margin of a fifth of the contrast lies within the noise.
    family : CodeFamily
        The ring code: posecell's own 12-bit family (:data:`~service.core.codes.POSECELL12`,
        the default) or the AICON / MicMac 14-bit one (:data:`~service.core.codes.AICON14`).
        A family with periodic words (14-bit codes of period 7) gives their roll
        only modulo the period.

    Returns
    -------
    list of CodeReading or None, length N
        ``None`` where the ring is not a code (a bit error), where a check
        fails (see the module docstring), or where the two ellipses read
        different codes.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be a 2-D grey image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.int16, np.float32, np.float64):
        img = img.astype(np.float32)
    e = _check_ellipses(ellipses)
    n = len(e)
    if n == 0:
        return []
    bg = None
    if background_dn is not None:
        bg = np.broadcast_to(np.asarray(background_dn, dtype=np.float64), (n,)).copy()
    # A degenerate ellipse from the blob detector is read as "no code", computed on a stand-in.
    valid = np.all(np.isfinite(e), axis=1) & (e[:, 2] > 0) & (e[:, 3] > 0)
    e = np.where(valid[:, None], e, np.array([0.0, 0.0, 1.0, 1.0, 0.0]))
    # The pipeline hands over every blob, most of them uncoded: a cheap look for any bright ring
    # first, so that the full reading runs only where there may be one.
    out: list[CodeReading | None] = [None] * n
    todo = np.flatnonzero(valid & _may_have_ring(img, e, family))
    if len(todo) == 0:
        return out
    readings = _read(img, e[todo], None if bg is None else bg[todo], min_confidence, min_snr,
                     min_minor_px, min_diameter_px, min_margin_snr, family)
    for i, reading in zip(todo, readings, strict=True):
        out[i] = reading
    return out


def _may_have_ring(img: NDArray[np.generic], e: Array, family: CodeFamily) -> NDArray[np.bool_]:
    """Whether anything in the ring zone is clearly brighter than the gap, per ellipse (N,).

    Generous on purpose: radii from 0.2 R inside the ring's inner edge to 0.2 R inside its outer
    edge (2.2-3.0 R for posecell's ring) cover ellipses that are 10-30 % off, and a quarter of
    the disk's contrast is far below a bright sector's level.
    """
    r0, r1 = family.ring_inner + 0.2, family.ring_outer - 0.2
    pts = np.concatenate([np.zeros((1, 2)), 1.5 * _unit_circle(12), r0 * _unit_circle(48),
                          0.5 * (r0 + r1) * _unit_circle(48), r1 * _unit_circle(48)])
    vals = _sample(img, e, _affine(e), pts)
    disk, gap, ring = vals[:, 0], np.median(vals[:, 1:13], axis=1), vals[:, 13:]
    with np.errstate(invalid="ignore"):
        ring_max = np.max(np.where(np.isfinite(ring), ring, -np.inf), axis=1)
        return (disk > gap) & (ring_max - gap > 0.25 * (disk - gap))


def _read(img: NDArray[np.generic], e: Array, bg: Array | None, min_confidence: float,
          min_snr: float, min_minor_px: float, min_diameter_px: float,
          min_margin_snr: float, family: CodeFamily) -> list[CodeReading | None]:
    """The full reading of :func:`read_codes` for valid ellipses (N, 5)."""
    n = len(e)
    # Read the ring twice: with the given ellipse and with its re-fit to the disk edge. Each can
    # be the worse one. A contour fit is off by a fraction of a pixel, while the re-fit of a dim,
    # noisy 8 px disk can turn by 10 deg. A reading counts when it passes every check, and the
    # two readings must not name different codes.
    e_fit = _refine_ellipse(img, e)
    both = np.concatenate([e, e_fit])
    # Integer images quantise weak noise to a zero spread; count at least the rounding error then.
    noise_floor_dn = 0.3 if np.issubdtype(img.dtype, np.integer) else 0.0
    r = _measure(img, both, None if bg is None else np.r_[bg, bg], family)
    b_px = np.minimum(both[:, 2], both[:, 3])
    a_px = np.maximum(both[:, 2], both[:, 3])
    good = (
        r["inside"]
        # Below this the ring is under 2 px wide across the minor axis and blur mixes its sectors.
        & (b_px >= min_minor_px)
        & (2 * a_px >= min_diameter_px)
        & (b_px >= MIN_AXIS_RATIO * a_px)
        & (r["contrast"] > min_snr * np.maximum(r["noise_dn"], noise_floor_dn))
        & (r["margin"] >= min_confidence)
        & (r["margin"] * r["contrast"]
           >= min_margin_snr * np.maximum(r["noise_dn"], noise_floor_dn))
        # The gap between disk and ring must be dark all round. Where blur and a steep view
        # squeeze the ring into it, the disk ellipse is too wide to place the ring.
        & (r["gap_spread"] <= MAX_GAP_SPREAD)
        # The threshold must split the ring into "like the gap" and "like the disk".
        & (r["threshold"] > 0.1) & (r["threshold"] < 0.8)
        # A sector far brighter than the disk is not the target's own ring.
        & (r["levels"].max(axis=1) <= MAX_SECTOR_LEVEL)
        & (r["codes"] > 0)
    )
    g_in, g_fit = good[:n], good[n:]
    code_in, code_fit = r["codes"][:n], r["codes"][n:]
    conflict = g_in & g_fit & (code_in != code_fit)
    # Of two agreeing readings, report the one with the wider margin.
    use_fit = g_fit & (~g_in | (r["margin"][n:] >= r["margin"][:n]))
    ok = (g_in | g_fit) & ~conflict
    pick = np.where(use_fit, n + np.arange(n), np.arange(n))
    r = {k: v[pick] for k, v in r.items()}
    e_fit = both[pick]
    # Target sector k was read as sector k + roll.
    own = (np.arange(family.n_bits)[None, :] + r["rolls"][:, None]) % family.n_bits
    bits = np.take_along_axis(r["bits"], own, axis=1)
    levels = np.take_along_axis(r["levels"], own, axis=1)
    out: list[CodeReading | None] = [None] * n
    for i in np.flatnonzero(ok):
        out[i] = CodeReading(
            code=int(r["codes"][i]),
            roll_deg=float(r["roll_deg"][i]),
            confidence=float(r["margin"][i]),
            bits=bits[i],
            levels=levels[i],
            disk_dn=float(r["disk_dn"][i]),
            background_dn=float(r["background_dn"][i]),
            ellipse=e_fit[i],
        )
    return out


def read_code(
    image: NDArray[np.generic],
    ellipse: tuple[float, float, float, float, float],
    background_dn: float | None = None,
    min_confidence: float = 0.2,
    family: CodeFamily = POSECELL12,
) -> CodeReading | None:
    """Decode one coded target; see :func:`read_codes` for the parameters.

    ``ellipse = (u_c, v_c, a_px, b_px, angle_rad)`` is the image of the central
    disk. The result is ``None`` unless the ring reads as a valid code with a
    margin of at least ``min_confidence``; the reader never guesses.
    """
    return read_codes(image, [ellipse], None if background_dn is None else [background_dn],
                      min_confidence=min_confidence, family=family)[0]
