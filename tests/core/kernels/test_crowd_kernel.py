"""Blobs near each other (``service.core._kernels.crowd_kernel``) against brute-force NumPy references.

``neighbours_kernel`` searches the pairs through a grid of the contours' boxes, each query within
its own radius; the reference looks at every pair (a dense (n, n) array) and applies the ring
rules of ``detect_candidates.neighbours`` with the host's ellipse from ``np.linalg.inv``. The
scenes are masks drawn with OpenCV: coded targets (a disk and the sectors of its ring, seen
obliquely), uncoded disks, rings that overlap, specks and scratches.

``mask_windows_kernel`` is compared with each window written out in NumPy: the rim's lower
quartile by ``np.sort``, the bright pixels outside the blob's own ellipse, and their 7 x 7
growth by ``scipy.ndimage.binary_dilation``.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from service.core._kernels.contour_kernel import classify_kernel, contour_stats_kernel
from service.core._kernels.crowd_kernel import mask_windows_kernel, neighbours_kernel
from service.core.targets.codes import RING_INNER, RING_OUTER
from service.core.targets.detect_candidates import MIN_PIECE_HALF, MIN_POLYGON_FILL


def _coded_scene(rng, height, width, n_coded, n_other):
    """0/255 mask of coded targets (disk, ring sectors) at random tilt and roll, and other blobs."""
    m = np.zeros((height, width), np.uint8)
    for _ in range(n_coded):
        R = rng.uniform(4, 12)
        cu, cv = rng.uniform(4 * R, width - 4 * R), rng.uniform(4 * R, height - 4 * R)
        squeeze, angle = rng.uniform(0.5, 1.0), rng.uniform(0, 180)
        cv2.ellipse(m, (round(cu), round(cv)), (round(R), round(R * squeeze)), angle, 0, 360, 255, -1)
        mid, thick = 0.5 * (RING_INNER + RING_OUTER) * R, (RING_OUTER - RING_INNER) * R
        bits = rng.random(12) < 0.5
        for k in np.flatnonzero(bits):  # each bright sector an arc of the ring (runs merge)
            axes = (round(mid), round(mid * squeeze))
            cv2.ellipse(m, (round(cu), round(cv)), axes, angle, 30 * k, 30 * k + 30, 255, max(1, round(thick)))
    for k in range(n_other):
        cu, cv = int(rng.integers(0, width)), int(rng.integers(0, height))
        if k % 3 == 0:
            r = int(rng.integers(2, 9))
            cv2.ellipse(m, (cu, cv), (r, int(rng.integers(1, r + 1))), float(rng.uniform(0, 180)), 0, 360, 255, -1)
        elif k % 3 == 1:
            m[cv : cv + 2, cu : cu + 2] = 255
        else:
            d = rng.integers(-15, 16, 2)
            cv2.line(m, (cu, cv), (cu + int(d[0]), cv + int(d[1])), 255, int(rng.integers(1, 3)))
    return m


def _inputs(mask):
    found, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    lengths = np.array([len(c) for c in found], dtype=np.intp)
    pts = np.require(np.concatenate(found).reshape(-1, 2), np.int32, ["C", "W"])
    box, area_px, poly_area, centre, mu, box_centre, reach = contour_stats_kernel(
        pts, np.cumsum(lengths) - lengths, lengths
    )
    h, w = mask.shape
    a, cut, small, big, long, disk_like, host = classify_kernel(
        box, area_px, poly_area, mu, w, h, 2, 6.0, 5000.0, 4.0, MIN_POLYGON_FILL
    )
    query = ~small & ~big & ~long
    return box, centre, mu, box_centre, reach, a, host & query, disk_like, query


def _neighbours_reference(box, centre, mu, box_centre, reach, a, host, disk_like, query):
    """Every pair at once: (host_of, near, number of pairs)."""
    n = len(centre)
    host_of, near = np.full(n, -1), np.full(n, np.inf)
    if n < 2:
        return host_of, near, 0
    # each query's radius: its window (1.25 reach + 6 px about the box centre), a host's ring too
    radius = 1.25 * reach + 6.0 + np.hypot(*(box_centre - centre).T)
    radius = np.where(host, np.maximum(radius, (RING_OUTER + 0.6) * a), radius)
    cx, cy, r = centre[:, 0, None], centre[:, 1, None], radius[:, None]
    reach_box = ~(
        (box[None, :, 0] - r > cx)
        | (box[None, :, 2] + r < cx)
        | (box[None, :, 1] - r > cy)
        | (box[None, :, 3] + r < cy)
    )
    pair = query[:, None] & reach_box & ~np.eye(n, dtype=bool)
    i, j = np.nonzero(pair)
    diff = centre[j] - centre[i]
    d = np.hypot(*diff.T) + 1e-9
    e = diff / d[:, None]
    M = lambda k: np.stack([np.stack([mu[k, 0], mu[k, 1]], -1), np.stack([mu[k, 1], mu[k, 2]], -1)], -2)  # noqa: E731
    per = np.zeros(len(i))
    is_host = host[i]
    # rho per px along e: a point at d px from the host's centre is at rho = d sqrt(e' M^-1 e / 4)
    # of its ellipse (semi-axes 2 sqrt(lambda), the edge at rho = 1). A 1 px line (>= 6 px: not small)
    # has zero moments, is "disk-like" (0 >= 0) and a host; its determinant counts as 1e-12 px^4
    Mh = M(i[is_host])
    det = np.linalg.det(Mh)
    flat = det <= 1e-12
    Mi_inv = np.empty_like(Mh)
    Mi_inv[~flat] = np.linalg.inv(Mh[~flat])
    Mi_inv[flat] = (
        np.stack([np.stack([Mh[flat, 1, 1], -Mh[flat, 0, 1]], -1), np.stack([-Mh[flat, 0, 1], Mh[flat, 0, 0]], -1)], -2)
        / 1e-12
    )
    per[is_host] = np.sqrt(np.einsum("ni,nij,nj->n", e[is_host], Mi_inv, e[is_host]) / 4)
    half = 2 * np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", e, M(j), e), 0))  # the piece's half extent along e
    rho = d * per
    piece = (
        (rho > RING_INNER - 0.6)
        & ((d - half) * per > 1.0)
        & ((d + half) * per < RING_OUTER + 0.4)
        & (half * per >= MIN_PIECE_HALF)
    )
    claim = is_host & np.where(disk_like[j], piece, rho < RING_OUTER + 0.5)
    claimed = np.zeros(n, bool)
    claimed[j[claim]] = True
    take = claim & ~claimed[i]  # a claimed host claims nothing
    for k in np.flatnonzero(take)[np.argsort(rho[take], kind="stable")[::-1]]:
        host_of[j[k]] = i[k]  # the nearest host (in its own radii) written last
    own_ring = host_of[j] == i
    with np.errstate(divide="ignore"):
        approach = np.where(
            own_ring,
            RING_INNER * (1 / np.maximum(per, 1e-9) + 0.5) - 6.0,
            np.hypot(*(centre[j] - box_centre[i]).T) - reach[j] - 0.5,
        )
    np.minimum.at(near, i, approach)
    return host_of, near, len(i)


def test_neighbours_are_the_brute_force_pairs_and_ring_rules(rng):
    n_claimed = n_near = 0
    for k in range(8):
        h, w = [(300, 400), (1030, 1300)][k % 2]
        mask = _coded_scene(rng, h, w, n_coded=[3, 25][k % 2], n_other=[40, 400][k % 2])
        args = _inputs(mask)
        host_of, near, n_pairs, visits = neighbours_kernel(
            *args, float(RING_INNER), float(RING_OUTER), MIN_PIECE_HALF, w, h
        )
        host_r, near_r, n_pairs_r = _neighbours_reference(*args)
        np.testing.assert_array_equal(host_of, host_r)
        # the same expressions in another order: round-off of distances of ~100 px
        np.testing.assert_allclose(near, near_r, rtol=0, atol=1e-9)
        assert n_pairs == n_pairs_r and visits >= n_pairs
        n_claimed, n_near = n_claimed + np.sum(host_of >= 0), n_near + np.sum(np.isfinite(near))
        assert not np.isfinite(near[~args[-1]]).any()  # only the queries get a distance
    assert n_claimed > 100 and n_near > 500  # ring pieces were claimed, windows found crowded


def test_neighbours_of_fewer_than_two_blobs_or_no_queries(rng):
    mask = _coded_scene(rng, 200, 200, n_coded=2, n_other=10)
    box, centre, mu, box_centre, reach, a, host, disk_like, query = _inputs(mask)
    const = (float(RING_INNER), float(RING_OUTER), MIN_PIECE_HALF, 200, 200)
    for n in (0, 1):
        s = slice(0, n)
        host_of, near, n_pairs, visits = neighbours_kernel(
            *(np.ascontiguousarray(x[s]) for x in (box, centre, mu, box_centre, reach, a, host, disk_like, query)),
            *const,
        )
        assert host_of.shape == near.shape == (n,) and n_pairs == visits == 0
    nobody = np.zeros_like(query)
    host_of, near, n_pairs, _ = neighbours_kernel(
        box, centre, mu, box_centre, reach, a, nobody, disk_like, nobody, *const
    )
    assert n_pairs == 0 and np.all(host_of == -1) and np.all(np.isinf(near))


# -- masking the other blobs in crowded windows ---------------------------------------------------


def _own_form(own, h):
    """(x - x0)' Q (x - x0) over a window's (s, s) pixels, float64, and the size of its terms."""
    x0, y0, qa, qb, qc = own
    dv, du = np.mgrid[-h : h + 1, -h : h + 1].astype(np.float64)
    x, y = du - x0, dv - y0
    return qa * x * x + 2 * qb * x * y + qc * y * y, qa * (du**2 + x0**2) + abs(qb) * (du**2 + dv**2) + qc * (
        dv**2 + y0**2
    )


def _mask_reference(img, cu, cv, half, crowd, own, seg):
    boff = np.full(len(cu), -1)
    parts, total = [], 0
    for i in crowd:
        h = half[i]
        s = 2 * h + 1
        P = img[cv[i] - h : cv[i] + h + 1, cu[i] - h : cu[i] + h + 1].astype(np.float32)
        dv, du = np.mgrid[-h : h + 1, -h : h + 1]
        d2 = du**2 + dv**2
        rim = np.sort(P[(d2 <= (h + 0.5) ** 2) & (d2 > (h - 1.0) ** 2)])
        level0 = rim[len(rim) // 4]
        outside = _own_form(own[i], h)[0] > 1
        bright = outside & (P > level0 + np.float32(seg[i]))
        grown = binary_dilation(bright, structure=np.ones((7, 7), bool))
        P[grown & outside] = level0
        boff[i], total = total, total + s * s
        parts.append(P.ravel())
    return (np.concatenate(parts) if parts else np.zeros(1, np.float32)), boff


def _crowded_image(rng, dtype, shape=(160, 220)):
    full = 255 if dtype == np.uint8 else 4095
    img = rng.normal(0.15 * full, 0.01 * full, shape)
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    for _ in range(60):  # disks, some overlapping others' windows
        cu, cv, r = rng.uniform(0, shape[1]), rng.uniform(0, shape[0]), rng.uniform(2, 9)
        img += rng.uniform(0.2, 0.7) * full * np.exp(-(np.maximum(np.hypot(u - cu, v - cv) - r, 0) ** 2) / 2)
    return np.clip(np.rint(img), 0, full).astype(dtype), full


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_masked_windows_are_the_numpy_window_rule(rng, dtype):
    img, full = _crowded_image(rng, dtype)
    n = 80
    half = rng.integers(3, 16, n).astype(np.intp)
    cu = np.array([rng.integers(h, img.shape[1] - h) for h in half], dtype=np.intp)
    cv = np.array([rng.integers(h, img.shape[0] - h) for h in half], dtype=np.intp)
    cu[:2], cv[:2] = half[:2], [img.shape[0] - 1 - half[1], half[1]]  # windows touching the image border
    own = np.full((n, 5), np.nan)
    for i in range(n):
        semi = rng.uniform(1.0, 0.8 * half[i], 2)
        ang = rng.uniform(0, np.pi)
        Rm = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        Q = Rm @ np.diag(1 / semi**2) @ Rm.T
        while True:  # no pixel within float32 round-off of the region's edge: the kernel's test is float32
            own[i] = [*rng.uniform(-1, 1, 2), Q[0, 0], Q[0, 1], Q[1, 1]]
            value, size = _own_form(own[i], half[i])
            if np.all(np.abs(value - 1) > 1e-5 * (1 + size)):
                break
    crowd = np.ascontiguousarray(np.sort(rng.choice(n, 50, replace=False)), dtype=np.intp)
    crowd[:2] = [0, 1]
    crowd = np.unique(crowd)
    seg = rng.uniform(0.02, 0.1, n) * full
    buf, boff = mask_windows_kernel(img, cu, cv, half, crowd, own, seg)
    buf_r, boff_r = _mask_reference(img, cu, cv, half, crowd, own, seg)
    np.testing.assert_array_equal(boff, boff_r)
    assert buf.dtype == np.float32
    np.testing.assert_array_equal(buf, buf_r)  # copies of pixels or of the rim quartile: exact
    changed = buf != np.concatenate(
        [img[cv[i] - half[i] : cv[i] + half[i] + 1, cu[i] - half[i] : cu[i] + half[i] + 1].ravel() for i in crowd]
    )
    assert 0.02 < changed.mean() < 0.8  # other blobs were masked, the windows' own kept


def test_no_crowded_window_masks_nothing(rng):
    img, _ = _crowded_image(rng, np.uint8, (40, 40))
    c, half = np.array([20, 20], np.intp), np.array([5, 8], np.intp)
    buf, boff = mask_windows_kernel(img, c, c, half, np.zeros(0, np.intp), np.full((2, 5), np.nan), np.ones(2))
    assert buf.shape == (1,) and np.all(boff == -1)


def test_a_straight_line_claims_no_ring_pieces():
    mask = np.zeros((100, 100), np.uint8)
    cv2.line(mask, (40, 50), (52, 50), 255, 1)  # 13 px: not small, zero moments
    cv2.line(mask, (44, 56), (58, 60), 255, 2)  # a scratch 6 px below it: long, not disk-like
    box, centre, mu, box_centre, reach, a, host, disk_like, query = _inputs(mask)
    assert len(box) == 2
    line = int(np.argmax(np.all(mu == 0, axis=1)))
    assert not host[line] and not disk_like[1 - line]  # a line of no area is no host, the scratch no disk
    host_of, _, _, _ = neighbours_kernel(
        box,
        centre,
        mu,
        box_centre,
        reach,
        a,
        host,
        disk_like,
        query,
        float(RING_INNER),
        float(RING_OUTER),
        MIN_PIECE_HALF,
        100,
        100,
    )
    assert host_of[1 - line] == -1, "the line claimed the scratch as its ring"
