"""The near-IR target renderer (service/sim/render.py) and the reference scene (service/sim/scene.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import apply_T, inv_T, make_T
from service.core.targets.codes import N_BITS, RING_INNER, RING_OUTER, bits_of
from service.core.targets.field import Field
from service.sim.render import RenderSettings, hot_pixel_indices, plane_axes_field, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

PIXEL_MM = 0.0067


def one_target(code: int = -1, diameter_mm: float = 6.0, xyz=(0.0, 0.0, 0.0)) -> Field:
    tid = f"C{code}" if code >= 0 else "P1"
    return Field("one", (tid,), np.array([xyz], dtype=float), np.array([code]), np.array([diameter_mm]))


def grid_of_targets(rng: np.random.Generator, coded: bool, n_side: tuple[int, int] = (5, 4)) -> Field:
    """Targets spread over the view at 1000 mm, each at a random sub-pixel phase."""
    xs = np.linspace(-270, 270, n_side[0])
    ys = np.linspace(-200, 200, n_side[1])
    xyz = np.array([(x, y, 0.0) for y in ys for x in xs]) + rng.uniform(-5, 5, (xs.size * ys.size, 3))
    xyz[:, 2] = 0.0
    n = len(xyz)
    codes = np.arange(1, n + 1) if coded else np.full(n, -1)
    ids = tuple(f"C{c}" if coded else f"P{i}" for i, c in enumerate(codes))
    return Field("grid", ids, xyz, codes, np.full(n, 10.0 if coded else 6.0))


def blob_centroid(image: np.ndarray, uv: np.ndarray, radius_px: float, background: float) -> np.ndarray:
    """Intensity-weighted centroid (2,) of image - background within radius_px of uv."""
    u0, v0 = np.round(uv).astype(int)
    r = int(np.ceil(radius_px))
    patch = image[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1].astype(float) - background
    vv, uu = np.mgrid[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1]
    w = patch * ((uu - uv[0]) ** 2 + (vv - uv[1]) ** 2 <= radius_px**2)
    return np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u, v = uv[:, 0], uv[:, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    img = image.astype(float)
    return (
        (1 - fu) * (1 - fv) * img[v0, u0]
        + fu * (1 - fv) * img[v0, u0 + 1]
        + (1 - fu) * fv * img[v0 + 1, u0]
        + fu * fv * img[v0 + 1, u0 + 1]
    )


def disk_radius_px(diameter_mm: float, distance_mm: float, c_mm: float = 12.0) -> float:
    return diameter_mm / 2 * c_mm / distance_mm / PIXEL_MM


# -- geometry ----------------------------------------------------------------

# One level across each target: its intensity centroid is its area centroid (the light's change
# across a target, the default, pulls it towards the light: test_the_light_falls_across_each_target)
EVEN = RenderSettings(shading=False)


@pytest.mark.parametrize("coded", [False, True])
def test_head_on_blob_centroid_matches_disk_centroid(rng, coded):
    cam = reference_camera()
    field = grid_of_targets(rng, coded)
    frame = render_frame(cam, field, reference_pose(90.0, 1000.0), EVEN)  # the geometry alone
    assert frame.ids == field.ids and frame.fully_visible.all()
    r_disk = disk_radius_px(10.0 if coded else 6.0, 1000.0)
    # the window must hold the blurred disk but stay clear of a code ring (at 2 R)
    window = 1.5 * r_disk if coded else r_disk + 3.0
    measured = np.array([blob_centroid(frame.image, uv, window, 8.0) for uv in frame.uv_disk_centroid])
    err = np.linalg.norm(measured - frame.uv_disk_centroid, axis=1)
    assert err.max() < 0.01
    # head-on, the disk images are circles up to distortion: centroid and centre nearly agree
    assert np.max(np.linalg.norm(frame.uv_disk_centroid - frame.uv_true, axis=1)) < 0.01


def test_blob_follows_sub_pixel_motion_of_the_target():
    cam = reference_camera()
    step_mm = 0.1 * PIXEL_MM * 1000.0 / 12.0  # 0.1 px at 1000 mm
    measured, truth = [], []
    for k in range(6):
        frame = render_frame(cam, one_target(xyz=(53.0 + k * step_mm, -31.0, 0.0)), reference_pose())
        truth.append(frame.uv_disk_centroid[0])
        measured.append(blob_centroid(frame.image, frame.uv_disk_centroid[0], 8.5, 8.0))
    shift_true = np.diff(np.array(truth), axis=0)
    shift_measured = np.diff(np.array(measured), axis=0)
    assert np.all(np.abs(shift_true[:, 0] - 0.1) < 0.01)
    assert np.max(np.abs(shift_measured - shift_true)) < 0.005


def test_uv_true_is_the_projection_of_the_target_centre(rng):
    cam = reference_camera()
    field = grid_of_targets(rng, coded=False)
    T = reference_pose(70.0, 900.0, roll_deg=20.0)
    frame = render_frame(cam, field, T)
    rows = field.indices_of(list(frame.ids))
    expected = cam.pixel_from_camera(apply_T(inv_T(T), field.xyz[rows]))
    assert np.allclose(frame.uv_true, expected, atol=1e-9)


def area_centroid_by_ray_casting(cam: BrownFraser, T_field_camera, radius_mm, uv_guess, half_px, step=0.125):
    """Independent area centroid of a disk at the field origin (plane z = 0): cast a ray per sub-pixel."""
    g = np.arange(-half_px, half_px, step) + step / 2
    uu, vv = np.meshgrid(uv_guess[0] + g, uv_guess[1] + g)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    rays_field = cam.rays_from_pixel(uv) @ T_field_camera[:3, :3].T
    centre = T_field_camera[:3, 3]
    t = -centre[2] / rays_field[:, 2]
    hit = centre[:2] + t[:, None] * rays_field[:, :2]
    inside = np.sum(hit**2, axis=1) <= radius_mm**2
    return uv[inside].mean(axis=0)


def test_eccentricity_bias_at_60_degrees_has_the_expected_size():
    cam = reference_camera()
    T = reference_pose(60.0, 400.0)
    big = render_frame(cam, one_target(diameter_mm=20.0), T, EVEN)  # the geometry alone
    small = render_frame(cam, one_target(diameter_mm=10.0), T, EVEN)
    bias_big = np.linalg.norm(big.uv_disk_centroid[0] - big.uv_true[0])
    bias_small = np.linalg.norm(small.uv_disk_centroid[0] - small.uv_true[0])
    # first-order theory for a disk of radius R at distance Z tilted by 30 deg, on axis:
    # the image centroid lies c R^2 sin(2 * tilt) / (2 Z^2) from the projected centre
    theory_px = 12.0 * 10.0**2 * np.sin(np.radians(60.0)) / 2 / 400.0**2 / PIXEL_MM
    assert 0.9 * theory_px < bias_big < 1.1 * theory_px
    assert 3.8 < bias_big / bias_small < 4.2  # grows with R^2
    # an independent area centroid (a ray per 1/8 px) agrees with the ground truth ...
    ray_cast = area_centroid_by_ray_casting(cam, T, 10.0, big.uv_true[0], 60)
    assert np.linalg.norm(ray_cast - big.uv_disk_centroid[0]) < 0.003
    # ... and so does the rendered blob, which is far from uv_true
    blob = blob_centroid(big.image, big.uv_disk_centroid[0], 60.0, 8.0)
    assert np.linalg.norm(blob - big.uv_disk_centroid[0]) < 0.01
    assert np.linalg.norm(blob - big.uv_true[0]) > 0.3


def test_reference_scene_bias_at_60_degrees_is_small_but_not_zero():
    frame = render_frame(reference_camera(), reference_field(), reference_pose(60.0))
    bias = np.linalg.norm(frame.uv_disk_centroid - frame.uv_true, axis=1)
    assert 0.003 < np.median(bias) < 0.05 and bias.max() < 0.1


def sector_samples(field_xyz, radius_mm, T_field_camera, cam, axes=None):
    """Pixels of the middle of each ring sector, and of the disk centre and the dark gap."""
    _, ex, ey = axes if axes is not None else plane_axes_field(None, 1)
    ang = (np.arange(N_BITS) + 0.5) * 2 * np.pi / N_BITS
    r_mid = 0.5 * (RING_INNER + RING_OUTER) * radius_mm
    pts = field_xyz + r_mid * (np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey)
    gap = field_xyz + 1.5 * radius_mm * (np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey)
    all_pts = np.vstack([pts, gap, field_xyz[None, :]])
    uv = cam.pixel_from_camera(apply_T(inv_T(T_field_camera), all_pts))
    return uv[:N_BITS], uv[N_BITS : 2 * N_BITS], uv[-1:]


@pytest.mark.parametrize("code, view_deg, roll_deg", [(7, 90.0, 37.0), (23, 60.0, -110.0), (1, 75.0, 0.0)])
def test_coded_ring_sectors_appear_where_the_bits_say(code, view_deg, roll_deg):
    cam = reference_camera()
    T = reference_pose(view_deg, 600.0, roll_deg=roll_deg, look_at_mm=(30.0, -20.0, 0.0))
    frame = render_frame(cam, one_target(code, 10.0, (30.0, -20.0, 0.0)), T)
    ring_uv, gap_uv, centre_uv = sector_samples(np.array([30.0, -20.0, 0.0]), 5.0, T, cam)
    ring = bilinear(frame.image, ring_uv) - 8.0
    peak = bilinear(frame.image, centre_uv)[0] - 8.0
    bits = bits_of(code)
    assert 0 < bits.sum() < N_BITS
    assert np.all(ring[bits] > 0.8 * peak) and np.all(ring[~bits] < 0.1 * peak)
    assert np.all(bilinear(frame.image, gap_uv) - 8.0 < 0.1 * peak)


def test_ring_follows_a_target_plane_given_by_its_normal():
    # a target on a wall facing field +x, seen by a camera looking along -x
    cam = reference_camera()
    normal = np.array([[1.0, 0.0, 0.0]])
    R_field_camera = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T = make_T(R_field_camera, [700.0, 0.0, 0.0])
    frame = render_frame(cam, one_target(5, 10.0), T, normals_field=normal)
    axes = tuple(a[0] for a in plane_axes_field(normal, 1))
    ring_uv, _, centre_uv = sector_samples(np.zeros(3), 5.0, T, cam, axes)
    ring = bilinear(frame.image, ring_uv) - 8.0
    peak = bilinear(frame.image, centre_uv)[0] - 8.0
    bits = bits_of(5)
    assert np.all(ring[bits] > 0.8 * peak) and np.all(ring[~bits] < 0.1 * peak)
    assert np.allclose(axes[1], [0.0, 1.0, 0.0]) and np.allclose(axes[2], [0.0, 0.0, 1.0])


def test_targets_behind_the_camera_or_seen_from_behind_are_not_drawn():
    cam = reference_camera()
    field = reference_field()
    flipped = np.tile([0.0, 0.0, -1.0], (len(field), 1))
    frame = render_frame(cam, field, reference_pose(), normals_field=flipped)
    assert frame.ids == () and frame.uv_true.shape == (0, 2)
    assert np.all(frame.image == 8)
    looking_away = reference_pose() @ make_T(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    assert render_frame(cam, field, looking_away).ids == ()


def test_a_target_cut_by_the_image_border_is_listed_but_not_fully_visible():
    cam = reference_camera()
    T = reference_pose()
    # field x = 360 mm at 1000 mm lies right at the image's right border
    frame = render_frame(cam, one_target(3, 10.0, (360.0, 0.0, 0.0)), T)
    assert frame.ids == ("C3",) and not frame.fully_visible[0]
    inside = render_frame(cam, one_target(3, 10.0, (300.0, 0.0, 0.0)), T)
    assert inside.fully_visible[0]


def test_unknown_diameters_default_to_10_mm_coded_and_6_mm_uncoded():
    cam, T = reference_camera(), reference_pose()
    xyz = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    unknown = Field("nan", ("C4", "P1"), xyz, np.array([4, -1]), np.array([np.nan, np.nan]))
    known = Field("mm", ("C4", "P1"), xyz, np.array([4, -1]), np.array([10.0, 6.0]))
    assert np.array_equal(render_frame(cam, unknown, T).image, render_frame(cam, known, T).image)
    bigger = Field("big", ("C4", "P1"), xyz, np.array([4, -1]), np.array([12.0, 6.0]))
    assert not np.array_equal(render_frame(cam, bigger, T).image, render_frame(cam, known, T).image)


# -- radiometry --------------------------------------------------------------


def centre_level(frame) -> float:
    u, v = np.round(frame.uv_true[0]).astype(int)
    return float(frame.image[v, u]) - 8.0


def test_brightness_falls_with_distance_squared_and_weakly_with_incidence():
    cam = reference_camera()
    big = one_target(diameter_mm=60.0)
    near = centre_level(render_frame(cam, big, reference_pose(90.0, 1000.0)))
    far = centre_level(render_frame(cam, big, reference_pose(90.0, 1500.0)))
    tilted = centre_level(render_frame(cam, big, reference_pose(60.0, 1000.0)))
    assert abs(near - 190.0) < 2.0
    assert abs(far / near - (1000.0 / 1500.0) ** 2) < 0.02
    assert abs(tilted / near - np.cos(np.radians(30.0)) ** 0.5) < 0.02


def test_the_light_falls_across_each_target():
    """Across a target, not only from one to the next: on a head-on plate a point's light goes as
    its ray's cos(field angle) to the 4 (vignetting) x 2 (distance squared) x 0.5 (incidence), so
    in a corner a 60 mm disk is ~3 % darker 15 px out from its centre than 15 px in. Evenly lit
    (``shading=False``) it is one level."""
    cam = reference_camera()
    big = one_target(diameter_mm=60.0, xyz=(300.0, 230.0, 0.0))
    settings = RenderSettings(bit_depth=16, background_dn=0.0, blur_sigma_px=0.0)
    u0, v0 = np.round(render_frame(cam, big, reference_pose(), settings).uv_true[0]).astype(int)
    px = np.array([[u0 - 15, v0], [u0 + 15, v0], [u0, v0 - 15], [u0, v0 + 15]], dtype=float)
    for shading in (True, False):
        img = render_frame(cam, big, reference_pose(), replace(settings, shading=shading)).image.astype(float)
        level = img[px[:, 1].astype(int), px[:, 0].astype(int)]
        rays = cam.rays_from_pixel(px)
        cos_field = rays[:, 2] / np.linalg.norm(rays, axis=1)
        model = cos_field**6.5 if shading else np.ones(4)
        np.testing.assert_allclose(level[1::2] / level[::2], model[1::2] / model[::2], rtol=2e-3)
        assert (level[0] / level[1] > 1.02) == shading  # the test sees a light that changes


def test_unlit_frame_is_only_background_but_still_reports_targets():
    frame = render_frame(reference_camera(), reference_field(), reference_pose(), RenderSettings(lit=False))
    assert len(frame.ids) == 230 and np.all(frame.image == 8)


def patch_stats(image: np.ndarray) -> tuple[float, float]:
    p = image[300:700, 400:900].astype(float)
    return float(p.mean()), float(p.std())


@pytest.mark.parametrize("background_dn", [8.0, 100.0])
def test_background_noise_matches_read_and_shot_noise(background_dn):
    s = RenderSettings(lit=False, background_dn=background_dn)
    frame = render_frame(reference_camera(), reference_field(), reference_pose(), s, np.random.default_rng(1))
    mean, std = patch_stats(frame.image)
    expected = np.sqrt(s.read_noise_dn**2 + background_dn / s.electrons_per_dn + 1.0 / 12.0)
    assert abs(mean - background_dn) < 0.05
    assert 0.95 * expected < std < 1.05 * expected


def test_low_signal_shot_noise_is_poisson():
    s = RenderSettings(lit=False, background_dn=3.0, electrons_per_dn=1.0, read_noise_dn=0.0)
    frame = render_frame(reference_camera(), one_target(), reference_pose(), s, np.random.default_rng(2))
    values = frame.image[300:700, 400:900].astype(float)
    assert abs(values.mean() - 3.0) < 0.03 and abs(values.var() - 3.0) < 0.08
    assert abs(np.mean(values == 0) - np.exp(-3.0)) < 0.003


def test_noise_is_reproducible_from_the_seed_and_absent_without_rng():
    cam, field, T = reference_camera(), reference_field(), reference_pose()
    a = render_frame(cam, field, T, rng=np.random.default_rng(5)).image
    b = render_frame(cam, field, T, rng=np.random.default_rng(5)).image
    c = render_frame(cam, field, T, rng=np.random.default_rng(6)).image
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.array_equal(render_frame(cam, field, T).image, render_frame(cam, field, T).image)


def test_saturation_clips_at_full_scale():
    cam, field, T = reference_camera(), reference_field(), reference_pose()
    normal = render_frame(cam, field, T, rng=np.random.default_rng(3)).image
    assert 150 < normal.max() < 255
    over = render_frame(cam, field, T, RenderSettings(exposure_scale=4.0), np.random.default_rng(3)).image
    assert over.max() == 255 and np.sum(over == 255) > 230 * 20
    over16 = render_frame(cam, field, T, RenderSettings(exposure_scale=4.0, bit_depth=16)).image
    assert over16.dtype == np.uint16 and over16.max() == 65535


@pytest.mark.parametrize("bit_depth", [12, 16])
def test_deeper_output_scales_the_8_bit_levels(bit_depth):
    cam, field, T = reference_camera(), reference_field(), reference_pose()
    img8 = render_frame(cam, field, T).image.astype(float)
    deep = render_frame(cam, field, T, RenderSettings(bit_depth=bit_depth)).image
    scale = (2**bit_depth - 1) / 255.0
    assert deep.dtype == np.uint16
    assert np.max(np.abs(deep / scale - img8)) <= 0.5 + 0.5 / scale + 1e-9
    assert np.median(deep) == pytest.approx(8.0 * scale, abs=0.5)


# -- artefacts ---------------------------------------------------------------


def test_occluders_remove_targets_from_fully_visible():
    cam, field, T = reference_camera(), reference_field(), reference_pose()
    clear = render_frame(cam, field, T)
    k = clear.ids.index("C8")
    u, v = clear.uv_true[k]
    occluded = render_frame(cam, field, T, RenderSettings(occluders=((u + 6.0, v, 12.0),)))
    assert occluded.ids == clear.ids  # still in the image
    hidden = {t for t, ok in zip(occluded.ids, occluded.fully_visible, strict=True) if not ok}
    assert "C8" in hidden and 1 <= len(hidden) <= 3
    assert occluded.image[round(v), round(u + 6.0)] == 8
    assert clear.image[round(v), round(u)] > 150


def test_hot_spot_raises_the_background_near_its_centre():
    cam, T = reference_camera(), reference_pose()
    off_view = one_target(xyz=(5000.0, 0.0, 0.0))
    s = RenderSettings(hot_spot_dn=40.0, hot_spot_sigma_px=250.0, hot_spot_uv=(500.0, 400.0))
    img = render_frame(cam, off_view, T, s).image.astype(float)
    assert img[400, 500] == pytest.approx(48.0, abs=0.6)
    assert img[400, 750] == pytest.approx(8.0 + 40.0 * np.exp(-0.5), abs=0.6)
    assert img[1020, 1290] == pytest.approx(8.0, abs=0.6)
    unlit = render_frame(cam, off_view, T, RenderSettings(hot_spot_dn=40.0, lit=False)).image
    assert np.all(unlit == 8)  # the glow comes from the ring light


def test_gradient_ramps_the_background_across_the_image():
    img = render_frame(
        reference_camera(), one_target(xyz=(5000.0, 0, 0)), reference_pose(), RenderSettings(gradient_dn=20.0)
    ).image
    assert np.all(img[:, 0] == 8) and np.all(img[:, -1] == 28) and np.all(np.diff(img[500].astype(int)) >= 0)


def test_settings_reject_impossible_values():
    with pytest.raises(ValueError, match="bit_depth"):
        RenderSettings(bit_depth=7)
    with pytest.raises(ValueError, match="supersample"):
        RenderSettings(supersample=0)
    with pytest.raises(ValueError, match="electrons_per_dn"):
        RenderSettings(electrons_per_dn=0.0)
    with pytest.raises(ValueError, match="occluder"):
        RenderSettings(occluders=((1.0, 2.0, -3.0),))


def test_a_disk_in_the_corner_covers_the_area_its_rays_hit():
    """The compiled coverage maps pixels to the target's plane through the camera's own correction:
    ~28 px of it in the corners, so a kernel that got it wrong would be far off here."""
    cam = reference_camera()
    T = reference_pose()
    xyz = np.array([300.0, 230.0, 0.0])
    frame = render_frame(
        cam,
        one_target(diameter_mm=20.0, xyz=tuple(xyz)),
        T,
        RenderSettings(blur_sigma_px=0.0, background_dn=0.0, shading=False),  # the geometry alone
    )
    img = frame.image.astype(float)
    peak = np.median(img[img > 0.99 * img.max()])  # fully covered pixels
    area_rendered_px2 = img.sum() / peak
    step = 0.125  # independent: a ray per sub-pixel, hit or miss
    uv0 = frame.uv_true[0]
    g = np.arange(-22.0, 22.0, step) + step / 2
    uu, vv = np.meshgrid(uv0[0] + g, uv0[1] + g)
    rays_field = cam.rays_from_pixel(np.stack([uu.ravel(), vv.ravel()], axis=1)) @ T[:3, :3].T
    t = -T[2, 3] / rays_field[:, 2]
    hit = T[:2, 3] + t[:, None] * rays_field[:, :2] - xyz[:2]
    area_cast_px2 = np.count_nonzero(np.sum(hit**2, axis=1) <= 10.0**2) * step**2
    assert np.linalg.norm(uv0 - [650, 515]) > 400  # in a corner indeed
    assert abs(area_rendered_px2 / area_cast_px2 - 1.0) < 0.005


# -- the reference scene -----------------------------------------------------


def test_reference_field_is_a_deterministic_plate_of_230_targets():
    f = reference_field()
    g = reference_field()
    assert f.ids == g.ids and np.array_equal(f.xyz, g.xyz)
    assert len(f) == 230 and f.is_planar() and np.all(f.xyz[:, 2] == 0.0)
    assert sorted(f.codes[f.is_coded].tolist()) == list(range(1, 31))
    assert {f.ids[i] for i in np.flatnonzero(f.is_coded)} == {f"C{c}" for c in range(1, 31)}
    assert {t for t in f.ids if t.startswith("P")} == {f"P{n}" for n in range(1, 201)}
    # code rings (3.2 R = 16 mm) keep well clear of their neighbours
    d = np.linalg.norm(f.xyz[:, None] - f.xyz[None], axis=2) + np.eye(len(f)) * 1e9
    assert d.min() > 2 * 16.0


def test_reference_pose_has_the_requested_view_angle_distance_and_roll():
    T = reference_pose(60.0, 1200.0, roll_deg=15.0, look_at_mm=(10.0, 20.0, 0.0))
    z_cam = T[:3, 2]
    assert np.degrees(np.arcsin(abs(z_cam[2]))) == pytest.approx(60.0)
    to_target = np.array([10.0, 20.0, 0.0]) - T[:3, 3]
    assert np.linalg.norm(to_target) == pytest.approx(1200.0)
    assert np.allclose(np.cross(to_target / 1200.0, z_cam), 0.0, atol=1e-12)
    head_on = reference_pose()
    assert np.allclose(head_on[:3, :3], np.diag([1.0, -1.0, -1.0]))
    rolled = reference_pose(roll_deg=90.0)
    assert np.allclose(rolled[:3, 0], [0.0, -1.0, 0.0], atol=1e-12)  # image +x turned towards +y


def test_reference_scene_shows_all_targets_head_on_and_most_at_60_degrees():
    cam, field = reference_camera(), reference_field()
    head_on = render_frame(cam, field, reference_pose(90.0))
    assert len(head_on.ids) == 230 and head_on.fully_visible.all()
    tilted = render_frame(cam, field, reference_pose(60.0))
    coded = np.array([t.startswith("C") for t in tilted.ids])
    assert tilted.fully_visible.sum() >= 200 and np.sum(tilted.fully_visible & coded) >= 25


def test_reference_plate_shows_at_least_four_coded_targets_in_close_partial_views(rng):
    cam, field = reference_camera(), reference_field()
    for _ in range(8):
        # at 500 mm the view spans ~350 x 275 mm; keep it on the 640 x 500 mm plate
        look_at = (rng.uniform(-140, 140), rng.uniform(-110, 110), 0.0)
        T = reference_pose(rng.uniform(60, 90), 500.0, rng.uniform(-180, 180), rng.uniform(-180, 180), look_at)
        frame = render_frame(cam, field, T)
        coded_visible = sum(ok and t.startswith("C") for t, ok in zip(frame.ids, frame.fully_visible, strict=True))
        assert coded_visible >= 4, look_at


def test_hot_pixels_are_the_sensors_the_same_in_every_frame_light_on_or_off():
    camera, field = reference_camera(), reference_field()
    settings = RenderSettings(hot_pixels=5e-4, read_noise_dn=0.0, electrons_per_dn=1e6)
    rng = np.random.default_rng(0)
    lit = render_frame(camera, field, reference_pose(), settings, rng).image
    dark = render_frame(camera, field, reference_pose(80.0, 1100.0), replace(settings, lit=False), rng).image
    expected = hot_pixel_indices(camera.height, camera.width, 5e-4, 0)
    assert expected.size == round(5e-4 * camera.width * camera.height)
    # in the dark frame the hot pixels are all that stands above the background
    assert np.array_equal(np.flatnonzero(dark > settings.background_dn + 100), expected)
    assert np.all(lit.reshape(-1)[expected] >= settings.background_dn + settings.hot_pixel_dn - 1)
    with pytest.raises(ValueError, match="hot_pixels"):
        RenderSettings(hot_pixels=0.5)
