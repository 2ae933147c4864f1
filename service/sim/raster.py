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
pixel centre plus the local Jacobian (analytic, through the correction and
the homography; the linearisation errs by ~1e-4 px). The loop over the box
pixels is compiled (:mod:`service.sim._raster_kernel`); this module prepares
its inputs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.targets.codes import N_BITS, bits_of
from service.sim._raster_kernel import SECTOR_BOUNDARY_COS, SECTOR_BOUNDARY_SIN, coverage_kernel

Array = NDArray[np.float64]

# Above this pixel reach (in disk radii) the edge bound is too loose to be worth it:
# every pixel of such a small target is supersampled.
_FULL_SUPERSAMPLE_REACH = 0.25
_REACH_SAFETY = 1.05  # the Jacobian varies slightly across a box


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

    correction = [float(getattr(camera, name)) for name in ("K1", "K2", "K3", "P1", "P2", "B1", "B2")]
    cam = np.array([width, height, *camera.pixel_size_mm, camera.x0_mm, camera.y0_mm, *correction], dtype=np.float64)
    return coverage_kernel(
        cam,
        np.ascontiguousarray(H9),
        np.ascontiguousarray(boxes, dtype=np.intp),
        np.ascontiguousarray(reach, dtype=np.float64),
        full,
        code_row,
        bits,
        before,
        bits != before,
        int(supersample),
        SECTOR_BOUNDARY_COS,
        SECTOR_BOUNDARY_SIN,
    )


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
