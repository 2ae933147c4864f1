"""Resection without a prior pose always finds its start (issue #11, item 2).

A plate of coded targets with one raised target (a block) counts as non-planar,
and the DLT, underdetermined with a single point off the plane, used to be the
only start tried: the frame failed although every observation was right. Every
applicable closed form must be tried until the adjustment confirms one.

Scenes are seeded: targets are placed by casting rays through random pixels onto
the plate (or onto a plane raised above it), so every target is in view. Each
case is seen from 0-60 deg off the plate's normal at 700-1400 mm. Poses must be
recovered to 1e-3 mm from exact pixels and, with noise, to within a two-sided
band of the noise-propagated sigma.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import apply_T, inv_T
from service.core.pose import resection
from service.core.pose.resection import resect, resect_closed_form
from service.core.pose.resection_closed_form import coplanar_majority
from service.core.results import PoseResult, Reason
from service.core.targets.codes import AICON14
from service.core.targets.decode import read_codes
from service.core.targets.detect import DetectSettings, detect_blobs
from service.core.targets.identify import match_coded
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.scene import reference_camera
from service.store import formats
from tests.conftest import shared_data
from tests.core.test_resection import camera_looking_at, pose_error

SIGMA_PX = 0.05
TILTS_DEG = (0.0, 20.0, 40.0, 60.0)  # of the optical axis from the plate's normal
DISTANCES_MM = (700.0, 1000.0, 1400.0)
CAMERA = reference_camera()
#: what a frame must never fail with when a good start exists
START_FAILURES = (Reason.behind_camera, Reason.no_convergence, Reason.degenerate_geometry)


def raised_plate_scene(
    rng: np.random.Generator, n: int, height_mm: np.ndarray, tilt_deg: float, distance_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_field_camera, p_field (n, 3) mm, exact uv (n, 2) px): target i at field z = ``height_mm[i]``."""
    T = camera_looking_at(90.0 - tilt_deg, distance_mm)
    uv = rng.uniform([40, 40], [CAMERA.width - 41, CAMERA.height - 41], (n, 2))
    d_field = CAMERA.rays_from_pixel(uv) @ T[:3, :3].T
    s = (height_mm - T[2, 3]) / d_field[:, 2]
    p = T[:3, 3] + s[:, None] * d_field
    p[:, 2] = height_mm  # exactly, not to round-off
    return T, p, CAMERA.pixel_from_camera(apply_T(inv_T(T), p))


def wrong_ids(rng: np.random.Generator, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``p`` with the targets ``rows`` read as other plate targets 80-250 mm away (a wrong code)."""
    p = p.copy()
    angle = rng.uniform(0.0, 2 * np.pi, len(rows))
    p[rows, :2] += rng.uniform(80.0, 250.0, (len(rows), 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
    p[rows, 2] = 0.0
    return p


def assert_every_view_resects(rng: np.random.Generator, n: int, height_mm, n_wrong: int = 0) -> None:
    """Resect the scene from every tilt and distance, exact and with noise; check pose and inliers.

    ``height_mm`` (n,) mm or a function of the rng giving it; ``n_wrong`` plate targets
    (never raised ones) get a wrong id and must be the only ones rejected.
    """
    z = []  # position errors over their sigma, every view and axis: a two-sided band
    for tilt_deg in TILTS_DEG:
        for distance_mm in DISTANCES_MM:
            h = height_mm(rng) if callable(height_mm) else np.asarray(height_mm, dtype=float)
            T_true, p, uv = raised_plate_scene(rng, n, h, tilt_deg, distance_mm)
            wrong = rng.choice(np.flatnonzero(h == 0.0), n_wrong, replace=False)
            p = wrong_ids(rng, p, wrong)
            view = f"tilt {tilt_deg:g} deg at {distance_mm:g} mm"
            if n_wrong == 0:
                res = resect(CAMERA, p, uv)
                dt, dtheta = pose_error(res.T_field_camera, T_true)
                assert np.max(np.abs(dt)) < 1e-3, (view, dt)
                assert np.max(np.abs(dtheta)) < 1e-8, (view, dtheta)
                assert res.rejected.size == 0, view
            res = resect(CAMERA, p, uv + rng.normal(0.0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
            dt, dtheta = pose_error(res.T_field_camera, T_true)
            assert sorted(res.rejected.tolist()) == sorted(wrong.tolist()), (view, res.rejected, wrong)
            assert np.all(np.abs(dt) < 5 * res.sigma_position_mm), (view, dt / res.sigma_position_mm)
            assert np.all(np.abs(dtheta) < 5 * np.radians(res.sigma_rotation_deg)), view
            f = 2 * int(res.inliers.sum()) - 6  # sigma0**2 f / sigma**2 is chi^2(f)
            band = np.sqrt(chi2.ppf([1e-5, 1 - 1e-5], f) / f) * SIGMA_PX
            assert band[0] < res.sigma0_px < band[1], (view, res.sigma0_px, band)
            z.extend(dt / res.sigma_position_mm)
    rms = np.sqrt(np.mean(np.square(z)))
    assert 0.5 < rms < 1.6, rms


def one_raised(n: int, raise_mm: float) -> np.ndarray:
    h = np.zeros(n)
    h[0] = raise_mm
    return h


# -- synthetic scenes ------------------------------------------------------------------


@pytest.mark.parametrize("raise_mm", [20.0, 50.0, 80.0, 200.0])
@pytest.mark.parametrize("n", [6, 8, 12, 30])
def test_a_plate_with_one_raised_target_resects_from_every_view(rng, n, raise_mm):
    # one raised target makes the field non-planar (relief over spread ~0.02-0.3), and the
    # DLT is then underdetermined: the homography of the plate's targets is the start
    assert_every_view_resects(rng, n, one_raised(n, raise_mm))


@pytest.mark.parametrize("raises_mm", [(60.0, 40.0), (80.0, 30.0, 55.0), (200.0, 200.0)])
@pytest.mark.parametrize("n", [8, 12, 30])
def test_a_plate_with_a_few_raised_targets_resects_from_every_view(rng, n, raises_mm):
    h = np.zeros(n)
    h[: len(raises_mm)] = raises_mm
    assert_every_view_resects(rng, n, h)


@pytest.mark.parametrize("relief_mm", [0.2, 0.5, 1.0, 3.0])
@pytest.mark.parametrize("n", [6, 12, 30])
def test_a_nearly_planar_plate_resects_from_every_view(rng, n, relief_mm):
    # relief about the thresholds between "flat" (planar start only) and "some relief"
    assert_every_view_resects(rng, n, lambda g: g.uniform(0.0, relief_mm, n))


@pytest.mark.parametrize(("n", "n_wrong"), [(8, 1), (12, 1), (12, 2), (20, 3), (30, 2), (30, 5)])
@pytest.mark.parametrize("raise_mm", [50.0, 80.0, 200.0])
def test_wrong_codes_next_to_one_raised_target_are_rejected_and_the_pose_recovered(rng, n, n_wrong, raise_mm):
    assert_every_view_resects(rng, n, one_raised(n, raise_mm), n_wrong=n_wrong)


def test_closed_form_alone_starts_a_plate_with_one_raised_target(rng):
    for tilt_deg in TILTS_DEG:
        T_true, p, uv = raised_plate_scene(rng, 8, one_raised(8, 200.0), tilt_deg, 700.0)
        dt, dtheta = pose_error(resect_closed_form(CAMERA, p, uv), T_true)
        # the homography of the plate's targets, not refined: exact for exact pixels
        assert np.max(np.abs(dt)) < 1e-6 and np.max(np.abs(dtheta)) < 1e-9, (tilt_deg, dt)


def test_coplanar_majority_leaves_out_the_raised_targets_and_needs_a_majority(rng):
    _, p, _ = raised_plate_scene(rng, 30, np.r_[50.0, 20.0, 0.5 * np.ones(28)], 30.0, 1000.0)
    on_plane = coplanar_majority(p)
    assert on_plane.tolist() == [False, False] + [True] * 28
    # a volume holds no plane with half its points
    T = camera_looking_at(70.0, 1000.0)
    p_volume = apply_T(
        T, CAMERA.rays_from_pixel(rng.uniform([15, 15], [1280, 1010], (30, 2))) * rng.uniform(700, 1400, (30, 1))
    )
    assert coplanar_majority(p_volume) is None


def test_the_usual_start_alone_serves_a_plate_a_volume_and_a_wrong_code(rng, monkeypatch):
    # the common frame pays for one closed form and one adjustment: no fallback is looked for
    def no_fallback(*args, **kwargs):
        raise AssertionError("fallback starts were looked for")

    monkeypatch.setattr(resection, "fallback_starts", no_fallback)
    for heights in (np.zeros(30), rng.uniform(0.0, 300.0, 30)):
        T_true, p, uv = raised_plate_scene(rng, 30, heights, 40.0, 1000.0)
        p = wrong_ids(rng, p, np.array([3]))
        res = resect(CAMERA, p, uv + rng.normal(0.0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
        assert res.rejected.tolist() == [3]
        dt, _ = pose_error(res.T_field_camera, T_true)
        assert np.all(np.abs(dt) < 5 * res.sigma_position_mm)


def test_a_pose_that_rejects_a_quarter_of_the_points_is_kept_when_no_start_does_better(rng):
    # five wrong codes of twenty: every start's adjustment succeeds but rejects more than a fifth,
    # so none is confirmed and the best is kept. It raised AssertionError("unknown resection
    # status 0"): the first adjustment's success was turned into an error (seen on a real panel
    # image measured with edge centres)
    T_true, p, uv = raised_plate_scene(rng, 20, np.zeros(20), 30.0, 1000.0)
    wrong = np.arange(5)
    p = wrong_ids(rng, p, wrong)
    res = resect(CAMERA, p, uv + rng.normal(0.0, SIGMA_PX, uv.shape), sigma_px=SIGMA_PX)
    assert sorted(res.rejected.tolist()) == wrong.tolist()
    dt, _ = pose_error(res.T_field_camera, T_true)
    assert np.all(np.abs(dt) < 5 * res.sigma_position_mm)


# -- the real panel: MicMac's Circ-Code-Target, with its raised block ------------------
#
# Read as tests/test_real_panel.py reads it (nominal camera, AICON 14-bit codes); the panel's
# targets 72, 73 and 74 sit on a block 204 mm above it.

PANEL = "micmac-circ-code-target"
PANEL_POSITIONS = "Positions-3D-14bit_lookup.txt"
PANEL_PIXEL_MM = 23.5 / 6000 * 3  # Nikon D5600, images scaled down 3x
PANEL_CAMERA = BrownFraser(2000, 1333, (PANEL_PIXEL_MM, PANEL_PIXEL_MM), 24.0)
PANEL_DISK_MM = 9.9
# the hand-set detection of tests/test_real_panel.py: it finds 2-3 block targets in 18 images
PANEL_DETECT = DetectSettings(min_contrast_dn=40.0, min_area_px=20, max_area_px=1000)


@pytest.fixture(scope="module")
def panel():
    data = shared_data(PANEL)
    field = formats.field_from_aicon_txt(
        (data / PANEL_POSITIONS).read_text(),
        PANEL_POSITIONS,
        coded_diameter_mm=PANEL_DISK_MM,
        uncoded_diameter_mm=PANEL_DISK_MM,
    )
    images = {p.name[:8]: formats.read_image(p) for p in sorted((data / "images").glob("*_Scaled.tif"))}
    return field, images


def _coded_observations(field, image, detect: DetectSettings) -> tuple[np.ndarray, np.ndarray]:
    """Field rows (N,) and pixels (N, 2) of the coded targets decoded in ``image``."""
    blobs, _ = detect_blobs(image, detect)
    ringed = np.flatnonzero(blobs.has_ring)
    readings = read_codes(image, blobs.ellipse[ringed], blobs.background_dn[ringed], family=AICON14)
    codes = np.full(len(blobs), -1, dtype=np.int64)
    codes[ringed] = [-1 if r is None else r.code for r in readings]
    m = match_coded(field, codes)
    return m.rows, blobs.uv[m.blobs]


def test_real_panel_coded_targets_with_one_block_target_resect(panel):
    # Every image's coded targets with all but one of the block's: each such set resects to the
    # pose and inliers of the adjustment started from the plate's coded targets' pose (the
    # planar start), and that is within the plate's own sigma of it (the nominal camera's ~1 px).
    field, images = panel
    block = np.flatnonzero(field.xyz[:, 2] > 100.0)
    n_sets = 0
    for name, image in images.items():
        rows, uv = _coded_observations(field, image, PANEL_DETECT)
        on_block = np.isin(rows, block)
        plate = resect(PANEL_CAMERA, field.xyz[rows[~on_block]], uv[~on_block], sigma_px=1.0)
        for b in np.flatnonzero(on_block):
            keep = ~on_block
            keep[b] = True
            p, q = field.xyz[rows[keep]], uv[keep]
            res = resect(PANEL_CAMERA, p, q, sigma_px=1.0)
            planar = resect(PANEL_CAMERA, p, q, sigma_px=1.0, T_field_camera_init=plate.T_field_camera)
            what = (name, field.ids[rows[b]])
            dt, dtheta = pose_error(res.T_field_camera, planar.T_field_camera)  # to the adjustment's tolerance
            assert np.max(np.abs(dt)) < 1e-3 and np.max(np.abs(dtheta)) < 1e-7, (what, dt)
            assert np.array_equal(res.inliers, planar.inliers), what
            dt, _ = pose_error(res.T_field_camera, plate.T_field_camera)
            assert np.all(np.abs(dt) < 4 * plate.sigma_position_mm), (what, dt / plate.sigma_position_mm)
            n_sets += 1
    assert n_sets >= 50  # 18 images show 2-3 block targets


def test_real_panel_images_with_one_block_target_are_measured(panel):
    # The whole frame with the default detection: no image fails for want of a start. Those whose
    # decoded targets hold just one block target had only the DLT start and failed with
    # behind_camera: 043_0005 and 043_0017 with the detection defaults of 2026-12, 043_0007,
    # 0011, 0017 and 0033 with the ones before.
    field, images = panel
    block = np.flatnonzero(field.xyz[:, 2] > 100.0)
    settings = MeasureSettings(code_family=AICON14, roi=False, sigma_px=1.0, max_sigma0_px=2.5)
    measurer = FrameMeasurer(PANEL_CAMERA, field, settings)
    one_block_target = []
    for name, image in images.items():
        result = measurer.measure(image).result
        rows, _ = _coded_observations(field, image, settings.detect)
        if np.isin(rows, block).sum() == 1:
            one_block_target.append(name)
            assert isinstance(result, PoseResult), (name, result)
            assert result.n_coded >= 12 and result.rms_px < 2.0, (name, result.n_coded, result.rms_px)
        if not isinstance(result, PoseResult):
            assert result.reason not in START_FAILURES, (name, result)
    if not one_block_target:
        pytest.skip(
            "no image shows just one block target with the default detection "
            "(test_real_panel_coded_targets_with_one_block_target_resect covers the case)"
        )
