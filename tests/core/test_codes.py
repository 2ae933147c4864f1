"""posecell's coded targets: the code family, and reading rings from rendered images.

Images come from the product's renderer (``service.sim.render``): exact
perspective and distortion, anti-aliased, blurred, with shot and read noise.
The disk ellipse that the reader needs is either the exact image of the disk
rim (projected, then fitted) or, as in the pipeline, ``cv2.fitEllipse`` on the
thresholded disk contour.
"""

from __future__ import annotations

import itertools
import sys

import cv2
import numpy as np
import pytest

from service.core.geometry.frames import apply_T, inv_T
from service.core.targets import codes as C
from service.core.targets.decode import read_code, read_codes
from service.core.targets.field import Field
from service.sim.render import RenderSettings, plane_axes_field, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

CODED_DIAMETER_MM = 10.0


# -- the code family ---------------------------------------------------------


def _rotations(word: int) -> list[int]:
    mask = (1 << C.N_BITS) - 1
    return [((word << k) | (word >> (C.N_BITS - k))) & mask for k in range(C.N_BITS)]


def test_family_has_149_codes_at_hamming_distance_2_under_every_rotation():
    words = C.code_words()
    assert C.n_codes() == len(words) == 149
    d_min = min(
        bin(x ^ r).count("1")
        for (i, x), (j, y) in itertools.product(enumerate(words), repeat=2)
        for k, r in enumerate(_rotations(y))
        if not (i == j and k == 0)
    )
    assert d_min == 2  # every single-bit error is detected; none is corrected


def test_every_single_bit_error_of_every_code_at_every_roll_is_no_code():
    for code in range(1, C.n_codes() + 1):
        bits = C.bits_of(code)
        for roll in range(C.N_BITS):
            read = np.roll(bits, roll)
            assert C.code_from_bits(read) == (code, roll)
            for k in range(C.N_BITS):
                bad = read.copy()
                bad[k] = ~bad[k]
                assert C.code_from_bits(bad) is None


def test_word_table_agrees_with_code_from_bits():
    code, roll = C.word_table()
    for word in range(1 << C.N_BITS):
        bits = np.array([(word >> k) & 1 for k in range(C.N_BITS)], dtype=bool)
        expected = C.code_from_bits(bits)
        assert (None if code[word] == 0 else (code[word], roll[word])) == expected


def test_bright_runs_cover_exactly_the_bright_sectors():
    for code in range(1, C.n_codes() + 1):
        covered = np.zeros(C.N_BITS, dtype=int)
        for first, n in C.bright_runs(code):
            covered[(first + np.arange(n)) % C.N_BITS] += 1
        assert np.array_equal(covered, C.bits_of(code).astype(int))


# -- scenes ------------------------------------------------------------------


def _all_codes_field(spacing_mm: float = 36.0, diameter_mm: float = CODED_DIAMETER_MM) -> Field:
    """Every code once, on a hexagonal grid clipped to a circle (in view at any camera roll)."""
    n = C.n_codes()
    k = np.arange(-10, 11)
    i, j = (a.ravel() for a in np.meshgrid(k, k))
    xy = spacing_mm * np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2], 1)
    xy = xy[np.argsort(np.hypot(*xy.T), kind="stable")[:n]]
    return Field(
        "all-codes",
        tuple(f"C{c}" for c in range(1, n + 1)),
        np.c_[xy, np.zeros(n)],
        np.arange(1, n + 1),
        np.full(n, diameter_mm),
    )


def _tilted_normals(field: Field, T_field_camera, view_deg, rng) -> np.ndarray:
    """Normals (N, 3) at exactly ``view_deg`` (N,) to each target's line of sight, random side."""
    to_camera = T_field_camera[:3, 3] - field.xyz
    d = to_camera / np.linalg.norm(to_camera, axis=1, keepdims=True)
    p = rng.normal(size=d.shape)
    p -= np.sum(p * d, axis=1, keepdims=True) * d
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    a = np.radians(view_deg)[:, None]
    return np.cos(a) * d + np.sin(a) * p


def _disk_ellipses(camera, field, T_field_camera, normals, rows):
    """Exact disk images (M, 5) (u, v, a, b, angle): the projected rim, fitted.

    Also the image direction (M,) deg of each target's local +x axis, as ``roll_deg`` defines it.
    """
    _, ex, ey = plane_axes_field(normals, len(field))
    T_camera_field = inv_T(T_field_camera)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ellipses, x_dir_deg = [], []
    for i in rows:
        r = field.diameters_mm[i] / 2
        rim = field.xyz[i] + r * (np.cos(t)[:, None] * ex[i] + np.sin(t)[:, None] * ey[i])
        uv = camera.pixel_from_camera(apply_T(T_camera_field, rim))
        (cu, cv), (w, h), ang = cv2.fitEllipse(uv.astype(np.float32))
        ellipses.append((cu, cv, w / 2, h / 2, np.radians(ang)))
        tip = np.stack([field.xyz[i], field.xyz[i] + 0.01 * ex[i]])
        centre_x = camera.pixel_from_camera(apply_T(T_camera_field, tip))
        du, dv = centre_x[1] - centre_x[0]
        x_dir_deg.append(np.degrees(np.arctan2(-dv, du)))
    return np.array(ellipses), np.array(x_dir_deg)


def _contour_ellipses(image, uv_guess, threshold_dn):
    """A simple blob detector's ellipses: cv2.fitEllipse on the thresholded contour by each uv."""
    mask = (image > threshold_dn).astype(np.uint8)
    _, labels, _, centroids = cv2.connectedComponentsWithStats(mask)
    out = []
    for uv in uv_guess:
        k = 1 + int(np.argmin(np.linalg.norm(centroids[1:] - uv, axis=1)))
        contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        (cu, cv), (w, h), ang = cv2.fitEllipse(max(contours, key=len))
        out.append((cu, cv, w / 2, h / 2, np.radians(ang)))
    return np.array(out)


def _angle_diff_deg(a, b):
    return (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0


def _render_tilted(field, distance_mm, view_deg, rng, settings=RenderSettings()):
    """A head-on camera with random roll; each target tilted by its own ``view_deg`` (N,) deg."""
    camera = reference_camera()
    T = reference_pose(view_angle_deg=90.0, distance_mm=distance_mm, roll_deg=rng.uniform(-180, 180))
    normals = _tilted_normals(field, T, view_deg, rng)
    frame = render_frame(camera, field, T, settings, rng=rng, normals_field=normals)
    rows = field.indices_of(list(frame.ids))[frame.fully_visible]
    ellipses, x_dir_deg = _disk_ellipses(camera, field, T, normals, rows)
    return frame, rows, ellipses, x_dir_deg


# -- reading rings -----------------------------------------------------------


@pytest.mark.parametrize("distance_mm", [1000.0, 2200.0], ids=["disk-18px", "disk-8px"])
def test_every_code_decodes_at_random_roll_and_view_angles_up_to_60_deg(distance_mm, rng):
    field = _all_codes_field()
    view_deg = rng.uniform(0.0, 60.0, len(field))
    view_deg[::7] = 60.0  # the limit itself, for a seventh of the codes
    frame, rows, ellipses, x_dir_deg = _render_tilted(field, distance_mm, view_deg, rng)
    assert len(rows) == C.n_codes()  # the whole plate is in view
    diameter_px = 2 * ellipses[:, 2:4].max(axis=1)
    assert np.median(diameter_px) == pytest.approx(10.0 * 12.0 / 0.0067 / distance_mm, rel=0.05)

    readings = read_codes(frame.image, ellipses)
    read = np.array([r.code if r else 0 for r in readings])
    truth = field.codes[rows]
    assert np.array_equal(read, truth), f"misread or missed codes: {truth[read != truth]}"
    confidence = np.array([r.confidence for r in readings])
    roll_err = _angle_diff_deg([r.roll_deg for r in readings], x_dir_deg)
    # Noise and blur keep the margin below 1; a 60 deg view of an 8 px disk still leaves one.
    assert 0.2 <= confidence.min() and np.median(confidence) < 0.99
    # The roll comes from the sector edges: 0.1 deg on 18 px disks, under 1.5 deg on 8 px disks.
    assert 0.02 < np.sqrt(np.mean(roll_err**2)) < 1.5
    assert np.all(np.array([np.array_equal(r.bits, C.bits_of(r.code)) for r in readings]))


@pytest.mark.parametrize("diameter_px", [8.0, 12.0, 25.0, 40.0])
def test_decoding_holds_for_disks_from_8_to_40_px_at_60_deg(diameter_px, rng):
    codes = rng.choice(np.arange(1, C.n_codes() + 1), 16, replace=False)
    distance_mm = 1000.0
    diameter_mm = diameter_px * distance_mm * 0.0067 / 12.0
    spacing = 2 * C.RING_OUTER * diameter_mm / 2 * 1.25
    xy = np.stack(np.meshgrid(np.arange(4) - 1.5, np.arange(4) - 1.5), -1).reshape(-1, 2) * spacing
    field = Field("sizes", tuple(f"C{c}" for c in codes), np.c_[xy, np.zeros(16)], codes, np.full(16, diameter_mm))
    frame, rows, ellipses, x_dir_deg = _render_tilted(field, distance_mm, np.full(16, 60.0), rng)
    assert len(rows) == 16
    readings = read_codes(frame.image, ellipses)
    assert [r.code if r else 0 for r in readings] == field.codes[rows].tolist()
    roll_err = _angle_diff_deg([r.roll_deg for r in readings], x_dir_deg)
    assert np.max(np.abs(roll_err)) < 6.0
    assert np.sqrt(np.mean(roll_err**2)) < 2.0


def test_one_bit_error_in_the_printed_ring_reads_as_no_code(rng, monkeypatch):
    field = _all_codes_field()
    view_deg = rng.uniform(0.0, 60.0, len(field))
    seed = int(rng.integers(1 << 31))
    # Control: the same scene with intact rings reads completely.
    frame, rows, ellipses, _ = _render_tilted(field, 1200.0, view_deg, np.random.default_rng(seed))
    intact_readings = read_codes(frame.image, ellipses)
    assert all(r is not None and r.code == c for r, c in zip(intact_readings, field.codes[rows]))

    wrong_bit = rng.integers(0, C.N_BITS, C.n_codes())
    flipped = {c: int(k) for c, k in zip(range(1, C.n_codes() + 1), wrong_bit)}
    intact = C.bits_of

    def bits_with_one_error(code: int) -> np.ndarray:
        bits = intact(code).copy()
        bits[flipped[code]] = ~bits[flipped[code]]
        return bits

    # Wherever the renderer looks the ring pattern up, it gets the damaged one.
    patched = [
        m
        for name, m in list(sys.modules.items())
        if name.startswith("service.sim") and getattr(m, "bits_of", None) is intact
    ]
    assert patched, "the renderer no longer draws rings through codes.bits_of; adapt this test"
    for module in patched:
        monkeypatch.setattr(module, "bits_of", bits_with_one_error)
    frame, rows, ellipses, _ = _render_tilted(field, 1200.0, view_deg, np.random.default_rng(seed))
    readings = read_codes(frame.image, ellipses)
    assert len(readings) == C.n_codes()
    assert all(r is None for r in readings), [r.code for r in readings if r]


def test_uncoded_disk_is_not_read_as_a_code(rng):
    field = reference_field(n_coded=0, n_uncoded=40, size_mm=(400.0, 300.0), uncoded_diameter_mm=10.0)
    frame, rows, ellipses, _ = _render_tilted(field, 1000.0, rng.uniform(0, 60, len(field)), rng)
    assert len(rows) == 40
    assert all(r is None for r in read_codes(frame.image, ellipses))


def test_bright_neighbour_disks_just_outside_the_ring_do_not_disturb_reading(rng):
    codes = rng.choice(np.arange(1, C.n_codes() + 1), 12, replace=False)
    r_mm = CODED_DIAMETER_MM / 2
    centres = np.stack([np.arange(12) % 4 * 90.0 - 135.0, np.arange(12) // 4 * 90.0 - 90.0], 1)
    # Four 6 mm neighbours per coded target, 1 mm clear of its ring, at a random angle.
    angles = rng.uniform(0, 2 * np.pi, (12, 1)) + np.arange(4) * np.pi / 2
    gap = C.RING_OUTER * r_mm + 1.0 + 3.0
    nb = (centres[:, None, :] + gap * np.stack([np.cos(angles), np.sin(angles)], -1)).reshape(-1, 2)
    xy = np.concatenate([centres, nb])
    n_nb = len(nb)
    field = Field(
        "neighbours",
        tuple([f"C{c}" for c in codes] + [f"P{k}" for k in range(n_nb)]),
        np.c_[xy, np.zeros(len(xy))],
        np.r_[codes, np.full(n_nb, -1)],
        np.r_[np.full(12, CODED_DIAMETER_MM), np.full(n_nb, 6.0)],
    )
    camera = reference_camera()
    T = reference_pose(
        view_angle_deg=45.0, distance_mm=900.0, azimuth_deg=rng.uniform(0, 360), roll_deg=rng.uniform(-180, 180)
    )
    frame = render_frame(camera, field, T, rng=rng)
    rows = np.arange(12)
    ellipses, _ = _disk_ellipses(camera, field, T, None, rows)
    readings = read_codes(frame.image, ellipses)
    assert [r.code if r else 0 for r in readings] == codes.tolist()


def test_reference_scene_decodes_from_contour_ellipses_with_noise_and_blur(rng):
    # The pipeline's situation: ellipses from a thresholded contour, a 60 deg view, more blur.
    field = reference_field()
    camera = reference_camera()
    settings = RenderSettings(blur_sigma_px=0.9, target_dn=120.0, read_noise_dn=2.5)
    T = reference_pose(view_angle_deg=30.0, distance_mm=1000.0, azimuth_deg=rng.uniform(0, 360))
    frame = render_frame(camera, field, T, settings, rng=rng)
    rows = field.indices_of(list(frame.ids))
    coded = np.flatnonzero((field.codes[rows] > 0) & frame.fully_visible)
    assert len(coded) >= 20
    ellipses = _contour_ellipses(frame.image, frame.uv_disk_centroid[coded], settings.background_dn + 30)
    readings = read_codes(frame.image, ellipses)
    truth = field.codes[rows[coded]]
    assert all(r is None or r.code == c for r, c in zip(readings, truth))  # never a wrong code
    # The far, dim, steep end of the plate may fall below the margin; nearly all must read.
    n_read = sum(r is not None for r in readings)
    assert n_read >= 0.9 * len(coded)
    confidence = np.array([r.confidence for r in readings if r is not None])
    assert 0.2 <= confidence.min() and np.median(confidence) < 0.99


def test_image_depth_does_not_change_the_reading(rng):
    field = _all_codes_field()
    frame, rows, ellipses, _ = _render_tilted(field, 1500.0, rng.uniform(0, 45, len(field)), rng)
    base = read_codes(frame.image, ellipses)
    for image in (frame.image.astype(np.uint16) * 257, frame.image.astype(np.float32) / 255):
        again = read_codes(image, ellipses)
        assert [r.code for r in again] == [r.code for r in base]
        assert np.allclose([r.confidence for r in again], [r.confidence for r in base], atol=0.02)


def test_read_code_returns_none_off_the_image_or_for_a_degenerate_ellipse(rng):
    field = _all_codes_field()
    frame, rows, ellipses, _ = _render_tilted(field, 1000.0, np.zeros(len(field)), rng)
    e = ellipses[0]
    assert read_code(frame.image, tuple(e)).code == field.codes[rows[0]]
    assert read_code(frame.image, (2.0, 3.0, e[2], e[3], e[4])) is None  # ring leaves the image
    assert read_code(frame.image, (e[0], e[1], 0.0, e[3], e[4])) is None
    assert read_code(frame.image, (e[0], e[1], np.nan, e[3], e[4])) is None
    flat = np.zeros((50, 60), np.uint8)
    assert read_code(flat, (30.0, 25.0, 4.0, 4.0, 0.0)) is None  # no contrast
    assert read_codes(frame.image, np.zeros((0, 5))) == []
    with pytest.raises(ValueError, match="shape"):
        read_codes(frame.image, np.zeros((3, 4)))
    with pytest.raises(ValueError, match="2-D"):
        read_codes(np.zeros((5, 5, 3)), ellipses[:1])


def test_given_background_level_reads_the_same_code(rng):
    field = _all_codes_field()
    frame, rows, ellipses, _ = _render_tilted(field, 1000.0, rng.uniform(0, 60, len(field)), rng)
    readings = read_codes(frame.image, ellipses, background_dn=RenderSettings().background_dn)
    assert [r.code if r else 0 for r in readings] == field.codes[rows].tolist()
    assert all(r.background_dn == RenderSettings().background_dn for r in readings)


@pytest.mark.parametrize("dtype, scale", [(np.uint8, 1), (np.uint16, 257), (np.float64, 1 / 255)])
def test_ring_samples_are_those_of_cv2_remap(dtype, scale, rng):
    # The compiled reader samples as the former vectorised one did through cv2.remap (positions
    # rounded to 1/32 px; 8-bit in fixed point): the same readings, at a fraction of the cost.
    from service.core._kernels import decode_kernel

    image = (rng.integers(0, 256, (40, 60)) * scale).astype(dtype)
    e = np.array([29.3, 19.7, 6.1, 4.2, 0.7])
    pts = rng.uniform(-5.5, 5.5, (4000, 2))  # some fall outside the image
    ca, sa = np.cos(e[4]), np.sin(e[4])
    m = (ca * e[2], -sa * e[3], sa * e[2], ca * e[3])
    mode = {np.uint8: decode_kernel.FIXED8, np.uint16: decode_kernel.ROUNDED}.get(dtype, decode_kernel.FLOAT)
    got = np.empty(len(pts))
    decode_kernel._sample(image, mode, e, *m, pts, got)
    u = (e[0] + m[0] * pts[:, 0] + m[1] * pts[:, 1]).astype(np.float32)[None]
    v = (e[1] + m[2] * pts[:, 0] + m[3] * pts[:, 1]).astype(np.float32)[None]
    ref = cv2.remap(
        image.astype(np.float32) if dtype == np.float64 else image,
        u,
        v,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )[0].astype(np.float64)
    inside = (u[0] >= 0) & (u[0] <= 59) & (v[0] >= 0) & (v[0] <= 39)
    assert 0.6 < inside.mean() < 0.95
    assert np.all(np.isnan(got[~inside]))
    if dtype == np.uint8:
        assert np.array_equal(got[inside], ref[inside])
    elif dtype == np.uint16:  # rounded in floating point: now and then 1 DN apart
        assert np.abs(got[inside] - ref[inside]).max() <= 1 and np.mean(got[inside] != ref[inside]) < 0.01
    else:
        assert np.allclose(got[inside], ref[inside], rtol=1e-5, atol=1e-6)
