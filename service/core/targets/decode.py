"""Reading the code ring of a coded target (see :mod:`service.core.targets.codes`) from a grey image.

The reader takes the code family as a parameter (:class:`~service.core.targets.codes.CodeFamily`):
posecell's own 12-bit ring (2.0-3.2 disk radii, the default) or the 14-bit ring of
AICON-style plates as MicMac MMVII reads them (2.0-3.0 R, :mod:`service.core.targets.codes_micmac`).
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

Steps, per target in one compiled loop (``read_codes`` calls
:func:`~service.core._kernels.decode_kernel.read_rings_kernel`; about 45 us per coded target, 1.4 ms
for a reference frame's 30; the former array expressions took 5.6 ms, the same readings):

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

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core._kernels import decode_kernel, warm_images
from service.core.targets.codes import POSECELL12, CodeFamily, family_word_table

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
# The re-fit is read on its own when it places every sample point within this many px of the given
# ellipse's (0: only when the two are the same ellipse, e.g. a re-fit that failed).
SAME_SAMPLES_PX = 0.0


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
    ring = np.concatenate([r * _unit_circle(family.n_bits * SAMPLES_PER_SECTOR, -1.0) for r in family.ring_radii])
    return np.concatenate([disk, gap, ring]), len(disk), len(gap)


@dataclass(frozen=True)
class _Layout:
    """A family's sample points and constants for :func:`~service.core._kernels.decode_kernel.read_rings_kernel`."""

    ring_pts: Array  # (1 + 12 + 3 * 48, 2): the disk's centre, the gap, the ring zone (a cheap look)
    refine_pts: Array  # (R * D, 2): radii x ray directions of the edge search
    rho: Array  # (R,) disk radii of the edge search
    dirs: Array  # (D, 2)
    lo_index: int  # np.percentile(..., 20)'s interpolation over the outer R * D samples
    lo_gamma: float
    pts: Array  # (P, 2): disk, gap, ring (see _pattern)
    n_disk: int
    n_gap: int
    core_a: int  # a sector core's first sample


EDGE_STEP = 0.1  # radii between the edge search's samples


@lru_cache(maxsize=4)
def _layout(family: CodeFamily) -> _Layout:
    r0, r1 = family.ring_inner + 0.2, family.ring_outer - 0.2
    ring_pts = np.concatenate(
        [
            np.zeros((1, 2)),
            1.5 * _unit_circle(12),
            r0 * _unit_circle(48),
            0.5 * (r0 + r1) * _unit_circle(48),
            r1 * _unit_circle(48),
        ]
    )
    # No further out than mid-gap, so that a ring squeezed against the disk by a steep view cannot
    # be taken for the disk's edge.
    rho = np.arange(0.4, 1.55, EDGE_STEP)
    dirs = _unit_circle(24)
    # the background level under the edge: the 20th percentile of the samples beyond 1.25 R, with
    # numpy's linear interpolation (virtual index n q + (1 - q) - 1)
    n_out, q = int(np.sum(rho > 1.25)) * len(dirs), np.true_divide(20, 100)
    virtual = n_out * q + (1 + q * (1 - 1 - 1)) - 1
    pts, n_disk, n_gap = _pattern(family)
    S = SAMPLES_PER_SECTOR
    a, b = (round(f * S) for f in SECTOR_CORE)
    assert b - S // 2 == S // 2 - a == RUN - 1  # the two halves of a core are runs of RUN samples
    return _Layout(
        ring_pts=ring_pts,
        refine_pts=(rho[:, None, None] * dirs[None]).reshape(-1, 2),
        rho=rho,
        dirs=dirs,
        lo_index=int(np.floor(virtual)),
        lo_gamma=float(virtual - np.floor(virtual)),
        pts=pts,
        n_disk=n_disk,
        n_gap=n_gap,
        core_a=a,
    )


def _check_ellipses(ellipses: ArrayLike) -> Array:
    e = np.asarray(ellipses, dtype=np.float64)
    if e.ndim == 1:
        e = e[None]
    if e.ndim != 2 or e.shape[1] != 5:
        raise ValueError(f"ellipses must be (N, 5) = (u_c, v_c, a_px, b_px, angle_rad), got shape {e.shape}")
    return e


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
        The ring code: posecell's own 12-bit family (:data:`~service.core.targets.codes.POSECELL12`,
        the default) or the AICON / MicMac 14-bit one (:data:`~service.core.targets.codes.AICON14`).
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
    # 8- and 16-bit images are read as they are (each its own compiled kernel); any other type as
    # float64, rounded like an integer image where it is one
    integer = img.dtype in (np.uint8, np.uint16, np.int16)
    if img.dtype == np.uint8:
        mode = decode_kernel.FIXED8
    elif img.dtype == np.uint16:
        mode = decode_kernel.ROUNDED
    else:
        img = img.astype(np.float64)
        mode = decode_kernel.ROUNDED if integer else decode_kernel.FLOAT
    e = _check_ellipses(ellipses)
    n = len(e)
    if n == 0:
        return []
    bg = np.full(n, np.nan)
    if background_dn is not None:
        bg[:] = np.broadcast_to(np.asarray(background_dn, dtype=np.float64), (n,))
    # A degenerate ellipse from the blob detector is read as "no code".
    valid = np.all(np.isfinite(e), axis=1) & (e[:, 2] > 0) & (e[:, 3] > 0)
    e = np.where(valid[:, None], e, np.array([0.0, 0.0, 1.0, 1.0, 0.0]))
    L = _layout(family)
    code_of, roll_of = family_word_table(family)
    # Integer images quantise weak noise to a zero spread; count at least the rounding error then.
    limits = np.array(
        [
            min_confidence,
            min_snr,
            min_minor_px,
            min_diameter_px,
            min_margin_snr,
            MIN_AXIS_RATIO,
            MAX_GAP_SPREAD,
            MAX_SECTOR_LEVEL,
            SAME_SAMPLES_PX,
        ],
        dtype=np.float64,
    )
    ok, codes, values, bits, levels, used = decode_kernel.read_rings_kernel(
        np.ascontiguousarray(img),
        mode,
        np.ascontiguousarray(e),
        valid,
        bg,
        L.ring_pts,
        L.refine_pts,
        L.rho,
        EDGE_STEP,
        L.dirs,
        L.lo_index,
        L.lo_gamma,
        L.pts,
        L.n_disk,
        L.n_gap,
        len(family.ring_radii),
        family.n_bits,
        SAMPLES_PER_SECTOR,
        L.core_a,
        RUN,
        code_of,
        roll_of,
        0.3 if integer else 0.0,
        limits,
    )
    out: list[CodeReading | None] = [None] * n
    K = decode_kernel
    values_py, codes_py = values.tolist(), codes.tolist()  # Python scalars in one go
    for i in np.flatnonzero(ok).tolist():
        v = values_py[i]
        out[i] = CodeReading(
            codes_py[i], v[K.ROLL_DEG], v[K.CONFIDENCE], bits[i], levels[i], v[K.DISK_DN], v[K.BACKGROUND_DN], used[i]
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
    return read_codes(
        image,
        [ellipse],
        None if background_dn is None else [background_dn],
        min_confidence=min_confidence,
        family=family,
    )[0]


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the reader's kernel for 8-bit, 16-bit and float images,
    writeable or not, with the background measured and given, so that no frame pays for it (each
    type ~10 s on one core). Cheap after the first call in a process."""
    for image in warm_images((np.uint8, np.uint16, np.float32), (48, 48)):
        if image.flags.writeable:  # its read-only view, next, shares the disk
            image[20:28, 20:28] = 200
        read_codes(image, [(23.5, 23.5, 4.0, 4.0, 0.0)])
        read_codes(image, [(23.5, 23.5, 4.0, 4.0, 0.0)], background_dn=[10.0])
