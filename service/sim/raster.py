"""Anti-aliased coverage of planar target patterns, inside pixel boxes only.

A pixel position is mapped back to a target's plane exactly: Brown/Fraser
correction to ideal coordinates, then the ray's intersection with the plane.
Ideal image to plane is a homography, so this gives exact perspective and
exact distortion with no inverse distortion per sample. Coordinates in the
plane are in disk radii (``xi``, ``eta``, origin at the disk centre, along the
target's local x and y); the pattern is the disk ``r <= 1`` and, for coded
targets, the sectors of the ring ``RING_INNER <= r <= RING_OUTER`` that
:func:`service.core.targets.codes.bits_of` sets.

A pixel whose square provably lies on one side of every pattern edge (a bound
from the local Jacobian) takes the pattern value at its centre; every other
pixel is supersampled ``supersample x supersample``, and each sub-sample is
itself a linear ramp across the edge (signed distance / local gradient), the
exact area coverage of a straight edge. Sub-sample positions come from the
pixel centre plus the local Jacobian (central differences of the exact map;
the linearisation errs by ~1e-4 px). Box pixels are computed in float32
(~1e-4 px), in batches of boxes of similar size padded to a common shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.targets.codes import N_BITS, RING_INNER, RING_OUTER, bits_of

Array = NDArray[np.float64]

# Above this pixel reach (in disk radii) the edge bound is too loose to be worth it:
# every pixel of such a small target is supersampled.
_FULL_SUPERSAMPLE_REACH = 0.25
_REACH_SAFETY = 1.05  # the Jacobian varies slightly across a box
_SECTOR_RAD = 2.0 * np.pi / N_BITS


def pattern_coverage(
    camera: BrownFraser,
    p0: Array,
    normal: Array,
    ex: Array,
    ey: Array,
    radius: Array,
    codes: NDArray[np.int64],
    boxes: NDArray[np.intp],
    supersample: int,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]]:
    """Fraction of each box pixel that each target's pattern covers.

    Parameters
    ----------
    camera : BrownFraser
    p0, normal, ex, ey : (M, 3) float, camera frame
        Disk centres (mm), plane normals towards the camera, local x and y axes (unit).
    radius : (M,) float, mm
        Disk radii.
    codes : (M,) int
        Code of each target, -1 for uncoded.
    boxes : (M, 4) int
        Inclusive pixel boxes ``u0, v0, u1, v1`` inside the image that hold each pattern.
    supersample : int
        Sub-samples per axis in pixels that an edge may cross.

    Returns
    -------
    owner : (K,) int
        Row of the target each entry belongs to.
    flat : (K,) int
        Pixel index ``v * width + u``.
    cover : (K,) float32 in (0, 1]
        Covered fraction; only non-zero entries are returned.
    """
    u0, v0, u1, v1 = boxes.T
    m = len(boxes)
    width, height = camera.width, camera.height
    H9 = _homographies(p0, normal, ex, ey, radius, camera.c_mm)
    coded = np.asarray(codes) >= 0
    bits = np.zeros((m + 1, N_BITS), dtype=bool)  # the last row serves every uncoded target
    code_row = np.full(m, m, dtype=np.intp)
    for k in np.flatnonzero(coded):
        bits[k] = bits_of(int(codes[k]))
        code_row[k] = k
    before = np.roll(bits, 1, axis=1)
    ring_codes = _Codes(row=code_row, bits=bits, bits_before=before, transitions=bits != before)

    # how far (disk radii) a pixel square reaches from its centre: max |J (+-1/2, +-1/2)|
    # over the box corners (a convex function of the pixel position peaks at a corner)
    corners_uv = np.stack(
        [np.stack([u0, v0], 1), np.stack([u1, v0], 1), np.stack([u0, v1], 1), np.stack([u1, v1], 1)], axis=1
    )
    corners_uv = corners_uv.reshape(-1, 2).astype(np.float64)
    Hc = np.repeat(H9, 4, axis=1)
    xy_c = camera.ideal_from_pixel(corners_uv)
    xi_c, eta_c, inv_w_c = _plane_from_ideal(Hc, xy_c[:, 0], xy_c[:, 1])
    j00, j01, j10, j11 = _plane_jacobian(camera, Hc, corners_uv, xi_c, eta_c, inv_w_c)
    half_diag = 0.5 * np.sqrt(np.maximum((j00 + j01) ** 2 + (j10 + j11) ** 2, (j00 - j01) ** 2 + (j10 - j11) ** 2))
    half_diag = np.where(np.isfinite(half_diag), half_diag, np.inf).reshape(m, 4)
    reach = _REACH_SAFETY * half_diag.max(axis=1) if m else np.zeros(0)
    full = reach > _FULL_SUPERSAMPLE_REACH

    owner_parts: list[NDArray[np.intp]] = []
    flat_parts: list[NDArray[np.intp]] = []
    cover_parts: list[NDArray[np.float32]] = []
    for sel in _box_batches(v1 - v0 + 1, u1 - u0 + 1):
        shape = (int(np.max(v1[sel] - v0[sel])) + 1, int(np.max(u1[sel] - u0[sel])) + 1)
        cover, rows, cols = _cover_batch(
            camera, sel, u0[sel], v0[sel], shape, H9, reach, full, coded, ring_codes, supersample
        )
        rows_ok = rows < height
        cols_ok = cols < width
        if not (rows_ok.all() and cols_ok.all()):  # padding that runs off the image
            cover *= rows_ok & cols_ok
        k = np.flatnonzero(cover)
        if k.size:
            per_box = cover.shape[1] * cover.shape[2]
            b, rem = np.divmod(k, per_box)
            r, c = np.divmod(rem, cover.shape[2])
            owner_parts.append(sel[b])
            flat_parts.append((v0[sel][b] + r) * width + u0[sel][b] + c)
            cover_parts.append(cover.reshape(-1)[k])
    if not owner_parts:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.float32)
    return np.concatenate(owner_parts), np.concatenate(flat_parts), np.concatenate(cover_parts)


def _homographies(p0: Array, normal: Array, ex: Array, ey: Array, radius: Array, c_mm: float) -> Array:
    """(9, M) rows of the homographies ideal (x, y, 1) -> local plane coordinates in disk radii.

    A ray d = (x, y, c) meets the plane n.(P - p0) = 0 at P = d (n.p0)/(n.d), so
    local x = [(n.p0) ex - (ex.p0) n].d / (R n.d), likewise y; signs are chosen
    so that the third row is positive for rays that hit the plane in front.
    """
    n_p0 = np.sum(normal * p0, axis=1, keepdims=True)
    a = -(n_p0 * ex - np.sum(ex * p0, axis=1, keepdims=True) * normal) / radius[:, None]
    b = -(n_p0 * ey - np.sum(ey * p0, axis=1, keepdims=True) * normal) / radius[:, None]
    w = -normal
    H = np.stack([a, b, w], axis=1)  # (M, 3, 3)
    H[:, :, 2] *= c_mm
    return H.reshape(-1, 9).T.copy()


def ideal_grid(camera: BrownFraser, u: Array, v: Array) -> tuple[Array, Array]:
    """``camera.ideal_from_pixel`` on the grid of columns ``u`` (M, 1, W) and rows ``v`` (M, H, 1).

    The Brown/Fraser correction of DESIGN section 2, regrouped so that every
    term in x' or y' alone is computed once per column or row: a third of
    the work of the general (N, 2) path, which dominates a frame otherwise.
    Returns ideal x, y (M, H, W) in mm.
    """
    cam = camera
    px, py = cam.pixel_size_mm
    xb = (u - (cam.width - 1) / 2.0) * px - cam.x0_mm
    yb = (v - (cam.height - 1) / 2.0) * py - cam.y0_mm
    xb2 = xb * xb
    yb2 = yb * yb
    r2 = xb2 + yb2
    one_plus_radial = r2 * cam.K3
    one_plus_radial += cam.K2
    one_plus_radial *= r2
    one_plus_radial += cam.K1
    one_plus_radial *= r2
    one_plus_radial += 1.0
    # x = xb (1 + radial) + P1 (r2 + 2 xb^2) + 2 P2 xb yb + B1 xb + B2 yb
    x = xb * one_plus_radial
    x += (2.0 * cam.P2 * xb) * yb
    x += (3.0 * cam.P1 * xb2 + cam.B1 * xb) + (cam.P1 * yb2 + cam.B2 * yb)
    # y = yb (1 + radial) + 2 P1 xb yb + P2 (r2 + 2 yb^2)
    y = yb * one_plus_radial
    y += (2.0 * cam.P1 * xb) * yb
    y += (cam.P2 * xb2) + (3.0 * cam.P2 * yb2)
    return x, y


def _plane_from_ideal(h: Array, x: Array, y: Array) -> tuple[Array, Array, Array]:
    """Local coordinates xi, eta (disk radii) and 1/w of ideal points ``x``, ``y`` (mm).

    ``h`` (9, ...) broadcasts against ``x``. Rays that miss the plane in front
    get NaN, which falls outside every pattern test.
    """
    w = h[6] * x
    w += h[7] * y
    w += h[8]
    bad = ~(w > 0)
    with np.errstate(divide="ignore"):
        inv_w = 1.0 / w
    if bad.any():
        inv_w[bad] = np.nan
    xi = h[0] * x
    xi += h[1] * y
    xi += h[2]
    xi *= inv_w
    eta = h[3] * x
    eta += h[4] * y
    eta += h[5]
    eta *= inv_w
    return xi, eta, inv_w


def _plane_jacobian(
    camera: BrownFraser, Hk: Array, uv: Array, xi: Array, eta: Array, inv_w: Array
) -> tuple[Array, Array, Array, Array]:
    """d(xi, eta)/d(u, v) at pixels ``uv`` (K, 2): (dxi/du, dxi/dv, deta/du, deta/dv), each (K,).

    ``Hk`` (9, K) is each pixel's homography, ``xi``, ``eta``, ``inv_w`` (K,) its values there.
    """
    Jd = camera.ideal_from_pixel_jacobian(uv)
    a00 = (Hk[0] - xi * Hk[6]) * inv_w
    a01 = (Hk[1] - xi * Hk[7]) * inv_w
    a10 = (Hk[3] - eta * Hk[6]) * inv_w
    a11 = (Hk[4] - eta * Hk[7]) * inv_w
    return (
        a00 * Jd[:, 0, 0] + a01 * Jd[:, 1, 0],
        a00 * Jd[:, 0, 1] + a01 * Jd[:, 1, 1],
        a10 * Jd[:, 0, 0] + a11 * Jd[:, 1, 0],
        a10 * Jd[:, 0, 1] + a11 * Jd[:, 1, 1],
    )


def _ramp(t: NDArray[np.float32]) -> NDArray[np.float32]:
    """Coverage of sub-samples whose centres lie ``t`` sub-sample widths inside a straight edge (in place)."""
    t += np.float32(0.5)
    return np.clip(t, np.float32(0.0), np.float32(1.0), out=t)


# -- the pattern -------------------------------------------------------------


@dataclass(frozen=True)
class _Codes:
    """Ring patterns of the drawn targets: ``row`` (M,) indexes ``bits`` (T, N_BITS).

    ``transitions[t, k]`` says whether sectors k - 1 and k differ.
    """

    row: NDArray[np.intp]
    bits: NDArray[np.bool_]
    bits_before: NDArray[np.bool_]  # bits_before[t, k] = bits[t, k - 1]
    transitions: NDArray[np.bool_]


def _sector_of(
    xi: NDArray[np.floating], eta: NDArray[np.floating]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.floating]]:
    """Sector index, nearest sector boundary and signed distance to that boundary's line.

    The distance is in the units of ``xi``, ``eta``, positive towards the
    sector above the boundary (counter-clockwise from local +x to +y).
    """
    phi = np.arctan2(eta, xi)
    phi *= 1.0 / _SECTOR_RAD
    phi[phi < 0] += N_BITS  # np.mod is several times slower than arctan2 itself
    sector = np.minimum(phi.astype(np.intp), N_BITS - 1)
    phi += 0.5
    boundary = phi.astype(np.intp)
    boundary[boundary == N_BITS] = 0
    angle = np.arange(N_BITS) * _SECTOR_RAD
    cos_b = np.cos(angle).astype(xi.dtype)[boundary]
    sin_b = np.sin(angle).astype(xi.dtype)[boundary]
    cos_b *= eta
    sin_b *= xi
    cos_b -= sin_b
    return sector, boundary, cos_b


def _classify(
    xi: Array, eta: Array, reach: Array, coded: NDArray[np.bool_], owner: NDArray[np.intp], codes: _Codes
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Pattern value at pixel centres, and which pixels' squares may cross an edge.

    ``xi``, ``eta`` (M, H, W) disk radii; ``reach`` and ``coded`` (M, 1, 1) per
    target: ``reach`` bounds the distance (disk radii) from a pixel centre to
    any point of its square. ``owner`` (M,) maps the batch to drawn-target rows.
    """
    rho2 = xi * xi
    rho2 += eta * eta
    value = rho2 <= 1.0
    edge = (rho2 >= np.maximum(1.0 - reach, 0.0) ** 2) & (rho2 <= (1.0 + reach) ** 2)
    if coded.any():
        lo = np.maximum(RING_INNER - reach, 0.0) ** 2
        ring = (rho2 > lo) & (rho2 < (RING_OUTER + reach) ** 2) & coded
        k = np.flatnonzero(ring)
        row = codes.row[owner[k // (xi.size // xi.shape[0])]]
        s = np.broadcast_to(reach, xi.shape).reshape(-1)[k]
        r = np.sqrt(rho2.reshape(-1)[k])
        sector, boundary, to_boundary = _sector_of(xi.reshape(-1)[k], eta.reshape(-1)[k])
        in_ring = (r >= RING_INNER) & (r <= RING_OUTER) & codes.bits[row, sector]
        near_sector = codes.transitions[row, boundary] & (np.abs(to_boundary) <= s)
        value.reshape(-1)[k] |= in_ring
        edge.reshape(-1)[k] |= (np.abs(r - RING_INNER) <= s) | (np.abs(r - RING_OUTER) <= s) | near_sector
    return value, edge


def _edge_coverage(
    xi: Array,
    eta: Array,
    J: tuple[Array, Array, Array, Array],
    reach: Array,
    coded: NDArray[np.bool_],
    full: NDArray[np.bool_],
    row: NDArray[np.intp],
    codes: _Codes,
    ss: int,
) -> NDArray[np.float32]:
    """Area coverage (E,) of edge pixels: ``ss x ss`` sub-samples, each a ramp across the edge.

    Per edge pixel: centre ``xi``, ``eta`` (disk radii), Jacobian ``J``
    (dxi/du, dxi/dv, deta/du, deta/dv), ``reach``, whether the target is
    ``coded``, is supersampled in ``full`` (small on screen) and its code ``row``.
    """
    f32 = np.float32
    # sub-samples along axis 0 so that numpy's inner loops run over the long pixel axis
    off = ((np.arange(ss) + 0.5) / ss - 0.5).astype(f32)[:, None]
    j00, j01, j10, j11 = (np.asarray(j, dtype=f32) for j in J)
    xi = xi.astype(np.float64)  # per-pixel maths is cheap; keep it exact
    eta = eta.astype(np.float64)
    rho_c = np.sqrt(xi * xi + eta * eta)  # np.hypot is ten times slower
    # gradients of the radial and of the tangential distance at the centre, disk radii per px
    safe = rho_c > 1e-9
    n0 = np.where(safe, xi / np.where(safe, rho_c, 1.0), 1.0).astype(f32)
    n1 = np.where(safe, eta / np.where(safe, rho_c, 1.0), 0.0).astype(f32)
    tiny = np.finfo(f32).tiny
    g_r = np.sqrt((j00 * n0 + j10 * n1) ** 2 + (j01 * n0 + j11 * n1) ** 2)
    g_t = np.sqrt((j10 * n0 - j00 * n1) ** 2 + (j11 * n0 - j01 * n1) ** 2)
    scale_r = f32(ss) / np.maximum(g_r, tiny)
    scale_t = f32(ss) / np.maximum(g_t, tiny)
    xi32, eta32 = xi.astype(f32), eta.astype(f32)
    cover = np.zeros(xi.shape, dtype=f32)

    def samples(k: NDArray[np.intp]) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        # the offsets form an ss x ss grid: add a u-row and a v-column once each
        x = ((xi32[k] + j00[k] * off)[:, None, :] + (j01[k] * off)[None, :, :]).reshape(ss * ss, -1)
        y = ((eta32[k] + j10[k] * off)[:, None, :] + (j11[k] * off)[None, :, :]).reshape(ss * ss, -1)
        rho = x * x
        rho += y * y
        return x, y, np.sqrt(rho, out=rho)

    def radial(rho: NDArray[np.float32], sr: NDArray[np.float32]) -> NDArray[np.float32]:
        # the ramp is monotonic, so the nearer of the two circles decides
        t = np.minimum(rho - f32(RING_INNER), f32(RING_OUTER) - rho)
        t *= sr
        return _ramp(t)

    disk = np.flatnonzero(rho_c <= 1.0 + reach)
    if disk.size:
        _, _, rho = samples(disk)
        cover[disk] += _ramp((f32(1.0) - rho) * scale_r[disk]).mean(axis=0)
    ring = np.flatnonzero(coded & (rho_c > RING_INNER - reach) & (rho_c < RING_OUTER + reach))
    if ring.size:
        sector, boundary, to_boundary = _sector_of(xi[ring], eta[ring])
        r_row = row[ring]
        near = full[ring] | (codes.transitions[r_row, boundary] & (np.abs(to_boundary) <= reach[ring]))
        plain = ring[~near]  # one sector: only the ring's circles cross the pixel
        if plain.size:
            _, _, rho = samples(plain)
            bit = codes.bits[r_row[~near], sector[~near]]
            cover[plain] += radial(rho, scale_r[plain]).mean(axis=0) * bit
        general = ring[near]
        if general.size:
            x, y, rho = samples(general)
            _, boundary_s, toward_upper = _sector_of(x, y)
            flat = row[general] * N_BITS + boundary_s
            upper = codes.bits.reshape(-1)[flat].astype(f32)
            lower = codes.bits_before.reshape(-1)[flat].astype(f32)
            toward_upper *= scale_t[general]
            upper -= lower
            upper *= _ramp(toward_upper)
            upper += lower
            value = radial(rho, scale_r[general]) * upper
            cover[general] += value.mean(axis=0)
    return cover


def _box_batches(h: NDArray[np.intp], w: NDArray[np.intp]) -> list[NDArray[np.intp]]:
    """Group boxes of similar size (within ~15 %) so that each group is rendered as one padded array."""
    ladder = np.unique(np.round(4.0 * 1.15 ** np.arange(80)).astype(np.intp))
    key = np.searchsorted(ladder, h) * ladder.size + np.searchsorted(ladder, w)
    order = np.argsort(key, kind="stable")
    splits = np.flatnonzero(np.diff(key[order])) + 1
    return [np.sort(g) for g in np.split(order, splits)] if h.size else []


def _cover_batch(
    camera: BrownFraser,
    sel: NDArray[np.intp],
    u0: NDArray[np.intp],
    v0: NDArray[np.intp],
    shape: tuple[int, int],
    H9: Array,
    reach: Array,
    full: NDArray[np.bool_],
    coded: NDArray[np.bool_],
    codes: _Codes,
    ss: int,
) -> tuple[NDArray[np.float32], NDArray[np.intp], NDArray[np.intp]]:
    """Coverage (M, H, W) of the boxes of drawn targets ``sel`` (M,), all padded to ``shape`` (H, W).

    ``u0``, ``v0`` (M,) are the boxes' top-left pixels. Also returns the pixel
    rows (M, H, 1) and columns (M, 1, W) of the padded boxes.
    """
    hb, wb = shape
    f32 = np.float32
    cols = u0[:, None, None] + np.arange(wb)[None, None, :]
    rows = v0[:, None, None] + np.arange(hb)[None, :, None]
    # float32 from here on: positions stay good to ~1e-4 px and the arrays are the bulk of a frame
    x, y = ideal_grid(camera, cols.astype(f32), rows.astype(f32))
    xi, eta, inv_w = _plane_from_ideal(H9[:, sel, None, None].astype(f32), x, y)
    s = reach[sel, None, None].astype(f32)
    value, edge = _classify(xi, eta, s, coded[sel, None, None], sel, codes)
    if full[sel].any():
        edge |= full[sel, None, None] & np.isfinite(xi)
    cover = value.astype(f32)
    e = np.flatnonzero(edge)
    if e.size:
        b, rem = np.divmod(e, hb * wb)
        r, c = np.divmod(rem, wb)
        t = sel[b]
        J = _grid_jacobian(xi, eta, b, r, c)
        bad = ~np.all(np.isfinite(J), axis=0)
        xi_e, eta_e = xi.reshape(-1)[e], eta.reshape(-1)[e]
        if bad.any():  # a one-pixel-wide box, or a neighbour whose ray misses the plane
            uv = np.stack([u0[b[bad]] + c[bad], v0[b[bad]] + r[bad]], axis=1).astype(np.float64)
            J[:, bad] = _plane_jacobian(
                camera,
                H9[:, t[bad]],
                uv,
                xi_e[bad].astype(np.float64),
                eta_e[bad].astype(np.float64),
                inv_w.reshape(-1)[e[bad]],
            )
        cover.reshape(-1)[e] = _edge_coverage(
            xi_e, eta_e, tuple(J), reach[t], coded[t], full[t], codes.row[t], codes, ss
        )
    return cover, rows, cols


def _grid_jacobian(
    xi: NDArray[np.float32], eta: NDArray[np.float32], b: NDArray[np.intp], r: NDArray[np.intp], c: NDArray[np.intp]
) -> NDArray[np.float32]:
    """d(xi, eta)/d(u, v) (4, E) at pixels (b, r, c) of the (M, H, W) grids, by differences.

    Central differences of this smooth map are exact to ~1e-7 relative (one-sided
    at a box border, ~1e-3, where edges are rare); far cheaper than the analytic
    chain through the distortion model.
    """
    _, hb, wb = xi.shape
    c_lo, c_hi = np.maximum(c - 1, 0), np.minimum(c + 1, wb - 1)
    r_lo, r_hi = np.maximum(r - 1, 0), np.minimum(r + 1, hb - 1)
    base = b * (hb * wb)
    left, right = base + r * wb + c_lo, base + r * wb + c_hi
    up, down = base + r_lo * wb + c, base + r_hi * wb + c
    xf, ef = xi.reshape(-1), eta.reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        du = np.float32(1.0) / (c_hi - c_lo).astype(np.float32)
        dv = np.float32(1.0) / (r_hi - r_lo).astype(np.float32)
        return np.stack(
            [
                (xf[right] - xf[left]) * du,
                (xf[down] - xf[up]) * dv,
                (ef[right] - ef[left]) * du,
                (ef[down] - ef[up]) * dv,
            ]
        )
