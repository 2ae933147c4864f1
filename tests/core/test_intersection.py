from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.geometry.frames import apply_T, assert_T, inv_T, make_T, pose_difference
from service.core.geometry.similarity import rigid_transform, rigid_transform_with_covariance
from service.core.pose.intersection import (
    Rig,
    epipolar_matches,
    intersect_rays,
    match_rig_images,
    pose_from_intersection,
)
from service.core.results import Reason, SolveError

SIGMA_PX = 0.1


# -- scene helper ------------------------------------------------------------------


def look_at(position, target, up_hint=(0.0, 1.0, 0.0)):
    """T_field_camera of a camera at ``position`` looking at ``target`` (x right, y down)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up_hint)
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), position)


@dataclass
class RigScene:
    rig: Rig
    p_field: np.ndarray  # (N, 3) targets on the plate z = 0
    T_field_master: np.ndarray
    uv_true: list  # K arrays (N, 2), NaN where outside an image

    @property
    def p_master(self):
        return apply_T(inv_T(self.T_field_master), self.p_field)

    def noisy_uv(self, rng, sigma_px=SIGMA_PX):
        return [uv + rng.normal(0.0, sigma_px, uv.shape) for uv in self.uv_true]


def make_rig_scene(
    camera,
    rng,
    view_angle_deg=60.0,
    baseline_mm=300.0,
    distance_mm=1000.0,
    n_targets=120,
    plate_mm=(700.0, 550.0),
    n_cameras=2,
):
    """A rig of ``n_cameras`` reference cameras on a line through the master, ``baseline_mm`` apart.

    The master sits ``distance_mm`` from the centre of a plate (field z = 0) of
    randomly placed targets; its optical axis meets the plate at
    ``view_angle_deg`` (90 = square on, as in the paper's Table 2). The other
    cameras are converged on the plate centre.
    """
    tilt = np.radians(90.0 - view_angle_deg)
    centre = np.zeros(3)
    master_pos = distance_mm * np.array([0.0, -np.sin(tilt), np.cos(tilt)])
    T_field_master = look_at(master_pos, centre)
    T_field_cameras = [T_field_master]
    for k in range(1, n_cameras):
        pos = master_pos + k * baseline_mm * T_field_master[:3, 0]
        T_field_cameras.append(look_at(pos, centre))
    rig = Rig.from_T_field_camera([camera] * n_cameras, T_field_cameras)
    half = np.asarray(plate_mm) / 2
    p_field = np.column_stack([rng.uniform(-half, half, size=(n_targets, 2)), np.zeros(n_targets)])
    uv_true = []
    for T in T_field_cameras:
        uv = camera.pixel_from_camera(apply_T(inv_T(T), p_field))
        uv[~camera.in_image(uv, margin_px=5.0)] = np.nan
        uv_true.append(uv)
    return RigScene(rig, p_field, T_field_master, uv_true)


@pytest.fixture
def scene(reference_camera, rng):
    return make_rig_scene(reference_camera, rng)


def seen_by_all(scene):
    return np.all([np.all(np.isfinite(uv), axis=1) for uv in scene.uv_true], axis=0)


def test_scene_helper_builds_the_stated_geometry(scene):
    assert_T(scene.rig.T_master_camera[1])
    assert np.linalg.norm(scene.rig.T_master_camera[1, :3, 3]) == pytest.approx(300.0)
    axis = scene.T_field_master[:3, 2]
    assert np.degrees(np.arcsin(abs(axis[2]))) == pytest.approx(60.0)
    assert np.linalg.norm(scene.T_field_master[:3, 3]) == pytest.approx(1000.0)
    assert 80 <= seen_by_all(scene).sum() <= 120


# -- intersection --------------------------------------------------------------------


def test_intersection_is_exact_without_noise_through_lens_distortion(scene):
    res = intersect_rays(scene.rig, scene.uv_true)
    both = seen_by_all(scene)
    assert np.array_equal(res.valid, both)
    assert np.max(np.abs(res.p_master[both] - scene.p_master[both])) < 1e-6
    assert np.nanmax(np.abs(res.residuals_px)) < 1e-6
    assert np.all(np.isnan(res.p_master[~both]))
    assert 10 < np.min(res.ray_angle_deg[both]) < np.max(res.ray_angle_deg[both]) < 25


def test_intersection_sigma_matches_its_covariance_monte_carlo(scene, rng):
    """Empirical scatter of intersected points vs their predicted covariance, per master axis."""
    both = seen_by_all(scene)
    uv = [u[both] for u in scene.uv_true]
    truth = scene.p_master[both]
    n_trials = 300
    uv_mc = [np.tile(u, (n_trials, 1)) + rng.normal(0, SIGMA_PX, (n_trials * len(u), 2)) for u in uv]
    res = intersect_rays(scene.rig, uv_mc, sigma_px=SIGMA_PX)
    assert np.all(res.valid)
    err = res.p_master - np.tile(truth, (n_trials, 1))
    z = err / res.sigma_mm  # unit variance per axis if the covariance is right
    ratio = z.std(axis=0)
    assert np.all((0.85 < ratio) & (ratio < 1.15)), ratio
    # whitened by the full covariance the errors are chi^2 with 3 degrees of freedom
    L = np.linalg.cholesky(res.covariance)
    w = np.linalg.solve(L, err[..., None])[..., 0]
    assert 0.85 * 3 < np.mean(np.sum(w**2, axis=1)) < 1.15 * 3
    # depth is the weak direction at this ray angle: guards against a trivially isotropic covariance
    assert np.median(res.sigma_mm[:, 2]) > 2 * np.median(res.sigma_mm[:, 0])


def test_intersection_estimates_sigma0_from_the_residuals(scene, rng):
    uv = scene.noisy_uv(rng)
    res = intersect_rays(scene.rig, uv)
    assert res.sigma_px is None
    assert 0.8 * SIGMA_PX < res.sigma0_px < 1.2 * SIGMA_PX
    # two rays give 4 coordinates and a redundancy of 1, so the rms is about half of sigma0
    assert 0.35 * SIGMA_PX < res.rms_px < 0.65 * SIGMA_PX
    assert res.redundancy == int(res.valid.sum())
    res_apriori = intersect_rays(scene.rig, uv, sigma_px=2 * SIGMA_PX)
    ratio = res_apriori.sigma_mm[res_apriori.valid] / res.sigma_mm[res_apriori.valid]
    assert np.allclose(ratio, 2 * SIGMA_PX / res.sigma0_px, rtol=1e-3)


def test_degenerate_points_are_flagged_not_guessed(scene):
    uv = [u.copy() for u in scene.uv_true]
    both = np.flatnonzero(seen_by_all(scene))
    uv[1][both[0]] = np.nan  # seen once
    # a second "camera" at the master's own centre: parallel rays for every point
    twin = Rig(scene.rig.cameras, np.array([np.eye(4), np.eye(4)]))
    res = intersect_rays(scene.rig, uv)
    assert not res.valid[both[0]] and res.n_rays[both[0]] == 1
    assert np.all(np.isnan(res.covariance[both[0]]))
    assert res.valid[both[1]]
    flat = intersect_rays(twin, [uv[0], uv[0]])
    assert not np.any(flat.valid) and np.isnan(flat.sigma0_px)
    # rays that meet only behind the master: camera 1 faces the master from 2 m ahead
    cam = scene.rig.cameras[0]
    R_half_turn = Rotation.from_euler("y", 180, degrees=True).as_matrix()
    T_master_facing = make_T(R_half_turn, [0.0, 0.0, 2000.0])
    T_facing_master = inv_T(T_master_facing)
    facing = Rig((cam, cam), np.array([np.eye(4), T_master_facing]))
    q_master = np.array([[-100.0, 50.0, -500.0]])
    uv_q = [
        cam.pixel_from_camera(-q_master),
        cam.pixel_from_camera(apply_T(T_facing_master, q_master)),
    ]
    assert np.all(np.isfinite(uv_q))
    behind = intersect_rays(facing, uv_q)
    assert not behind.valid[0] and np.isnan(behind.p_master[0, 0])
    # the same rig intersects a point between the cameras
    q_between = -q_master
    uv_between = [
        cam.pixel_from_camera(q_between),
        cam.pixel_from_camera(apply_T(T_facing_master, q_between)),
    ]
    assert np.allclose(intersect_rays(facing, uv_between).p_master, q_between, atol=1e-6)


# -- epipolar matching -----------------------------------------------------------------


def shuffled_other_image(scene, rng, sigma_px=SIGMA_PX):
    """Targets of camera 1 in random order plus the permutation back to field rows."""
    uv0, uv1 = scene.noisy_uv(rng, sigma_px)
    rows1 = np.flatnonzero(np.all(np.isfinite(uv1), axis=1))
    perm = rng.permutation(rows1)
    return uv0, uv1[perm], perm


def test_epipolar_matching_pairs_uncoded_targets_without_mismatches(reference_camera, rng):
    scene = make_rig_scene(reference_camera, rng, n_targets=200)
    uv0, uv1, perm = shuffled_other_image(scene, rng)
    pairs = epipolar_matches(scene.rig, uv0, uv1, 1, tol_px=5 * SIGMA_PX)
    assert np.array_equal(perm[pairs[:, 1]], pairs[:, 0]), "a pair joins two different targets"
    n_both = seen_by_all(scene).sum()
    assert 0.7 * n_both <= len(pairs) <= n_both
    assert len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1]))
    # a depth window removes ghost intersections and so resolves more targets
    window = epipolar_matches(scene.rig, uv0, uv1, 1, tol_px=5 * SIGMA_PX, depth_range_mm=(600, 1500))
    assert np.array_equal(perm[window[:, 1]], window[:, 0])
    assert len(window) >= len(pairs)


def test_epipolar_tolerance_band_is_measured_in_pixels(scene):
    uv0, uv1 = scene.uv_true
    i = np.flatnonzero(seen_by_all(scene))[:1]
    T_other_master = inv_T(scene.rig.T_master_camera[1])
    # the epipolar line's local direction in image 1: images of two points on the master ray
    ends = scene.rig.cameras[1].pixel_from_camera(
        apply_T(T_other_master, np.array([[0.99], [1.01]]) * scene.p_master[i])
    )
    along = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    across = np.array([-along[1], along[0]])
    for shift_px, kept in ((0.9, True), (1.1, False), (-0.9, True), (-1.1, False)):
        pairs = epipolar_matches(scene.rig, uv0[i], uv1[i] + shift_px * across, 1, tol_px=1.0)
        assert (len(pairs) == 1) is kept, shift_px


def test_ambiguous_epipolar_candidates_are_rejected(scene):
    uv0, uv1 = scene.uv_true
    rows = np.flatnonzero(seen_by_all(scene))
    i = rows[0]
    # a decoy on i's epipolar line: the image of a point further along the master ray
    decoy = scene.rig.cameras[1].pixel_from_camera(
        apply_T(inv_T(scene.rig.T_master_camera[1]), scene.p_master[[i]] * 1.1)
    )
    other = np.concatenate([uv1[rows], decoy])
    pairs = epipolar_matches(scene.rig, uv0[rows], other, 1, tol_px=0.5)
    assert 0 not in pairs[:, 0], "ambiguous target was guessed"
    assert len(pairs) > 0.7 * len(rows)
    # the decoy's depth is outside a tight window, so the window resolves it
    z = scene.p_master[i, 2]
    pairs_w = epipolar_matches(scene.rig, uv0[rows], other, 1, tol_px=0.5, depth_range_mm=(z - 50, z + 50))
    assert [0, 0] in pairs_w.tolist()


def test_matched_images_feed_intersection_for_a_three_camera_rig(reference_camera, rng):
    scene = make_rig_scene(reference_camera, rng, baseline_mm=200.0, n_cameras=3)
    noisy = scene.noisy_uv(rng)
    master_rows = np.flatnonzero(np.isfinite(noisy[0][:, 0]))
    images = [noisy[0][master_rows]]
    for uv in noisy[1:]:
        rows = rng.permutation(np.flatnonzero(np.isfinite(uv[:, 0])))
        images.append(uv[rows])
    obs = match_rig_images(scene.rig, images, tol_px=0.5)
    for k in (1, 2):
        matched = np.isfinite(obs[k][:, 0])
        truth = noisy[k][master_rows[matched]]
        assert np.array_equal(obs[k][matched], truth)
    res = intersect_rays(scene.rig, obs, sigma_px=SIGMA_PX)
    assert np.sum(res.n_rays == 3) > 50
    err = res.p_master[res.valid] - scene.p_master[master_rows[res.valid]]
    assert np.all(np.abs(err) < 5 * res.sigma_mm[res.valid])


# -- closed-form similarity -------------------------------------------------------------


def test_umeyama_recovers_a_known_similarity_exactly(rng):
    p_b = rng.normal(0, 300, (25, 3))
    R = Rotation.random(random_state=3).as_matrix()
    t = rng.normal(0, 1000, 3)
    fit = rigid_transform(1.7 * p_b @ R.T + t, p_b, with_scale=True)
    assert fit.scale == pytest.approx(1.7, rel=1e-12)
    assert np.allclose(fit.R_a_b, R, atol=1e-12) and np.allclose(fit.t_a_b, t, atol=1e-9)
    assert fit.rms_mm < 1e-9
    rigid = rigid_transform(p_b @ R.T + t, p_b)
    assert rigid.scale == 1.0
    assert_T(rigid.T_a_b)
    assert np.allclose(rigid.T_a_b, make_T(R, t), atol=1e-9)


def test_umeyama_keeps_a_proper_rotation_for_coplanar_points(rng):
    p_b = np.column_stack([rng.uniform(-300, 300, (12, 2)), np.zeros(12)])
    T = make_T(Rotation.random(random_state=5).as_matrix(), [100.0, -20.0, 900.0])
    fit = rigid_transform(apply_T(T, p_b), p_b)
    assert np.linalg.det(fit.R_a_b) == pytest.approx(1.0)
    assert np.allclose(fit.T_a_b, T, atol=1e-9)


def test_umeyama_weights_drop_outliers_and_residuals_show_them(rng):
    p_b = rng.normal(0, 200, (10, 3))
    T = make_T(Rotation.random(random_state=7).as_matrix(), [5.0, 6.0, 7.0])
    p_a = apply_T(T, p_b)
    p_a[3] += [40.0, 0.0, 0.0]
    w = np.ones(10)
    w[3] = 0.0
    fit = rigid_transform(p_a, p_b, weights=w)
    assert np.allclose(fit.T_a_b, T, atol=1e-9) and fit.n_points == 9
    assert np.allclose(fit.residuals_mm[3], [40.0, 0.0, 0.0], atol=1e-9)
    assert rigid_transform(p_a, p_b).rms_mm > 5.0


def test_umeyama_rejects_too_few_and_collinear_points():
    with pytest.raises(SolveError) as e:
        rigid_transform(np.zeros((2, 3)), np.ones((2, 3)))
    assert e.value.reason is Reason.too_few_targets
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(SolveError) as e:
        rigid_transform(line + 10, line)
    assert e.value.reason is Reason.degenerate_geometry


def test_covariance_weighted_fit_equals_closed_form_for_equal_isotropic_covariances(rng):
    p_b = rng.normal(0, 200, (15, 3))
    p_b -= p_b.mean(axis=0)  # b's origin at the centroid decouples position from rotation
    T = make_T(Rotation.random(random_state=9).as_matrix(), [50.0, -60.0, 700.0])
    p_a = apply_T(T, p_b) + rng.normal(0, 0.05, p_b.shape)
    closed = rigid_transform(p_a, p_b)
    covariance = np.broadcast_to(0.05**2 * np.eye(3), (15, 3, 3))
    refined = rigid_transform_with_covariance(p_a, p_b, covariance)
    assert np.allclose(refined.T_a_b, closed.T_a_b, atol=1e-9)
    assert np.allclose(refined.residuals_mm, closed.residuals_mm, atol=1e-9)
    assert 0.6 < refined.sigma0 < 1.4
    assert np.allclose(refined.covariance[3:, 3:], 0.05**2 / 15 * np.eye(3), atol=1e-12)
    assert np.allclose(refined.covariance[:3, 3:], 0.0, atol=1e-12)


# -- pose from intersection ---------------------------------------------------------------


def test_pose_from_intersection_recovers_master_pose_without_noise(scene):
    res = pose_from_intersection(scene.rig, scene.p_field, scene.uv_true, sigma_px=SIGMA_PX)
    dt, dr_deg = pose_difference(res.T_field_master, scene.T_field_master)
    assert dt < 1e-6 and dr_deg < 1e-7
    assert np.allclose(res.T_field_camera[1], scene.T_field_master @ scene.rig.T_master_camera[1])
    assert res.rms_mm < 1e-6 and res.n_points == seen_by_all(scene).sum()
    assert np.all(res.sigma_position_mm > 0) and np.all(res.sigma_rotation_deg > 0)


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_pose_covariance_matches_monte_carlo_scatter(scene, rng):
    """Pose errors over noisy trials vs the covariance propagated from the points' covariances."""
    n_trials = 400
    errors = np.empty((n_trials, 6))
    sigma0 = np.empty(n_trials)
    for n in range(n_trials):
        uv = scene.noisy_uv(rng)
        res = pose_from_intersection(scene.rig, scene.p_field, uv, sigma_px=SIGMA_PX)
        dR = res.T_field_master[:3, :3] @ scene.T_field_master[:3, :3].T
        errors[n, :3] = Rotation.from_matrix(dR).as_rotvec()  # left perturbation, field axes
        errors[n, 3:] = res.T_field_master[:3, 3] - scene.T_field_master[:3, 3]
        sigma0[n] = res.sigma0
    predicted = np.sqrt(np.diag(res.covariance))
    ratio = errors.std(axis=0) / predicted
    assert np.all((0.85 < ratio) & (ratio < 1.15)), ratio
    assert np.all(np.abs(errors.mean(axis=0)) < 0.25 * predicted)
    assert 0.9 < np.mean(sigma0) < 1.1
    assert np.allclose(res.sigma_rotation_deg, np.degrees(predicted[:3]))
    assert np.allclose(res.sigma_position_mm, predicted[3:])


def test_pose_from_intersection_uses_sigma0_without_an_apriori_sigma(scene, rng):
    uv = scene.noisy_uv(rng)
    free = pose_from_intersection(scene.rig, scene.p_field, uv)
    fixed = pose_from_intersection(scene.rig, scene.p_field, uv, sigma_px=SIGMA_PX)
    s0 = free.intersection.sigma0_px
    assert 0.8 * SIGMA_PX < s0 < 1.2 * SIGMA_PX
    assert np.allclose(free.sigma_position_mm, fixed.sigma_position_mm * s0 / SIGMA_PX, rtol=1e-9)
    assert np.allclose(free.T_field_master, fixed.T_field_master, atol=1e-9)


def test_pose_from_intersection_needs_three_intersected_targets(scene):
    rows = np.flatnonzero(seen_by_all(scene))[:2]
    uv = [u[rows] for u in scene.uv_true]
    with pytest.raises(SolveError) as e:
        pose_from_intersection(scene.rig, scene.p_field[rows], uv)
    assert e.value.reason is Reason.too_few_targets and "2 targets" in e.value.message
