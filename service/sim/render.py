"""Realistic near-IR images of retro-reflective targets, with ground truth.

Image formation, in this order (levels in 8-bit DN, scaled to the bit depth last):

1. Geometry. Each target is a planar pattern in its own plane (normal from
   ``normals_field``, default field +z; local x = field x projected into the
   plane, see :func:`plane_axes_field`): the disk ``r <= R`` and, for a coded
   target, the ring sectors of :mod:`service.core.targets.codes`. Every sample of a
   pixel is mapped back to the plane exactly (``ideal_from_pixel`` -> ray ->
   plane -> local x, y), which gives exact perspective and distortion.
2. Anti-aliasing, inside each target's bounding box only: exact coverage of
   pixels away from edges, ``supersample x supersample`` sub-samples (each a
   ramp across the edge) in pixels that an edge may cross; see
   :mod:`service.sim.raster`.
3. Radiometry: the ring light sits at the projection centre, so the returned
   light falls with distance squared (``target_dn`` at :data:`REFERENCE_DISTANCE_MM`),
   with ``cos(incidence) ** INCIDENCE_POWER`` (retro-reflective sheeting is
   wide-angle) and with the natural vignetting ``cos(field angle) **
   VIGNETTING_POWER``: a level at each target's centre and, across its pattern,
   that level's change in the image to first order (the light is no
   step from one target to the next: a level per target hid that a fixed edge
   level, and an intensity centroid, move towards the light).
4. Optics: Gaussian blur ``blur_sigma_px`` (cv2) of the target light, and the smear of the
   camera's motion during the exposure (``motion_blur_px`` along ``motion_angle_deg``:
   :func:`smear`, centred, so ``uv_true`` is the mid-exposure position); then the
   ring light's hot spot (only when lit) and the linear gradient are added,
   occluders darken all of that down to the dark level, and ``background_dn``
   is added.
5. Sensor: shot noise is Poisson in electrons (``electrons_per_dn``), read
   noise Gaussian; the sum is clipped at full scale (saturation) and rounded.
   Poisson is drawn exactly where a pixel expects fewer than
   :data:`EXACT_POISSON_BELOW_E` electrons and as its normal approximation
   (same mean and variance, skewness below 0.22) elsewhere, because exact
   Poisson draws for a full frame cost more than the whole render budget.

Ground truth: ``uv_true`` is the projection of the target's centre,
``uv_disk_centroid`` the area centroid of the disk's image (a 32-gon of the
disk's area, projected through the distortion model: good to ~1e-5 px).
Targets behind the camera, seen from behind or at grazing incidence (beyond
``arccos(MIN_INCIDENCE_COS)``) are neither drawn nor reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, ndtri

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import apply_T, check_T, inv_T
from service.core.targets.codes import RING_OUTER
from service.core.targets.field import Field
from service.sim._raster_kernel import noise_kernel, quantise_kernel
from service.sim.raster import pattern_coverage

Array = NDArray[np.float64]

REFERENCE_DISTANCE_MM = 1000.0
INCIDENCE_POWER = 0.5
VIGNETTING_POWER = 4.0
MIN_INCIDENCE_COS = 0.05
DEFAULT_CODED_DIAMETER_MM = 10.0
DEFAULT_UNCODED_DIAMETER_MM = 6.0
EXACT_POISSON_BELOW_E = 20.0
OUTLINE_POINTS = 32  # polygon vertices per circle for centroids, boxes and visibility


@dataclass(frozen=True)
class RenderSettings:
    """How a frame is rendered; levels in 8-bit DN (scaled up for deeper images)."""

    supersample: int = 4  # per axis, inside target boxes
    blur_sigma_px: float = 0.6  # Gaussian PSF (optics + pixel crosstalk)
    background_dn: float = 8.0  # dark background level
    target_dn: float = 190.0  # fully lit, head-on target at REFERENCE_DISTANCE_MM, on axis
    exposure_scale: float = 1.0  # multiplies target_dn (exposure time / ring-light power)
    read_noise_dn: float = 1.2
    electrons_per_dn: float = 10.0  # shot noise: Poisson in electrons
    bit_depth: int = 8  # 8 -> uint8, up to 16 -> uint16 (values scaled to the depth)
    hot_spot_dn: float = 0.0  # broad additive glow of the ring light, Gaussian (only when lit)
    hot_spot_sigma_px: float = 250.0
    hot_spot_uv: tuple[float, float] | None = None  # default: image centre
    gradient_dn: float = 0.0  # linear ramp: 0 at the left image edge, gradient_dn at the right
    # the image's motion during the exposure: a uniform smear this long (px, centred on the
    # mid-exposure position) in this direction (deg from +u towards +v); a camera on a moving arm
    motion_blur_px: float = 0.0
    motion_angle_deg: float = 0.0
    occluders: tuple[tuple[float, float, float], ...] = ()  # dark discs (u, v, radius_px)
    lit: bool = True  # ring light on? if False, targets are not bright (only background)
    # hot pixels: this share of the sensor's pixels, the same ones in every frame of a seed (a property
    # of the sensor), hot_pixel_dn above the background whether the light is on or off (dark current)
    hot_pixels: float = 0.0
    hot_pixel_dn: float = 200.0
    hot_pixel_seed: int = 0
    # dead pixels: this share of the sensor's pixels, no response (0 DN whatever the light), the same
    # ones in every frame of a seed
    dead_pixels: float = 0.0
    dead_pixel_seed: int = 1
    # a white card held before the lens under the ring light (flat frames, to map dead pixels): with
    # the light on the whole image at this level, 45 % less in the corners (the light's cone and the
    # lens's vignetting), the scene behind it hidden; 0: no card
    card_dn: float = 0.0
    # the light's change across each target's pattern (step 3 of the module's docstring); False:
    # one level a target, for the tests of the geometry alone (an intensity centroid of an evenly
    # lit pattern is its area centroid)
    shading: bool = True

    def __post_init__(self) -> None:
        if int(self.supersample) != self.supersample or self.supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {self.supersample}")
        if not 8 <= int(self.bit_depth) <= 16 or int(self.bit_depth) != self.bit_depth:
            raise ValueError(f"bit_depth must be an integer from 8 to 16, got {self.bit_depth}")
        for name in (
            "blur_sigma_px",
            "background_dn",
            "target_dn",
            "exposure_scale",
            "read_noise_dn",
            "hot_spot_dn",
            "motion_blur_px",
            "hot_pixel_dn",
            "card_dn",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and non-negative, got {v}")
        for name in ("electrons_per_dn", "hot_spot_sigma_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and positive, got {v}")
        for name in ("hot_pixels", "dead_pixels"):
            if not 0.0 <= getattr(self, name) <= 0.01:
                raise ValueError(f"{name} must be a share of the pixels in [0, 0.01], got {getattr(self, name)}")
        if not np.isfinite(self.motion_angle_deg):
            raise ValueError(f"motion_angle_deg must be finite, got {self.motion_angle_deg}")
        if not np.isfinite(self.gradient_dn):
            raise ValueError(f"gradient_dn must be finite, got {self.gradient_dn}")
        for occ in self.occluders:
            if len(occ) != 3 or not np.all(np.isfinite(occ)) or not occ[2] > 0:
                raise ValueError(f"an occluder must be (u, v, radius_px) with radius > 0, got {occ}")


@dataclass(frozen=True)
class RenderedFrame:
    """A rendered image and its ground truth.

    ``ids`` (N,): targets at least partly in the image, in field order;
    ``uv_true`` (N, 2) px: projection of each target's 3-D centre (through the
    distortion model); ``uv_disk_centroid`` (N, 2) px: area centroid of the
    disk's image (differs from ``uv_true`` by the perspective/eccentricity
    bias); ``fully_visible`` (N,) bool: the whole target (disk and, for coded
    targets, ring) inside the image by 1 px and not touched by an occluder;
    ``T_field_camera`` (4, 4).
    """

    image: NDArray[np.generic]
    ids: tuple[str, ...]
    uv_true: Array
    uv_disk_centroid: Array
    fully_visible: NDArray[np.bool_]
    T_field_camera: Array


# -- per-target geometry ----------------------------------------------------


def plane_axes_field(normals_field: NDArray[np.float64] | None, n: int) -> tuple[Array, Array, Array]:
    """Unit normal, local x and local y (each (n, 3), field frame) of each target's plane.

    Local x is field x projected into the plane (field y if the normal is
    along x); local y = normal x local x, so (x, y, normal) is right-handed.
    """
    if normals_field is None:
        normal = np.tile([0.0, 0.0, 1.0], (n, 1))
    else:
        normal = np.asarray(normals_field, dtype=np.float64)
        if normal.shape != (n, 3):
            raise ValueError(f"normals_field must have shape ({n}, 3), got {normal.shape}")
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        if not np.all(np.isfinite(length)) or np.any(length < 1e-12):
            raise ValueError("normals_field must be finite and non-zero")
        normal = normal / length
    ref = np.where(np.abs(normal[:, :1]) > 0.999, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    x = ref - np.sum(ref * normal, axis=1, keepdims=True) * normal
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return normal, x, np.cross(normal, x)


def _ring_points(p0: Array, ex: Array, ey: Array, radius: Array) -> Array:
    """(M, OUTLINE_POINTS, 3) vertices of polygons approximating circles of ``radius`` (M,) about ``p0``.

    The vertices sit slightly outside the circle, where the regular polygon
    has the circle's area: the slivers it adds and cuts then balance, and its
    image's area centroid matches the disk image's to O(K^-4) instead of
    O(K^-2) (6e-6 px instead of 3e-3 px for a 20 mm disk at 400 mm, 60 deg).
    """
    k = OUTLINE_POINTS
    phi = np.arange(k) * (2.0 * np.pi / k)
    cs = np.cos(phi)[None, :, None]
    sn = np.sin(phi)[None, :, None]
    r = radius[:, None, None] * np.sqrt(2.0 * np.pi / (k * np.sin(2.0 * np.pi / k)))
    return p0[:, None, :] + r * (cs * ex[:, None, :] + sn * ey[:, None, :])


def _polygon_centroid(uv: Array) -> Array:
    """Area centroids (M, 2) of closed polygons ``uv`` (M, K, 2)."""
    ref = uv.mean(axis=1, keepdims=True)  # centring keeps the shoelace sums well conditioned
    p = uv - ref
    q = np.roll(p, -1, axis=1)
    cross = p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1]
    area = cross.sum(axis=1)
    cx = ((p[..., 0] + q[..., 0]) * cross).sum(axis=1) / (3.0 * area)
    cy = ((p[..., 1] + q[..., 1]) * cross).sum(axis=1) / (3.0 * area)
    return ref[:, 0, :] + np.stack([cx, cy], axis=1)


# -- image-level helpers -----------------------------------------------------


@lru_cache(maxsize=1)
def _normal_table() -> NDArray[np.float32]:
    """Standard normal quantiles of the 65536 midpoints of [0, 1], scaled to unit variance."""
    z = ndtri((np.arange(65536) + 0.5) / 65536.0)
    table = (z / z.std()).astype(np.float32)
    table.setflags(write=False)
    return table


def _accumulate(
    flat: NDArray[np.intp], values: NDArray[np.float32], size: int, overlapping: bool
) -> NDArray[np.float32]:
    """Sum ``values`` into a zero image of ``size`` pixels at ``flat`` indices."""
    if overlapping:
        return np.bincount(flat, weights=values, minlength=size).astype(np.float32)
    out = np.zeros(size, dtype=np.float32)
    out[flat] = values  # boxes are disjoint, so no index repeats
    return out


def _boxes_overlap(u0: NDArray[np.intp], v0: NDArray[np.intp], u1: NDArray[np.intp], v1: NDArray[np.intp]) -> bool:
    """Whether any two of the inclusive pixel boxes may share a pixel (True for very many boxes)."""
    if u0.size > 2000:  # the pairwise test would need too much memory
        return True
    i, j = np.triu_indices(u0.size, 1)
    return bool(np.any((u0[j] <= u1[i]) & (u0[i] <= u1[j]) & (v0[j] <= v1[i]) & (v0[i] <= v1[j])))


SMEAR_SAMPLES_PER_PX = 16  # points of the smear's segment per px, each spread bilinearly


def smear_kernel(length_px: float, angle_deg: float) -> NDArray[np.float32]:
    """The normalised kernel of a uniform smear ``length_px`` long at ``angle_deg`` (from +u towards
    +v), centred on the kernel's middle pixel: the segment's points, each shared bilinearly between
    its four pixels. Point-symmetric, so correlation (``cv2.filter2D``) is the convolution."""
    if not (np.isfinite(length_px) and length_px >= 0 and np.isfinite(angle_deg)):
        raise ValueError(f"a smear needs a finite length >= 0 and angle, got {length_px} px at {angle_deg} deg")
    half = int(np.ceil(length_px / 2)) + 1
    n = max(2, int(np.ceil(length_px * SMEAR_SAMPLES_PER_PX)))
    t = (np.arange(n) + 0.5) / n - 0.5  # symmetric about 0
    a = np.radians(angle_deg)
    x, y = half + t * length_px * np.cos(a), half + t * length_px * np.sin(a)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    k = np.zeros((2 * half + 1, 2 * half + 1))
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    return (k / k.sum()).astype(np.float32)


def image_motion_px(
    camera: BrownFraser, field: Field, T_field_camera_start: Array, T_field_camera_end: Array
) -> tuple[float, float]:
    """The smear (length px, angle deg from +u towards +v) of a camera moving from one pose to the
    other during an exposure: the median image motion of the field's targets in view in both.

    One uniform smear stands for the frame: a translation moves every target alike; a rotation
    about the optical axis or a change of distance moves them apart, which the median averages."""
    ends = []
    for T in (T_field_camera_start, T_field_camera_end):
        p_cam = apply_T(inv_T(np.asarray(T, dtype=np.float64)), field.xyz)
        ends.append((p_cam[:, 2] > 1.0, camera.pixel_from_camera(p_cam)))
    (front0, uv0), (front1, uv1) = ends
    seen = front0 & front1 & camera.in_image(uv0) & camera.in_image(uv1)
    if not np.any(seen):
        return 0.0, 0.0
    du, dv = np.median(uv1[seen] - uv0[seen], axis=0)
    return float(np.hypot(du, dv)), float(np.degrees(np.arctan2(dv, du)))


def smear(image: NDArray[np.generic], length_px: float, angle_deg: float) -> NDArray[np.generic]:
    """``image`` smeared as by the camera's motion during the exposure (:func:`smear_kernel`), in its
    own type (rounded): a degradation for real images (``posecell bench real``)."""
    img = np.asarray(image)
    out: NDArray[np.generic] = cv2.filter2D(
        img, -1, smear_kernel(length_px, angle_deg), borderType=cv2.BORDER_REFLECT_101
    )
    return out


def _compose(
    signal: NDArray[np.float32], settings: RenderSettings, rng: np.random.Generator | None
) -> NDArray[np.generic]:
    """Blur, glow, gradient, occluders, background, noise, saturation and quantisation."""
    s = settings
    f32 = np.float32
    height, width = signal.shape
    img = signal
    if s.lit and s.card_dn > 0:
        r2 = (np.arange(width, dtype=f32)[None, :] - f32((width - 1) / 2)) ** 2 / f32(((width - 1) / 2) ** 2)
        r2 = (
            r2 + (np.arange(height, dtype=f32)[:, None] - f32((height - 1) / 2)) ** 2 / f32(((height - 1) / 2) ** 2)
        ) / 2
        img[:] = f32(s.card_dn) * (f32(1.0) - f32(0.45) * r2)
    if s.blur_sigma_px > 0:
        k = 2 * int(np.ceil(3.0 * s.blur_sigma_px)) + 1  # +-3 sigma; cv2 normalises the kernel
        # in place: every fresh full-frame buffer costs ~1 ms of page faults
        img = cv2.GaussianBlur(signal, (k, k), s.blur_sigma_px, dst=signal, borderType=cv2.BORDER_REFLECT_101)
    if s.motion_blur_px > 0:
        img = cv2.filter2D(
            img, -1, smear_kernel(s.motion_blur_px, s.motion_angle_deg), borderType=cv2.BORDER_REFLECT_101
        )
    if s.gradient_dn != 0:
        img += (np.arange(width, dtype=f32) * f32(s.gradient_dn / max(width - 1, 1)))[None, :]
    if s.lit and s.hot_spot_dn > 0:
        cu, cv = s.hot_spot_uv if s.hot_spot_uv is not None else ((width - 1) / 2, (height - 1) / 2)
        k2 = -0.5 / s.hot_spot_sigma_px**2
        gu = np.exp(k2 * (np.arange(width) - cu) ** 2).astype(f32)
        gv = (s.hot_spot_dn * np.exp(k2 * (np.arange(height) - cv) ** 2)).astype(f32)
        img += gv[:, None] * gu[None, :]  # separable Gaussian
    # an occluder's edge is the blurred edge of a half-plane seen through a pixel
    sigma_edge = float(np.hypot(s.blur_sigma_px, np.sqrt(1.0 / 12.0)))
    for u, v, r in s.occluders:
        pad = r + 5.0 * sigma_edge
        c0, c1 = max(int(np.floor(u - pad)), 0), min(int(np.ceil(u + pad)), width - 1)
        r0, r1 = max(int(np.floor(v - pad)), 0), min(int(np.ceil(v + pad)), height - 1)
        if c1 < c0 or r1 < r0:
            continue
        d = np.hypot(np.arange(c0, c1 + 1)[None, :] - u, np.arange(r0, r1 + 1)[:, None] - v)
        img[r0 : r1 + 1, c0 : c1 + 1] *= (1.0 - ndtr((r - d) / sigma_edge)).astype(f32)
    img += f32(s.background_dn)
    if s.hot_pixels > 0:
        img.reshape(-1)[hot_pixel_indices(height, width, s.hot_pixels, s.hot_pixel_seed)] += f32(s.hot_pixel_dn)
    if rng is not None:
        # variance (DN^2) = level / e + read^2 = (level + read^2 e) / e, e = electrons_per_dn; normal
        # variates by inverse transform of 16-bit uniforms: four times faster than rng.standard_normal
        # for a frame, the tails cut at 4.3 sigma, which no image statistic here depends on
        epd = s.electrons_per_dn
        u16 = rng.integers(0, 65536, size=img.shape, dtype=np.uint16)
        z_table = _normal_table() * f32(1.0 / np.sqrt(epd))
        low = img < f32(EXACT_POISSON_BELOW_E / epd) if float(img.min()) * epd < EXACT_POISSON_BELOW_E else None
        exact = None
        if low is not None:  # too few electrons for the normal approximation: Poisson itself
            lam_e = np.maximum(img[low], 0).astype(np.float64) * epd
            exact = rng.poisson(lam_e) / epd + (s.read_noise_dn * np.sqrt(epd)) * z_table[u16[low]]
        noise_kernel(img, u16, z_table, f32(s.read_noise_dn**2 * epd))
        if low is not None:
            img[low] = exact
    if s.dead_pixels > 0:
        img.reshape(-1)[hot_pixel_indices(height, width, s.dead_pixels, s.dead_pixel_seed)] = f32(0.0)
    full_scale = 2**s.bit_depth - 1
    out = np.empty(img.shape, dtype=np.uint8 if s.bit_depth == 8 else np.uint16)
    quantise_kernel(img, f32(full_scale / 255.0), full_scale, out)
    return out


@lru_cache(maxsize=4)
def hot_pixel_indices(height: int, width: int, share: float, seed: int) -> NDArray[np.intp]:
    """The flat indices of a ``height`` x ``width`` sensor's hot (or dead) pixels: ``share`` of them,
    drawn once from ``seed`` (the same in every frame, as a sensor's are)."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(height * width, round(share * height * width), replace=False))


@dataclass(frozen=True)
class _Targets:
    """Targets that may show in the image (M of them), camera frame, mm."""

    index: NDArray[np.intp]  # (M,) field rows
    p0: Array  # (M, 3) centres
    normal: Array  # (M, 3)
    ex: Array  # (M, 3)
    ey: Array  # (M, 3)
    radius: Array  # (M,) disk radius
    coded: NDArray[np.bool_]  # (M,)
    uv_true: Array  # (M, 2)
    uv_disk_centroid: Array  # (M, 2)
    outline_uv: Array  # (M, OUTLINE_POINTS, 2) outer edge of the whole pattern
    relative_level: Array  # (M,) a fully covered pixel's brightness before blur, in units of target_dn x exposure_scale
    light_gradient: Array  # (M, 2) d ln(relative_level) / d(u, v) per px across the target's image


def _targets_in_view(
    camera: BrownFraser,
    field: Field,
    T_field_camera: Array,
    normals_field: NDArray[np.float64] | None,
) -> _Targets:
    n = len(field)
    T_camera_field = inv_T(T_field_camera)
    R = T_camera_field[:3, :3]
    p0 = apply_T(T_camera_field, field.xyz)
    normal_f, ex_f, ey_f = plane_axes_field(normals_field, n)
    normal, ex, ey = normal_f @ R.T, ex_f @ R.T, ey_f @ R.T
    coded = field.codes >= 0
    diameter = field.diameters_mm.copy()
    unknown = ~np.isfinite(diameter)
    diameter[unknown] = np.where(coded[unknown], DEFAULT_CODED_DIAMETER_MM, DEFAULT_UNCODED_DIAMETER_MM)
    if np.any(diameter <= 0):
        raise ValueError("every target diameter must be positive")
    radius = diameter / 2.0
    outer = np.where(coded, RING_OUTER * radius, radius)
    dist = np.linalg.norm(p0, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = -np.sum(normal * p0, axis=1) / dist
    z_min = p0[:, 2] - outer * np.hypot(ex[:, 2], ey[:, 2])  # nearest point of the pattern's rim
    keep = np.flatnonzero((z_min > 1e-3) & (cos_inc > MIN_INCIDENCE_COS))

    # coarse cull in ideal coordinates: the inverse distortion is only trusted near the sensor
    rim = _ring_points(p0[keep], ex[keep], ey[keep], outer[keep])
    rim_ideal = camera.c_mm * rim[..., :2] / rim[..., 2:]
    sensor_ideal = camera.ideal_from_pixel(camera.pixel_grid(9, 9))
    lo, hi = sensor_ideal.min(axis=0), sensor_ideal.max(axis=0)
    pad = 0.1 * (hi - lo)
    near = np.all((rim_ideal.max(axis=1) > lo - pad) & (rim_ideal.min(axis=1) < hi + pad), axis=1)
    keep, rim = keep[near], rim[near]
    m = keep.size
    coded_k = coded[keep]
    disk = np.where(coded_k[:, None, None], _ring_points(p0[keep], ex[keep], ey[keep], radius[keep]), rim)
    pts = np.concatenate([p0[keep], disk.reshape(-1, 3), rim[coded_k].reshape(-1, 3)])
    uv = camera.pixel_from_camera(pts)
    uv_true = uv[:m]
    disk_uv = uv[m : m + m * OUTLINE_POINTS].reshape(m, OUTLINE_POINTS, 2)
    outline_uv = disk_uv.copy()
    outline_uv[coded_k] = uv[m + m * OUTLINE_POINTS :].reshape(-1, OUTLINE_POINTS, 2)
    finite = np.all(np.isfinite(outline_uv), axis=(1, 2)) & np.all(np.isfinite(uv_true), axis=1)

    relative_level = _relative_level(p0[keep], normal[keep])
    f = finite
    return _Targets(
        index=keep[f],
        p0=p0[keep][f],
        normal=normal[keep][f],
        ex=ex[keep][f],
        ey=ey[keep][f],
        radius=radius[keep][f],
        coded=coded_k[f],
        uv_true=uv_true[f],
        uv_disk_centroid=_polygon_centroid(disk_uv[f]),
        outline_uv=outline_uv[f],
        relative_level=relative_level[f],
        light_gradient=_light_gradient(camera, p0[keep][f], normal[keep][f], ex[keep][f], ey[keep][f]),
    )


def _relative_level(p: Array, normal: Array) -> Array:
    """The brightness of a target's point ``p`` (M, 3) camera frame, mm, on its plane of ``normal``."""
    d = np.linalg.norm(p, axis=1)
    cos_inc = -np.sum(normal * p, axis=1) / d
    return (REFERENCE_DISTANCE_MM / d) ** 2 * cos_inc**INCIDENCE_POWER * (p[:, 2] / d) ** VIGNETTING_POWER


def _light_gradient(camera: BrownFraser, p0: Array, normal: Array, ex: Array, ey: Array, step_mm: float = 0.5) -> Array:
    """d ln(level) / d(u, v) per px at each target's centre (M, 2): the level and the image position
    half a mm along the plane's axes, ``g' J = d ln L / d(x, y)`` with J the plane-to-image Jacobian."""
    ln0 = np.log(_relative_level(p0, normal))
    uv0 = camera.pixel_from_camera(p0)
    dln, J = np.empty((len(p0), 2)), np.empty((len(p0), 2, 2))
    for k, axis in enumerate((ex, ey)):
        p = p0 + step_mm * axis
        dln[:, k] = (np.log(_relative_level(p, normal)) - ln0) / step_mm
        J[:, :, k] = (camera.pixel_from_camera(p) - uv0) / step_mm
    # J' g = d ln L / d(x, y) by Cramer's rule: no LAPACK call in the render process, whose BLAS threads
    # spun between renders on a CPU it shares with the service (a 20 Hz stream fell to 5-7 Hz)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 1, 0] * J[:, 0, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.column_stack(
            [
                (dln[:, 0] * J[:, 1, 1] - J[:, 1, 0] * dln[:, 1]) / det,
                (J[:, 0, 0] * dln[:, 1] - J[:, 0, 1] * dln[:, 0]) / det,
            ]
        )
    return np.where(np.isfinite(g), g, 0.0)


@dataclass(frozen=True)
class _Footprint:
    """What a pose gives whatever the light: the targets in view and the pixels their patterns cover."""

    targets: _Targets
    boxed: NDArray[np.intp]  # (m,) rows of ``targets`` with a pixel box in the image
    owner: NDArray[np.intp]  # (K,) row of ``boxed`` of each covered pixel
    flat: NDArray[np.intp]  # (K,) pixel index v * width + u
    cover: NDArray[np.float32]  # (K,) covered fraction
    shade: NDArray[np.float32]  # (K,) the light at the pixel relative to its target's centre
    overlapping: bool  # whether two boxes may share a pixel
    in_image: NDArray[np.bool_]  # (m,) covers at least part of a pixel


@dataclass(frozen=True, eq=False)
class _Pose:
    """A footprint's key: the very camera and field objects, the pose's bytes, the normals and the sampling."""

    camera: BrownFraser
    field: Field
    T_field_camera: Array
    normals_field: NDArray[np.float64] | None
    supersample: int

    def _bytes(self) -> tuple[bytes, bytes | None, int]:
        normals = None if self.normals_field is None else self.normals_field.tobytes()
        return self.T_field_camera.tobytes(), normals, self.supersample

    def __hash__(self) -> int:
        return hash((id(self.camera), id(self.field), *self._bytes()))

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, _Pose)
            and other.camera is self.camera
            and other.field is self.field
            and other._bytes() == self._bytes()
        )


def _footprint(
    camera: BrownFraser,
    field: Field,
    T_field_camera: Array,
    normals_field: NDArray[np.float64] | None,
    supersample: int,
) -> _Footprint:
    """The targets in view from ``T_field_camera`` and their coverage of the pixels.

    The simulated camera renders the same pose again and again: every frame of a still cell, and
    the frames it asked for ahead when the exposure steps. The footprint is three quarters of a
    frame's work, so the last few are kept.
    """
    T = T_field_camera.copy()  # the key's own, read-only: a caller's later change cannot alter it
    T.setflags(write=False)
    normals = None if normals_field is None else np.array(normals_field, dtype=np.float64)
    if normals is not None:
        normals.setflags(write=False)
    return _footprint_of(_Pose(camera, field, T, normals, supersample))


@lru_cache(maxsize=8)
def _footprint_of(pose: _Pose) -> _Footprint:
    camera, field = pose.camera, pose.field
    width, height = camera.width, camera.height
    tg = _targets_in_view(camera, field, pose.T_field_camera, pose.normals_field)
    # pixel boxes: every pixel whose square may touch the pattern (the outline polygon's
    # edges cut inside the circle, so pad by the largest sagitta too)
    ext = tg.outline_uv.max(axis=1) - tg.outline_uv.min(axis=1)
    sag = 0.5 * ext.max(axis=1, keepdims=True) * (1.0 - np.cos(np.pi / OUTLINE_POINTS)) + 0.51
    lo = np.floor(tg.outline_uv.min(axis=1) - sag).astype(np.intp)
    hi = np.ceil(tg.outline_uv.max(axis=1) + sag).astype(np.intp)
    u0, v0 = np.maximum(lo[:, 0], 0), np.maximum(lo[:, 1], 0)
    u1, v1 = np.minimum(hi[:, 0], width - 1), np.minimum(hi[:, 1], height - 1)
    boxed = np.flatnonzero((u1 >= u0) & (v1 >= v0))
    u0, v0, u1, v1 = u0[boxed], v0[boxed], u1[boxed], v1[boxed]
    owner, flat, cover = pattern_coverage(
        camera,
        tg.p0[boxed],
        tg.normal[boxed],
        tg.ex[boxed],
        tg.ey[boxed],
        tg.radius[boxed],
        field.codes[tg.index[boxed]],
        np.stack([u0, v0, u1, v1], axis=1),
        pose.supersample,
    )
    in_image = np.bincount(owner, weights=cover, minlength=boxed.size) > 0
    # the light at each covered pixel relative to its target's centre, to first order (<= ~3 % across
    # a pattern): 1 + g . (uv - uv_centre), g . uv_centre once a target (a pose's pixels: ~50 000)
    v_px, u_px = np.divmod(flat, width)
    g = tg.light_gradient[boxed].astype(np.float32)
    at_centre = np.sum(g * tg.uv_true[boxed], axis=1, dtype=np.float32)
    shade = (1.0 - at_centre[owner]) + g[owner, 0] * u_px.astype(np.float32) + g[owner, 1] * v_px.astype(np.float32)
    fp = _Footprint(tg, boxed, owner, flat, cover, shade, _boxes_overlap(u0, v0, u1, v1), in_image)
    for a in (boxed, owner, flat, cover, shade, in_image):
        a.setflags(write=False)  # shared by every frame of this pose
    return fp


def render_frame(
    camera: BrownFraser,
    field: Field,
    T_field_camera: NDArray[np.float64],
    settings: RenderSettings = RenderSettings(),
    rng: np.random.Generator | None = None,
    normals_field: NDArray[np.float64] | None = None,
) -> RenderedFrame:
    """Render the image ``camera`` takes of ``field`` from pose ``T_field_camera``.

    Parameters
    ----------
    camera : BrownFraser
        Interior orientation, including distortion.
    field : Field
        Targets, field frame, mm; NaN diameters mean 10 mm (coded) / 6 mm (uncoded).
    T_field_camera : (4, 4) float
        The camera's pose in the field.
    settings : RenderSettings
    rng : np.random.Generator or None
        Source of shot and read noise; None renders noise-free (deterministic).
    normals_field : (N, 3) float or None
        Plane normal of each target (any length); default the field's own
        (``field.normals``), else +z. The target is seen only from the side its
        normal points to.

    Returns
    -------
    RenderedFrame
        The (height, width) image and the ground truth of the targets that are
        at least partly in it.
    """
    T_field_camera = check_T(T_field_camera, "T_field_camera").copy()
    normals_field = field.normals if normals_field is None else normals_field
    fp = _footprint(camera, field, T_field_camera, normals_field, settings.supersample)
    tg, boxed = fp.targets, fp.boxed
    level_dn = (
        settings.target_dn * settings.exposure_scale * tg.relative_level[boxed]
        if settings.lit
        else np.zeros(boxed.size)
    )
    values = fp.cover * level_dn.astype(np.float32)[fp.owner]
    if settings.shading:
        values *= fp.shade
    signal = _accumulate(fp.flat, values, camera.width * camera.height, fp.overlapping)
    image = _compose(signal.reshape(camera.height, camera.width), settings, rng)

    shown = boxed[fp.in_image]
    outline = tg.outline_uv[shown]
    fully = np.all(camera.in_image(outline, margin_px=1.0), axis=1)
    for ou, ov, r in settings.occluders:
        lo_o, hi_o = outline.min(axis=1), outline.max(axis=1)
        near_o = np.flatnonzero(fully & np.all((lo_o - r <= [ou, ov]) & ([ou, ov] <= hi_o + r), axis=1))
        for k in near_o:
            contour = outline[k].astype(np.float32).reshape(-1, 1, 2)
            if cv2.pointPolygonTest(contour, (float(ou), float(ov)), True) >= -r:
                fully[k] = False
    return RenderedFrame(
        image=image,
        ids=tuple(field.ids[i] for i in tg.index[shown]),
        uv_true=tg.uv_true[shown],
        uv_disk_centroid=tg.uv_disk_centroid[shown],
        fully_visible=fully,
        T_field_camera=T_field_camera,
    )
