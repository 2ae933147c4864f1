"""The edge centres (``edge_kernel.edge_centres_kernel``) against a NumPy fit.

The reference finds each disk's edge as the kernel's docstring says, with array operations: per
row (column) of the window that crosses the disk steeply, the run of pixels above the half level
through the centroid's pixel (``np.flatnonzero`` of those below it on either side), the linear
crossings at its ends; then the direct conic through all of them by ``np.linalg.solve`` (the same
tiny ridge), the same acceptance, and the centre's sigma from the points' algebraic residuals,
summed point by point, over the conic's RMS gradient.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels.edge_kernel import MARGIN_PX, MIN_POINTS, STEEP, edge_centres_kernel
from service.core.targets.detect import detect_blobs
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose


def _run_ends(line, centre, level):
    """Linear crossings of the sloped ``level`` (one value a pixel of ``line``, linear in the index)
    at both ends of the run above it through ``centre``, or None."""
    above = line > level
    if not above[centre]:
        return None
    left, right = np.flatnonzero(~above[:centre]), np.flatnonzero(~above[centre + 1 :]) + centre + 1
    if left.size == 0 or right.size == 0:
        return None  # the run reaches the window's edge
    i, j = left[-1] + 1, right[0] - 1
    # the line between two pixels meets the level's line between them: (d_line - d_level) t = -(line - level)
    x0 = (i - 1) + (level[i - 1] - line[i - 1]) / ((line[i] - line[i - 1]) - (level[i] - level[i - 1]))
    x1 = j + (line[j] - level[j]) / ((line[j] - line[j + 1]) - (level[j] - level[j + 1]))
    return x0, x1


def _reference(image, uv, e, bg, gradient=(0.0, 0.0)):
    """(centre (2,), sigma) of the disk's edge fit, or None; its half level scaled by the light
    ``1 + gu (u - cu) + gv (v - cv)`` about its centroid."""
    img = image.astype(np.float64)
    cu, cv = uv
    a, b, ang = e[2], e[3], e[4]
    if not (np.isfinite(uv).all() and a > 0 and b > 0):
        return None
    R = int(np.ceil(a)) + MARGIN_PX
    ur, vr = int(np.rint(cu)), int(np.rint(cv))
    h, w = img.shape
    if ur - R < 0 or vr - R < 0 or ur + R >= w or vr + R >= h:
        return None
    core = np.median(img[vr - 1 : vr + 2, ur - 1 : ur + 2])
    if not core > bg:
        return None
    half = 0.5 * (bg + core)
    su, sv = 0.5 * (core - bg) * gradient[0], 0.5 * (core - bg) * gradient[1]
    us, vs = np.arange(ur - R, ur + R + 1), np.arange(vr - R, vr + R + 1)
    ext_u = np.hypot(a * np.cos(ang), b * np.sin(ang))
    ext_v = np.hypot(a * np.sin(ang), b * np.cos(ang))
    pts = []
    for v in range(vr - R, vr + R + 1):
        level = half + su * (us - cu) + sv * (v - cv)
        if abs(v - cv) <= STEEP * ext_v and (ends := _run_ends(img[v, ur - R : ur + R + 1], R, level)):
            pts += [(ur - R + x - cu, v - cv) for x in ends]
    for u in range(ur - R, ur + R + 1):
        level = half + su * (u - cu) + sv * (vs - cv)
        if abs(u - cu) <= STEEP * ext_u and (ends := _run_ends(img[vr - R : vr + R + 1, u], R, level)):
            pts += [(u - cu, vr - R + y - cv) for y in ends]
    if len(pts) < MIN_POINTS:
        return None
    x, y = (np.array(pts) / a).T
    M = np.column_stack([x * x, x * y, y * y, x, y])
    G = M.T @ M
    G += np.eye(5) * (1e-9 * np.trace(G) + 1e-12)
    A, B, C, D, E = np.linalg.solve(G, M.sum(axis=0))
    det = A * C - B * B / 4
    if not det > 0:
        return None
    x0, y0 = -0.5 * (C * D - 0.5 * B * E) / det, -0.5 * (A * E - 0.5 * B * D) / det
    if not (np.hypot(x0, y0) * a < 0.5 * b + 0.5 and 1 + 0.5 * (D * x0 + E * y0) > 0):
        return None
    f = M @ [A, B, C, D, E] - 1
    grad2 = (2 * A * x + B * y + D) ** 2 + (B * x + 2 * C * y + E) ** 2
    n = len(pts)
    ss = np.sum(f**2) / np.mean(grad2) * a * a  # the residuals' sum of squares over the RMS gradient
    return np.array([cu + x0 * a, cv + y0 * a]), np.sqrt(ss / (n - 5) * 2 / n)


@pytest.fixture(scope="module")
def scene():
    settings = RenderSettings(read_noise_dn=2.0)
    pose = reference_pose(view_angle_deg=65.0)
    frame = render_frame(reference_camera(), reference_field(), pose, settings, np.random.default_rng(3))
    blobs, _ = detect_blobs(frame.image)
    return frame.image, blobs


def _check(image, uv, e, bg, gradient=None):
    gradient = np.zeros((len(uv), 2)) if gradient is None else gradient
    got_uv, sigma, ok = edge_centres_kernel(image, uv, e, bg, gradient)
    for i in range(len(uv)):
        ref = _reference(image, uv[i], e[i], bg[i], gradient[i])
        assert (ref is not None) == ok[i], i
        if ok[i]:  # the same crossings; sums and a solve in another order: round-off
            np.testing.assert_allclose(got_uv[i], ref[0], rtol=0, atol=1e-9, err_msg=str(i))
            assert sigma[i] == pytest.approx(ref[1], rel=1e-6)
        else:
            np.testing.assert_array_equal(got_uv[i], uv[i])
            assert np.isnan(sigma[i])
    return ok


@pytest.mark.parametrize("deep", [False, True])
@pytest.mark.parametrize("light", [False, True])
def test_edge_centres_are_the_numpy_fit(scene, deep, light, rng):
    """With one half level, and with a level following a light across each disk (a gradient of up
    to 0.3 % a px, as a ring light's fall-off at a frame's corner, and to 1 %)."""
    image, blobs = scene
    image = image.astype(np.uint16) * 257 if deep else image
    bg = blobs.background_dn * (257 if deep else 1)
    gradient = rng.uniform(-0.01, 0.01, (len(blobs), 2)) if light else None
    ok = _check(image, blobs.uv, blobs.ellipse, np.ascontiguousarray(bg), gradient)
    assert ok.mean() > 0.97


def test_poor_starts_no_disk_and_the_border_are_judged_as_numpy_judges_them(scene, rng):
    image, blobs = scene
    h, w = image.shape
    n = 60
    uv, e, bg = blobs.uv[:n].copy(), blobs.ellipse[:n].copy(), blobs.background_dn[:n].copy()
    uv += rng.uniform(-0.6, 0.6, (n, 2))  # a contour's errors
    e[:, 2:4] *= rng.uniform(0.85, 1.15, (n, 1))
    image = image.copy()
    image[h // 2 - 100 : h // 2 + 100, 20:220] = 10  # a flat patch, and ellipses on it: no edge
    uv[:4] = [[60.0 + 30 * k, h / 2] for k in range(4)]
    uv[4] = [2.0, 100.0]  # the window leaves the image
    e[5, 2] = np.nan  # no ellipse
    bg[6] = 255.0  # a background above the core: nothing to find
    ok = _check(image, np.ascontiguousarray(uv), np.ascontiguousarray(e), np.ascontiguousarray(bg))
    assert not ok[:7].any() and ok[7:].mean() > 0.9
    none = edge_centres_kernel(image, np.zeros((0, 2)), np.zeros((0, 5)), np.zeros(0), np.zeros((0, 2)))
    assert [x.shape for x in none] == [(0, 2), (0,), (0,)]
