"""The full frame's contour statistics, shape classes and windows (``service.core._kernels.contour_kernel``).

The contours are OpenCV's (``cv2.findContours``, as ``detect_candidates.contours`` takes them) of
seeded masks with every kind of blob a frame has: disks, ellipses, rings (holes), single
pixels, lines in all directions, blobs joined at a corner and blobs cut by the image border.
``contour_stats_kernel`` is compared with ``cv2.boundingRect``, ``cv2.contourArea``,
``cv2.moments`` and the pixel count of ``cv2.drawContours`` filled; ``classify_kernel`` with
the moments' ellipse from ``np.linalg.eigvalsh``; ``windows_kernel`` with the window rule
written with ``np.searchsorted`` / ``np.maximum.at`` and its ellipse checked on the axes
``np.linalg.eigh`` gives.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.core._kernels.contour_kernel import classify_kernel, contour_stats_kernel, windows_kernel
from service.core.targets.detect_candidates import MIN_POLYGON_FILL, WINDOW_MARGIN_PX, WINDOW_RADII

RADII = np.array(WINDOW_RADII, dtype=np.intp)


def _mask(rng, height, width, n):
    """0/255 mask (H, W) of ``n`` random blobs of every kind, some at the image border."""
    m = np.zeros((height, width), np.uint8)
    for k in range(n):
        cu, cv = int(rng.integers(0, width)), int(rng.integers(0, height))
        kind = k % 7
        if kind == 0:  # a disk or ellipse, any size and angle
            axes = (int(rng.integers(1, 25)), int(rng.integers(1, 25)))
            cv2.ellipse(m, (cu, cv), axes, float(rng.uniform(0, 180)), 0, 360, 255, -1)
        elif kind == 1:  # a ring: a contour with a hole (the external one only counts)
            r = int(rng.integers(6, 30))
            cv2.circle(m, (cu, cv), r, 255, int(rng.integers(2, 6)))
        elif kind == 2:  # a single pixel
            m[cv, cu] = 255
        elif kind == 3:  # a 1 px line, any direction (a zero-area contour)
            d = rng.integers(-12, 13, 2)
            cv2.line(m, (cu, cv), (cu + int(d[0]), cv + int(d[1])), 255, 1)
        elif kind == 4:  # two squares touching at a corner (a contour through one pixel twice)
            m[cv : cv + 4, cu : cu + 4] = 255
            m[cv + 4 : cv + 8, cu + 4 : cu + 8] = 255
        elif kind == 5:  # a speck of noise
            m[cv : cv + 3, cu : cu + 2] = rng.integers(0, 2, (3, 2))[: height - cv, : width - cu] * 255
        else:  # a polygon with concave parts
            pts = np.array([cu, cv]) + rng.integers(-15, 16, (int(rng.integers(3, 9)), 2))
            cv2.fillPoly(m, [pts.astype(np.int32)], 255)
    m[:, :3] = 0  # the first columns empty, so a blob at the last column is cut, not wrapped
    m[0:5, 10:14] = 255  # at the top border
    m[height - 3 :, width - 9 :] = 255  # in the bottom right corner
    return m


def _contours(mask):
    found, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    lengths = np.array([len(c) for c in found], dtype=np.intp)
    pts = np.concatenate(found).reshape(-1, 2) if found else np.zeros((0, 2), np.int32)
    return found, np.require(pts, np.int32, ["C", "W"]), np.cumsum(lengths) - lengths, lengths


def _stats_reference(found, shape):
    """Per contour, from OpenCV: box, pixel area, polygon area, centroid, moments, box centre, reach."""
    rows = []
    for c in found:
        x, y, w, h = cv2.boundingRect(c)
        box = (x, y, x + w - 1, y + h - 1)
        filled = cv2.drawContours(np.zeros(shape, np.uint8), [c], -1, 1, thickness=-1)
        M = cv2.moments(c)
        area = cv2.contourArea(c)
        if area > 0:
            centre = (M["m10"] / M["m00"], M["m01"] / M["m00"])
            mu = (M["mu20"] / M["m00"], M["mu11"] / M["m00"], M["mu02"] / M["m00"])
        else:  # a pixel or a line: the box's middle, no moments
            centre, mu = (x + (w - 1) / 2, y + (h - 1) / 2), (0.0, 0.0, 0.0)
        bc = ((box[0] + box[2]) // 2, (box[1] + box[3]) // 2)
        reach = int(np.ceil(np.max(np.hypot(*(c.reshape(-1, 2) - bc).T))))
        rows.append((box, np.count_nonzero(filled), area, centre, mu, bc, reach))
    return [np.array(col) for col in zip(*rows)]


@pytest.mark.parametrize("shape", [(240, 320), (1030, 1300)])
def test_contour_stats_are_opencvs_box_moments_and_filled_pixel_count(rng, shape):
    mask = _mask(rng, *shape, n=120 if shape[0] < 500 else 400)
    found, pts, starts, lengths = _contours(mask)
    box, area_px, poly_area, centre, mu, box_centre, reach = contour_stats_kernel(pts, starts, lengths)
    box_r, area_r, poly_r, centre_r, mu_r, bc_r, reach_r = _stats_reference(found, shape)
    np.testing.assert_array_equal(box, box_r)
    np.testing.assert_array_equal(box_centre, bc_r)
    np.testing.assert_array_equal(reach, reach_r)
    # Pick's theorem counts the lattice points in and on the polygon: the filled pixels, exactly
    np.testing.assert_array_equal(area_px, area_r)
    np.testing.assert_array_equal(poly_area, poly_r)  # half-integers, exact in both
    # cv2.moments sums about the image origin and takes the centroid out after: ~1e-16 of
    # coordinates^2 ~ 1e6 px^2 over areas >= 1/2, so ~1e-9 px^2 at worst; the kernel sums about
    # the first vertex
    np.testing.assert_allclose(centre, centre_r, rtol=0, atol=1e-9)
    np.testing.assert_allclose(mu, mu_r, rtol=0, atol=1e-8)
    flat = poly_r == 0
    assert flat.sum() > 10 and (~flat).sum() > 30  # pixels and lines, and blobs with an area


def test_contour_stats_of_no_contours_and_of_one_pixel():
    none = contour_stats_kernel(np.zeros((0, 2), np.int32), np.zeros(0, np.intp), np.zeros(0, np.intp))
    assert [a.shape for a in none] == [(0, 4), (0,), (0,), (0, 2), (0, 3), (0, 2), (0,)]
    box, area_px, poly_area, centre, mu, box_centre, reach = contour_stats_kernel(
        np.array([[7, 3]], np.int32), np.zeros(1, np.intp), np.ones(1, np.intp)
    )
    np.testing.assert_array_equal(box, [[7, 3, 7, 3]])
    assert area_px[0] == 1 and poly_area[0] == 0 and reach[0] == 0
    np.testing.assert_array_equal(centre, [[7.0, 3.0]])
    np.testing.assert_array_equal(mu, 0.0)


def _classify_reference(box, area_px, poly_area, mu, width, height, border, min_area, max_area, max_aspect, fill):
    M = np.stack([np.stack([mu[:, 0], mu[:, 1]], -1), np.stack([mu[:, 1], mu[:, 2]], -1)], -2)
    finite = np.all(np.isfinite(mu), axis=1)
    lam = np.full((len(mu), 2), np.nan)
    lam[finite] = np.linalg.eigvalsh(M[finite])  # ascending
    a, b = 2 * np.sqrt(lam[:, 1]), 2 * np.sqrt(np.maximum(lam[:, 0], 0))
    b[np.isnan(lam[:, 0])] = np.nan
    cut = (
        (box[:, 0] < border)
        | (box[:, 1] < border)
        | (box[:, 2] > width - 1 - border)
        | (box[:, 3] > height - 1 - border)
    )
    small, big = area_px < min_area, area_px > max_area
    with np.errstate(invalid="ignore"):
        long = ~(b * max_aspect >= a)
        disk_like = ~long & (poly_area > 0) & (poly_area >= fill * np.pi * a * b)  # no area: no disk
    return a, cut, small, big, long, disk_like, disk_like & ~small & ~big


def test_classes_follow_from_the_moments_ellipse(rng):
    seen = np.zeros(6, dtype=int)
    for shape in [(240, 320), (1030, 1300)]:
        mask = _mask(rng, *shape, n=300)
        found, pts, starts, lengths = _contours(mask)
        box, area_px, poly_area, _, mu, _, _ = contour_stats_kernel(pts, starts, lengths)
        mu[:3] = [[np.nan, 0, 1], [4.0, 0.0, 4.0], [1.0, 0.99999, 1.0]]  # NaN, a circle, a needle
        for border, min_area, max_area, max_aspect in [
            (2, 6.0, 5000.0, 4.0),
            (0, 1.0, 80.0, 2.0),
            (40, 30.0, 300.0, 8.0),
        ]:
            args = (shape[1], shape[0], border, min_area, max_area, max_aspect, MIN_POLYGON_FILL)
            got = classify_kernel(box, area_px, poly_area, mu, *args)
            ref = _classify_reference(box, area_px, poly_area, mu, *args)
            # the semi-major axis by the closed form and by LAPACK: round-off of px-sized values
            np.testing.assert_allclose(got[0], ref[0], rtol=1e-12, atol=1e-12, equal_nan=True)
            for name, g, r in zip(("cut", "small", "big", "long", "disk_like", "host"), got[1:], ref[1:]):
                np.testing.assert_array_equal(g, r, err_msg=name)
            seen += [np.sum(x) for x in got[1:]]
    assert np.all(seen > 0)  # every class was met
    empty = classify_kernel(
        np.zeros((0, 4), np.intp), np.zeros(0), np.zeros(0), np.zeros((0, 3)), 9, 9, 2, 6.0, 5e3, 4.0, 0.9
    )
    assert all(x.shape == (0,) for x in empty)


def test_classes_at_the_border_limits():
    # a box exactly border px from each edge is in; one px closer is cut
    width, height, border = 100, 80, 2
    box = np.array([[2, 2, 97, 77], [1, 2, 97, 77], [2, 1, 97, 77], [2, 2, 98, 77], [2, 2, 97, 78]], dtype=np.intp)
    mu = np.tile([4.0, 0.0, 4.0], (5, 1))
    got = classify_kernel(box, np.full(5, 50.0), np.full(5, 50.0), mu, width, height, border, 6.0, 5e3, 4.0, 0.9)
    np.testing.assert_array_equal(got[1], [False, True, True, True, True])


def _windows_reference(box_centre, reach, mu, centre, todo, near, width, height, window_px, radii, margin):
    need = reach[todo] + margin
    if window_px > 0:
        radius = np.full(len(todo), window_px // 2)
    else:
        step = np.minimum(np.searchsorted(radii, need), len(radii) - 1)
        top = np.zeros(len(radii), dtype=np.intp)
        np.maximum.at(top, step, need)
        radius = np.maximum(top[step], need)
    cu, cv = box_centre[todo, 0], box_centre[todo, 1]
    radius = np.minimum(radius, np.min([cu, cv, width - 1 - cu, height - 1 - cv], axis=0))
    return radius, radius < need, radius + margin + 0.5 > near[todo]


def test_windows_follow_the_radius_steps_and_hold_the_blob_ellipse(rng):
    n_limited = n_crowded = n_solid = 0
    for shape, window_px in [((240, 320), 0), ((1030, 1300), 0), ((1030, 1300), 25)]:
        mask = _mask(rng, *shape, n=300)
        found, pts, starts, lengths = _contours(mask)
        box, area_px, poly_area, centre, mu, box_centre, reach = contour_stats_kernel(pts, starts, lengths)
        reach[:2] = [400, 1]  # beyond the largest radius step, and the smallest
        todo = np.ascontiguousarray(np.sort(rng.choice(len(box), len(box) * 2 // 3, replace=False)), dtype=np.intp)
        near = np.where(rng.random(len(box)) < 0.5, np.inf, rng.uniform(0, 30, len(box)))
        args = (box_centre, reach, mu, centre, todo, near, shape[1], shape[0], window_px, RADII, WINDOW_MARGIN_PX)
        radius, own, limited = windows_kernel(*args)
        radius_r, limited_r, crowded = _windows_reference(*args)
        np.testing.assert_array_equal(radius, radius_r)
        np.testing.assert_array_equal(limited, limited_r)
        np.testing.assert_array_equal(np.isfinite(own[:, 0]), crowded)
        n_limited, n_crowded = n_limited + limited.sum(), n_crowded + crowded.sum()
        assert not crowded.all()
        # the own region's centre, and its ellipse x' Q x = 1 through the moments' ellipse axes
        # (2 sqrt(lambda)) grown by g = 1 + 1.5 px / b: the points on both axes give 1
        k = np.flatnonzero(crowded)
        c = todo[k]
        np.testing.assert_allclose(own[k, :2], centre[c] - box_centre[c], rtol=0, atol=1e-12)
        M = np.stack([np.stack([mu[c, 0], mu[c, 1]], -1), np.stack([mu[c, 1], mu[c, 2]], -1)], -2)
        lam, vec = np.linalg.eigh(M)
        solid = lam[:, 0] > 1e-3  # blobs with an area (pixels and lines have no ellipse, Q = 0)
        Q = np.stack([np.stack([own[k, 2], own[k, 3]], -1), np.stack([own[k, 3], own[k, 4]], -1)], -2)
        semi = 2 * np.sqrt(np.maximum(lam, 0))
        g = 1 + 1.5 / np.maximum(semi[:, 0], 0.5)
        for axis in (0, 1):
            x = (g * semi[:, axis])[:, None] * vec[:, :, axis]
            value = np.einsum("ni,nij,nj->n", x, Q, x)
            np.testing.assert_allclose(value[solid], 1.0, rtol=1e-9)  # 2x2 algebra on px-sized numbers
        np.testing.assert_array_equal(Q[np.all(mu[c] == 0, axis=1)], 0.0)
        n_solid += solid.sum()
    assert n_limited > 5 and n_crowded > 20 and n_solid > 10


def test_windows_edge_cases():
    one = np.zeros((1, 2), np.intp)
    mu, centre, reach = np.array([[4.0, 0.0, 4.0]]), np.zeros((1, 2)), np.array([3], np.intp)
    none = windows_kernel(one, reach, mu, centre, np.zeros(0, np.intp), np.array([np.inf]), 9, 9, 0, RADII, 2)
    assert none[0].shape == (0,) and none[1].shape == (0, 5) and none[2].shape == (0,)
    # a blob in the image corner: no room for a window at all
    radius, own, limited = windows_kernel(
        one, reach, mu, centre, np.zeros(1, np.intp), np.array([0.0]), 9, 9, 0, RADII, 2
    )
    assert radius[0] == 0 and limited[0] and np.isfinite(own[0]).all()
