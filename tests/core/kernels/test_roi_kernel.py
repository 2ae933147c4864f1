"""ROI tracking's compiled bookkeeping against the numpy expressions it replaces."""

from __future__ import annotations

import numpy as np

from service.core._kernels.roi_kernel import gather_found_kernel, window_half_size_kernel


def test_window_sizes_equal_the_numpy_formula_for_coded_and_uncoded_targets(rng):
    radius_mm = rng.uniform(1.0, 8.0, 300)
    coded = rng.random(300) < 0.2
    c_mm, pixel_mm = 12.0, 0.0067
    for _ in range(20):
        rows = rng.choice(300, 230, replace=False)
        depth = rng.uniform(-50.0, 3000.0, 230)  # below 1 mm too
        allowance = rng.uniform(0.5, 10.0)
        r_px = radius_mm[rows] * c_mm / np.maximum(depth, 1.0) / pixel_mm
        half = np.ceil(r_px + 3.0 + allowance)
        half[coded[rows]] = np.minimum(half[coded[rows]], np.floor(2.0 * r_px[coded[rows]] - 4.0))
        expected = np.maximum(half, 3).astype(np.int64)
        got = window_half_size_kernel(radius_mm * c_mm, coded, rows, depth, pixel_mm, allowance)
        np.testing.assert_array_equal(got, expected)
        assert got.min() == 3 and got.max() > 3  # both the floor and the sizes were exercised


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
