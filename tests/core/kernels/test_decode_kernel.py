"""The compiled code-ring reader (``service.core._kernels.decode_kernel``) against a NumPy reader.

The reference reads a ring the way ``service.core.targets.decode`` describes it, on whole arrays:
the pattern's points placed by the ellipse's affine map and sampled by ``cv2.remap`` (bilinear,
constant border), the disk and gap levels by ``np.median``, the gap noise from the median of
angular neighbours' differences, the ring's profile averaged over radii and halves, running
means of the mid-sample values as a sliding window, and every phase's sector levels, widest-gap
threshold and margin at once. Given the ellipse the kernel reports it used (the given one or its
re-fit), that reading must be the kernel's: code, bits, levels, margin, disk and background DN.
The scenes are the product's renderer's (``service.sim.render``), so the codes, the rolls and
the disks' true ellipses are known as well.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.core._kernels.decode_kernel import (
    BACKGROUND_DN,
    CONFIDENCE,
    DISK_DN,
    FIXED8,
    ROLL_DEG,
    ROUNDED,
    _may_have_ring,
    read_rings_kernel,
)
from service.core.targets import codes as C
from service.core.targets import decode as D
from tests.core.test_codes import _all_codes_field, _angle_diff_deg, _render_tilted

FAMILY = C.POSECELL12
LIMITS = dict(min_confidence=0.2, min_snr=8.0, min_minor_px=1.9, min_diameter_px=6.5, min_margin_snr=4.0)


def _kernel(image, e, bg=None, todo=None):
    """read_rings_kernel with read_codes' pattern, tables and limits (its defaults)."""
    L = D._layout(FAMILY)
    code_of, roll_of = C.family_word_table(FAMILY)
    limits = np.array(
        [*LIMITS.values(), D.MIN_AXIS_RATIO, D.MAX_GAP_SPREAD, D.MAX_SECTOR_LEVEL, D.SAME_SAMPLES_PX], dtype=np.float64
    )
    n = len(e)
    return read_rings_kernel(
        image,
        FIXED8 if image.dtype == np.uint8 else ROUNDED,
        np.ascontiguousarray(e, dtype=np.float64),
        np.ones(n, bool) if todo is None else todo,
        np.full(n, np.nan) if bg is None else bg,
        L.ring_pts,
        L.refine_pts,
        L.rho,
        D.EDGE_STEP,
        L.dirs,
        L.lo_index,
        L.lo_gamma,
        L.pts,
        L.n_disk,
        L.n_gap,
        len(FAMILY.ring_radii),
        FAMILY.n_bits,
        D.SAMPLES_PER_SECTOR,
        L.core_a,
        D.RUN,
        code_of,
        roll_of,
        0.3,
        limits,
    )


def _remap(image, e, pts):
    """The image at the ellipse's normalised points (cv2.remap, float32 maps as the kernel places
    them); NaN outside [0, W - 1] x [0, H - 1]."""
    ca, sa = np.cos(e[4]), np.sin(e[4])
    u = (e[0] + ca * e[2] * pts[:, 0] - sa * e[3] * pts[:, 1]).astype(np.float32)
    v = (e[1] + sa * e[2] * pts[:, 0] + ca * e[3] * pts[:, 1]).astype(np.float32)
    out = cv2.remap(image, u[None], v[None], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)[0].astype(np.float64)
    h, w = image.shape
    out[~((u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1))] = np.nan
    return out


def _read_reference(image, e, bg_given=np.nan):
    """(code, bits (K,) and levels (T, K) of the T tied best phases, in the target's order; margin,
    disk DN, background DN), or None."""
    K, S, run = FAMILY.n_bits, D.SAMPLES_PER_SECTOR, D.RUN
    pts, n_disk, n_gap = D._pattern(FAMILY)
    b_px, a_px = min(e[2], e[3]), max(e[2], e[3])
    if not (
        b_px >= LIMITS["min_minor_px"] and 2 * a_px >= LIMITS["min_diameter_px"] and b_px >= D.MIN_AXIS_RATIO * a_px
    ):
        return None
    vals = _remap(image, e, pts)
    if not np.all(np.isfinite(vals)):
        return None  # the pattern leaves the image
    disk, gap, ring = vals[:n_disk], vals[n_disk : n_disk + n_gap], vals[n_disk + n_gap :]
    disk_dn, gap_dn = np.median(disk), np.median(gap)
    bg = gap_dn if np.isnan(bg_given) else bg_given
    circles = gap.reshape(2, -1)  # the gap's two radii, the same angles
    noise = 1.4826 / np.sqrt(2) * np.median(np.abs(circles - np.roll(circles, 1, axis=1)))
    spread = np.ptp(circles.mean(axis=0))
    contrast = disk_dn - bg
    scale = contrast if contrast > 0 else 1.0
    noise = max(noise, 0.3)
    if not (contrast > LIMITS["min_snr"] * noise and spread / scale <= D.MAX_GAP_SPREAD):
        return None
    x = (ring.reshape(len(FAMILY.ring_radii), K * S) - bg) / scale  # radii x samples
    h = len(FAMILY.ring_radii) // 2
    run_means = []
    for half in (x[:h].mean(axis=0), x[h:].mean(axis=0)):
        mid = 0.5 * (half + np.roll(half, -1))
        windows = np.lib.stride_tricks.sliding_window_view(np.concatenate([mid, mid[: run - 1]]), run)
        run_means.append(windows.mean(axis=1))
    run_in, run_out = run_means
    j, k = np.arange(S)[:, None], np.arange(K)[None]
    i0, i1 = (j + S * k + round(D.SECTOR_CORE[0] * S)) % (K * S), (j + S * k + S // 2) % (K * S)
    parts = np.stack([run_in[i0], run_in[i1], run_out[i0], run_out[i1]])  # (4, phases, sectors)
    lv = parts.mean(axis=0)
    srt = np.sort(lv, axis=1)
    gi = np.argmax(np.diff(srt, axis=1), axis=1)
    thr = 0.5 * (srt[np.arange(S), gi] + srt[np.arange(S), gi + 1])
    bright = lv > thr[:, None]
    margin = np.where(bright, parts.min(axis=0), np.inf).min(axis=1) - np.where(
        ~bright, parts.max(axis=0), -np.inf
    ).max(axis=1)
    best = int(np.argmax(margin))
    # phases whose margins tie in exact arithmetic (8-bit samples, runs of equal values) differ by
    # round-off, which breaks the tie one way here and maybe the other in the kernel's running sums;
    # a tie across the phases' wrap reads the same code a sector further round
    tied = np.flatnonzero(margin >= margin[best] - 1e-12)
    code_of, roll_of = C.family_word_table(FAMILY)
    words = np.sum(bright.astype(np.int64) << np.arange(K), axis=1)
    code, roll = int(code_of[words[best]]), int(roll_of[words[best]])
    assert np.all(code_of[words[tied]] == code)
    bits, levels = bright[best], lv[best]
    good = (
        margin[best] >= LIMITS["min_confidence"]
        and margin[best] * contrast >= LIMITS["min_margin_snr"] * noise
        and 0.1 < thr[best] < 0.8
        and levels.max() <= D.MAX_SECTOR_LEVEL
        and code > 0
    )
    if not good:
        return None
    # target sector k was read as sector k + roll
    in_order = np.array([lv[t][(np.arange(K) + roll_of[words[t]]) % K] for t in tied])
    return code, bits[(np.arange(K) + roll) % K], in_order, margin[best], disk_dn, bg


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(20261126)
    field = _all_codes_field()
    frame, rows, ellipses, x_dir_deg = _render_tilted(field, 1000.0, rng.uniform(0, 55, len(field)), rng)
    return frame.image, field.codes[rows], ellipses, x_dir_deg


def _compare(image, truth, given, bg=None):
    ok, code, values, bits, levels, used = _kernel(image, given, bg)
    for i in np.flatnonzero(ok):
        ref = _read_reference(image, used[i], np.nan if bg is None else bg[i])
        assert ref is not None, f"target {i}: the kernel's reading fails every check in numpy"
        code_r, bits_r, levels_r, margin_r, disk_r, bg_r = ref
        assert code[i] == code_r == truth[i]
        np.testing.assert_array_equal(bits[i], bits_r)
        np.testing.assert_array_equal(bits[i], C.bits_of(int(code[i])))
        # the same samples (remap's, exactly, for 8 bits), sums of them in another order: one of
        # the tied phases' levels to round-off
        assert np.min(np.max(np.abs(levels_r - levels[i]), axis=1)) < 1e-12, i
        assert values[i, CONFIDENCE] == pytest.approx(margin_r, abs=1e-12)
        assert values[i, DISK_DN] == disk_r and values[i, BACKGROUND_DN] == bg_r
    return ok, values, used


def test_readings_are_the_numpy_reading_with_the_ellipse_used(scene):
    image, truth, ellipses, x_dir_deg = scene
    ok, values, used = _compare(image, truth, ellipses)
    assert ok.mean() > 0.97  # all but a steep one or two
    # the roll from the sector edges against the rendered target's +x direction (test_codes: 0.1 deg
    # on 18 px disks)
    roll_err = _angle_diff_deg(values[ok, ROLL_DEG], x_dir_deg[ok])
    assert np.sqrt(np.mean(roll_err**2)) < 0.5 and np.max(np.abs(roll_err)) < 2.0
    # the ellipse used is the disk's true image (cv2.fitEllipse of its projected rim) to ~0.1 px
    np.testing.assert_allclose(used[ok, :2], ellipses[ok, :2], rtol=0, atol=0.25)


def test_re_fit_recovers_a_poor_ellipse_and_is_read_as_numpy_reads_it(scene, rng):
    image, truth, ellipses, _ = scene
    # a contour fit's errors: 0.4 px off, 8 % small, turned by 3 deg
    poor = ellipses.copy()
    poor[:, :2] += rng.uniform(-0.4, 0.4, (len(poor), 2))
    poor[:, 2:4] *= 0.92
    poor[:, 4] += np.radians(3.0)
    ok, _, used = _compare(image, truth, poor)
    assert ok.mean() > 0.9
    refit = ok & np.any(used != poor, axis=1)
    assert refit.mean() > 0.5  # the re-fit was read (and taken) for most
    err_before = np.hypot(*(poor[refit, :2] - ellipses[refit, :2]).T)
    err_after = np.hypot(*(used[refit, :2] - ellipses[refit, :2]).T)
    assert np.median(err_after) < 0.5 * np.median(err_before)


def test_given_background_and_a_16_bit_image_read_the_same(scene):
    image, truth, ellipses, _ = scene
    sub = slice(0, 40)
    bg = np.full(40, 22.0)
    ok, values, _ = _compare(image, truth[sub], ellipses[sub], bg)
    assert ok.mean() > 0.9 and np.all(values[ok, BACKGROUND_DN] == 22.0)
    deep = image.astype(np.uint16) * 257
    ok16, code16, values16, _, levels16, used16 = _kernel(deep, ellipses[sub])
    for i in np.flatnonzero(ok16):
        code_r, _, levels_r, margin_r, disk_r, _ = _read_reference(deep, used16[i])
        # a 16-bit image is interpolated in floating point and rounded (cv2.remap in fixed point):
        # now and then 1 DN apart, i.e. 1 / contrast ~ 1e-4 of a level
        assert code16[i] == code_r == truth[i]
        assert np.min(np.max(np.abs(levels_r - levels16[i]), axis=1)) < 1e-3, i
        assert abs(values16[i, DISK_DN] - disk_r) <= 1 and values16[i, CONFIDENCE] == pytest.approx(margin_r, abs=1e-3)
    assert ok16.mean() > 0.9


def test_no_reading_where_numpy_finds_none(scene):
    image, truth, ellipses, _ = scene
    h, w = image.shape
    bad = ellipses[:8].copy()
    bad[0, :2] = [3.0, 3.0]  # the ring leaves the image at the top left ...
    bad[1, :2] = [w - 4.0, h / 2]  # ... and at the right border
    bad[2, 2:4] = [1.0, 1.0]  # too small to decode
    bad[3, 3] = 0.2 * bad[3, 2]  # too steep a view (b < MIN_AXIS_RATIO a)
    bad[4, :2] = [w / 2, 40.0]  # over background: no disk, no ring
    blank = image.copy()
    # an uncoded disk: a target whose ring is painted over with the background
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    e = bad[5]
    rr = np.hypot(u - e[0], v - e[1]) / max(e[2], e[3])
    blank[(rr > 1.5) & (rr < 4.0)] = np.median(image)
    ok, code, values, bits, levels, used = _kernel(blank, bad)
    for i in range(6):
        assert not ok[i] and _read_reference(blank, bad[i]) is None, i
        assert code[i] == 0 and np.all(np.isnan(values[i])) and not bits[i].any()
        np.testing.assert_array_equal(used[i], bad[i])  # no re-fit is kept without a reading
    assert ok[6:].all()
    # todo: only these; and no targets at all
    todo = np.zeros(8, bool)
    todo[7] = True
    assert np.flatnonzero(_kernel(image, ellipses[:8], todo=todo)[0]).tolist() == [7]
    empty = _kernel(image, np.zeros((0, 5)))
    assert [x.shape for x in empty] == [(0,), (0,), (0, 4), (0, 12), (0, 12), (0, 5)]


def test_ring_look_is_the_numpy_look_at_every_sample(scene, rng):
    """The cheap look for a ring (step 0; it ends at the first circle of the ring zone with a
    bright sample) answers as the brightest of all its samples does, by cv2.remap: coded targets,
    the same disks with their rings painted over, ellipses anywhere (most over background, some
    half outside the image) and ellipses whose disk is dimmer than the gap."""
    image, _, ellipses, _ = scene
    h, w = image.shape
    L = D._layout(FAMILY)
    blank = image.copy()
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    for e in ellipses[:20]:
        rr = np.hypot(u - e[0], v - e[1]) / max(e[2], e[3])
        blank[(rr > 1.5) & (rr < 4.0)] = np.median(image)
    anywhere = np.column_stack(
        [
            rng.uniform(-20, w + 20, 300),
            rng.uniform(-20, h + 20, 300),
            rng.uniform(2, 15, (300, 2)),
            rng.uniform(-np.pi, np.pi, 300),
        ]
    )
    cases = [(image, ellipses), (blank, ellipses[:40]), (image, anywhere), (blank, anywhere)]
    n_ring = n_none = 0
    for img, es in cases:
        for e in es:
            vals = _remap(img, e, L.ring_pts)
            disk, gap, ring = vals[0], np.median(vals[1:13]), vals[13:]
            ring = ring[np.isfinite(ring)]
            expected = bool(disk > gap and ring.size and ring.max() - gap > 0.25 * (disk - gap))
            got = _may_have_ring(
                img, FIXED8, np.ascontiguousarray(e), L.ring_pts, np.empty(len(L.ring_pts)), np.empty(12)
            )
            assert got == expected, e
            n_ring += expected
            n_none += not expected
    assert n_ring > 100 and n_none > 100  # both answers, many times
