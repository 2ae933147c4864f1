"""ROI tracking's compiled bookkeeping against the numpy expressions it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels.roi_kernel import gather_found_kernel, measure_predicted_kernel, window_half_size_kernel
from service.core.targets.detect_types import DetectSettings
from service.core.targets.detect_windows import assess, assess_constants, measure_all
from tests.core.kernels.test_detect_kernel import _scene


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


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_predicted_windows_are_measured_and_assessed_as_the_numpy_path_does(rng, dtype):
    """The one call of ROI tracking against measure_all + assess + the selection of accepted
    windows (what measure_windows did in numpy): the same disks, rows, sigma, fill and indices."""
    img, full, centres, radii = _scene(rng, dtype)
    n = len(centres)
    uv = centres + rng.uniform(-1.5, 1.5, (n, 2))
    uv[0] = [np.nan, 40.0]  # no prediction
    uv[1] = [3.0, 3.0]  # a window reaching out of the image
    half = np.ascontiguousarray(np.ceil(radii + 5), dtype=np.intp)
    half[2] = 2  # too small for its disk: refused
    seg, contrast = 0.03 * full, 0.08 * full
    limits, codes = assess_constants(DetectSettings())
    frozen = img.view()
    frozen.flags.writeable = False  # a replayed frame is read-only: the same measurement
    table, sigma, fill, found = measure_predicted_kernel(frozen, uv, half, seg, contrast, float(full), limits, codes)

    finite = np.isfinite(uv).all(axis=1)
    c = np.rint(np.where(finite[:, None], uv, -1e6)).astype(np.intp).T.copy()
    meas, placed = measure_all(img, c[0], c[1], np.where(finite, half, 0), np.full(n, seg), full, None)
    reason, sigma_ref, fill_ref = assess(meas, placed, DetectSettings(), np.full(n, contrast))
    ok = ((reason < 0) & ~meas.edge & placed).nonzero()[0]
    assert 0 < ok.size < n - 3 and not placed[:2].any() and found[2] == -1  # accepted, refused, outside
    np.testing.assert_array_equal(found[ok], np.arange(ok.size))
    assert np.all(np.delete(found, ok) == -1)
    np.testing.assert_array_equal(table, meas.table[:, ok])
    np.testing.assert_array_equal(sigma, sigma_ref[ok])
    np.testing.assert_array_equal(fill, fill_ref[ok])
