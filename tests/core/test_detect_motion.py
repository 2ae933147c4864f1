"""Targets smeared by the camera's motion during the exposure: a camera riding a moving arm.

A uniform motion smears each disk along a segment (:func:`service.sim.render.smear_kernel`); the
smeared disk's centroid is the disk's at mid-exposure, the instant the service pairs with the
robot's pose. The shape tests must take such a disk for a disk: its kurtosis along the motion
is not an ellipse's (2 for a sharp one) but lies between 1.8 and 2.45, which the window's test
allows where the blob's axes leave room for a smear (``detect_kernel._kurtosis_range``); before,
a 6 px smear rejected 60 % of the reference frame's targets and gave no pose.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.bench.speed import frames_along_path
from service.core.geometry.frames import pose_difference
from service.core.results import PoseResult
from service.core.targets.detect import detect_blobs
from service.pipeline.measure import FrameMeasurer
from service.sim.render import RenderSettings, render_frame, smear, smear_kernel
from service.sim.scene import reference_camera, reference_field, reference_pose


def smeared(length_px: float, angle_deg: float, seed: int = 5):
    settings = RenderSettings(motion_blur_px=length_px, motion_angle_deg=angle_deg)
    return render_frame(reference_camera(), reference_field(), reference_pose(), settings, np.random.default_rng(seed))


@pytest.mark.parametrize("length_px, angle_deg", [(6.0, 0.0), (5.0, 30.0), (8.0, 90.0)])
def test_smear_kernel_is_a_centred_uniform_segment(length_px, angle_deg):
    k = smear_kernel(length_px, angle_deg).astype(np.float64)
    n = k.shape[0]
    c = np.arange(n) - n // 2
    u, v = np.meshgrid(c, c)
    assert k.shape == (n, n) and n % 2 == 1 and k.sum() == pytest.approx(1.0, abs=1e-6) and k.min() >= 0
    assert abs((k * u).sum()) < 1e-6 and abs((k * v).sum()) < 1e-6  # centred: mid-exposure
    a = np.radians(angle_deg)
    along, across = u * np.cos(a) + v * np.sin(a), -u * np.sin(a) + v * np.cos(a)
    # a uniform segment: variance L^2 / 12 along it, and only the bilinear spread's (< 1/4 px^2) across
    assert (k * along**2).sum() == pytest.approx(length_px**2 / 12, abs=0.2)
    assert (k * across**2).sum() < 0.25
    with pytest.raises(ValueError, match="finite length"):
        smear_kernel(-1.0, 0.0)
    with pytest.raises(ValueError, match="motion_angle_deg"):
        RenderSettings(motion_blur_px=4.0, motion_angle_deg=float("nan"))


def test_smear_keeps_the_image_type_and_its_light():
    img = np.zeros((40, 40), np.uint8)
    img[18:23, 18:23] = 200
    out = smear(img, 6.0, 45.0)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert abs(int(out.sum()) - int(img.sum())) < 0.02 * int(img.sum())  # rounding only
    assert out.max() < img.max()  # spread out


@pytest.mark.parametrize("length_px, angle_deg", [(4.0, 0.0), (6.0, 30.0), (8.0, 120.0)])
def test_smeared_targets_are_measured_at_mid_exposure(length_px, angle_deg):
    frame = smeared(length_px, angle_deg)
    blobs, _ = detect_blobs(frame.image)
    d, i = cKDTree(blobs.uv).query(frame.uv_disk_centroid)
    found = d < 0.5
    assert found.mean() >= 0.97  # a 6 px smear measured 40 % before
    err = blobs.uv[i[found]] - frame.uv_disk_centroid[found]
    assert np.all(np.abs(err.mean(axis=0)) < 0.005)  # no bias along the motion: the mid-exposure centre
    # the predicted precision still describes the smeared disks
    z = err / blobs.sigma_px[i[found], None]
    assert 0.75 < np.sqrt(np.mean(z**2)) < 1.35
    assert np.sqrt(np.mean(err**2)) < 0.03


def test_a_smeared_frame_gives_its_pose_and_its_codes_and_roi_tracking_keeps_it():
    frame = smeared(6.0, 30.0)
    out = FrameMeasurer(reference_camera(), reference_field()).measure(frame.image)
    assert isinstance(out.result, PoseResult)
    assert pose_difference(out.result.T_field_camera, frame.T_field_camera)[0] < 0.05
    truth = dict(zip(frame.ids, frame.uv_true, strict=True))
    named = list(out.result.targets.ids)
    assert len(named) >= 0.97 * len(frame.ids)
    uv = np.asarray(out.result.targets.uv_px)
    assert all(np.hypot(*(uv[k] - truth[t])) < 1.0 for k, t in enumerate(named))  # every name right
    # along a path, 4 ms a frame, every frame smeared
    path = frames_along_path(20, 2, RenderSettings(exposure_scale=0.8, motion_blur_px=6.0, motion_angle_deg=30.0))
    tracker = FrameMeasurer(reference_camera(), reference_field())
    outs = [tracker.measure(f.image, t_s=k * 0.004) for k, f in enumerate(path)]
    assert [o.mode for o in outs].count("roi") == len(path) - 1
    errs = [pose_difference(o.result.T_field_camera, f.T_field_camera)[0] for o, f in zip(outs, path, strict=True)]
    assert max(errs) < 0.1
