"""Rig calibration: the relative orientation of rigidly mounted cameras from simultaneous images.

A synthetic rig of calibrated cameras (the reference camera and a variant) looks at a 3-D field
from convergent, rolled epochs; images are exact projections plus Gaussian noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.calib.bundle import Datum, ScaleBar
from service.core.calib.rig import RigImage, calibrate_rig, rig_from_dict
from service.core.geometry.frames import inv_T, make_T
from service.core.pose.intersection import intersect_rays
from service.core.results import Reason, SolveError
from service.core.targets.field import Field
from tests.core.test_bundle import NOISE_PX, TRUE_CAMERA, convergent_poses, field_3d

SECOND_CAMERA = dataclasses.replace(TRUE_CAMERA, c_mm=12.4, x0_mm=-0.02, K1=-9e-4)
#: camera 1 in camera 0's frame: 250 mm to the right, turned 12 deg towards camera 0's axis
T_MASTER_CAMERA1 = make_T(Rotation.from_euler("xyz", [2.0, -12.0, 3.0], degrees=True).as_matrix(), [250.0, 5.0, -10.0])
T_MASTER_CAMERA2 = make_T(Rotation.from_euler("xyz", [-15.0, 4.0, -2.0], degrees=True).as_matrix(), [10.0, 220.0, 15.0])


def rig_images(rng, field, poses, cameras, T_master, epoch_errors=None):
    """Images of every epoch by every camera; ``epoch_errors`` (E, K, 4, 4): camera k at epoch e is
    really at ``T_field_rig @ T_master[k] @ epoch_errors[e, k]`` (errors the rig model does not know)."""
    images = []
    for e, T_field_rig in enumerate(poses):
        for k, (cam, T_mc) in enumerate(zip(cameras, T_master, strict=True)):
            T = T_field_rig @ T_mc if epoch_errors is None else T_field_rig @ T_mc @ epoch_errors[e, k]
            p_camera = (field.xyz - T[:3, 3]) @ T[:3, :3]
            uv = cam.pixel_from_camera(p_camera)
            seen = cam.in_image(uv, 5.0) & (p_camera[:, 2] > 0)
            images.append(
                RigImage(
                    f"e{e}",
                    k,
                    tuple(np.array(field.ids)[seen]),
                    uv[seen] + rng.normal(0.0, NOISE_PX, (int(seen.sum()), 2)),
                    f"cam{k}-e{e}",
                )
            )
    return images


def small_T(rng, sigma_deg: float, sigma_mm: float) -> np.ndarray:
    return make_T(
        Rotation.from_rotvec(np.radians(rng.normal(0.0, sigma_deg, 3))).as_matrix(), rng.normal(0.0, sigma_mm, 3)
    )


def sync_and_flex_errors(rng, n_epochs: int, T_master, sync_s=0.5e-3, rate=(3.0, 30.0), flex=(0.003, 0.03)):
    """(E, K, 4, 4) per-epoch errors of a rig carried by a robot: camera k >= 1 exposes ``sync_s`` (rms)
    after camera 0 while the rig moves at ``rate`` (deg/s, mm/s rms per axis), and the mount flexes
    by ``flex`` (deg, mm rms per axis) as the rig is turned from epoch to epoch."""
    out = np.tile(np.eye(4), (n_epochs, len(T_master), 1, 1))
    for e in range(n_epochs):
        for k in range(1, len(T_master)):
            dt_s = rng.normal(0.0, sync_s)
            w_deg, v_mm = rng.normal(0.0, rate[0], 3) * dt_s, rng.normal(0.0, rate[1], 3) * dt_s
            T_rig_rigmoved = make_T(Rotation.from_rotvec(np.radians(w_deg)).as_matrix(), v_mm)
            out[e, k] = inv_T(T_master[k]) @ T_rig_rigmoved @ T_master[k] @ small_T(rng, *flex)
    return out


def relative_orientation_error(result, k: int, T_true) -> np.ndarray:
    """(6,): rotation about camera 0's axes (deg) and origin error (mm) of T_master_camera[k]."""
    T = result.rig.T_master_camera[k]
    rot = Rotation.from_matrix(T[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return np.r_[np.degrees(rot), T[:3, 3] - T_true[:3, 3]]


def pose_z(result, k: int, T_true) -> np.ndarray:
    """Errors of T_master_camera[k] in units of its sigma: rotation about, origin along camera 0's axes."""
    T = result.rig.T_master_camera[k]
    rot = Rotation.from_matrix(T[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return np.r_[
        np.degrees(rot) / result.sigma_rotation_deg[k], (T[:3, 3] - T_true[:3, 3]) / result.sigma_position_mm[k]
    ]


@pytest.mark.parametrize("seed", [1, 3, 4])
def test_rig_calibration_recovers_the_relative_orientation_within_3_sigma(seed):
    rng = np.random.default_rng(seed)
    field = field_3d(rng, 150)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 8), cams, (np.eye(4), T_MASTER_CAMERA1))
    result = calibrate_rig(cams, field, images, sigma_px=NOISE_PX)
    z = pose_z(result, 1, T_MASTER_CAMERA1)
    assert np.all(np.abs(z) < 3.0), z
    assert 0.8 * NOISE_PX < result.sigma0_px < 1.25 * NOISE_PX
    assert np.all(result.sigma_position_mm[1] > 0) and np.all(result.sigma_position_mm[1] < 0.1)
    assert np.all(result.sigma_rotation_deg[0] == 0) and np.allclose(result.rig.T_master_camera[0], np.eye(4))
    assert len(result.epochs) == 8 and result.T_field_rig.shape == (8, 4, 4)


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_rig_sigmas_agree_with_the_scatter_of_repeated_calibrations():
    # 40 trials: a sample standard deviation is known to 1/sqrt(78) = 11 %; the band is 3 of those
    rng = np.random.default_rng(5)
    field = field_3d(rng, 80)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    poses = convergent_poses(rng, 6)
    errors, sigmas = [], []
    for _ in range(40):
        result = calibrate_rig(
            cams,
            field,
            rig_images(rng, field, poses, cams, (np.eye(4), T_MASTER_CAMERA1)),
            sigma_px=NOISE_PX,
            reject_outliers=False,
            jackknife=False,
            T_master_camera_init=(np.eye(4), T_MASTER_CAMERA1),
        )
        errors.append(
            pose_z(result, 1, T_MASTER_CAMERA1) * np.r_[result.sigma_rotation_deg[1], result.sigma_position_mm[1]]
        )
        sigmas.append(np.r_[result.sigma_rotation_deg[1], result.sigma_position_mm[1]])
    ratio = np.sqrt(np.mean(np.square(errors), axis=0)) / np.mean(sigmas, axis=0)
    assert np.all((0.67 < ratio) & (ratio < 1.33)), ratio


@pytest.mark.slow
def test_rig_sigma_stays_honest_when_epochs_carry_synchronisation_and_flex_errors():
    # Camera 1 exposes 0.5 ms (rms) off camera 0 while the robot moves the rig, and its mount flexes
    # by 0.003 deg / 0.03 mm per epoch: errors common to an epoch, unknown to the rig model. The
    # formal sigma sees only the image noise (its epochs' targets average down); the jackknife sees
    # the epochs disagree. 40 trials: the Monte-Carlo scatter is known to 11 %, the band is 30 %.
    rng = np.random.default_rng(11)
    field = field_3d(rng, 80)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    T_master = (np.eye(4), T_MASTER_CAMERA1)
    poses = convergent_poses(rng, 8)
    errors, formal, reported = [], [], []
    for _ in range(40):
        images = rig_images(rng, field, poses, cams, T_master, sync_and_flex_errors(rng, len(poses), T_master))
        result = calibrate_rig(
            cams, field, images, sigma_px=NOISE_PX, reject_outliers=False, T_master_camera_init=T_master
        )
        assert result.sigma_source == "max(formal, jackknife)"
        errors.append(relative_orientation_error(result, 1, T_MASTER_CAMERA1))
        formal.append(np.r_[result.sigma_rotation_formal_deg[1], result.sigma_position_formal_mm[1]])
        reported.append(np.r_[result.sigma_rotation_deg[1], result.sigma_position_mm[1]])
    scatter = np.sqrt(np.mean(np.square(errors), axis=0))
    assert np.all(scatter / np.mean(formal, axis=0) > 2.0), scatter / np.mean(formal, axis=0)  # optimistic
    ratio = np.mean(reported, axis=0) / scatter
    assert np.all((0.7 < ratio) & (ratio < 1.3)), ratio
    assert any("scatters between epochs" in w for w in result.warnings)


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_jackknife_does_not_inflate_an_honest_rig_sigma():
    # no epoch errors: the formal sigma is right (test above this one), so max(formal, jackknife)
    # may only add the jackknife's own sampling error: on average less than 30 %
    rng = np.random.default_rng(12)
    field = field_3d(rng, 80)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    poses = convergent_poses(rng, 8)
    ratios = []
    for _ in range(12):
        result = calibrate_rig(
            cams,
            field,
            rig_images(rng, field, poses, cams, (np.eye(4), T_MASTER_CAMERA1)),
            sigma_px=NOISE_PX,
            reject_outliers=False,
        )
        jack = np.r_[result.sigma_rotation_jackknife_deg[1], result.sigma_position_jackknife_mm[1]]
        formal = np.r_[result.sigma_rotation_formal_deg[1], result.sigma_position_formal_mm[1]]
        assert np.all(np.isfinite(jack) & (jack > 0))
        ratios.append(np.r_[result.sigma_rotation_deg[1], result.sigma_position_mm[1]] / formal)
    assert np.all(np.array(ratios) >= 1.0)
    mean = np.mean(ratios, axis=0)
    assert np.all((1.0 <= mean) & (mean < 1.3)), mean


def test_rig_json_reports_both_sigmas_and_which_one_is_used(rng):
    field = field_3d(rng, 100)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 5), cams, (np.eye(4), T_MASTER_CAMERA1))
    cal = calibrate_rig(cams, field, images, sigma_px=NOISE_PX).to_dict()["calibration"]
    assert cal["sigma_source"] == "max(formal, jackknife)"
    assert len(cal["sigma_formal"]["position_mm"]) == 2 and len(cal["sigma_jackknife"]["rotation_deg"]) == 2
    few = [im for im in images if im.epoch in ("e0", "e1")]
    two = calibrate_rig(cams, field, few, sigma_px=NOISE_PX)
    assert two.sigma_source == "formal" and np.array_equal(two.sigma_position_mm, two.sigma_position_formal_mm)
    assert any("only 2 epochs" in w for w in two.warnings)
    assert two.to_dict()["calibration"]["sigma_jackknife"]["position_mm"][1] == [None, None, None]  # JSON, no NaN


def test_three_camera_rig_with_refined_interiors():
    rng = np.random.default_rng(9)
    field = field_3d(rng, 150)
    cams = (TRUE_CAMERA, SECOND_CAMERA, TRUE_CAMERA)
    T_master = (np.eye(4), T_MASTER_CAMERA1, T_MASTER_CAMERA2)
    images = rig_images(rng, field, convergent_poses(rng, 8), cams, T_master)
    start = tuple(dataclasses.replace(c, c_mm=c.c_mm * 1.003) for c in cams)  # c off by 0.3 %
    result = calibrate_rig(start, field, images, free_interior=("c_mm", "x0_mm", "y0_mm"), sigma_px=NOISE_PX)
    for k in (1, 2):
        assert np.all(np.abs(pose_z(result, k, T_master[k])) < 3.0)
    for cam, true, sig in zip(result.rig.cameras, cams, result.sigma_interior, strict=True):
        assert abs(cam.c_mm - true.c_mm) < 3 * sig["c_mm"] and sig["c_mm"] > 0 and sig["K1"] == 0.0


def test_rig_json_gives_the_rig_forward_intersection_needs(rng):
    field = field_3d(rng, 150)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 6), cams, (np.eye(4), T_MASTER_CAMERA1))
    result = calibrate_rig(cams, field, images, sigma_px=NOISE_PX)
    rig = rig_from_dict(result.to_dict())
    assert rig.n_cameras == 2 and np.allclose(rig.T_master_camera, result.rig.T_master_camera, atol=1e-8)
    # a point 1.2 m in front of the master camera, seen by both cameras: intersected where it is
    p_master = np.array([[30.0, -20.0, 1200.0]])
    uv = [
        cam.pixel_from_camera((p_master - T[:3, 3]) @ T[:3, :3])
        for cam, T in zip(cams, (np.eye(4), T_MASTER_CAMERA1), strict=True)
    ]
    got = intersect_rays(rig, uv)
    assert got.valid[0] and np.linalg.norm(got.p_master[0] - p_master[0]) < 0.2
    d = result.to_dict()
    assert d["model"] == "rig" and len(d["sigma_position_mm"]) == 2 and "sigma0_px" in d["calibration"]


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_rig_can_survey_the_field_too(rng):
    truth = field_3d(rng, 120)
    nominal = dataclasses.replace(truth, xyz=truth.xyz + rng.normal(0.0, 0.3, truth.xyz.shape))
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, truth, convergent_poses(rng, 8), cams, (np.eye(4), T_MASTER_CAMERA1))
    fixed = calibrate_rig(cams, nominal, images, sigma_px=NOISE_PX)
    surveyed = calibrate_rig(cams, nominal, images, field_fixed=False, sigma_px=NOISE_PX)
    assert fixed.sigma0_px > 3 * NOISE_PX  # the wrong nominal field shows in the residuals
    assert 0.8 * NOISE_PX < surveyed.sigma0_px < 1.25 * NOISE_PX
    assert np.all(np.abs(pose_z(surveyed, 1, T_MASTER_CAMERA1)[:3]) < 3.0)  # rotation: scale-free


def test_a_camera_never_oriented_with_the_master_is_refused(rng):
    field = field_3d(rng, 100)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 4), cams, (np.eye(4), T_MASTER_CAMERA1))
    images = [
        im if im.camera == 0 or im.epoch != "e0" else dataclasses.replace(im, epoch="alone")
        for im in images
        if im.camera == 0 or im.epoch == "e0"
    ]
    images = [im for im in images if not (im.camera == 0 and im.epoch == "alone")]
    with pytest.raises(SolveError) as e:
        calibrate_rig(cams, field, images)
    assert e.value.reason == Reason.too_few_targets and "camera 0" in e.value.message


def test_rig_needs_two_cameras_and_known_camera_indices(rng):
    field = field_3d(rng, 50)
    with pytest.raises(ValueError):
        calibrate_rig((TRUE_CAMERA,), field, [])
    with pytest.raises(SolveError) as e:
        calibrate_rig((TRUE_CAMERA, TRUE_CAMERA), field, [RigImage("e0", 2, ("T0",), np.zeros((1, 2)))])
    assert e.value.reason == Reason.bad_input
    assert inv_T(np.eye(4)).shape == (4, 4)


# -- the datum and the inputs: the bundle's checks ------------------------------------------------


def with_unseen_target(field: Field, tid: str = "ghost") -> Field:
    """``field`` plus a target that no image of :func:`rig_images` over ``field`` sees."""
    return Field(
        field.name,
        (*field.ids, tid),
        np.vstack([field.xyz, [0.0, 0.0, 5000.0]]),
        np.r_[field.codes, -1],
        np.r_[field.diameters_mm, 6.0],
    )


@pytest.mark.parametrize("field_fixed", [True, False])
@pytest.mark.parametrize("tid", ["ghost", "nowhere"])
def test_a_scale_bar_on_a_target_no_image_saw_is_refused_by_name(rng, field_fixed, tid):
    # "ghost" is in the field but outside every image; "nowhere" is in neither
    field = field_3d(rng, 60)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 4), cams, (np.eye(4), T_MASTER_CAMERA1))
    bar = ScaleBar(field.ids[0], tid, 500.0)
    with pytest.raises(SolveError) as e:
        calibrate_rig(cams, with_unseen_target(field), images, field_fixed=field_fixed, datum=Datum(scale_bars=(bar,)))
    assert e.value.reason == Reason.bad_input
    assert f"{field.ids[0]}-{tid}" in e.value.message and f"target {tid!r}" in e.value.message


@pytest.mark.parametrize("distance_mm, sigma_mm", [(500.0, 0.0), (0.0, 0.01), (500.0, float("nan"))])
def test_a_scale_bar_needs_a_positive_distance_and_sigma(rng, distance_mm, sigma_mm):
    field = field_3d(rng, 60)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 4), cams, (np.eye(4), T_MASTER_CAMERA1))
    bar = ScaleBar(field.ids[0], field.ids[1], distance_mm, sigma_mm)
    with pytest.raises(SolveError) as e:
        calibrate_rig(cams, field, images, field_fixed=False, datum=Datum(scale_bars=(bar,)))
    assert e.value.reason == Reason.bad_input and "positive distance and sigma" in e.value.message


def test_an_image_naming_a_target_twice_or_with_non_finite_pixels_is_refused_by_name(rng):
    field = field_3d(rng, 60)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 4), cams, (np.eye(4), T_MASTER_CAMERA1))
    im = images[3]
    twice = dataclasses.replace(im, ids=(*im.ids[:-1], im.ids[0]))
    nan = dataclasses.replace(im, uv=np.vstack([im.uv[:-1], [np.nan, 10.0]]))
    unnamed = dataclasses.replace(nan, name="")
    for bad, words in (
        (twice, "'cam1-e1' names a target twice"),
        (nan, "'cam1-e1' has non-finite"),
        (unnamed, "camera 1 at epoch 'e1'"),
    ):
        with pytest.raises(SolveError) as e:
            calibrate_rig(cams, field, [*images[:3], bad, *images[4:]])
        assert e.value.reason == Reason.bad_input and words in e.value.message


def test_a_rig_with_a_fixed_field_takes_no_control_points(rng):
    field = field_3d(rng, 60)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 4), cams, (np.eye(4), T_MASTER_CAMERA1))
    with pytest.raises(ValueError, match="field_fixed"):
        calibrate_rig(cams, field, images, datum=Datum(control=field.ids[:4]))


def test_a_surveyed_rig_takes_its_scale_from_a_scale_bar_and_keeps_control_points(rng):
    # a nominal field 1 % too large: without a bar the baseline comes out 1 % long, with one it is right
    truth = field_3d(rng, 80)
    nominal = dataclasses.replace(truth, xyz=truth.xyz * 1.01)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, truth, convergent_poses(rng, 6), cams, (np.eye(4), T_MASTER_CAMERA1))
    a, b = 0, int(np.argmax(np.linalg.norm(truth.xyz - truth.xyz[0], axis=1)))
    length = float(np.linalg.norm(truth.xyz[b] - truth.xyz[a]))
    bar = ScaleBar(truth.ids[a], truth.ids[b], length, 0.01)
    kw = {"field_fixed": False, "sigma_px": NOISE_PX, "reject_outliers": False, "jackknife": False}
    baseline = float(np.linalg.norm(T_MASTER_CAMERA1[:3, 3]))
    with_bar = calibrate_rig(cams, nominal, images, datum=Datum(scale_bars=(bar,)), **kw)
    without = calibrate_rig(cams, nominal, images, **kw)
    assert abs(np.linalg.norm(with_bar.rig.T_master_camera[1, :3, 3]) / baseline - 1.0) < 1e-3
    assert abs(np.linalg.norm(without.rig.T_master_camera[1, :3, 3]) / baseline - 1.01) < 1e-3
    i, j = with_bar.field.index[truth.ids[a]], with_bar.field.index[truth.ids[b]]
    assert abs(np.linalg.norm(with_bar.field.xyz[i] - with_bar.field.xyz[j]) - length) < 0.05
    # control points, as the bundle takes them: fixed at their (true) coordinates, sigma 0
    control = tuple(truth.ids[k] for k in (a, b, 10, 20, 30))
    known = dataclasses.replace(nominal, xyz=np.where(np.isin(truth.ids, control)[:, None], truth.xyz, nominal.xyz))
    fixed = calibrate_rig(cams, known, images, datum=Datum(control=control), **kw)
    rows = fixed.field.indices_of(list(control))
    assert np.array_equal(fixed.field.xyz[rows], truth.xyz[truth.indices_of(list(control))])
    assert np.all(fixed.sigma_xyz_mm[rows] == 0.0)
