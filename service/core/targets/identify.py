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
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from service.core._kernels import kernel_array, kernel_vector
from service.core._kernels.geometry_kernels import (
    eccentricity_kernel,
    match_kernel,
    project_kernel,
    whitened_ideal_kernel,
)
from service.core.geometry.camera_model import BrownFraser
from service.core.targets.field import Field

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_NORMAL_FIELD = np.array([0.0, 0.0, 1.0])
MAX_VIEW_DEG = 85.0  # a disk seen further from its normal is a sliver: not predicted (fields with normals)
# in-plane axes (1, 3) of the default plane, as eccentricity_px's general rule gives them for the normal +z
_DEFAULT_AXES = (np.array([[0.0, 1.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]))


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
    codes_read = np.asarray(codes_read, dtype=np.int64)
    field_rows = np.flatnonzero(field.codes >= 0)
    top = int(max(codes_read.max(initial=0), field.codes.max(initial=0))) + 1
    row_of_code = np.full(top, -1, dtype=np.int64)
    row_of_code[field.codes[field_rows]] = field_rows
    times_read = np.bincount(codes_read[codes_read >= 0], minlength=top)
    blobs = np.flatnonzero(codes_read >= 0)
    code = codes_read[blobs]
    keep = (times_read[code] == 1) & (row_of_code[code] >= 0)
    return Matches(row_of_code[code[keep]], blobs[keep].astype(np.int64))


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
    free = np.ones(len(blob_uv), bool) if taken is None else ~np.asarray(taken, dtype=bool)
    cand = match_kernel(
        kernel_array(uv_predicted).reshape(-1, 2),
        kernel_array(blob_uv).reshape(-1, 2),
        free,
        float(tolerance_px),
    )
    ok = cand >= 0
    return Matches(rows[ok], cand[ok])


@overload
def project_field(
    camera: BrownFraser,
    field: Field,
    T_field_camera: Array,
    margin_px: float = ...,
    *,
    with_depth: Literal[False] = ...,
) -> tuple[IntArray, Array]: ...


@overload
def project_field(
    camera: BrownFraser, field: Field, T_field_camera: Array, margin_px: float = ..., *, with_depth: Literal[True]
) -> tuple[IntArray, Array, Array]: ...


def project_field(
    camera: BrownFraser, field: Field, T_field_camera: Array, margin_px: float = 0.0, *, with_depth: bool = False
) -> tuple[IntArray, Array] | tuple[IntArray, Array, Array]:
    """Rows and pixel positions (N, 2) of field targets in front of the camera and inside the image,
    and, in a field with normals, facing it: a target seen from behind, or at more than
    :data:`MAX_VIEW_DEG` from its normal, is not predicted (it cannot be measured, and predicted it
    could take a visible target's match).

    With ``with_depth`` also their depth (N,) mm along the optical axis. One compiled pass (the
    prediction of every target runs once or twice per ROI frame).
    """
    T = np.asarray(T_field_camera, dtype=np.float64)
    uv, depth, inside = project_kernel(
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        field.xyz,
        *camera.projection_args,
        float(margin_px),
    )
    rows = inside.nonzero()[0]
    if field.has_normals and field.normals is not None:
        to_camera = T[:3, 3] - field.xyz[rows]
        facing = np.einsum("ij,ij->i", field.normals[rows], to_camera)
        rows = rows[facing > np.cos(np.radians(MAX_VIEW_DEG)) * np.linalg.norm(to_camera, axis=1)]
    if with_depth:
        return rows, uv[rows], depth[rows]
    return rows, uv[rows]


def plane_axes(normals_field: Array) -> tuple[Array, Array]:
    """Two in-plane unit axes (each (N, 3), field frame) of the plane of each unit normal (N, 3),
    right-handed with it; any pair will do for a circle's image, whose conic does not depend on them."""
    nx, ny, nz = normals_field[:, 0], normals_field[:, 1], normals_field[:, 2]
    zero = np.zeros_like(nx)
    # normal x (1, 0, 0) or, for a normal near x, normal x (0, 1, 0); by hand: np.cross costs more here
    ex = np.where((np.abs(nx) < 0.9)[:, None], np.stack([zero, nz, -ny], 1), np.stack([-nz, zero, nx], 1))
    ex /= np.linalg.norm(ex, axis=1, keepdims=True)
    ey = np.stack([ny * ex[:, 2] - nz * ex[:, 1], nz * ex[:, 0] - nx * ex[:, 2], nx * ex[:, 1] - ny * ex[:, 0]], 1)
    # writable C arrays: one compiled kernel for every way the inputs come
    return kernel_array(ex), kernel_array(ey)


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
    ex, ey = _DEFAULT_AXES if normals_field is None else plane_axes(np.broadcast_to(normals_field, (n, 3)))
    T = np.asarray(T_field_camera, dtype=np.float64)
    R_camera_field = np.ascontiguousarray(T[:3, :3].T)
    t_camera_field = -R_camera_field @ T[:3, 3]
    radius = kernel_vector(radius_mm, n)
    # the pixels' whitening (inverse ideal-from-pixel Jacobian) in one compiled pass, as the resection gets it
    _, W = whitened_ideal_kernel(kernel_array(uv), *camera.whitening_args)
    return eccentricity_kernel(
        ex,
        ey,
        kernel_array(p_field),
        R_camera_field,
        t_camera_field,
        float(camera.c_mm),
        radius,
        W,
    )
