"""ROI tracking's compiled bookkeeping against the numpy expressions it replaces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core._kernels.roi_kernel import OWN_RADII, gather_found_kernel, ring_masks_kernel, window_half_size_kernel
from service.core.targets.identify import plane_axes


def test_window_sizes_equal_the_numpy_formula(rng):
    radius_mm = rng.uniform(1.0, 8.0, 300)
    c_mm, pixel_mm = 12.0, 0.0067
    for _ in range(20):
        rows = rng.choice(300, 230, replace=False)
        depth = rng.uniform(-50.0, 3000.0, 230)  # below 1 mm too
        allowance, rim = rng.uniform(0.5, 10.0), rng.uniform(3.0, 8.0)
        r_px = radius_mm[rows] * c_mm / np.maximum(depth, 1.0) / pixel_mm
        expected = np.maximum(np.ceil(r_px + rim + allowance), 3).astype(np.int64)
        got = window_half_size_kernel(radius_mm * c_mm, rows, depth, pixel_mm, allowance, rim)
        np.testing.assert_array_equal(got, expected)


def test_found_targets_are_gathered_with_their_largest_offset_from_the_window_centre(rng):
    blob_uv = rng.uniform(0, 1000, (200, 2))
    rows = rng.choice(400, 230, replace=False)
    found = np.where(rng.random(230) < 0.8, rng.integers(0, 200, 230), -1)
    uv_pred = rng.uniform(0, 1000, (230, 2))
    rows_ok, uv, worst = gather_found_kernel(found, blob_uv, rows, uv_pred)
    ok = found >= 0
    np.testing.assert_array_equal(rows_ok, rows[ok])
    np.testing.assert_array_equal(uv, blob_uv[found[ok]])
    off = uv - np.rint(uv_pred[ok])
    assert worst == np.max(off[:, 0] ** 2 + off[:, 1] ** 2)
    none = gather_found_kernel(np.full(230, -1), blob_uv, rows, uv_pred)
    assert none[0].size == 0 and none[1].shape == (0, 2)


@pytest.mark.parametrize("planes", ["field", "own"])  # every target in the field's x-y plane, or each in its own
def test_a_coded_targets_own_region_is_its_disk_seen_through_the_pinhole_grown_to_the_gap(rng, planes):
    """The own region's edge against the disk's circle at OWN_RADII radii projected point by point
    through the pinhole (the affine is the projection's first order: a 5 mm disk at ~1 m is
    projected to within 1 % of the region's size: seen 0.4 % at 60 deg), in oblique views."""
    n_field = 40
    xyz = np.column_stack([rng.uniform(-300, 300, (n_field, 2)), np.zeros(n_field)])
    radius_mm = rng.uniform(3.0, 6.0, n_field)
    coded = rng.random(n_field) < 0.5
    f_px = 1791.0
    theta = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    if planes == "field":
        ex, ey = np.tile([1.0, 0.0, 0.0], (n_field, 1)), np.tile([0.0, 1.0, 0.0], (n_field, 1))
    else:  # a cell's floor and walls: planes turned up to 50 deg from the field's, some facing away
        normals = Rotation.from_euler("xy", rng.uniform(-50, 50, (n_field, 2)), degrees=True).apply([0.0, 0.0, 1.0])
        ex, ey = plane_axes(normals)
    for view_deg in (90.0, 60.0, 40.0):
        R_fc = Rotation.from_euler("xz", [180.0 + (90.0 - view_deg), rng.uniform(0, 360)], degrees=True).as_matrix()
        centre = np.array([rng.uniform(-50, 50), rng.uniform(-50, 50), 0.0])
        c_field = centre - 1000.0 * R_fc[:, 2]  # the camera 1 m from the plate's point, looking at it
        R_cf, t_cf = R_fc.T, -R_fc.T @ c_field
        rows = np.arange(n_field, dtype=np.int64)

        def pixel(p_field):
            p = p_field @ R_cf.T + t_cf
            return f_px * p[:, :2] / p[:, 2:3]

        uv_pred = pixel(xyz) + 650.0 + rng.uniform(-0.5, 0.5, (n_field, 2))
        own = ring_masks_kernel(
            R_cf, t_cf, xyz, ex, ey, radius_mm, coded, rows, uv_pred, f_px, np.full(n_field, 40), 2.0
        )
        assert np.all(np.isnan(own[~coded])) and np.all(np.isfinite(own[coded]))
        for j in np.flatnonzero(coded):
            ring = xyz[j] + OWN_RADII * radius_mm[j] * (np.outer(np.cos(theta), ex[j]) + np.outer(np.sin(theta), ey[j]))
            d = pixel(ring) - pixel(xyz[j : j + 1])  # about the disk's centre's image
            x0, y0, qa, qb, qc = own[j]
            assert np.allclose([x0, y0], uv_pred[j] - np.rint(uv_pred[j]))
            rho = qa * d[:, 0] ** 2 + 2 * qb * d[:, 0] * d[:, 1] + qc * d[:, 1] ** 2  # 1 on the region's edge
            assert np.all(np.abs(np.sqrt(rho) - 1.0) < 1e-2), (view_deg, j, np.abs(np.sqrt(rho) - 1).max())
    # a ring that stays clear of its window (head-on, a small window) is not masked: no region
    R_cf, t_cf = np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 1000.0])
    uv_pred = np.zeros((n_field, 2))
    ex, ey = np.tile([1.0, 0.0, 0.0], (n_field, 1)), np.tile([0.0, 1.0, 0.0], (n_field, 1))
    small = ring_masks_kernel(R_cf, t_cf, xyz, ex, ey, radius_mm, coded, rows, uv_pred, f_px, np.full(n_field, 3), 2.0)
    large = ring_masks_kernel(R_cf, t_cf, xyz, ex, ey, radius_mm, coded, rows, uv_pred, f_px, np.full(n_field, 40), 2.0)
    assert np.all(np.isnan(small)) and np.all(np.isfinite(large[coded]))
