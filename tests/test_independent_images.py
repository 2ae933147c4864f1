"""posecell on images it did not make: its printed sheet rasterised by cairo, imaged through OpenCV.

The chain (``service/bench/independent.py``) shares no image geometry with posecell's renderer or
measurement: CairoSVG draws the sheet's SVG, OpenCV's lens model and ``cv2.remap`` image it, the
pixels integrate 4 x 4 sub-pixels. posecell measures with its defaults and the Brown/Fraser model
fitted to OpenCV's camera; the peer of ``posecell bench speed`` measures the same frames with
OpenCV's own model and the identities given.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.bench.independent import (
    DIST_OPENCV,
    HEIGHT,
    K_OPENCV,
    PIXEL_MM,
    VIEWS,
    WIDTH,
    Light,
    Score,
    _visible,
    corner_field,
    frames_of,
    image_of_sheet,
    measure_peer,
    measure_posecell,
    path_frames,
    sheet,
)
from service.bench.speed import peer_measure
from service.core.geometry.frames import pose_difference
from service.core.geometry.opencv_compat import brown_from_opencv
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer
from service.sim.scene import reference_pose


def test_the_chain_images_a_disk_where_opencv_projects_its_centre():
    """The chain itself, without posecell: a head-on disk's background-free intensity centroid lies
    on OpenCV's projection of its centre (the raster's and the camera's pixel conventions agree)."""
    light = Light(falloff=0.0, blur_px=0.0, electrons_per_dn=1e6, read_noise_dn=0.0)
    frame = image_of_sheet(reference_pose(90.0, 1000.0), light, np.random.default_rng(0))
    img = frame.image.astype(np.float64) - light.background_dn
    errors = []
    for i in np.flatnonzero(_visible(frame) & np.array([t.startswith("P") for t in frame.ids])):
        u, v = np.rint(frame.uv_true[i]).astype(int)
        h = int(np.ceil(frame.radius_px[i])) + 3  # uncoded: nothing else within 3 px of the disk
        w = img[v - h : v + h + 1, u - h : u + h + 1]
        vv, uu = np.mgrid[v - h : v + h + 1, u - h : u + h + 1]
        errors.append([np.sum(w * uu) / w.sum(), np.sum(w * vv) / w.sum()] - frame.uv_true[i])
    e = np.array(errors)
    assert len(e) > 150
    # 8-bit quantisation of the edge pixels and the disk's perspective shift (< 0.01 px) remain
    assert np.sqrt(np.mean(e**2)) < 0.02 and np.all(np.abs(e.mean(axis=0)) < 0.003), (e.mean(axis=0), np.abs(e).max())


def _whole_rings(frame) -> int:
    """Coded targets whose whole ring (3.2 disk radii) lies in the image, 2 px clear of its border."""
    uv, m = frame.uv_true, 3.2 * frame.radius_px + 2.0
    inside = (uv[:, 0] > m) & (uv[:, 0] < WIDTH - 1 - m) & (uv[:, 1] > m) & (uv[:, 1] < HEIGHT - 1 - m)
    return int((inside & np.array([t.startswith("C") for t in frame.ids])).sum())


@pytest.fixture(scope="module")
def measurer():
    fit = brown_from_opencv(K_OPENCV, DIST_OPENCV, WIDTH, HEIGHT, (PIXEL_MM, PIXEL_MM))
    assert fit.rms_px < 0.005  # the user's conversion of an OpenCV calibration
    return FrameMeasurer(fit.camera, sheet()[1])


# VIEWS[6:8]: overexposed, most disks clipped (before clipped disks were measured: no pose at 2x)
# VIEWS[9]: close, a coded target fills a noise tile (before: 1-3 of them a frame refused as faint)
@pytest.mark.parametrize("view", [VIEWS[k] for k in (0, 2, 3, 5, 6, 7, 9)], ids=lambda v: v.name)
def test_posecell_measures_the_independent_images_with_its_defaults_better_than_the_peer(measurer, view):
    ours, peer = Score(), Score()
    frames = frames_of(view, 2, seed=7)
    for frame in frames:
        measure_posecell(measurer, frame, ours)
        measure_peer(sheet()[1], frame, peer)
    coded_in_view = sum(_whole_rings(f) for f in frames)
    assert ours.failed == 0 and ours.wrong == 0, view.name  # a pose every frame, no target misnamed
    assert ours.found >= 0.98 * ours.visible and ours.coded >= coded_in_view, (ours.found, ours.visible, ours.coded)
    rms = float(np.sqrt(np.mean(np.square(ours.centre_err))))
    # seen 0.010-0.021 px; below 0.004 the noise or the blur would have gone missing
    assert 0.004 < rms < 0.03, (view.name, rms)
    assert max(ours.pose_mm) < 0.06 and max(ours.pose_deg) < 0.003, (ours.pose_mm, ours.pose_deg)
    peer_rms = float(np.sqrt(np.mean(np.square(peer.centre_err))))
    assert rms < 0.5 * peer_rms, (rms, peer_rms)  # seen 4-9x smaller
    assert np.median(ours.pose_mm) <= np.median(peer.pose_mm), (ours.pose_mm, peer.pose_mm)


def _radial_bias(frames, score_of) -> float:
    """The mean centre error (px) away from the principal point of the targets over 300 px from it."""
    bias = []
    for frame in frames:
        uv, truth = score_of(frame)
        out = truth - K_OPENCV[:2, 2]
        r = np.hypot(*out.T)
        bias += list((np.sum((uv - truth) * out, axis=1) / r)[r > 300])
    return float(np.mean(bias))


def test_a_frame_darker_in_its_corners_is_measured_as_one_evenly_lit(measurer):
    """VIEWS[10]: the same views with the corners 60 % darker than the centre, and evenly lit. The
    light falls outwards across each disk; the edges' level follows the light fitted to the frame's
    plateaus, so the centres are not pulled towards the image centre (with one level: -0.0059
    against -0.0014 px evenly lit, the pose 0.022 against 0.013 mm). The peer's are (-0.011 against
    -0.005: the test sees a light that pulls)."""
    dark, even = VIEWS[10], replace(VIEWS[10], light=replace(VIEWS[10].light, falloff=0.0))
    bias, peer_bias, pose = {}, {}, {}
    for view in (dark, even):
        frames = frames_of(view, 3, seed=5)
        poses = []

        def ours(frame, poses=poses):
            out = measurer.measure(frame.image)
            assert isinstance(out.result, PoseResult)
            poses.append(pose_difference(out.result.T_field_camera, frame.T_field_camera)[0])
            truth = dict(zip(frame.ids, frame.uv_true, strict=True))
            return np.array([t.uv for t in out.result.targets]), np.array([truth[t.id] for t in out.result.targets])

        def peer(frame):
            uv = peer_measure(frame.image, K_OPENCV, DIST_OPENCV)
            d, j = cKDTree(frame.uv_true).query(uv, distance_upper_bound=2.0)
            return uv[np.isfinite(d)], frame.uv_true[j[np.isfinite(d)]]

        measurer.reset()
        bias[view.light.falloff], peer_bias[view.light.falloff] = _radial_bias(frames, ours), _radial_bias(frames, peer)
        pose[view.light.falloff] = float(np.median(poses))
    assert abs(bias[0.6] - bias[0.0]) < 0.0015, bias  # seen: -0.0012 against -0.0014
    assert peer_bias[0.6] - peer_bias[0.0] < -0.003, peer_bias
    assert pose[0.6] < 1.3 * pose[0.0], pose  # seen: 0.0129 against 0.0132 mm (6 frames)


def test_an_out_of_focus_frame_is_measured_above_the_blur_that_joins_disks_to_rings(measurer):
    """VIEWS[11]: blurred by 2.5 px, each coded target's disk and ring are one blob at the noise's
    segmentation level, refused as merged; no ring was read and no frame gave a pose. Such a frame
    is detected again with the level at 30 % of the targets' brightness. Where that cannot help
    either (blurred by 3 px at 1.4 m: 4 px disks), the failure says what was tried."""
    measurer.reset()
    ours = Score()
    for frame in frames_of(VIEWS[11], 2, seed=7):
        measure_posecell(measurer, frame, ours)
    assert ours.failed == 0 and ours.wrong == 0, (ours.failed, ours.wrong)
    # seen (3 frames): 655 of 660 named, 82 coded, 0.033 px, 0.029 mm
    assert ours.found >= 0.9 * ours.visible and ours.coded >= 30, (ours.found, ours.visible, ours.coded)
    rms = float(np.sqrt(np.mean(np.square(ours.centre_err))))
    assert rms < 0.05 and max(ours.pose_mm) < 0.1, (rms, ours.pose_mm)
    far = frames_of(replace(VIEWS[11], distance_mm=1400.0, light=Light(blur_px=3.0)), 1, seed=7)[0]
    out = measurer.measure(far.image).result
    assert not isinstance(out, PoseResult) and "segmentation level at 30%" in out.message, out
    assert "the targets' edges are blurred" in out.message and "check the lens's focus" in out.message, out


def test_a_grazing_view_names_every_target_the_blobs_left_unnamed(measurer):
    """VIEWS[12]: at 30 deg a far coded target's disk joins its ring's near arc at the segmentation
    level; the blob is no disk and 1-3 targets a frame went unnamed (seen: 447 of 452, 55 of 59
    coded). The full frame now measures the targets in view that no blob named in windows about the
    pose's prediction, their rings masked, as ROI tracking does: every one is named, at the others'
    accuracy."""
    measurer.reset()
    ours = Score()
    frames = frames_of(VIEWS[12], 2, seed=7)
    for frame in frames:
        measure_posecell(measurer, frame, ours)
    coded_in_view = sum(int(np.sum(_visible(f) & np.array([t.startswith("C") for t in f.ids]))) for f in frames)
    assert ours.failed == 0 and ours.wrong == 0, (ours.failed, ours.wrong)
    assert ours.found >= ours.visible and ours.coded >= coded_in_view, (ours.found, ours.visible, ours.coded)
    rms = float(np.sqrt(np.mean(np.square(ours.centre_err))))
    assert rms < 0.03 and max(ours.pose_mm) < 0.04, (rms, ours.pose_mm)


@pytest.mark.parametrize("blur_px", [0.6, 1.2, 2.0])
def test_each_frame_says_how_blurred_its_targets_are(measurer, blur_px):
    """The blur the frame's disks show (their second moments beyond the disk's own) is the chain's
    optics' with the pixel's width (1/12 px^2) to 10 % (seen: 0.66, 1.22, 1.87 px against 0.67,
    1.23, 2.02); beyond BLURRED_PX (1.5 px) the frame says to check the focus."""
    measurer.reset()
    view = replace(VIEWS[1], light=replace(VIEWS[1].light, blur_px=blur_px))
    for frame in frames_of(view, 2, seed=7):
        out = measurer.measure(frame.image)
        assert isinstance(out.result, PoseResult) and out.brightness is not None
        expected = np.hypot(blur_px, np.sqrt(1 / 12))
        assert abs(out.brightness.blur_px / expected - 1) < 0.1, (out.brightness.blur_px, expected)
        assert bool(out.brightness.focus_note) == (blur_px > 1.5), out.brightness.focus_note


def _tracked(measurer: FrameMeasurer, frames) -> tuple[Score, list[str]]:
    """Frames 4 ms apart measured as the service tracks (the first in full): the ROI frames' score and every mode."""
    measurer.reset()
    roi, modes = Score(), []
    for k, frame in enumerate(frames):
        probe = Score()
        modes.append(measure_posecell(measurer, frame, probe, t_s=k * 0.004))
        if modes[-1] == "roi":
            roi.merge(probe)
    return roi, modes


def test_roi_tracking_follows_the_independent_images(measurer):
    """Frames 4 ms apart along a path: after the first, each is measured in windows about the
    predicted targets, as the service does, and holds the full frame's accuracy."""
    roi, modes = _tracked(measurer, path_frames(8, seed=3))
    assert modes[0] == "full" and modes[1:].count("roi") >= 6, modes
    # seen: every one (before the coded targets' rings were masked in their windows, 97.7 %: in these
    # oblique views the ring reaches a window that holds the disk)
    assert roi.failed == 0 and roi.wrong == 0 and roi.found >= 0.99 * roi.visible, (roi.found, roi.visible)
    rms = float(np.sqrt(np.mean(np.square(roi.centre_err))))
    assert 0.004 < rms < 0.03 and max(roi.pose_mm) < 0.06, (rms, roi.pose_mm)


def test_roi_tracking_follows_an_out_of_focus_path(measurer):
    """Blurred by 2.5 px, a disk's tail reaches 3 px beyond its edge at the segmentation level: ROI
    windows with the fixed 3 px rim refused it as too big and kept 78 % of the targets (41 of 269
    coded; seen 2026-12-06). Their rim now follows the last frame's blur (BLUR_RIM_SIGMAS)."""
    roi, modes = _tracked(measurer, path_frames(6, seed=3, light=replace(VIEWS[11].light, blur_px=2.5)))
    assert modes[0] == "full" and modes[1:].count("roi") >= 4, modes
    # seen: 2038 of 2037 over 9 frames, 269 coded (one more than "visible", whose disk is cut by the border)
    assert roi.failed == 0 and roi.wrong == 0 and roi.found >= 0.98 * roi.visible, (roi.found, roi.visible)
    assert roi.coded >= 0.9 * 30 * modes[1:].count("roi"), roi.coded
    assert max(roi.pose_mm) < 0.08, roi.pose_mm


def _wall_errors(measurer: FrameMeasurer, frames, t_s=None) -> tuple[Score, np.ndarray, np.ndarray, int]:
    """posecell on ``frames`` of the corner: its score, the centre errors (k, 2) px of the floor's and
    of the wall's targets, and the wall's coded targets named."""
    score, floor, wall, wall_coded = Score(), [], [], 0
    for k, frame in enumerate(frames):
        truth_of = dict(zip(frame.ids, frame.uv_true, strict=True))
        out = measurer.measure(frame.image, t_s=None if t_s is None else k * t_s)
        assert isinstance(out.result, PoseResult), out.result
        score.pose_mm.append(pose_difference(out.result.T_field_camera, frame.T_field_camera)[0])
        for t in out.result.targets:
            e = np.subtract(t.uv, truth_of[t.id])
            assert np.hypot(*e) < 1.0, t.id  # none named wrongly
            on_wall = t.id.startswith("W") or (t.id.startswith("C") and int(t.id[1:]) > 30)
            (wall if on_wall else floor).append(e)
            wall_coded += on_wall and t.id.startswith("C")
    return score, np.array(floor), np.array(wall), wall_coded


def test_a_corner_of_floor_and_wall_is_measured_in_each_targets_own_plane():
    """Two sheets at right angles (CORNER): once the field gives each target's normal, the wall's
    centres are corrected for their own perspective shift. Without normals (every disk taken to lie
    in the floor's plane) they were shifted by the floor's: a bias of -0.012 px across the wall
    (seen), and the pose 2-2.5 times further from the truth."""
    fit = brown_from_opencv(K_OPENCV, DIST_OPENCV, WIDTH, HEIGHT, (PIXEL_MM, PIXEL_MM))
    frames = frames_of(VIEWS[8], 2, seed=7)
    seen = {}
    for with_normals in (True, False):
        score, floor, wall, _ = _wall_errors(FrameMeasurer(fit.camera, corner_field(with_normals)), frames)
        assert len(floor) >= 300 and len(wall) >= 150, (len(floor), len(wall))
        seen[with_normals] = (np.abs(wall.mean(axis=0)).max(), np.sqrt(np.mean(wall**2)), max(score.pose_mm))
    (bias, rms, pose_mm), (bias_flat, rms_flat, pose_flat) = seen[True], seen[False]
    assert bias < 0.004 < 0.008 < bias_flat, seen  # seen 0.0008 and 0.0127 px
    assert rms < 0.95 * rms_flat and pose_mm < 0.04 and pose_mm < pose_flat, seen


def test_roi_tracking_keeps_the_walls_coded_targets():
    """ROI tracking masks a coded target's ring about the disk's ellipse predicted in the target's own
    plane: along a path of the corner every coded target of the wall is kept (predicted in the
    floor's plane, 15-18 of 20 were lost to masks cut to the wrong ellipse)."""
    fit = brown_from_opencv(K_OPENCV, DIST_OPENCV, WIDTH, HEIGHT, (PIXEL_MM, PIXEL_MM))
    frames = path_frames(6, seed=5, corner=True)
    measurer = FrameMeasurer(fit.camera, corner_field())
    first = _wall_errors(measurer, frames[:1])
    tracked = _wall_errors(measurer, frames[1:], t_s=0.004)
    assert first[3] == 20 and tracked[3] == 20 * 5, (first[3], tracked[3])
    assert max(tracked[0].pose_mm) < 0.06
