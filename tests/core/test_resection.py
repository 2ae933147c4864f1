"""Space resection (paper section 4.3): closed form, adjustment, precision, gross errors, failures.

Scenes are synthetic and seeded: targets are placed by casting rays through
random pixels onto the field, so every target is in view, and their exact
pixels come from the camera model's forward projection.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import apply_T, inv_T, make_T
from service.core.pose.resection import ResectionResult, resect, resect_closed_form
from service.core.results import Reason, SolveError

SIGMA_PX = 0.05


def camera_looking_at(view_angle_deg: float, distance_mm: float, roll_deg: float = 17.0) -> np.ndarray:
    """T_field_camera of a camera whose optical axis meets the plate z = 0 at its centre.

    ``view_angle_deg`` is the angle between the optical axis and the plate (90 = square on).
    """
    a = np.radians(view_angle_deg)
    back = np.array([np.cos(a), 0.0, np.sin(a)])  # from the plate centre to the camera
    z = -back
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    R = R @ Rotation.from_rotvec([0.0, 0.0, np.radians(roll_deg)]).as_matrix()
    return make_T(R, np.array([30.0, -20.0, 0.0]) + distance_mm * back)


def plate_scene(
    camera: BrownFraser,
    rng: np.random.Generator,
    n: int = 230,
    view_angle_deg: float = 90.0,
    distance_mm: float = 1000.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_field_camera, p_field (n, 3) mm on the plate z = 0, exact uv (n, 2) px)."""
    T = camera_looking_at(view_angle_deg, distance_mm)
    uv = rng.uniform([15, 15], [camera.width - 16, camera.height - 16], (n, 2))
    d_field = camera.rays_from_pixel(uv) @ T[:3, :3].T
    s = -T[2, 3] / d_field[:, 2]
    p_field = T[:3, 3] + s[:, None] * d_field
    p_field[:, 2] = 0.0
    return T, p_field, camera.pixel_from_camera(apply_T(inv_T(T), p_field))


def volume_scene(
    camera: BrownFraser, rng: np.random.Generator, n: int = 60
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A non-planar field: targets at 700-1400 mm depth all over the image."""
    T = camera_looking_at(70.0, 1000.0)
    uv = rng.uniform([15, 15], [camera.width - 16, camera.height - 16], (n, 2))
    p_camera = camera.rays_from_pixel(uv) * rng.uniform(700, 1400, (n, 1))
    p_field = apply_T(T, p_camera)
    return T, p_field, camera.pixel_from_camera(p_camera)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error (3,) mm and rotation error (3,) rad about the field axes (left-applied)."""
    dtheta = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return T_est[:3, 3] - T_true[:3, 3], dtheta


# -- noise-free recovery ---------------------------------------------------------


def test_resection_recovers_pose_from_noise_free_points_to_1e_6_mm(reference_camera, rng):
    T_true, p, uv = plate_scene(reference_camera, rng)
    res = resect(reference_camera, p, uv)
    dt, dtheta = pose_error(res.T_field_camera, T_true)
    assert np.max(np.abs(dt)) < 1e-6
    assert np.max(np.abs(dtheta)) < 1e-9
    assert res.converged and res.rejected.size == 0
    assert res.sigma0_px < 1e-6 and res.rms_px < 1e-6
    assert res.final_cost <= res.initial_cost


def test_closed_form_recovers_planar_pose_in_front_of_the_plate(reference_camera, rng):
    T_true, p, uv = plate_scene(reference_camera, rng, n=30, view_angle_deg=65.0)
    T = resect_closed_form(reference_camera, p, uv)
    dt, dtheta = pose_error(T, T_true)
    assert np.max(np.abs(dt)) < 1e-6
    assert np.max(np.abs(dtheta)) < 1e-9
    assert np.all(apply_T(inv_T(T), p)[:, 2] > 0)


def test_closed_form_handles_a_non_planar_field(reference_camera, rng):
    T_true, p, uv = volume_scene(reference_camera, rng)
    dt, dtheta = pose_error(resect_closed_form(reference_camera, p, uv), T_true)
    assert np.max(np.abs(dt)) < 1e-6
    assert np.max(np.abs(dtheta)) < 1e-9
    # With noise the closed form is a start close enough for the adjustment.
    uv_noisy = uv + rng.normal(0, SIGMA_PX, uv.shape)
    dt, _ = pose_error(resect_closed_form(reference_camera, p, uv_noisy), T_true)
    assert np.max(np.abs(dt)) < 5.0
    res = resect(reference_camera, p, uv_noisy, sigma_px=SIGMA_PX)
    dt, dtheta = pose_error(res.T_field_camera, T_true)
    assert np.all(np.abs(dt) < 4 * res.sigma_position_mm)
    assert np.all(np.abs(dtheta) < 4 * np.radians(res.sigma_rotation_deg))
    assert 0.5 * SIGMA_PX < res.sigma0_px < 2 * SIGMA_PX


@pytest.mark.parametrize("n", [4, 5])
def test_resection_of_four_or_five_non_planar_points(reference_camera, rng, n):
    T_true, p, uv = volume_scene(reference_camera, rng, n=n)
    dt, _ = pose_error(resect(reference_camera, p, uv).T_field_camera, T_true)
    assert np.max(np.abs(dt)) < 1e-6
    res = resect(reference_camera, p, uv + rng.normal(0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
    dt, dtheta = pose_error(res.T_field_camera, T_true)
    assert np.all(np.abs(dt) < 4 * res.sigma_position_mm)
    assert np.all(np.abs(dtheta) < 4 * np.radians(res.sigma_rotation_deg))


@pytest.mark.parametrize(("n", "relief_mm"), [(6, 5.0), (6, 40.0), (230, 5.0), (230, 40.0)])
def test_resection_of_a_plate_with_relief(reference_camera, rng, n, relief_mm):
    """Targets standing off a plate: neither exactly planar nor a volume."""
    T = camera_looking_at(70.0, 1000.0)
    uv = rng.uniform([15, 15], [reference_camera.width - 16, reference_camera.height - 16], (n, 2))
    d_field = reference_camera.rays_from_pixel(uv) @ T[:3, :3].T
    height = rng.uniform(0, relief_mm, n)
    s = (height - T[2, 3]) / d_field[:, 2]
    p = T[:3, 3] + s[:, None] * d_field
    uv = reference_camera.pixel_from_camera(apply_T(inv_T(T), p))
    dt, _ = pose_error(resect(reference_camera, p, uv).T_field_camera, T)
    assert np.max(np.abs(dt)) < 1e-6
    res = resect(reference_camera, p, uv + rng.normal(0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
    dt, dtheta = pose_error(res.T_field_camera, T)
    assert np.all(np.abs(dt) < 4 * res.sigma_position_mm)
    assert np.all(np.abs(dtheta) < 4 * np.radians(res.sigma_rotation_deg))


# -- precision -----------------------------------------------------------------


@pytest.mark.slow
def test_predicted_sigma_matches_monte_carlo_scatter_with_005_px_noise(reference_camera, rng):
    """400 trials: the empirical std per axis agrees with the predicted sigma within 15 %."""
    T_true, p, uv = plate_scene(reference_camera, rng)
    n_trials = 400
    errors = np.empty((n_trials, 6))
    predicted = np.empty((n_trials, 6))
    sigma0 = np.empty(n_trials)
    n_rejected = 0
    for k in range(n_trials):
        res = resect(reference_camera, p, uv + rng.normal(0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
        dt, dtheta = pose_error(res.T_field_camera, T_true)
        errors[k] = np.r_[dtheta, dt]
        predicted[k] = np.r_[np.radians(res.sigma_rotation_deg), res.sigma_position_mm]
        sigma0[k] = res.sigma0_px
        n_rejected += res.rejected.size
    ratio = errors.std(axis=0, ddof=1) / predicted.mean(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    # No bias beyond the Monte Carlo's own uncertainty.
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * predicted.mean(axis=0) / np.sqrt(n_trials))
    assert 0.95 * SIGMA_PX < sigma0.mean() < 1.05 * SIGMA_PX
    assert np.all((0.8 * SIGMA_PX < sigma0) & (sigma0 < 1.2 * SIGMA_PX))
    assert n_rejected <= 0.02 * n_trials  # the snooping hardly ever rejects a good point


def test_a_posteriori_covariance_agrees_with_a_priori_one_when_sigma_is_right(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng)
    uv_noisy = uv + rng.normal(0, SIGMA_PX, uv.shape)
    post = resect(reference_camera, p, uv_noisy)
    prior = resect(reference_camera, p, uv_noisy, sigma_px=SIGMA_PX)
    np.testing.assert_allclose(post.T_field_camera, prior.T_field_camera, atol=1e-12)
    ratio = post.sigma_position_mm / prior.sigma_position_mm
    assert np.allclose(ratio, post.sigma0_px / SIGMA_PX)
    assert np.all((0.85 < ratio) & (ratio < 1.15))
    np.testing.assert_allclose(post.covariance, post.covariance.T, atol=0)
    assert np.all(np.linalg.eigvalsh(post.covariance) > 0)


def test_residuals_are_in_pixels_of_the_distorted_camera(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng, n=80)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    res = resect(reference_camera, p, uv_obs)
    uv_computed = reference_camera.pixel_from_camera(apply_T(inv_T(res.T_field_camera), p))
    np.testing.assert_allclose(res.residuals_px, uv_obs - uv_computed, atol=1e-4)
    assert 0.5 * SIGMA_PX < res.rms_px < 2 * SIGMA_PX
    assert res.rms_px == pytest.approx(np.sqrt(np.mean(res.residuals_px**2)))


@pytest.mark.parametrize("view_angle_deg", [60.0, 90.0])
def test_resection_of_a_plate_viewed_at_60_and_90_degrees(reference_camera, rng, view_angle_deg):
    T_true, p, uv = plate_scene(reference_camera, rng, view_angle_deg=view_angle_deg)
    res = resect(reference_camera, p, uv + rng.normal(0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
    dt, dtheta = pose_error(res.T_field_camera, T_true)
    assert np.all(np.abs(dt) < 4 * res.sigma_position_mm)
    assert np.all(np.abs(dtheta) < 4 * np.radians(res.sigma_rotation_deg))
    assert 0.5 * SIGMA_PX < res.sigma0_px < 2 * SIGMA_PX
    # Sub-0.1 mm at 1 m from 1/20 px, as in the paper's Table 3.
    assert np.all((1e-3 < res.sigma_position_mm) & (res.sigma_position_mm < 0.1))
    if view_angle_deg == 90.0:
        # Square on, the centre's lateral position trades against the rotation:
        # depth is the best-determined coordinate (the paper's Table 3 pattern).
        lateral = res.sigma_position_mm[:2]
        assert np.all(res.sigma_position_mm[2] < 0.6 * lateral)


def test_resection_agrees_with_opencv_solvepnp(reference_camera, rng):
    T_true, p, uv = plate_scene(reference_camera, rng)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    res = resect(reference_camera, p, uv_obs)
    # OpenCV gets the same observations as ideal coordinates (K = I, no distortion),
    # so the only difference is its unweighted cost in ideal instead of pixel units.
    n_ideal = reference_camera.ideal_from_pixel(uv_obs) / reference_camera.c_mm
    ok, rvec, tvec = cv2.solvePnP(p, n_ideal, np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    T_camera_field = make_T(Rotation.from_rotvec(rvec.ravel()).as_matrix(), tvec.ravel())
    dt, dtheta = pose_error(res.T_field_camera, inv_T(T_camera_field))
    assert np.all(np.abs(dt) < 0.25 * res.sigma_position_mm), dt / res.sigma_position_mm
    assert np.all(np.abs(dtheta) < 0.25 * np.radians(res.sigma_rotation_deg))
    dt_true, _ = pose_error(inv_T(T_camera_field), T_true)
    assert np.all(np.abs(dt_true) < 4 * res.sigma_position_mm)  # both are near the truth
    # Noise-free, both reach the same pose (to OpenCV's own termination, ~1e-8 mm).
    res = resect(reference_camera, p, uv)
    n_ideal = reference_camera.ideal_from_pixel(uv) / reference_camera.c_mm
    ok, rvec, tvec = cv2.solvePnP(p, n_ideal, np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
    T_camera_field = make_T(Rotation.from_rotvec(rvec.ravel()).as_matrix(), tvec.ravel())
    dt, dtheta = pose_error(res.T_field_camera, inv_T(T_camera_field))
    assert np.max(np.abs(dt)) < 1e-5 and np.max(np.abs(dtheta)) < 1e-8


@pytest.mark.parametrize(("shift_mm", "turn_deg"), [(50.0, 5.0), (200.0, 15.0)])
def test_resection_converges_from_a_perturbed_start(reference_camera, rng, shift_mm, turn_deg):
    T_true, p, uv = plate_scene(reference_camera, rng, n=100, view_angle_deg=60.0)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    from_closed_form = resect(reference_camera, p, uv_obs)
    axis = rng.normal(size=3)
    dR = Rotation.from_rotvec(np.radians(turn_deg) * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    T_init = make_T(dR @ T_true[:3, :3], T_true[:3, 3] + shift_mm * direction / np.linalg.norm(direction))
    res = resect(reference_camera, p, uv_obs, T_field_camera_init=T_init)
    assert res.converged
    assert res.initial_cost > 1e3 * res.final_cost
    dt, dtheta = pose_error(res.T_field_camera, from_closed_form.T_field_camera)
    assert np.max(np.abs(dt)) < 1e-6
    assert np.max(np.abs(dtheta)) < 1e-9


# -- gross errors ---------------------------------------------------------------


@pytest.mark.parametrize("sigma_px", [None, SIGMA_PX])
def test_gross_errors_are_found_rejected_and_reported(reference_camera, rng, sigma_px):
    T_true, p, uv = plate_scene(reference_camera, rng, n=60)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    wrong = rng.choice(60, size=3, replace=False)
    shift_px = rng.uniform(5, 20, 3)
    angle = rng.uniform(0, 2 * np.pi, 3)
    uv_obs[wrong] += shift_px[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    res = resect(reference_camera, p, uv_obs, sigma_px=sigma_px)
    assert sorted(res.rejected.tolist()) == sorted(wrong.tolist())
    assert res.inliers.sum() == 57
    np.testing.assert_allclose(np.linalg.norm(res.residuals_px[wrong], axis=1), shift_px, atol=0.5)
    dt, dtheta = pose_error(res.T_field_camera, T_true)
    assert np.all(np.abs(dt) < 4 * res.sigma_position_mm)
    assert np.all(np.abs(dtheta) < 4 * np.radians(res.sigma_rotation_deg))
    assert 0.5 * SIGMA_PX < res.sigma0_px < 2 * SIGMA_PX


def test_gross_errors_are_kept_when_rejection_is_off(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng, n=60)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    uv_obs[7] += [12.0, -5.0]
    res = resect(reference_camera, p, uv_obs, reject_outliers=False)
    assert res.rejected.size == 0
    assert res.sigma0_px > 10 * SIGMA_PX


@pytest.mark.parametrize("sigma_px", [None, SIGMA_PX])
def test_more_gross_errors_than_good_points_is_a_failure(reference_camera, rng, sigma_px):
    _, p, uv = plate_scene(reference_camera, rng, n=20)
    uv_obs = uv + rng.normal(0, SIGMA_PX, uv.shape)
    angle = rng.uniform(0, 2 * np.pi, 11)
    uv_obs[:11] += rng.uniform(5, 40, (11, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
    with pytest.raises(SolveError) as e:
        resect(reference_camera, p, uv_obs, sigma_px=sigma_px)
    assert e.value.reason == Reason.too_few_targets


# -- degenerate input -----------------------------------------------------------


def test_fewer_than_four_points_is_too_few_targets(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng, n=3)
    for solve in (resect, resect_closed_form):
        with pytest.raises(SolveError) as e:
            solve(reference_camera, p, uv)
        assert e.value.reason == Reason.too_few_targets


def test_collinear_field_points_are_degenerate_geometry(reference_camera, rng):
    T = camera_looking_at(75.0, 1000.0)
    p = np.column_stack([np.linspace(-200, 200, 12), np.zeros(12), np.zeros(12)])
    uv = reference_camera.pixel_from_camera(apply_T(inv_T(T), p))
    for solve in (resect, resect_closed_form):
        with pytest.raises(SolveError) as e:
            solve(reference_camera, p, uv)
        assert e.value.reason == Reason.degenerate_geometry


def test_a_plate_seen_edge_on_is_degenerate_geometry(reference_camera, rng):
    # Camera in the plate's plane: every target images onto one line.
    R = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    T = make_T(R, [0.0, -1000.0, 0.0])
    p = np.column_stack([rng.uniform(-200, 200, 20), rng.uniform(-200, 200, 20), np.zeros(20)])
    uv = reference_camera.pixel_from_camera(apply_T(inv_T(T), p))
    with pytest.raises(SolveError) as e:
        resect(reference_camera, p, uv)
    assert e.value.reason == Reason.degenerate_geometry


def test_points_behind_the_camera_are_refused(reference_camera, rng):
    T_true, p, uv = volume_scene(reference_camera, rng)
    # Mirroring the targets through the projection centre keeps their image
    # coordinates but puts them all behind the camera.
    p_behind = 2 * T_true[:3, 3] - p
    for solve in (resect, resect_closed_form):
        with pytest.raises(SolveError) as e:
            solve(reference_camera, p_behind, uv)
        assert e.value.reason == Reason.behind_camera


def test_a_start_pose_facing_away_is_refused_not_followed(reference_camera, rng):
    T_true, p, uv = plate_scene(reference_camera, rng, n=40)
    # Turned 180 deg about the field z axis, with its centre mirrored through the
    # plate: every target is behind it, yet the collinearity equations fit exactly.
    T_away = T_true.copy()
    T_away[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ T_true[:3, :3]
    T_away[2, 3] = -T_true[2, 3]
    assert np.all(apply_T(inv_T(T_away), p)[:, 2] < 0)
    with pytest.raises(SolveError) as e:
        resect(reference_camera, p, uv, T_field_camera_init=T_away)
    assert e.value.reason == Reason.behind_camera


def test_non_finite_input_is_bad_input_and_wrong_shapes_raise(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng, n=10)
    uv[3, 0] = np.nan
    with pytest.raises(SolveError) as e:
        resect(reference_camera, p, uv)
    assert e.value.reason == Reason.bad_input
    with pytest.raises(ValueError, match="shape"):
        resect(reference_camera, p[:, :2], uv)
    with pytest.raises(ValueError, match="points"):
        resect(reference_camera, p[:5], uv)


def test_result_is_a_frozen_record(reference_camera, rng):
    _, p, uv = plate_scene(reference_camera, rng, n=20)
    res = resect(reference_camera, p, uv)
    assert isinstance(res, ResectionResult)
    assert res.covariance.shape == (6, 6) and res.residuals_px.shape == (20, 2)
    assert res.inliers.dtype == bool and res.n_iter >= 1
    with pytest.raises(AttributeError):
        res.sigma0_px = 1.0  # type: ignore[misc]
