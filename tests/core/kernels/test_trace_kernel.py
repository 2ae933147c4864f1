"""The external contours (``service.core._kernels.trace_kernel``) are OpenCV's, vertex for vertex.

``external_contours_kernel`` is compared with ``cv2.findContours(mask, RETR_EXTERNAL,
CHAIN_APPROX_SIMPLE)`` on the seeded masks of the contour statistics' tests (disks, rings,
single pixels, lines, blobs joined at a corner, blobs at the border), on masks of dense random
noise (holes in blobs in holes, blobs at every border) and on nested rings with a pixel inside:
the same vertices, in the same order.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.core._kernels.trace_kernel import FG, NEW, RIGHT, external_contours_kernel, words_of
from service.core.targets.detect_candidates import contours
from tests.core.kernels.test_contour_kernel import _mask


def _opencv(mask):
    found, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    lengths = np.array([len(c) for c in found], dtype=np.intp)
    pts = np.concatenate(found).reshape(-1, 2) if found else np.zeros((0, 2), np.int32)
    return pts, np.cumsum(lengths) - lengths, lengths


def _assert_as_opencv(mask):
    want = _opencv(mask)
    m = mask.copy()
    got = external_contours_kernel(m, words_of(m))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert set(np.unique(m)) <= {0, FG, NEW, RIGHT}  # only the marks were written
    return got


@pytest.mark.parametrize("shape", [(240, 320), (61, 77), (33, 9), (1030, 1300)])
def test_contours_of_every_kind_of_blob_are_opencvs(rng, shape):
    for _ in range(3):
        _assert_as_opencv(_mask(rng, *shape, n=int(rng.integers(1, 300))))


@pytest.mark.parametrize("density", [0.05, 0.3, 0.6])
def test_contours_of_dense_noise_are_opencvs(rng, density):
    # blobs inside holes of other blobs (not external: skipped), blobs touching every border
    for shape in [(64, 80), (97, 41), (8, 8)]:
        m = ((rng.random(shape) < density) * 255).astype(np.uint8)
        m[-1], m[:, 0] = 255, 255 * (rng.random(shape[0]) < 0.5)
        _assert_as_opencv(m)


def test_nested_rings_give_the_outer_contour_only():
    m = np.zeros((100, 100), np.uint8)
    cv2.circle(m, (50, 50), 40, 255, 3)
    cv2.circle(m, (50, 50), 20, 255, 3)
    m[50, 50] = 255
    _, starts, _ = _assert_as_opencv(m)
    assert starts.size == 1


def test_empty_and_full_masks():
    pts, starts, lengths = _assert_as_opencv(np.zeros((13, 21), np.uint8))
    assert pts.shape == (0, 2) and starts.size == lengths.size == 0
    pts, _, lengths = _assert_as_opencv(np.full((13, 21), 255, np.uint8))
    assert lengths.tolist() == [4]


def test_growing_outputs_and_the_contours_of_any_mask_type(rng):
    # more contours and vertices than the kernel's first buffers hold (256, 4096)
    m = ((rng.random((300, 400)) < 0.2) * 255).astype(np.uint8)
    pts, starts, _ = _assert_as_opencv(m)
    assert starts.size > 256 and len(pts) > 4096
    # a bool or read-only mask is traced on a 0/255 copy, and left as it was
    want, before = contours(m.copy()), m.copy()
    for other in (m > 0, np.require(m, requirements=["C"]).view()):
        other.flags.writeable = False
        got = contours(other)
        np.testing.assert_array_equal(got.box, want.box)
        np.testing.assert_array_equal(got.centre, want.centre)
    np.testing.assert_array_equal(m, before)  # the read-only mask's memory was not written
