"""Sub-pixel target measurement (paper section 4.2) on rendered IR frames with ground truth.

Frames come from :mod:`service.sim.render` (seeded noise, blur, anti-aliasing,
exact perspective and distortion); the truth is each disk's area centroid in
the image. The reference frame is DESIGN section 7's: 30 coded and 200
uncoded targets, head-on at 1 m (disks of 5.4 and 9 px radius).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.core.geometry.frames import apply_T, inv_T
from service.core.results import Reason, SolveError
from service.core.targets.detect import REASONS, Blobs, DetectSettings, detect_blobs, measure_windows
from service.core.targets.field import Field
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

SEED = 20261125


def render(settings: RenderSettings | None = None, pose=None, field=None, seed: int | None = SEED):
    rng = None if seed is None else np.random.default_rng(seed)
    return render_frame(
        reference_camera(),
        reference_field() if field is None else field,
        reference_pose() if pose is None else pose,
        settings or RenderSettings(),
        rng,
    )


def match(blobs: Blobs, uv_true: np.ndarray, tol_px: float = 0.5) -> np.ndarray:
    """Index of the blob measured at each true centre, -1 if none is within ``tol_px``."""
    if len(blobs) == 0:
        return np.full(len(uv_true), -1)
    d, i = cKDTree(blobs.uv).query(uv_true)
    return np.where(d < tol_px, i, -1)


def disk_axes_px(frame, field: Field) -> np.ndarray:
    """Semi-axes a, b and angle (N, 3) of each disk's image: the uniform ellipse with the second
    moments of its outline, projected through the camera model (perspective and distortion)."""
    phi = np.linspace(0.0, 2.0 * np.pi, 96, endpoint=False)
    idx = field.indices_of(list(frame.ids))
    r = field.diameters_mm[idx, None] / 2.0
    rim = field.xyz[idx, None, :] + np.stack([r * np.cos(phi), r * np.sin(phi), 0.0 * r * phi], axis=-1)
    uv = reference_camera().pixel_from_camera(apply_T(inv_T(frame.T_field_camera), rim.reshape(-1, 3)))
    x, y = (uv.reshape(len(idx), -1, 2) - frame.uv_disk_centroid[:, None, :]).transpose(2, 0, 1)
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = cross.sum(axis=1) / 2.0
    uu = ((x * x + x * x1 + x1 * x1) * cross).sum(axis=1) / (12.0 * area)
    vv = ((y * y + y * y1 + y1 * y1) * cross).sum(axis=1) / (12.0 * area)
    uv_ = ((x * y1 + 2 * x * y + 2 * x1 * y1 + x1 * y) * cross).sum(axis=1) / (24.0 * area)
    root = np.sqrt(0.25 * (uu - vv) ** 2 + uv_**2)
    axes = 2.0 * np.sqrt(np.stack([0.5 * (uu + vv) + root, 0.5 * (uu + vv) - root], axis=1))
    return np.column_stack([axes, 0.5 * np.arctan2(2.0 * uv_, uu - vv)])


def pair_field(separations_mm, diameter_mm=6.0) -> Field:
    """Pairs of uncoded disks at the given centre separations (row y = 100) and one lone disk
    under each pair (row y = -100), all on the z = 0 plate."""
    ids, xyz = [], []
    for k, sep in enumerate(separations_mm):
        x = -250.0 + 100.0 * k
        ids += [f"A{k}", f"B{k}", f"S{k}"]
        xyz += [(x - sep / 2, 100.0, 0.0), (x + sep / 2, 100.0, 0.0), (x, -100.0, 0.0)]
    n = len(ids)
    return Field(
        name="pairs",
        ids=tuple(ids),
        xyz=np.array(xyz),
        codes=-np.ones(n, dtype=np.int64),
        diameters_mm=np.full(n, diameter_mm),
    )


@pytest.fixture(scope="module")
def reference():
    frame = render()
    return frame, *detect_blobs(frame.image)


@pytest.fixture(scope="module")
def noise_free():
    # evenly lit across each target: the estimators' own floors (the light's change across a target
    # moves an intensity centroid towards it: tests/core/test_edge_centre.py)
    frame = render(RenderSettings(shading=False), seed=None)
    return frame, *detect_blobs(frame.image)


def test_reference_frame_finds_every_disk_and_no_ring_piece(reference):
    frame, blobs, rejected = reference
    found = match(blobs, frame.uv_disk_centroid)
    assert np.all(found >= 0), f"missed {np.array(frame.ids)[found < 0]}"
    assert len(blobs) == len(frame.ids)  # nothing else: no ring piece, no noise speck
    counts = rejected.counts
    # every code has at least two bright runs, so at least 60 ring pieces, and nothing else is rejected
    assert counts["ring"] >= 2 * 30
    assert sum(counts.values()) == counts["ring"]
    assert set(counts) == set(REASONS)


def test_centroid_error_matches_the_predicted_precision_without_bias(reference):
    frame, blobs, _ = reference
    found = match(blobs, frame.uv_disk_centroid)
    err = blobs.uv[found] - frame.uv_disk_centroid
    rms = np.sqrt(np.mean(err**2))
    predicted = np.sqrt(np.mean(blobs.sigma_px**2))
    # two-sided: the reference noise gives ~0.013 px; vanishing noise or a bias fails
    assert 0.007 < rms < 0.03
    assert 0.7 * predicted < rms < 1.4 * predicted
    # 460 coordinates of ~0.013 px noise: a mean beyond 0.004 px is a bias
    assert np.all(np.abs(err.mean(axis=0)) < 0.004)
    assert np.max(np.abs(err)) < 5 * predicted


@pytest.mark.parametrize(
    ("centre", "rms_px", "max_px"),
    [
        ("centroid", 0.003, 0.01),  # only 8-bit quantisation is left (here 0.0016 and 0.005 px)
        # the edge is sampled where rows and columns cross it, each crossing interpolated between two
        # pixels: a floor of its own (here 0.008 and 0.021 px), below any real image's noise (with the
        # default render's read noise the edge is the better: 0.011 against 0.013 px RMS)
        ("edge", 0.01, 0.03),
    ],
)
def test_noise_free_frame_is_measured_to_a_few_thousandths_of_a_pixel(noise_free, centre, rms_px, max_px):
    frame = noise_free[0]
    blobs, _ = detect_blobs(frame.image, DetectSettings(centre=centre))
    found = match(blobs, frame.uv_disk_centroid)
    assert np.all(found >= 0)
    err = blobs.uv[found] - frame.uv_disk_centroid
    assert np.sqrt(np.mean(err**2)) < rms_px
    assert np.max(np.abs(err)) < max_px
    assert np.abs(err.mean(axis=0)).max() < 0.1 * rms_px  # no bias


def test_ellipse_is_the_disk_edge_head_on_and_in_an_oblique_view(reference):
    frame, blobs, _ = reference
    found = match(blobs, frame.uv_disk_centroid)
    # the distortion squeezes the corners' disks radially by up to 6 %
    ratio = blobs.ellipse[found, 2:4] / disk_axes_px(frame, reference_field())[:, :2]
    assert np.all(np.abs(np.median(ratio, axis=0) - 1.0) < 0.01) and np.all(np.abs(ratio - 1.0) < 0.04)
    np.testing.assert_allclose(blobs.ellipse[found, :2], blobs.uv[found])

    tilted = render(pose=reference_pose(view_angle_deg=60.0))
    tb, _ = detect_blobs(tilted.image)
    found = match(tb, tilted.uv_disk_centroid)
    ok = found >= 0
    assert np.mean(ok[tilted.fully_visible]) > 0.97
    assert len(tb) == ok.sum()  # no ring piece or anything else taken for a disk
    # foreshortened along v (the plate is tilted about the field x axis), less where the lens squeezes
    truth = disk_axes_px(tilted, reference_field())[ok]
    ratio = tb.ellipse[found[ok], 2:4] / truth[:, :2]  # b down to 4 px
    assert np.all(np.abs(np.median(ratio, axis=0) - 1.0) < 0.015) and np.all(np.abs(ratio - 1.0) < 0.06)
    assert 0.75 < np.median(tb.ellipse[:, 3] / tb.ellipse[:, 2]) < 0.9
    turn = np.angle(np.exp(2j * (tb.ellipse[found[ok], 4] - truth[:, 2]))) / 2.0  # axes are modulo pi
    oval = truth[:, 1] < 0.9 * truth[:, 0]  # where the angle is well defined
    assert oval.sum() > 100 and np.mean(np.abs(np.degrees(turn[oval]))) < 2.0
    err = tb.uv[found[ok]] - tilted.uv_disk_centroid[ok]
    assert np.sqrt(np.mean(err**2)) < 1.5 * np.sqrt(np.mean(tb.sigma_px**2))


def test_saturated_targets_are_measured_and_flagged():
    # twice the exposure: most disks' flat tops clipped at 255. Clipping a symmetric plateau keeps it
    # symmetric, so the centres hold; before, every clipped disk was rejected and the frame had no pose
    frame = render(RenderSettings(exposure_scale=2.0))
    blobs, rejected = detect_blobs(frame.image)
    found = match(blobs, frame.uv_disk_centroid)
    assert rejected.counts["saturated"] == 0
    ok = found >= 0
    assert ok.sum() >= 0.95 * len(frame.ids)
    clipped = blobs.saturated[found[ok]]
    assert clipped.sum() >= 200 and np.all(blobs.peak_dn[blobs.saturated] == 255)
    err = blobs.uv[found[ok]] - frame.uv_disk_centroid[ok]
    assert np.sqrt(np.mean(err[clipped] ** 2)) < 0.05
    assert np.all(np.abs(err) < 6 * blobs.sigma_px[found[ok], None])


def test_saturated_targets_are_rejected_and_counted_when_asked():
    frame = render(RenderSettings(exposure_scale=2.0))
    blobs, rejected = detect_blobs(frame.image, DetectSettings(max_saturated_px=2))
    found = match(blobs, frame.uv_disk_centroid)
    assert rejected.counts["saturated"] >= 200
    assert rejected.counts["saturated"] + np.sum(found >= 0) == len(frame.ids)
    # the few accepted ones are the corners (vignetting), with at most a pixel or two at full scale
    ok = found >= 0
    assert not blobs.saturated.any()
    err = blobs.uv[found[ok]] - frame.uv_disk_centroid[ok]
    assert np.all(np.abs(err) < 6 * blobs.sigma_px[found[ok], None])


def test_disks_cut_by_the_image_border_are_rejected_not_mismeasured():
    frame = render(pose=reference_pose(distance_mm=900.0))  # the plate overfills the image
    blobs, rejected = detect_blobs(frame.image)
    uncoded_cut = ~frame.fully_visible & np.array([i.startswith("P") for i in frame.ids])
    assert uncoded_cut.sum() >= 20
    assert np.all(match(blobs, frame.uv_true[uncoded_cut], tol_px=3.0) < 0)
    assert rejected.counts["cut_off"] >= uncoded_cut.sum()
    found = match(blobs, frame.uv_disk_centroid)
    err = blobs.uv[found[found >= 0]] - frame.uv_disk_centroid[found >= 0]
    assert len(err) == len(blobs)  # everything accepted is a disk, and well measured
    assert np.max(np.abs(err)) < 6 * np.max(blobs.sigma_px)


def test_merged_and_overlapping_disks_are_rejected():
    # 6 mm disks overlapping by a sixth, touching, and 0.5 and 1 mm apart (their blur tails merge).
    # Disks overlapping by a third or more look like one ellipse and are not caught.
    seps = (5.0, 6.0, 6.5, 7.0)
    field = pair_field(seps)
    frame = render(RenderSettings(exposure_scale=0.5), field=field)  # overlaps must not saturate
    blobs, rejected = detect_blobs(frame.image)
    uv = dict(zip(frame.ids, frame.uv_disk_centroid, strict=True))
    for k in range(len(seps)):
        pair = np.array([uv[f"A{k}"], uv[f"B{k}"], 0.5 * (uv[f"A{k}"] + uv[f"B{k}"])])
        assert np.all(match(blobs, pair, tol_px=3.0) < 0), f"pair {seps[k]} mm was measured"
        assert match(blobs, np.array([uv[f"S{k}"]]))[0] >= 0
    assert rejected.counts["merged_or_misshapen"] == len(seps)
    assert len(blobs) == len(seps)


def test_disk_notched_by_a_dark_occluder_is_rejected():
    field = pair_field((20.0, 20.0, 20.0))  # well separated: only the lone disks are notched
    clean = render(field=field)
    uv = dict(zip(clean.ids, clean.uv_disk_centroid, strict=True))
    radius_px = 3.0 * 12.0 / 1000.0 / 0.0067
    occluders = tuple(
        (uv[f"S{k}"][0] + radius_px + 4.0 - depth, uv[f"S{k}"][1], 4.0) for k, depth in enumerate((2.0, 3.0, 4.0))
    )  # px of the disk covered
    frame = render(RenderSettings(occluders=occluders), field=field)
    blobs, rejected = detect_blobs(frame.image)
    lone = np.array([uv[f"S{k}"] for k in range(3)])
    assert np.all(match(blobs, lone, tol_px=2.0) < 0)
    assert rejected.counts["merged_or_misshapen"] == 3
    assert np.all(match(blobs, np.array([uv[f"{p}{k}"] for p in "AB" for k in range(3)])) >= 0)


def test_hot_spot_and_gradient_background_still_give_every_target():
    frame = render(RenderSettings(hot_spot_dn=40.0, gradient_dn=30.0, exposure_scale=0.8))
    blobs, _ = detect_blobs(frame.image)
    found = match(blobs, frame.uv_disk_centroid)
    assert np.all(found >= 0)
    assert len(blobs) == len(frame.ids)
    err = blobs.uv[found] - frame.uv_disk_centroid
    predicted = np.sqrt(np.mean(blobs.sigma_px**2))
    assert 0.7 * predicted < np.sqrt(np.mean(err**2)) < 1.4 * predicted
    assert np.all(np.abs(err.mean(axis=0)) < 0.005)
    # the background under each target follows the ramp and the glow
    assert np.ptp(blobs.background_dn) > 30.0


@pytest.mark.parametrize(("bit_depth", "settings"), [(16, DetectSettings()), (12, DetectSettings(saturation_dn=4095))])
def test_deeper_images_give_the_same_centres(reference, bit_depth, settings):
    _, blobs8, _ = reference
    frame = render(RenderSettings(bit_depth=bit_depth))  # the same noise, quantised finer
    assert frame.image.dtype == np.uint16
    blobs, _ = detect_blobs(frame.image, settings)
    found = match(blobs, frame.uv_disk_centroid)
    assert np.all(found >= 0) and len(blobs) == len(frame.ids)
    diff = blobs.uv[found] - blobs8.uv[match(blobs8, frame.uv_disk_centroid)]
    assert np.sqrt(np.mean(diff**2)) < 0.004  # 8-bit quantisation noise
    ratio = blobs.sigma_px[found] / blobs8.sigma_px[match(blobs8, frame.uv_disk_centroid)]
    assert abs(np.median(ratio) - 1.0) < 0.05 and np.all(np.abs(ratio - 1.0) < 0.3)


def test_measure_windows_gives_the_centres_of_detect_blobs(noise_free, reference):
    frame, blobs, _ = noise_free
    coded = np.array([i.startswith("C") for i in frame.ids])
    half = np.where(coded, 14, 10)  # disk radius + 2 px + the prediction error
    rng = np.random.default_rng(7)
    for offset in (0.0, 1.2):  # predictions off by up to 1.2 px
        predicted = frame.uv_disk_centroid + rng.uniform(-offset, offset, (len(coded), 2))
        measured, index = measure_windows(frame.image, predicted, half)
        assert np.all(index >= 0)
        np.testing.assert_allclose(measured.uv[index], blobs.uv[match(blobs, frame.uv_disk_centroid)], atol=1e-3)
    # with noise, other windows see other noise: the centres agree to within their precision
    frame, blobs, _ = reference
    measured, index = measure_windows(frame.image, frame.uv_disk_centroid + 0.7, half)
    ref = match(blobs, frame.uv_disk_centroid)
    assert np.all(index >= 0)
    d = measured.uv[index] - blobs.uv[ref]
    assert np.sqrt(np.mean(d**2)) < 1.2 * np.sqrt(np.mean(blobs.sigma_px**2))


def test_measure_windows_reports_empty_off_target_and_outside_windows(reference):
    frame, blobs, _ = reference
    p = frame.uv_disk_centroid[frame.ids.index("P100")]
    predicted = np.array(
        [
            p,  # a good prediction
            p + np.array([36.0, 0.0]),  # half-way to the next target: nothing there
            p + np.array([5.0, 0.0]),  # off by 5 px: the disk reaches the window's edge
            [3.0, 500.0],  # at the border: a window as large as the image allows (3 px), nothing in it
            [np.nan, np.nan],  # no prediction
        ]
    )
    measured, index = measure_windows(frame.image, predicted, 9)
    assert index.tolist() == [0, -1, -1, -1, -1]
    assert len(measured) == 1
    np.testing.assert_allclose(measured.uv[0], blobs.uv[match(blobs, p[None])[0]], atol=0.05)


def test_windows_at_the_image_border_measure_whole_disks_and_refuse_cut_ones():
    """A window that would leave the image is made as large as the image allows: a whole disk near the
    border is measured (as in the full frame), one the border cuts crosses its rim and is refused."""
    frame = render(pose=reference_pose(distance_mm=900.0))  # the plate overfills the image
    blobs, _ = detect_blobs(frame.image)
    uncoded = np.array([i.startswith("P") for i in frame.ids])
    h, w = frame.image.shape
    uv = frame.uv_disk_centroid
    gap = np.minimum.reduce([uv[:, 0], w - 1 - uv[:, 0], uv[:, 1], h - 1 - uv[:, 1]])
    half = 10  # disk radius (~6 px here) + blur + the prediction error
    near = uncoded & frame.fully_visible & (gap < half - 0.5) & (gap > -0.5)  # the full window leaves the image
    cut = uncoded & ~frame.fully_visible & (gap > -0.5)
    assert near.sum() >= 5 and cut.sum() >= 10, (near.sum(), cut.sum())
    measured, index = measure_windows(frame.image, uv[near | cut], half)
    at_border, cut_off = index[near[near | cut]], index[cut[near | cut]]
    assert np.all(cut_off == -1), cut_off
    # every one the full frame measures (the others lie within ~7 px of the border, too near for its
    # windows too) is measured, where the window's full size would have left the image
    ref = match(blobs, uv[near])
    ok = ref >= 0
    assert ok.sum() >= 2 and np.all(at_border[ok] >= 0), (at_border, ref)
    ref = ref[ok]
    d = measured.uv[at_border[ok]] - blobs.uv[ref]
    assert np.all(np.abs(d) < 4 * blobs.sigma_px[ref, None] + 0.01), d


def test_not_an_image_is_bad_input():
    with pytest.raises(SolveError) as e:
        detect_blobs(np.zeros((100, 100), dtype=np.float32))
    assert e.value.reason == Reason.bad_image
    with pytest.raises(SolveError):
        measure_windows(np.zeros((100, 100, 3), dtype=np.uint8), np.zeros((1, 2)), 5)


def test_an_empty_frame_gives_no_blobs():
    frame = render(RenderSettings(lit=False))
    blobs, rejected = detect_blobs(frame.image)
    assert len(blobs) == 0 and len(rejected) == 0


def test_a_reused_mask_buffer_gives_the_same_blobs(reference):
    frame, blobs, rejections = reference
    buffer = np.full(frame.image.shape, 7, dtype=np.uint8)  # stale content must not matter
    for _ in range(2):
        again, again_rej = detect_blobs(frame.image, mask_buffer=buffer)
        assert np.array_equal(again.uv, blobs.uv) and np.array_equal(again.has_ring, blobs.has_ring)
        assert again_rej.counts == rejections.counts
    wrong = np.zeros((10, 10), dtype=np.uint8)  # another shape: ignored
    assert np.array_equal(detect_blobs(frame.image, mask_buffer=wrong)[0].uv, blobs.uv)


def test_blobs_of_no_disk_shape_are_rejected_without_being_measured():
    # printed glyphs (an L, a C, a 7: bright, but filling under half of their moments' ellipse) are
    # misshapen before any window is measured; the disks beside them are measured as ever
    image = np.full((200, 300), 12, np.uint8)
    disks = np.array([[40.3, 50.6], [150.2, 60.1], [250.7, 140.4]])
    for u, v in disks:
        cv2.circle(image, (round(u * 16), round(v * 16)), 6 * 16, 200, -1, cv2.LINE_AA, shift=4)
    cv2.polylines(image, [np.array([[60, 120], [60, 170], [100, 170]], np.int32)], False, 180, 4)
    cv2.ellipse(image, (170, 150), (22, 22), 0, 45, 315, 180, 4)
    cv2.polylines(image, [np.array([[210, 30], [250, 30], [225, 90]], np.int32)], False, 180, 4)
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    blobs, rejected = detect_blobs(image)
    assert rejected.counts["merged_or_misshapen"] == 3
    assert rejected.work.n_measured == 3  # the disks only
    assert np.all(match(blobs, disks, tol_px=0.1) >= 0) and len(blobs) == 3
