"""The defect patch, compiled, against the numpy expressions it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels.defects_kernel import patch_kernel
from service.core.targets.defects import DefectMap


def _numpy_patch(m: DefectMap, flat: np.ndarray) -> np.ndarray:
    """The patched values as array expressions: the least-differing pair of good opposite neighbours,
    else the good neighbours' mean, else the value itself."""
    a, b = flat[m._pair_a].astype(np.float64), flat[m._pair_b].astype(np.float64)
    step = np.where(m._pair_good, np.abs(a - b), np.inf)
    best = np.argmin(step, axis=1)
    rows = np.arange(a.shape[0])
    value = 0.5 * (a[rows, best] + b[rows, best])
    lone = ~np.isfinite(step[rows, best])
    n_good = (m._weights > 0).sum(axis=1)
    mean = np.einsum("ij,ij->i", flat[m._neighbours].astype(np.float64), m._weights)
    value[lone] = np.where(n_good[lone] > 0, mean[lone], flat[m._flat[lone]])
    return np.rint(value).astype(flat.dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_patch_equals_the_numpy_expressions_with_clusters_and_borders(rng, dtype):
    h, w = 60, 80
    img = rng.integers(0, np.iinfo(dtype).max // 4, (h, w)).astype(dtype)
    uv = np.unique(np.column_stack([rng.integers(0, w, 400), rng.integers(0, h, 400)]), axis=0)
    # clusters (a defect among defects: some with no good pair, one with no good neighbour) and corners
    block = np.array([[u, v] for u in range(10, 13) for v in range(20, 23)])
    uv = np.unique(np.vstack([uv, block, [[0, 0], [w - 1, h - 1], [0, h - 1]]]), axis=0)
    m = DefectMap(w, h, uv)
    expected = img.reshape(-1).copy()
    expected[m._flat] = _numpy_patch(m, img.reshape(-1))
    flat = img.reshape(-1).copy()
    saved = np.empty(m._flat.size, dtype=dtype)
    patch_kernel(flat, m._flat, m._pair_a, m._pair_b, m._pair_good, m._neighbours, m._weights, saved)
    np.testing.assert_array_equal(flat, expected)
    np.testing.assert_array_equal(saved, img.reshape(-1)[m._flat])
    assert flat[21 * w + 11] == img[21, 11]  # the block's centre: no good neighbour, left as it was
