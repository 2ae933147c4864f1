"""Detection that adapts to the image: noise and background measured, work bounded whatever the frame holds.

Frames of two kinds: rendered by :mod:`service.sim.render` (read noise, hot spot, gradient), and
drawn by another route -- OpenCV's anti-aliased ellipses, area-averaged from 4x, on a textured,
noisy background with a ramp, a glow and printed labels (``cv2.putText``) -- so that the detector
is not tuned to our renderer alone. The work is counted (contours, candidates, measured windows,
neighbour pairs), never timed.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.core.targets.detect import DetectSettings, detect_blobs, measure_windows
from service.pipeline.measure import FrameMeasurer
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

#: an ordinary IR camera at some gain (issue #11): sigma 4 DN read noise, background 12 DN, peaks ~235 DN
NOISY = RenderSettings(read_noise_dn=4.0, background_dn=12.0, target_dn=220.0)


def render(settings: RenderSettings, seed: int = 3, **pose):
    return render_frame(
        reference_camera(), reference_field(), reference_pose(**pose), settings, np.random.default_rng(seed)
    )


def total_noise_dn(s: RenderSettings) -> float:
    """The renderer's background sigma: read noise, the background's shot noise and 8-bit rounding."""
    return float(np.sqrt(s.read_noise_dn**2 + s.background_dn / s.electrons_per_dn + 1.0 / 12.0))


def cv_drawn_frame(rng: np.random.Generator, shape=(1030, 1300), sub: int = 4):
    """Disks drawn by OpenCV on a textured background with labels; not our renderer.

    14 x 10 filled ellipses (semi-axes 3-12 px, b/a 0.5-1, any angle, 90-160 DN), drawn anti-aliased at
    ``sub`` x and area-averaged, blurred 0.7 px; the background: 10 DN, a woven texture (0-4 DN), blurred
    grain, a 25 DN ramp and a 45 DN glow; 40 printed labels (60 DN, at least 8 px from any disk); read
    noise 2 DN and shot noise. Returns the 8-bit image, the centres (N, 2) px and semi-axes (N, 2) px.
    """
    h, w = shape
    big = np.zeros((h * sub, w * sub), np.float32)
    centres, axes = [], []
    for y in np.linspace(80, h - 80, 10):
        for x in np.linspace(80, w - 80, 14):
            cx, cy = x + rng.uniform(-20, 20), y + rng.uniform(-20, 20)
            a = rng.uniform(3.0, 12.0)
            b = a * rng.uniform(0.5, 1.0)
            box = (((cx + 0.5) * sub - 0.5, (cy + 0.5) * sub - 0.5), (2 * a * sub, 2 * b * sub), rng.uniform(0, 180))
            cv2.ellipse(big, box, float(rng.uniform(90, 160)), -1, cv2.LINE_AA)
            centres.append((cx, cy))
            axes.append((a, b))
    image = cv2.GaussianBlur(cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA), (0, 0), 0.7)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    weave = 4.0 * (np.sin(u * 1.3 + v * 1.1) * np.sin(u * 0.9 - v * 1.2)) ** 2
    grain = 2.0 * cv2.GaussianBlur(rng.normal(0, 3, (h, w)).astype(np.float32), (0, 0), 1.2)
    glow = 45.0 * np.exp(-((u - 0.6 * w) ** 2 + (v - 0.4 * h) ** 2) / (2 * 180.0**2))
    labels = np.zeros((h, w), np.float32)
    occupied = np.zeros((h, w), np.uint8)
    for (cx, cy), (a, _) in zip(centres, axes, strict=True):
        cv2.circle(occupied, (int(cx), int(cy)), int(a + 8), 1, -1)
    k = 0
    while k < 40:
        text = f"P{rng.integers(100, 999)} X{k}"
        x0, y0 = int(rng.integers(20, w - 200)), int(rng.integers(30, h - 20))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        if not occupied[y0 - th - 2 : y0 + 4, x0 - 2 : x0 + tw + 2].any():
            cv2.putText(labels, text, (x0, y0), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 60.0, 1, cv2.LINE_AA)
            k += 1
    image = image + 10.0 + weave + grain + 25.0 * u / w + glow + labels
    image = image + rng.normal(0, 2.0, (h, w)) + rng.normal(0, 1.0, (h, w)) * np.sqrt(np.maximum(image, 0) / 10)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), np.array(centres), np.array(axes)


def with_sticker(frame, side_px: int = 56, level_dn: float = 150.0):
    """The frame with a bright square (a white sticker) inside the field, as far from its targets as
    can be; and the square's centre (u, v) + 1/2 px."""
    lo = frame.uv_disk_centroid.min(axis=0).astype(int) + 100
    hi = frame.uv_disk_centroid.max(axis=0).astype(int) - 100
    v, u = np.mgrid[lo[1] : hi[1] : 2, lo[0] : hi[0] : 2]
    gap = cKDTree(frame.uv_disk_centroid).query(np.column_stack([u.ravel(), v.ravel()]))[0]
    u0, v0 = u.ravel()[np.argmax(gap)], v.ravel()[np.argmax(gap)]
    sticker = np.zeros(frame.image.shape, dtype=np.float32)
    sticker[v0 - side_px // 2 : v0 + side_px // 2, u0 - side_px // 2 : u0 + side_px // 2] = level_dn
    image = np.clip(frame.image + cv2.GaussianBlur(sticker, (0, 0), 0.8), 0, 255).astype(np.uint8)
    return image, (u0, v0)


# -- noise and background --------------------------------------------------------


@pytest.mark.parametrize("read_noise_dn", [0.5, 2.0, 8.0])
def test_noise_is_measured_from_the_image(read_noise_dn):
    settings = RenderSettings(read_noise_dn=read_noise_dn, background_dn=12.0)
    _, rejected = detect_blobs(render(settings).image)
    expected = total_noise_dn(settings)
    # two-sided: the background's rounding to whole DN per 8 px cell adds a little
    assert 0.9 * expected < rejected.work.noise_dn < 1.15 * expected + 0.1
    assert rejected.work.noise_max_dn < 1.4 * expected + 0.2  # no tile thrown by the targets in it


def test_noisy_frame_is_measured_in_bounded_work():
    frame = render(NOISY)
    blobs, rejected = detect_blobs(frame.image)
    work = rejected.work
    # before: ~13 600 contours of noise and 1.4 million neighbour pairs within an 82 px radius
    assert work.n_contours < 400
    assert work.n_candidates < 350 and work.n_measured < 260
    assert work.n_pairs < 1000 and work.n_visits < 5000
    d, k = cKDTree(blobs.uv).query(frame.uv_disk_centroid)
    assert np.sum(d < 0.5) >= 225 and len(blobs) <= len(frame.ids)  # every disk but the odd saturated one
    err = blobs.uv[k[d < 0.5]] - frame.uv_disk_centroid[d < 0.5]
    predicted = np.sqrt(np.mean(blobs.sigma_px**2))
    assert 0.7 * predicted < np.sqrt(np.mean(err**2)) < 1.4 * predicted
    outcome = FrameMeasurer(reference_camera(), reference_field()).measure(frame.image)
    assert outcome.result.ok and outcome.result.n_coded >= 28, outcome.result


def test_a_frame_of_pure_noise_gives_nothing_to_measure():
    rng = np.random.default_rng(5)
    for image in (
        np.clip(rng.normal(40, 20, (1030, 1300)), 0, 255).astype(np.uint8),
        rng.integers(0, 256, (1030, 1300), dtype=np.uint8),
    ):
        blobs, rejected = detect_blobs(image)
        assert len(blobs) == 0
        # before: 30 000 contours, 50 million pairs and 1 140 windows for N(40, 20)
        assert rejected.work.n_contours < 50 and rejected.work.n_measured < 10 and rejected.work.n_pairs < 100


def test_the_measured_windows_are_capped_at_the_brightest():
    frame = render(RenderSettings())
    blobs, rejected = detect_blobs(frame.image, DetectSettings(max_candidates=100))
    assert rejected.work.n_measured == 100 and len(blobs) <= 100
    assert rejected.counts["too_many"] > 0
    # the kept ones are the brightest: the 10 mm coded disks (their peaks top the 6 mm ones')
    assert np.median(blobs.peak_dn) >= np.median(detect_blobs(frame.image)[0].peak_dn)


def test_hot_spot_gradient_and_noise_together_still_give_every_target():
    frame = render(
        RenderSettings(read_noise_dn=3.0, background_dn=12.0, hot_spot_dn=50.0, gradient_dn=30.0, exposure_scale=0.8)
    )
    blobs, rejected = detect_blobs(frame.image)
    d, _ = cKDTree(blobs.uv).query(frame.uv_disk_centroid)
    assert np.all(d < 0.5) and len(blobs) == len(frame.ids)
    assert rejected.work.n_contours < 400


# -- not our renderer ---------------------------------------------------------------


def test_opencv_drawn_disks_on_a_textured_labelled_background():
    image, centres, _ = cv_drawn_frame(np.random.default_rng(5))
    blobs, rejected = detect_blobs(image)
    d, k = cKDTree(blobs.uv).query(centres)
    assert np.all(d < 0.3), np.flatnonzero(d >= 0.3)  # every disk
    assert len(blobs) == len(centres)  # and nothing else: no glyph, speck or weave taken for a disk
    err = blobs.uv[k] - centres
    predicted = np.sqrt(np.mean(blobs.sigma_px**2))
    # the grain is correlated over pixels, which the predicted (white-noise) precision leaves out
    assert 0.7 * predicted < np.sqrt(np.mean(err**2)) < 2.0 * predicted
    assert np.all(np.abs(err.mean(axis=0)) < 0.02)
    assert rejected.work.n_measured < 2.5 * len(centres) and rejected.work.n_pairs < 5 * len(centres)


def test_glyphs_and_rings_are_not_taken_for_disks():
    # a disk's flux over its plateau is its ellipse's area; a printed "0" or a ring has a dim centre
    image = np.full((200, 400), 10, np.uint8)
    cv2.putText(image, "0 8 O", (20, 120), cv2.FONT_HERSHEY_SIMPLEX, 1.2, 200, 2, cv2.LINE_AA)
    cv2.circle(image, (320, 100), 12, 200, 3, cv2.LINE_AA)
    cv2.circle(image, (370, 100), 8, 200, -1, cv2.LINE_AA)
    blobs, _ = detect_blobs(cv2.GaussianBlur(image, (0, 0), 0.7))
    assert len(blobs) == 1 and np.allclose(blobs.uv[0], (370, 100), atol=0.1)


def test_glyphs_filling_too_little_of_their_ellipse_are_not_measured():
    # the "1" fills 0.84 of its moments' ellipse, the "2" and the "7" 0.6 (the disks beside them 1.0):
    # no window is measured for any of them (a "6" or a "9" this bold fills 0.97: the measurement's
    # shape tests reject those)
    image = np.full((120, 560), 10, np.uint8)
    cv2.putText(image, "1 2 7", (10, 80), cv2.FONT_HERSHEY_SIMPLEX, 1.2, 200, 3, cv2.LINE_AA)
    for u in (440, 480, 520):
        cv2.circle(image, (u, 60), 8, 200, -1, cv2.LINE_AA)
    blobs, rejected = detect_blobs(cv2.GaussianBlur(image, (0, 0), 0.7))
    assert len(blobs) == 3 and np.allclose(np.sort(blobs.uv[:, 0]), (440, 480, 520), atol=0.1)
    assert rejected.work.n_measured == 3  # the disks' windows only
    assert (rejected.reason == "merged_or_misshapen").sum() == 3


def test_dots_beside_a_bright_sticker_are_not_its_ring():
    # a white sticker (56 px square, as on real panels) passes for a disk; the dots round it, at 2-3
    # of its radii, are not pieces of its ring (they are narrower than any ring could be)
    frame = render(RenderSettings())
    image, (u0, v0) = with_sticker(frame)
    blobs, rejected = detect_blobs(image)
    d, _ = cKDTree(blobs.uv).query(frame.uv_disk_centroid)
    ring = np.linalg.norm(frame.uv_disk_centroid - (u0 - 0.5, v0 - 0.5), axis=1) < 3.2 * 32
    assert ring.sum() >= 4  # dots where the sticker's ring would be
    assert np.all(d < 0.5), np.array(frame.ids)[d >= 0.5]


def test_measure_windows_follows_the_given_noise():
    frame = render(NOISY)
    quiet, found_quiet = measure_windows(frame.image, frame.uv_disk_centroid, 12)
    noise = total_noise_dn(NOISY)
    loud, found = measure_windows(frame.image, frame.uv_disk_centroid, 12, DetectSettings(noise_dn=noise))
    # the rim's noise crosses 10 DN now and then, and such a window seemed crossed by a blob
    assert np.sum(found >= 0) >= np.sum(found_quiet >= 0) and np.sum(found >= 0) >= 220


def test_a_working_range_narrows_the_areas_to_the_targets_the_field_can_show():
    from service.pipeline.ranges import detect_settings_for_range

    camera, field = reference_camera(), reference_field()
    detect = detect_settings_for_range(DetectSettings(), field, camera, (800.0, 1300.0))
    # 6 mm dots at 1.3 m: radius 4.1 px; 10 mm coded disks at 0.8 m: 11.2 px
    assert 10 <= detect.min_area_px <= 20 and 600 <= detect.max_area_px <= 1000
    frame = render(RenderSettings())
    image, (u0, v0) = with_sticker(frame)  # 56 px square: bigger than any target at 0.8 m
    blobs, rejected = detect_blobs(image, detect)
    d, _ = cKDTree(blobs.uv).query(frame.uv_disk_centroid)
    assert np.all(d < 0.5) and len(blobs) == len(frame.ids)
    big = rejected.box[rejected.reason == "too_big"]  # the sticker, and long arcs of the coded rings
    assert np.any((big[:, 0] < u0) & (big[:, 2] > u0) & (big[:, 1] < v0) & (big[:, 3] > v0))
    with pytest.raises(ValueError):
        detect_settings_for_range(DetectSettings(), field, camera, (1300.0, 800.0))
