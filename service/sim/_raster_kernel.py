"""The renderer's per-pixel loops, compiled (numba): pattern coverage inside the boxes, noise and quantisation.

The simulated camera renders its 20 frames a second on one core; as numpy array passes a
1300 x 1030 frame of the reference plate took 35-70 ms (the padded boxes' ~170 000 pixels
went through some forty full-array passes, the frame's 1.3 M pixels through ten), which
missed frames whenever the host was slow. One loop per pixel does the same arithmetic as
the description in :mod:`service.sim.raster`, in float64, in a third of the time or less.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from service.core._kernels.geometry_kernels import correction_point
from service.core.targets.codes import N_BITS, RING_INNER, RING_OUTER

_SECTOR_RAD = 2.0 * math.pi / N_BITS
_PER_QUADRANT = N_BITS // 4
if N_BITS % 4:
    raise ImportError(f"the sector search goes quadrant by quadrant: {N_BITS} sectors do not fill four")
SECTOR_BOUNDARY_COS = np.cos(np.arange(N_BITS) * _SECTOR_RAD)
SECTOR_BOUNDARY_SIN = np.sin(np.arange(N_BITS) * _SECTOR_RAD)


@njit(cache=True, nogil=True, inline="always")
def _ramp(t):
    """Coverage of a sub-sample whose centre lies ``t`` sub-sample widths inside a straight edge."""
    return min(max(t + 0.5, 0.0), 1.0)


@njit(cache=True, nogil=True, inline="always")
def _sector_of(xi, eta, cos_b, sin_b):
    """Sector index, nearest sector boundary and signed distance (units of ``xi``) to that boundary's line,
    positive towards the sector above it (counter-clockwise from local +x to +y).

    By the quadrant's signs and cross products with the boundaries in it: the angle itself (atan2,
    ~45 ns) was half of a frame's coverage work; this is exact where it matters, at the boundaries.
    """
    if xi > 0.0 and eta >= 0.0:
        sector = 0
    elif xi <= 0.0 and eta > 0.0:
        sector = _PER_QUADRANT
    elif xi < 0.0 and eta <= 0.0:
        sector = 2 * _PER_QUADRANT
    elif xi >= 0.0 and eta < 0.0:
        sector = 3 * _PER_QUADRANT
    else:  # the centre itself
        return 0, 0, 0.0
    first = sector
    for j in range(first + 1, first + _PER_QUADRANT):
        if cos_b[j] * eta - sin_b[j] * xi >= 0.0:
            sector = j
    above = sector + 1 if sector + 1 < N_BITS else 0
    to_lower = cos_b[sector] * eta - sin_b[sector] * xi  # >= 0
    to_upper = cos_b[above] * eta - sin_b[above] * xi  # < 0
    if to_lower <= -to_upper:
        return sector, sector, to_lower
    return sector, above, to_upper


@njit(cache=True, nogil=True, error_model="numpy")
def coverage_kernel(cam, H9, boxes, reach, full, code_row, bits, bits_before, transitions, ss, cos_b, sin_b):
    """Covered fraction of every pixel of every box: (owner, flat, cover) of the non-zero ones.

    ``cam`` (13,): width, height, pixel u, v mm, x0, y0, K1, K2, K3, P1, P2, B1, B2 (the Brown/Fraser
    correction of DESIGN section 2); ``H9`` (9, M) each target's homography ideal ->
    disk radii; ``boxes`` (M, 4) inclusive ``u0, v0, u1, v1``; ``reach`` (M,) disk radii a pixel square
    reaches from its centre; ``full`` (M,) supersample every pixel; ``code_row`` (M,) row of ``bits``
    (the last row, all False, for an uncoded target); ``ss`` sub-samples per axis.
    """
    width = int(cam[0])
    px, py, x0, y0 = cam[2], cam[3], cam[4], cam[5]
    K1, K2, K3, P1, P2, B1, B2 = cam[6], cam[7], cam[8], cam[9], cam[10], cam[11], cam[12]
    cu, cv = (cam[0] - 1.0) / 2.0, (cam[1] - 1.0) / 2.0
    m = boxes.shape[0]
    total = 0
    for k in range(m):
        total += (boxes[k, 2] - boxes[k, 0] + 1) * (boxes[k, 3] - boxes[k, 1] + 1)
    owner = np.empty(total, dtype=np.intp)
    flat = np.empty(total, dtype=np.intp)
    cover = np.empty(total, dtype=np.float32)
    uncoded_row = bits.shape[0] - 1
    inv_ss2 = 1.0 / (ss * ss)
    n = 0
    for k in range(m):
        h0, h1, h2, h3, h4, h5, h6, h7, h8 = (
            H9[0, k],
            H9[1, k],
            H9[2, k],
            H9[3, k],
            H9[4, k],
            H9[5, k],
            H9[6, k],
            H9[7, k],
            H9[8, k],
        )
        s = reach[k]
        row = code_row[k]
        coded = row != uncoded_row
        disk_lo2 = max(1.0 - s, 0.0) ** 2
        disk_hi2 = (1.0 + s) ** 2
        ring_lo2 = max(RING_INNER - s, 0.0) ** 2
        ring_hi2 = (RING_OUTER + s) ** 2
        for v in range(boxes[k, 1], boxes[k, 3] + 1):
            y = (v - cv) * py - y0
            for u in range(boxes[k, 0], boxes[k, 2] + 1):
                # ideal coordinates: the correction of the measured sensor position
                x = (u - cu) * px - x0
                dx, dy, c00, c01, c10, c11 = correction_point(x, y, K1, K2, K3, P1, P2, B1, B2)
                xi_ideal, yi_ideal = x + dx, y + dy
                w = h6 * xi_ideal + h7 * yi_ideal + h8
                if not w > 0.0:  # the ray misses the plane in front
                    continue
                inv_w = 1.0 / w
                xi = (h0 * xi_ideal + h1 * yi_ideal + h2) * inv_w
                eta = (h3 * xi_ideal + h4 * yi_ideal + h5) * inv_w
                # the pattern at the centre, and whether the pixel's square may cross an edge
                rho2 = xi * xi + eta * eta
                value = rho2 <= 1.0
                edge = full[k] or (disk_lo2 <= rho2 <= disk_hi2)
                near_sector = False
                sector = 0
                if coded and ring_lo2 < rho2 < ring_hi2:
                    r = math.sqrt(rho2)
                    sector, boundary, to_boundary = _sector_of(xi, eta, cos_b, sin_b)
                    if RING_INNER <= r <= RING_OUTER and bits[row, sector]:
                        value = True
                    near_sector = full[k] or (transitions[row, boundary] and abs(to_boundary) <= s)
                    if abs(r - RING_INNER) <= s or abs(r - RING_OUTER) <= s or near_sector:
                        edge = True
                if not edge:
                    if value:
                        owner[n], flat[n], cover[n] = k, v * width + u, 1.0
                        n += 1
                    continue
                # the square's map to the plane, linearised: d(xi, eta)/d(u, v), through the correction
                d00, d01, d10, d11 = c00 * px, c01 * py, c10 * px, c11 * py
                a00, a01 = (h0 - xi * h6) * inv_w, (h1 - xi * h7) * inv_w
                a10, a11 = (h3 - eta * h6) * inv_w, (h4 - eta * h7) * inv_w
                j00, j01 = a00 * d00 + a01 * d10, a00 * d01 + a01 * d11
                j10, j11 = a10 * d00 + a11 * d10, a10 * d01 + a11 * d11
                # gradients of the radial and the tangential distance, disk radii per px
                rho_c = math.sqrt(rho2)
                n0, n1 = (xi / rho_c, eta / rho_c) if rho_c > 1e-9 else (1.0, 0.0)
                g_r = math.sqrt((j00 * n0 + j10 * n1) ** 2 + (j01 * n0 + j11 * n1) ** 2)
                g_t = math.sqrt((j10 * n0 - j00 * n1) ** 2 + (j11 * n0 - j01 * n1) ** 2)
                scale_r = ss / max(g_r, 1e-300)
                scale_t = ss / max(g_t, 1e-300)
                in_disk = rho_c <= 1.0 + s
                in_ring = coded and RING_INNER - s < rho_c < RING_OUTER + s
                ring_bit = 1.0 if bits[row, sector] else 0.0
                acc = 0.0
                for a in range(ss):
                    oa = (a + 0.5) / ss - 0.5
                    for b in range(ss):
                        ob = (b + 0.5) / ss - 0.5
                        xs = xi + j00 * oa + j01 * ob
                        ys = eta + j10 * oa + j11 * ob
                        rho = math.sqrt(xs * xs + ys * ys)
                        if in_disk:
                            acc += _ramp((1.0 - rho) * scale_r)
                        if in_ring:
                            radial_cover = _ramp(min(rho - RING_INNER, RING_OUTER - rho) * scale_r)
                            if near_sector:  # a sector boundary may cross the square: the sample's own
                                _, bs, toward_upper = _sector_of(xs, ys, cos_b, sin_b)
                                upper = 1.0 if bits[row, bs] else 0.0
                                lower = 1.0 if bits_before[row, bs] else 0.0
                                acc += radial_cover * (lower + (upper - lower) * _ramp(toward_upper * scale_t))
                            else:  # one sector: only the ring's circles cross the pixel
                                acc += radial_cover * ring_bit
                c = acc * inv_ss2
                if c > 0.0:
                    owner[n], flat[n], cover[n] = k, v * width + u, c
                    n += 1
    return owner[:n], flat[:n], cover[:n]


@njit(cache=True, nogil=True, error_model="numpy")
def noise_kernel(img, u16, z_table, read_e2):
    """Shot and read noise in place: ``img += sqrt(img + read_e2) * z_table[u16]`` (float32, DN).

    ``z_table`` holds normal quantiles scaled to ``1 / sqrt(electrons per DN)``, so the variance is
    ``(level e + read_e2) / e`` DN^2; levels below zero count as zero (the exact Poisson part of very
    dark pixels is drawn by the caller).
    """
    flat_img = img.reshape(-1)
    flat_u = u16.reshape(-1)
    for i in range(flat_img.size):
        level = flat_img[i]
        flat_img[i] = level + np.sqrt(max(level, np.float32(0.0)) + read_e2) * z_table[flat_u[i]]


@njit(cache=True, nogil=True, error_model="numpy")
def quantise_kernel(img, scale, full_scale, out):
    """``out = trunc(clip(img * scale + 0.5, 0, full_scale + 0.5))``: rounding to the nearest level, saturated."""
    flat_img = img.reshape(-1)
    flat_out = out.reshape(-1)
    top = np.float32(full_scale + 0.5)
    for i in range(flat_img.size):
        flat_out[i] = int(min(max(flat_img[i] * scale + np.float32(0.5), np.float32(0.0)), top))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the types the renderer passes."""
    cam = np.array([4.0, 4.0, 0.01, 0.01, 0, 0, 0, 0, 0, 0, 0, 0, 0])
    H9 = np.zeros((9, 1))
    H9[[0, 4, 8], 0] = 1.0
    bits = np.zeros((2, N_BITS), dtype=np.bool_)
    coverage_kernel(
        cam, H9, np.array([[0, 0, 1, 1]], dtype=np.intp), np.full(1, 0.3), np.zeros(1, dtype=np.bool_),
        np.zeros(1, dtype=np.intp), bits, bits, bits, 4, SECTOR_BOUNDARY_COS, SECTOR_BOUNDARY_SIN,
    )  # fmt: skip
    img = np.ones((2, 2), dtype=np.float32)
    noise_kernel(img, np.zeros((2, 2), dtype=np.uint16), np.zeros(65536, dtype=np.float32), np.float32(1.0))
    for dtype in (np.uint8, np.uint16):
        quantise_kernel(img, np.float32(1.0), 255, np.empty((2, 2), dtype=dtype))
