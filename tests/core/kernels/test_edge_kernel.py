"""The edge centres (``decode_kernel.edge_centres_kernel``, the code reader's re-fit) against NumPy.

The reference fits the disk's ellipse to its half-level edge as the re-fit does, on whole arrays:
the rays' samples by ``cv2.remap`` (bilinear, exactly the kernel's samples for 8 bits), the disk
level as their innermost circle's median and the background as ``np.percentile`` (20) of those
beyond 1.25 radii, each ray's first sample below half level and the linear crossing before it, a
direct conic fit by ``np.linalg.solve``, the blur's inward shift of a curved edge (sigma from the
edges' slopes) and the fit again, the same acceptance; the centre's sigma from the edge points'
radial scatter about the fitted ellipse.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels.decode_kernel import FIXED8, ROUNDED, edge_centres_kernel
from service.core.targets import decode as D
from service.core.targets.codes import POSECELL12
from service.core.targets.detect import detect_blobs
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose
from tests.core.kernels.test_decode_kernel import _remap

L = D._layout(POSECELL12)


def _conic(points):
    """Direct least-squares conic ``A x^2 + B xy + C y^2 + D x + E y = 1`` through ``points`` (n, 2)
    (the kernel's tiny ridge), as (centre x, y, semi-axes A >= B, major angle, valid)."""
    x, y = points.T
    M = np.column_stack([x * x, x * y, y * y, x, y])
    G = M.T @ M
    G += np.eye(5) * (1e-9 * np.trace(G) + 1e-12)
    a, b, c, d, e = np.linalg.solve(G, M.sum(axis=0))
    det = a * c - b * b / 4
    cx, cy = -0.5 * (c * d - 0.5 * b * e) / det, -0.5 * (a * e - 0.5 * b * d) / det
    mu = 1 + 0.5 * (d * cx + e * cy)
    lam = np.linalg.eigvalsh(np.array([[a, b / 2], [b / 2, c]]) / mu)
    ok = det > 0 and mu > 0 and np.all(lam > 0)
    angle = 0.5 * np.arctan2(b / mu, (a - c) / mu) + 0.5 * np.pi
    angle = angle - np.pi if angle > 0.5 * np.pi else angle
    return cx, cy, 1 / np.sqrt(lam[0]), 1 / np.sqrt(lam[1]), angle, ok


def _edge_reference(image, e):
    """(centre (2,) px, sigma px) of the ellipse ``e`` re-fitted to the half-level edge, or None
    (a flat patch divides by zero: those rays find no edge, as in the kernel)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return _fit_edge(image, e)


def _fit_edge(image, e):
    rho, dirs, step = L.rho, L.dirs, D.EDGE_STEP
    vals = np.nan_to_num(_remap(image, e, L.refine_pts), nan=0.0).reshape(len(rho), len(dirs))
    hi, lo = np.median(vals[0]), np.percentile(vals[rho > 1.25].ravel(), 20)
    x = (vals - lo) / (hi - lo)
    below = x < 0.5
    hit = below.any(axis=0)
    first = np.argmax(below, axis=0)
    i1 = np.clip(first, 1, len(rho) - 1)
    cols = np.arange(len(dirs))
    x0, x1 = x[i1 - 1, cols], x[i1, cols]
    r = rho[i1 - 1] + step * (x0 - 0.5) / (x0 - x1)
    found = hit & (first > 0) & np.isfinite(r) & (hi > lo)
    ca, sa = np.cos(e[4]), np.sin(e[4])
    M = np.array([[ca * e[2], -sa * e[3]], [sa * e[2], ca * e[3]]])
    ray = dirs @ M.T
    rim = np.linalg.norm(ray, axis=1)
    size = np.sqrt(e[2] * e[3])
    cx, cy, A, B, angle, ok = (
        v * size if k < 4 else v for k, v in enumerate(_conic(r[found, None] * ray[found] / size))
    )
    slope = (x0 - x1) / step / rim
    var = np.where(found & (slope > 0), 1 / (2 * np.pi * slope**2), np.nan)
    finite = var[np.isfinite(var)]
    sigma = np.sqrt(np.median(finite)) if finite.size else np.nan
    rx, ry = r * ray[:, 0] - cx, r * ray[:, 1] - cy
    c, s = np.cos(angle), np.sin(angle)
    t = np.arctan2((-s * rx + c * ry) / B, (c * rx + s * ry) / A)
    kappa = A * B / (A * A * np.sin(t) ** 2 + B * B * np.cos(t) ** 2) ** 1.5
    shift = 0.5 * sigma * sigma * kappa / rim
    shifted = r + np.where(np.isfinite(shift) & ok, np.minimum(shift, 0.5), 0.0)
    cx, cy, A, B, angle, ok2 = (
        v * size if k < 4 else v for k, v in enumerate(_conic(shifted[found, None] * ray[found] / size))
    )
    b0 = min(e[2], e[3])
    ok = ok and ok2 and found.sum() >= 16 and np.hypot(cx, cy) < 0.5 * b0 + 0.5
    ok = ok and 0.6 < min(A, B) / b0 < 1.6 and 0.75 < max(A, B) / max(e[2], e[3]) < 1.33
    if not ok:
        return None
    p = shifted[found, None] * ray[found] - [cx, cy]
    c, s = np.cos(angle), np.sin(angle)
    q = np.hypot((c * p[:, 0] + s * p[:, 1]) / A, (-s * p[:, 0] + c * p[:, 1]) / B)
    res = np.linalg.norm(p, axis=1) * (1 - 1 / q)
    n = int(found.sum())
    return e[:2] + [cx, cy], np.sqrt(np.sum(res**2) / (n - 5) * 2 / n)


@pytest.fixture(scope="module")
def scene():
    settings = RenderSettings(read_noise_dn=2.0)
    frame = render_frame(
        reference_camera(), reference_field(), reference_pose(view_angle_deg=65.0), settings, np.random.default_rng(3)
    )
    blobs, _ = detect_blobs(frame.image)
    return frame.image, blobs.ellipse


def _run(image, e):
    mode = FIXED8 if image.dtype == np.uint8 else ROUNDED
    return edge_centres_kernel(
        image, mode, np.ascontiguousarray(e), L.rho, D.EDGE_STEP, L.dirs, L.refine_pts, L.lo_index, L.lo_gamma
    )


def test_edge_centres_are_the_numpy_fit(scene):
    image, ellipses = scene
    uv, sigma, ok = _run(image, ellipses)
    assert ok.mean() > 0.97
    for i in range(len(ellipses)):
        ref = _edge_reference(image, ellipses[i])
        assert (ref is not None) == ok[i], i
        if ok[i]:  # the same samples; sums and a solve in another order: round-off
            np.testing.assert_allclose(uv[i], ref[0], rtol=0, atol=1e-9, err_msg=str(i))
            assert sigma[i] == pytest.approx(ref[1], rel=1e-6)
        else:
            np.testing.assert_array_equal(uv[i], ellipses[i, :2])
            assert np.isnan(sigma[i])


def test_poor_starts_and_no_disk_are_judged_as_numpy_judges_them(scene, rng):
    image, ellipses = scene
    h, w = image.shape
    poor = ellipses[:60].copy()
    poor[:, :2] += rng.uniform(-0.6, 0.6, (60, 2))  # a contour's errors
    poor[:, 2:4] *= rng.uniform(0.85, 1.15, (60, 1))
    image = image.copy()
    image[h // 2 - 100 : h // 2 + 100, 20:220] = 10  # a flat patch, and five ellipses on it: no edge
    poor[:5, :2] = [[60.0 + 30 * k, h / 2] for k in range(5)]
    poor[5, 2:4] *= 3  # far too big: the fit lands far from it
    uv, sigma, ok = _run(image, poor)
    assert not ok[:6].any() and ok[6:].mean() > 0.9
    for i in range(60):
        ref = _edge_reference(image, poor[i])
        assert (ref is not None) == ok[i], i
        if ok[i]:
            np.testing.assert_allclose(uv[i], ref[0], rtol=0, atol=1e-9)
    none = _run(image, np.zeros((0, 5)))
    assert [x.shape for x in none] == [(0, 2), (0,), (0,)]
    nan = poor[:1].copy()
    nan[0, 2] = np.nan
    assert not _run(image, nan)[2][0]
