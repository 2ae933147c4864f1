from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.opencv_compat import brown_from_opencv, opencv_from_brown


def test_inverse_correction_agrees_with_forward_over_whole_sensor(reference_camera):
    cam = reference_camera
    uv = cam.pixel_grid(131, 104)
    back = cam.pixel_from_ideal(cam.ideal_from_pixel(uv))
    assert np.max(np.abs(back - uv)) < 1e-6


def test_correction_is_not_identity_for_the_reference_lens(reference_camera):
    # guards the round trip above against a model that silently does nothing
    uv = reference_camera.pixel_grid(5, 5)
    ideal_px = reference_camera.ideal_from_pixel(uv) / 0.0067
    plain_px = (reference_camera.sensor_from_pixel(uv) - [0.031, -0.024]) / 0.0067
    assert np.max(np.linalg.norm(ideal_px - plain_px, axis=1)) > 5.0


def test_sensor_coordinates_follow_design_convention():
    cam = BrownFraser(width=1300, height=1030, pixel_size_mm=(0.0067, 0.0067), c_mm=12.0)
    assert np.allclose(cam.sensor_from_pixel([[649.5, 514.5]]), 0.0)
    assert np.allclose(cam.sensor_from_pixel([[0.0, 0.0]]), [[-649.5 * 0.0067, -514.5 * 0.0067]])


def test_projection_obeys_collinearity_without_distortion():
    cam = BrownFraser(width=1300, height=1030, pixel_size_mm=(0.0067, 0.0067), c_mm=12.0)
    p = np.array([[100.0, -50.0, 1000.0]])
    uv = cam.pixel_from_camera(p)
    assert np.allclose(uv, [[649.5 + 12 * 0.1 / 0.0067, 514.5 - 12 * 0.05 / 0.0067]])
    assert np.all(np.isnan(cam.pixel_from_camera([[0.0, 0.0, -5.0]])))


def test_rays_point_back_at_the_projected_point(reference_camera, rng):
    p = rng.uniform([-300, -250, 800], [300, 250, 1500], size=(50, 3))
    uv = reference_camera.pixel_from_camera(p)
    rays = reference_camera.rays_from_pixel(uv)
    assert np.allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-10)


def test_ideal_from_pixel_jacobian_matches_finite_differences(reference_camera):
    uv = np.array([[10.0, 20.0], [1200.0, 900.0], [650.0, 515.0]])
    J = reference_camera.ideal_from_pixel_jacobian(uv)
    h = 1e-4
    for k in range(2):
        d = np.zeros(2)
        d[k] = h
        num = (reference_camera.ideal_from_pixel(uv + d) - reference_camera.ideal_from_pixel(uv - d)) / (2 * h)
        assert np.allclose(J[:, :, k], num, rtol=1e-6, atol=1e-12)


def test_camera_json_round_trip_keeps_every_parameter(reference_camera):
    d = json.loads(json.dumps(reference_camera.to_dict()))
    assert d["model"] == "brown-fraser"
    d["unknown_future_key"] = 1
    assert BrownFraser.from_dict(d) == reference_camera


@pytest.mark.parametrize(
    "bad, message",
    [({"width": 10}, "missing the key"), ({"model": "fisheye"}, "unsupported camera model"), ([], "JSON object")],
)
def test_camera_json_errors_say_what_is_wrong(bad, message):
    with pytest.raises(ValueError, match=message):
        BrownFraser.from_dict(bad)


def test_opencv_conversion_reproduces_projection_and_reports_its_residual(reference_camera, rng):
    fit = opencv_from_brown(reference_camera)
    assert fit.rms_px < 0.05  # B2 (shear) and the K3 vs r^6 scaling differ; the rest is representable
    p = rng.uniform([-300, -250, 900], [300, 250, 1200], size=(200, 3))
    uv_bf = reference_camera.pixel_from_camera(p)
    uv_cv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), fit.K, fit.dist)
    assert np.max(np.linalg.norm(uv_cv.reshape(-1, 2) - uv_bf, axis=1)) < 4 * fit.max_px + 1e-3


def test_brown_from_opencv_round_trip(reference_camera):
    cv = opencv_from_brown(reference_camera)
    back = brown_from_opencv(cv.K, cv.dist, 1300, 1030, (0.0067, 0.0067))
    assert back.rms_px < 0.05
    uv = reference_camera.pixel_grid(21, 17)
    diff = (back.camera.ideal_from_pixel(uv) - reference_camera.ideal_from_pixel(uv)) / 0.0067
    assert np.max(np.abs(diff)) < 0.2


@pytest.mark.parametrize("window", [(0, 0, 1300, 1030), (200, 100, 1000, 800), (1, 3, 64, 48), (650, 515, 650, 515)])
def test_a_window_of_the_sensor_maps_its_pixels_as_the_whole_sensor_does(reference_camera, rng, window):
    x, y, w, h = window
    crop = reference_camera.cropped(x, y, w, h)
    assert (crop.width, crop.height) == (w, h) and crop.K1 == reference_camera.K1
    p_camera = np.column_stack([rng.uniform(-300, 300, 50), rng.uniform(-250, 250, 50), rng.uniform(800, 1200, 50)])
    np.testing.assert_allclose(
        crop.pixel_from_camera(p_camera), reference_camera.pixel_from_camera(p_camera) - (x, y), atol=1e-9
    )
    uv = rng.uniform(0, (w - 1, h - 1), (50, 2))
    np.testing.assert_allclose(crop.ideal_from_pixel(uv), reference_camera.ideal_from_pixel(uv + (x, y)), atol=1e-12)


@pytest.mark.parametrize(
    "window", [(-1, 0, 10, 10), (0, 0, 1301, 10), (1200, 0, 101, 10), (0, 1000, 10, 31), (0, 0, 0, 5)]
)
def test_a_window_beyond_the_sensor_is_refused(reference_camera, window):
    with pytest.raises(ValueError, match="not inside the 1300 x 1030 px sensor"):
        reference_camera.cropped(*window)


def test_the_compiled_projection_and_whitening_take_each_cameras_own_numbers(reference_camera, rng):
    """The numbers the kernels take are converted once per camera (``projection_args``,
    ``whitening_args``): a copy made after the original's were cached (cropped, re-parametrised)
    projects and whitens with its own, as its methods do."""
    from service.core._kernels.geometry_kernels import project_kernel, whitened_ideal_kernel

    assert reference_camera.projection_args and reference_camera.whitening_args  # cached on the original
    p_camera = rng.uniform([-200, -150, 800], [200, 150, 1200], size=(40, 3))
    eye = np.eye(3)
    for cam in (
        reference_camera.cropped(100, 60, 900, 700),
        reference_camera.with_params(reference_camera.params() * 1.05),
    ):
        uv, _, _ = project_kernel(eye, np.zeros(3), p_camera, *cam.projection_args, 0.0)
        np.testing.assert_allclose(uv, cam.pixel_from_camera(p_camera), rtol=0, atol=1e-9)
        xy, W = whitened_ideal_kernel(np.ascontiguousarray(uv), *cam.whitening_args)
        np.testing.assert_allclose(xy, cam.ideal_from_pixel(uv), rtol=0, atol=1e-12)
        np.testing.assert_allclose(W, np.linalg.inv(cam.ideal_from_pixel_jacobian(uv)), rtol=1e-9)
