"""Self-calibrating bundle adjustment on seeded synthetic networks (the reference camera of service.sim.scene).

Images are the exact projections of the targets through the reference camera (its
real-lens distortion included) plus Gaussian noise of ``NOISE_PX`` per coordinate;
the adjustment starts from a nominal camera (c off by 2.5 %, no distortion, principal
point at the centre) and closed-form resections.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.core.calib.bundle import Datum, ImagePoints, ScaleBar, calibrate_camera, network_geometry
from service.core.calib.bundle_model import BundleModel, ExtraRows
from service.core.calib.bundle_solve import gauge_basis, params_from_T
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.geometry.frames import inv_T
from service.core.pose.resection import resect
from service.core.results import Reason, SolveError
from service.core.targets.field import Field
from service.sim import scene

NOISE_PX = 0.05
TRUE_CAMERA = scene.reference_camera()
NOMINAL_CAMERA = BrownFraser(TRUE_CAMERA.width, TRUE_CAMERA.height, TRUE_CAMERA.pixel_size_mm, 12.3)


def field_3d(rng: np.random.Generator, n: int = 120, relief_mm: float = 120.0) -> Field:
    """n targets over the reference plate's 640 x 500 mm, at heights 0..relief_mm."""
    xy = rng.uniform([-320.0, -250.0], [320.0, 250.0], (n, 2))
    xyz = np.c_[xy, rng.uniform(0.0, relief_mm, n)]
    return Field("synthetic", tuple(f"T{i}" for i in range(n)), xyz, np.full(n, -1), np.full(n, 6.0))


def convergent_poses(
    rng: np.random.Generator,
    n: int,
    rolls=(0.0, 90.0, 180.0, 270.0),
    view_angle_deg=(50.0, 65.0),
    roll_jitter_deg: float = 8.0,
) -> list[np.ndarray]:
    """Views from all around the plate, tilted by 25-40 deg, rolled in turn by ``rolls``."""
    poses = []
    for k in range(n):
        poses.append(
            scene.reference_pose(
                view_angle_deg=rng.uniform(*view_angle_deg),
                distance_mm=rng.uniform(1050.0, 1200.0),
                roll_deg=rolls[k % len(rolls)] + rng.uniform(-roll_jitter_deg, roll_jitter_deg),
                azimuth_deg=k * 360.0 / n + rng.uniform(-10, 10),
                look_at_mm=(rng.uniform(-40, 40), rng.uniform(-40, 40), 0.0),
            )
        )
    return poses


def observe(
    rng: np.random.Generator,
    field: Field,
    poses,
    camera: BrownFraser = TRUE_CAMERA,
    noise_px: float = NOISE_PX,
    with_pose: bool = False,
) -> list[ImagePoints]:
    images = []
    for k, T in enumerate(poses):
        p_camera = (field.xyz - T[:3, 3]) @ T[:3, :3]
        uv = camera.pixel_from_camera(p_camera)
        seen = camera.in_image(uv, 5.0) & (p_camera[:, 2] > 0)
        noisy = uv[seen] + rng.normal(0.0, noise_px, (int(seen.sum()), 2))
        images.append(ImagePoints(f"img{k:02d}", tuple(np.array(field.ids)[seen]), noisy, T if with_pose else None))
    return images


def z_scores(result) -> dict[str, float]:
    return {n: (getattr(result.camera, n) - getattr(TRUE_CAMERA, n)) / result.sigma[n] for n in result.free}


# -- the model ----------------------------------------------------------------------


@pytest.mark.parametrize("space", ["pixel", "ideal"])
def test_analytic_jacobian_is_the_derivative_of_the_residuals(space, rng):
    cams = [TRUE_CAMERA, dataclasses.replace(TRUE_CAMERA, c_mm=12.2, K1=-8e-4)]
    n, s = 10, 3
    pts = np.c_[rng.uniform(-200, 200, (n, 2)), rng.uniform(-50, 50, n)]
    stations = np.c_[rng.normal(0, 0.2, (s, 3)), np.array([0, 0, 1000.0]) + rng.normal(0, 20, (s, 3))]
    offsets = np.array([[0.05, -0.1, 0.02, -150.0, 5.0, 10.0]])
    st, k, i = (np.array(a) for a in zip(*[(a, b, c) for a in range(s) for b in range(2) for c in range(n)]))
    free = np.ones(n, bool)
    free[0] = False
    extra = ExtraRows(
        control=((1, pts[1] + 0.1, 0.05),), bars=((2, 3, 100.0, 0.01),), inner=(np.arange(1, n), pts[1:] + 0.2, 7, 3.0)
    )
    model = BundleModel(
        cams,
        [("c_mm", "x0_mm", "K1", "P2", "B1"), ("c_mm", "K2", "B2", "y0_mm")],
        st,
        k,
        i,
        rng.uniform(0, 1000, (len(st), 2)),
        s,
        free,
        True,
        pts,
        offsets,
        space,
        0.1,
        extra,
    )
    x = model.pack(cams, stations, offsets, pts)
    J = model.jacobian(x).toarray()
    numeric = np.zeros_like(J)
    for j in range(len(x)):
        h = 1e-4 * max(abs(x[j]), 1e-9) if j < model.n_interior else 1e-6 * max(1.0, abs(x[j]))
        e = np.zeros_like(x)
        e[j] = h
        numeric[:, j] = (model.residuals(x + e) - model.residuals(x - e)) / (2 * h)
    scale = np.abs(numeric).max(axis=0) + 1e-12
    assert np.max(np.abs(J - numeric) / scale) < 1e-5


def test_field_similarity_leaves_every_image_residual_unchanged(rng):
    # the free network's datum defect: rotation, translation and scale of the field frame
    field = field_3d(rng, 12)
    poses = convergent_poses(rng, 3)
    st = np.array([params_from_T(inv_T(T)) for T in poses])
    s, i = (np.array(a) for a in zip(*[(a, c) for a in range(3) for c in range(12)]))
    model = BundleModel(
        [TRUE_CAMERA],
        [PARAMETER_NAMES],
        s,
        np.zeros_like(s),
        i,
        rng.uniform(0, 1000, (36, 2)),
        3,
        np.ones(12, bool),
        False,
        field.xyz,
        np.zeros((0, 6)),
        "pixel",
        0.1,
        ExtraRows(),
    )
    x = model.pack([TRUE_CAMERA], st, np.zeros((0, 6)), field.xyz)
    J = model.jacobian(x).toarray()
    E = gauge_basis(model, x, 7)
    assert np.abs(J @ E).max() < 1e-9 * np.abs(J).max() * np.abs(E).max()
    assert np.linalg.matrix_rank(E) == 7


# -- recovery and precision ----------------------------------------------------------------


@pytest.mark.parametrize("seed", [11, 12, 13, 14])
def test_self_calibration_recovers_every_interior_parameter_within_3_sigma(seed):
    rng = np.random.default_rng(seed)
    field = field_3d(rng)
    images = observe(rng, field, convergent_poses(rng, 12))
    result = calibrate_camera(NOMINAL_CAMERA, field, images, sigma_px=NOISE_PX)
    assert result.free == PARAMETER_NAMES
    z = z_scores(result)
    assert all(abs(v) < 3.0 for v in z.values()), z
    assert 0.8 * NOISE_PX < result.sigma0_px < 1.25 * NOISE_PX
    rms = [im.rms_px for im in result.images]
    assert 0.6 * NOISE_PX < min(rms) and max(rms) < 1.5 * NOISE_PX
    assert result.n_rejected <= 2  # Gaussian noise: at most a rare false alarm
    assert result.correlation.shape == (10, 10) and np.allclose(np.diag(result.correlation), 1.0)


def test_ideal_space_residuals_recover_the_camera_too(rng):
    field = field_3d(rng)
    images = observe(rng, field, convergent_poses(rng, 12))
    result = calibrate_camera(NOMINAL_CAMERA, field, images, sigma_px=NOISE_PX, residual_space="ideal")
    assert all(abs(v) < 3.0 for v in z_scores(result).values())
    assert 0.7 * NOISE_PX < result.sigma0_px < 1.3 * NOISE_PX  # ideal-coordinate residuals, in px


@pytest.mark.slow
def test_sigmas_agree_with_monte_carlo_scatter_within_20_percent():
    # 150 trials: the standard error of a sample standard deviation is 1/sqrt(2 * 149) = 5.8 %,
    # so 20 % is a 3.4-sigma margin per parameter. Same geometry, new noise each trial.
    rng = np.random.default_rng(7)
    field = field_3d(rng, n=40)
    poses = convergent_poses(rng, 8)
    estimates, sigmas = [], []
    for _ in range(150):
        images = observe(rng, field, poses, with_pose=True)
        r = calibrate_camera(TRUE_CAMERA, field, images, sigma_px=NOISE_PX, reject_outliers=False)
        estimates.append(r.camera.params())
        sigmas.append([r.sigma[n] for n in PARAMETER_NAMES])
    scatter = np.std(estimates, axis=0, ddof=1)
    ratio = scatter / np.mean(sigmas, axis=0)
    assert np.all((0.8 < ratio) & (ratio < 1.2)), dict(zip(PARAMETER_NAMES, np.round(ratio, 3), strict=True))


def test_gross_errors_are_rejected_and_do_not_bias_the_camera(rng):
    field = field_3d(rng)
    images = observe(rng, field, convergent_poses(rng, 12))
    bad = []
    for k in range(12):  # one wrong measurement in each image, 2-30 px off
        im = images[k]
        j = int(rng.integers(len(im.ids)))
        uv = im.uv.copy()
        uv[j] += rng.choice([-1, 1], 2) * rng.uniform(2.0, 30.0, 2)
        images[k] = dataclasses.replace(im, uv=uv)
        bad.append((k, im.ids[j]))
    result = calibrate_camera(NOMINAL_CAMERA, field, images, sigma_px=NOISE_PX)
    rejected = {(int(result.image_index[m]), result.ids[m]) for m in np.flatnonzero(~result.inliers)}
    assert set(bad) <= rejected
    assert len(rejected - set(bad)) <= 2
    assert all(abs(v) < 3.0 for v in z_scores(result).values())
    assert 0.8 * NOISE_PX < result.sigma0_px < 1.25 * NOISE_PX
    assert {r["image"] for r in result.rejected()} >= {f"img{k:02d}" for k, _ in bad}


def test_fixed_parameters_keep_their_start_values_and_zero_sigma(rng):
    field = field_3d(rng)
    images = observe(rng, field, convergent_poses(rng, 10))
    start = dataclasses.replace(NOMINAL_CAMERA, K3=TRUE_CAMERA.K3, B1=TRUE_CAMERA.B1, B2=TRUE_CAMERA.B2)
    result = calibrate_camera(
        start, field, images, free=("c_mm", "x0_mm", "y0_mm", "K1", "K2", "P1", "P2"), sigma_px=NOISE_PX
    )
    for n in ("K3", "B1", "B2"):
        assert getattr(result.camera, n) == getattr(start, n) and result.sigma[n] == 0.0
    assert result.correlation.shape == (7, 7)
    assert all(abs(v) < 3.0 for v in z_scores(result).values())


def test_calibrated_camera_resects_a_new_image_to_the_noise_level(rng):
    field = field_3d(rng)
    result = calibrate_camera(NOMINAL_CAMERA, field, observe(rng, field, convergent_poses(rng, 12)), sigma_px=NOISE_PX)
    image = observe(rng, field, convergent_poses(rng, 1))[0]
    for camera, lo, hi in ((result.camera, 0.7, 1.4), (NOMINAL_CAMERA, 20.0, np.inf)):
        r = resect(camera, field.xyz[field.indices_of(list(image.ids))], image.uv, reject_outliers=False)
        assert lo * NOISE_PX < r.rms_px < hi * NOISE_PX


# -- datum and field survey -------------------------------------------------------------------


def test_free_network_keeps_the_nominal_frame_and_surveys_the_targets(rng):
    truth = field_3d(rng)
    nominal = dataclasses.replace(truth, xyz=truth.xyz + rng.normal(0.0, 0.5, truth.xyz.shape))
    images = observe(rng, truth, convergent_poses(rng, 12))
    result = calibrate_camera(NOMINAL_CAMERA, nominal, images, sigma_px=NOISE_PX)
    p, p0 = result.field.xyz, nominal.xyz
    # inner constraints: no shift, rotation or scale of the adjusted targets against the nominal ones
    q0 = p0 - p0.mean(0)
    assert np.allclose(p.mean(0), p0.mean(0), atol=1e-6)
    assert np.abs(np.sum(np.cross(q0, p - p0), axis=0)).max() < 1e-3 * len(p)
    assert abs(np.sum(q0 * (p - p0))) < 1e-3 * len(p)
    # the survey: the adjusted shape is the true one, to its sigma
    d_true = np.linalg.norm(truth.xyz[:, None] - truth.xyz[None], axis=2)
    d_adj = np.linalg.norm(p[:, None] - p[None], axis=2)
    d_nom = np.linalg.norm(p0[:, None] - p0[None], axis=2)
    scale = np.median(d_adj[d_true > 0] / d_true[d_true > 0])
    assert abs(scale - 1.0) < 2e-3  # the nominal field's scale, from 0.5 mm noise on 120 targets
    shape_err = np.abs(d_adj / scale - d_true)[np.triu_indices(len(p), 1)]
    assert np.median(shape_err) < 0.2 * np.median(np.abs(d_nom - d_true)[np.triu_indices(len(p), 1)])
    assert np.all(result.sigma_xyz_mm > 0) and np.median(result.sigma_xyz_mm) < 0.05


def test_scale_bar_sets_the_scale_of_a_wrongly_scaled_nominal_field(rng):
    truth = field_3d(rng)
    nominal = dataclasses.replace(truth, xyz=truth.xyz * 1.01)
    images = observe(rng, truth, convergent_poses(rng, 12))
    a, b = 0, int(np.argmax(np.linalg.norm(truth.xyz - truth.xyz[0], axis=1)))
    length = float(np.linalg.norm(truth.xyz[b] - truth.xyz[a]))
    bar = ScaleBar(truth.ids[a], truth.ids[b], length, 0.01)
    with_bar = calibrate_camera(NOMINAL_CAMERA, nominal, images, datum=Datum(scale_bars=(bar,)), sigma_px=NOISE_PX)
    without = calibrate_camera(NOMINAL_CAMERA, nominal, images, sigma_px=NOISE_PX)
    i, j = with_bar.field.index[truth.ids[a]], with_bar.field.index[truth.ids[b]]
    assert abs(np.linalg.norm(with_bar.field.xyz[i] - with_bar.field.xyz[j]) - length) < 0.05
    k = int(np.argmin(np.abs(np.linalg.norm(truth.xyz - truth.xyz[a], axis=1) - 0.5 * length)))
    check = np.linalg.norm(with_bar.field.xyz[k] - with_bar.field.xyz[i])
    assert abs(check / np.linalg.norm(truth.xyz[k] - truth.xyz[a]) - 1.0) < 1e-3
    ratio = np.linalg.norm(without.field.xyz[j] - without.field.xyz[i]) / length
    assert abs(ratio - 1.01) < 1e-3  # no bar: the nominal field's (wrong) scale
    # the camera does not depend on the datum
    assert abs(with_bar.camera.c_mm - without.camera.c_mm) < 0.1 * with_bar.sigma["c_mm"]


def test_control_points_stay_fixed_and_unknown_targets_are_intersected(rng):
    truth = field_3d(rng)
    control = [
        int(np.argmin(np.linalg.norm(truth.xyz[:, :2] - c, axis=1)))
        for c in ((-300, -230), (300, -230), (300, 230), (-300, 230), (0, 0), (0, 200))
    ]
    known = Field("control", tuple(truth.ids[i] for i in control), truth.xyz[control], np.full(6, -1), np.full(6, 6.0))
    images = observe(rng, truth, convergent_poses(rng, 12))
    result = calibrate_camera(NOMINAL_CAMERA, known, images, datum=Datum(control=known.ids), sigma_px=NOISE_PX)
    assert len(result.field) == len(truth)
    for tid in known.ids:
        i = result.field.index[tid]
        assert np.array_equal(result.field.xyz[i], truth.xyz[truth.index[tid]])
        assert np.all(result.sigma_xyz_mm[i] == 0.0)
    new = [t for t in result.field.ids if t not in known.index]
    rows = result.field.indices_of(new)
    z = (result.field.xyz[rows] - truth.xyz[truth.indices_of(new)]) / result.sigma_xyz_mm[rows]
    assert 0.5 < np.mean(z**2) < 2.0  # the surveyed targets scatter as their sigma says
    assert all(abs(v) < 3.0 for v in z_scores(result).values())


def test_a_new_target_seen_in_one_image_is_left_out_of_the_field_with_a_warning(rng):
    """A target of no known position seen in a single image has no coordinates: the calibration
    goes on, says so, and the refined field (and its per-target arrays) leave it out (a NaN row
    made the field refuse itself: 'field coordinates must be finite')."""
    truth = field_3d(rng)
    control = [
        int(np.argmin(np.linalg.norm(truth.xyz[:, :2] - c, axis=1)))
        for c in ((-300, -230), (300, -230), (300, 230), (-300, 230))
    ]
    known = Field("control", tuple(truth.ids[i] for i in control), truth.xyz[control], np.full(4, -1), np.full(4, 6.0))
    images = observe(rng, truth, convergent_poses(rng, 12))
    lonely = next(t for t in images[0].ids if t not in known.index)
    images = [images[0]] + [
        ImagePoints(im.name, tuple(t for t in im.ids if t != lonely), im.uv[[t != lonely for t in im.ids]])
        for im in images[1:]
    ]
    result = calibrate_camera(NOMINAL_CAMERA, known, images, datum=Datum(control=known.ids), sigma_px=NOISE_PX)
    assert lonely not in result.field.index and len(result.field) == len(truth) - 1
    assert len(result.sigma_xyz_mm) == len(result.n_rays) == len(result.target_rms_px) == len(result.field)
    assert np.all(np.isfinite(result.field.xyz))
    assert any(repr(lonely) in w and "left out of the field" in w for w in result.warnings)
    assert [t["id"] for t in result.report()["targets"]] == list(result.field.ids)


def test_datum_with_too_few_control_points_is_refused(rng):
    truth = field_3d(rng)
    images = observe(rng, truth, convergent_poses(rng, 8))
    with pytest.raises(SolveError) as e:
        calibrate_camera(NOMINAL_CAMERA, truth, images, datum=Datum(control=truth.ids[:2]))
    assert e.value.reason == Reason.bad_input and "3" in e.value.message


# -- degenerate networks ------------------------------------------------------------------------


def test_images_parallel_to_a_planar_field_are_refused_with_advice(rng):
    plate = scene.reference_field()
    poses = [scene.reference_pose(90.0, 1000.0 + 40 * k, 90.0 * k, 0.0, (25.0 * k, 0, 0)) for k in range(6)]
    with pytest.raises(SolveError) as e:
        calibrate_camera(NOMINAL_CAMERA, plate, observe(rng, plate, poses))
    assert e.value.reason == Reason.degenerate_geometry
    assert "head-on" in e.value.message and "convergent" in e.value.message and "rolled" in e.value.message


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_convergent_images_of_a_plate_without_roll_are_refused_with_advice(rng):
    # the classic weak network: the principal distance and point trade off against the poses
    plate = scene.reference_field()
    poses = [scene.reference_pose(55.0, 1100.0, 0.0, azimuth) for azimuth in range(0, 360, 45)]
    assert network_geometry(plate.xyz, poses)["roll_spread_deg"] < 1.0
    with pytest.raises(SolveError) as e:
        calibrate_camera(NOMINAL_CAMERA, plate, observe(rng, plate, poses))
    assert e.value.reason == Reason.degenerate_geometry
    assert "not rolled" in e.value.message and "rolled by 90" in e.value.message
    rolled = [scene.reference_pose(55.0, 1100.0, 90.0 * (k % 2) + 0.3 * a, a) for k, a in enumerate(range(0, 360, 45))]
    calibrate_camera(NOMINAL_CAMERA, plate, observe(rng, plate, rolled))  # the same views, half rolled: fine


def test_too_few_images_are_refused(rng):
    field = field_3d(rng)
    with pytest.raises(SolveError) as e:
        calibrate_camera(NOMINAL_CAMERA, field, observe(rng, field, convergent_poses(rng, 2)))
    assert e.value.reason == Reason.degenerate_geometry and "at least 3" in e.value.message


def test_weighted_control_points_move_within_their_sigma(rng):
    truth = field_3d(rng)
    ids = truth.ids[:8]
    nominal = dataclasses.replace(truth, xyz=truth.xyz.copy())
    nominal.xyz[:8] += rng.normal(0.0, 0.2, (8, 3))  # surveyed to 0.2 mm
    images = observe(rng, truth, convergent_poses(rng, 12))
    result = calibrate_camera(
        NOMINAL_CAMERA, nominal, images, datum=Datum(control=ids, control_sigma_mm=0.2), sigma_px=NOISE_PX
    )
    rows = result.field.indices_of(list(ids))
    assert np.all(result.sigma_xyz_mm[rows] > 0) and np.all(result.sigma_xyz_mm[rows] < 0.2)
    assert result.datum["kind"] == "control points" and result.datum["control_sigma_mm"] == 0.2
    assert all(abs(v) < 3.0 for v in z_scores(result).values())
