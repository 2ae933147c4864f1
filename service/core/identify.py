"""Target identification (the paper, section 4.2): coded targets first, then the rest from the pose.

Coded targets name themselves; a pose from them predicts where every uncoded
target must appear, and each prediction is matched to the nearest measured blob
(the paper's second step). Matching is one-to-one and refuses ambiguity: a
prediction with two blobs inside the tolerance, or a blob claimed by two
predictions, is left out rather than guessed.

Also here: the perspective (eccentricity) bias of circular targets. The image of
a circle's centre is not the centre of the circle's elliptical image; from the
pose, the target's diameter and its plane, the offset is computed exactly in
ideal coordinates (the centre of the image conic) and removed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.core.camera_model import BrownFraser
from service.core.field import Field
from service.core.frames import apply_T, inv_T
from service.core.geometry_kernels import eccentricity_kernel

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_NORMAL_FIELD = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Matches:
    """Field rows paired with blob indices; ``rows`` (N,) and ``blobs`` (N,) int."""

    rows: IntArray
    blobs: IntArray


def match_coded(field: Field, codes_read: NDArray[np.int64]) -> Matches:
    """Pair decoded blobs with the field's coded targets.

    ``codes_read`` (M,) holds the code read for each blob, -1 where none was.
    A code read twice in one image (a reflection, a misread) names neither blob.
    """
    row_of_code = {int(c): i for i, c in enumerate(field.codes) if c >= 0}
    codes_read = np.asarray(codes_read, dtype=np.int64)
    valid = codes_read >= 0
    values, counts = np.unique(codes_read[valid], return_counts=True)
    once = set(values[counts == 1].tolist())
    rows, blobs = [], []
    for b in np.flatnonzero(valid):
        code = int(codes_read[b])
        if code in once and code in row_of_code:
            rows.append(row_of_code[code])
            blobs.append(int(b))
    return Matches(np.array(rows, dtype=np.int64), np.array(blobs, dtype=np.int64))


def match_predicted(
    uv_predicted: Array,
    rows: IntArray,
    blob_uv: Array,
    tolerance_px: float,
    taken: NDArray[np.bool_] | None = None,
) -> Matches:
    """Match predicted positions (N, 2) px of field ``rows`` to blobs (M, 2) px, one to one.

    A prediction is matched when exactly one free blob lies within
    ``tolerance_px`` and that blob is within tolerance of no other prediction.
    """
    rows = np.asarray(rows, dtype=np.int64)
    if len(rows) == 0 or len(blob_uv) == 0:
        return Matches(np.empty(0, np.int64), np.empty(0, np.int64))
    free = np.ones(len(blob_uv), bool) if taken is None else ~taken
    free_idx = np.flatnonzero(free)
    if len(free_idx) == 0:
        return Matches(np.empty(0, np.int64), np.empty(0, np.int64))
    tree = cKDTree(blob_uv[free_idx])
    d, j = tree.query(uv_predicted, k=2, distance_upper_bound=tolerance_px)
    single = np.isfinite(d[:, 0]) & ~np.isfinite(d[:, 1])
    cand = free_idx[np.minimum(j[single, 0], len(free_idx) - 1)]
    # a blob wanted by two predictions belongs to neither
    vals, counts = np.unique(cand, return_counts=True)
    unique_blob = np.isin(cand, vals[counts == 1])
    return Matches(rows[single][unique_blob], cand[unique_blob])


def project_field(
    camera: BrownFraser, field: Field, T_field_camera: Array, margin_px: float = 0.0
) -> tuple[IntArray, Array]:
    """Rows and pixel positions (N, 2) of field targets in front of the camera and inside the image."""
    p_camera = apply_T(inv_T(T_field_camera), field.xyz)
    front = p_camera[:, 2] > 0
    uv = np.full((len(field), 2), np.nan)
    uv[front] = camera.pixel_from_camera(p_camera[front])
    inside = front & camera.in_image(uv, margin_px)
    rows = np.flatnonzero(inside)
    return rows.astype(np.int64), uv[rows]


def eccentricity_px(
    camera: BrownFraser,
    p_field: Array,
    radius_mm: Array,
    T_field_camera: Array,
    uv: Array,
    normals_field: Array | None = None,
) -> Array:
    """Offset (N, 2) px of each disk image's centre from the image of the disk's centre.

    Parameters
    ----------
    p_field : (N, 3) float, mm — disk centres.
    radius_mm : (N,) float — disk radii.
    uv : (N, 2) float, px — where the disks were measured (for the local pixel scale).
    normals_field : (N, 3) or None — disk plane normals; default the field's +z.

    Subtract the result from measured centroids to get the image of the centre.
    """
    n = len(p_field)
    if normals_field is None:  # one plane for all: its axes once
        normal = DEFAULT_NORMAL_FIELD[None, :]
    else:
        normal = np.broadcast_to(normals_field, (n, 3))
    # any in-plane axes will do: the conic of a circle does not depend on them
    nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
    zero = np.zeros_like(nx)
    # normal x (1, 0, 0) or, for a normal near x, normal x (0, 1, 0); by hand: np.cross costs more here
    ex = np.where((np.abs(nx) < 0.9)[:, None], np.stack([zero, nz, -ny], 1), np.stack([-nz, zero, nx], 1))
    ex /= np.linalg.norm(ex, axis=1, keepdims=True)
    ey = np.stack([ny * ex[:, 2] - nz * ex[:, 1], nz * ex[:, 0] - nx * ex[:, 2], nx * ex[:, 1] - ny * ex[:, 0]], 1)
    # writable C arrays: one compiled kernel for every way the inputs come
    ex, ey = (np.require(np.broadcast_to(a, (n, 3)), np.float64, ['C', 'W']) for a in (ex, ey))
    T_camera_field = inv_T(T_field_camera)
    R = np.ascontiguousarray(T_camera_field[:3, :3])
    p_camera = np.ascontiguousarray(apply_T(T_camera_field, np.asarray(p_field, dtype=np.float64)))
    radius = np.require(np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), (n,)), np.float64, ['C', 'W'])
    offset_mm = eccentricity_kernel(ex, ey, p_camera, R, float(camera.c_mm), radius)
    J = camera.ideal_from_pixel_jacobian(uv)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    out = np.empty((n, 2))
    out[:, 0] = (J[:, 1, 1] * offset_mm[:, 0] - J[:, 0, 1] * offset_mm[:, 1]) / det
    out[:, 1] = (J[:, 0, 0] * offset_mm[:, 1] - J[:, 1, 0] * offset_mm[:, 0]) / det
    return out
