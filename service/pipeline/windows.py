"""Targets measured in windows about their images predicted by a pose: ROI tracking's frames, and
the full frame's targets in view that no blob named (:class:`~service.pipeline.measure.FrameMeasurer`).

A window is a circle about the rounded prediction, as large as the disk's image, its blur (the
last frame's) and the prediction's allowance need (:meth:`PredictedWindows.half_size`). In an
oblique view a coded target's ring comes inside any window that holds its disk: it is masked about
the disk's predicted ellipse (grown to 1.5 radii), as the full frame masks a crowded window's
neighbours. A window that found no disk, because something bright beside the disk (printed text, a
hot pixel, a stray reflection) crossed its rim or joined its blob, is measured once more with all
but the disk's predicted region masked: in `posecell bench speed`'s frames with 0.05 % hot pixels
ROI tracking then named 97.7 % of the targets in view instead of 91.7 %. A disk so measured is
kept only close to its prediction, where its blur stays inside that region (MASKED_CENTRED_PX).

Pure: arrays in, arrays out; the measurement is :func:`~service.core.targets.detect.measure_windows`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.core._kernels import roi_kernel
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import inv_T
from service.core.results import SolveError
from service.core.targets.detect import Blobs, DetectSettings, measure_windows
from service.core.targets.field import Field
from service.core.targets.identify import plane_axes

Array = NDArray[np.float64]
Rows = NDArray[np.int64]

#: ROI windows about precise predictions allow this fraction of ``roi_prediction_error_px``
TIGHT_SLACK = 0.25
#: An ROI window's rim lies this many of the last frame's blur sigmas beyond the disk (3 px at least): a
#: disk blurred by 2.5 px reached the 3 px rim at the segmentation level and was refused as too big
BLUR_RIM_SIGMAS = 2.5
#: A disk measured again with all but its predicted region (1.5 radii) masked is kept this close to
#: its prediction, px: its blur then stays inside the region
MASKED_CENTRED_PX = 1.0


class PredictedWindows:
    """The field's disks as windows measure them: their radii, in-plane axes and which are coded."""

    def __init__(self, camera: BrownFraser, field: Field) -> None:
        self.field = field
        self.radius_mm = (
            np.where(np.isfinite(field.diameters_mm), field.diameters_mm, np.where(field.is_coded, 10.0, 6.0)) / 2.0
        )
        self._radius_c = self.radius_mm * camera.c_mm  # per field row, for the compiled window sizes
        self._pixel_mm = float(camera.mean_pixel_size_mm)
        self._f_px = float(camera.c_mm / camera.mean_pixel_size_mm)  # the masks' pinhole
        self._coded = np.ascontiguousarray(field.codes >= 0)
        self._every = np.ones(len(field), dtype=bool)
        # each target's in-plane axes (field rows, 3), for the masks: its own plane's, or the field's x, y
        n = len(field)
        self._plane_axes = (
            plane_axes(field.normals)
            if field.has_normals and field.normals is not None
            else (np.tile([1.0, 0.0, 0.0], (n, 1)), np.tile([0.0, 1.0, 0.0], (n, 1)))
        )

    def half_size(self, rows: Rows, depth_mm: Array, allowance_px: float, blur_px: float) -> Rows:
        """Half window (px) per target of ``rows`` at ``depth_mm``: the disk's image radius, its blur's
        rim (BLUR_RIM_SIGMAS of ``blur_px``, 3 px at least) and the prediction's ``allowance_px``."""
        # compiled: as array expressions they were 2 % of an ROI frame
        rim_px = max(3.0, BLUR_RIM_SIGMAS * blur_px)
        return roi_kernel.window_half_size_kernel(self._radius_c, rows, depth_mm, self._pixel_mm, allowance_px, rim_px)

    def measure(
        self,
        image: NDArray[np.generic],
        T_pred: Array,
        rows: Rows,
        uv_pred: Array,
        half: Rows,
        detect: DetectSettings,
        ring_inner: float,
    ) -> tuple[Blobs, NDArray[np.intp]] | None:
        """The disks measured in the windows of half size ``half`` about the predictions ``uv_pred``
        (N, 2) px of the targets ``rows`` by the pose ``T_pred`` (T_field_camera), and per window
        the index of its disk among them or -1 (:func:`~service.core.targets.detect.measure_windows`);
        coded targets' rings (from ``ring_inner`` disk radii) masked. None when the windows cannot
        be measured."""
        try:
            own = self._own_regions(T_pred, rows, uv_pred, half, self._coded, ring_inner)
            return measure_windows(image, uv_pred, half, detect, own)
        except (ValueError, SolveError):
            return None

    def measure_missed(
        self,
        image: NDArray[np.generic],
        T_pred: Array,
        rows: Rows,
        uv_pred: Array,
        half: Rows,
        detect: DetectSettings,
        blobs: Blobs,
        found: NDArray[np.intp],
    ) -> tuple[Blobs, NDArray[np.intp]]:
        """:meth:`measure`'s ``blobs`` and ``found`` with the windows that found no disk measured
        again, all but each disk's predicted region masked; not those the image's border cuts (the
        frame's edge is no rim: such a disk stays refused)."""
        height, width = np.shape(image)[:2]
        missed = (found < 0).nonzero()[0]
        h, (u, v) = half[missed], np.rint(uv_pred[missed]).T
        missed = missed[(np.minimum(u, v) >= h) & (u < width - h) & (v < height - h)]
        if not missed.size:
            return blobs, found
        own = self._own_regions(T_pred, rows[missed], uv_pred[missed], half[missed], self._every, 0.0)
        try:
            again, found_again = measure_windows(image, uv_pred[missed], half[missed], detect, own)
        except (ValueError, SolveError):
            return blobs, found
        ok = found_again >= 0
        ok[ok] = np.hypot(*(again.uv[found_again[ok]] - uv_pred[missed[ok]]).T) <= MASKED_CENTRED_PX
        found = found.copy()
        found[missed[ok]] = found_again[ok] + len(blobs)
        return blobs.join(again), found

    def _own_regions(
        self,
        T_pred: Array,
        rows: Rows,
        uv_pred: Array,
        half: Rows,
        which: NDArray[np.bool_],
        ring_inner: float,
    ) -> Array:
        """The windows' own regions (n, 5) about the disks of ``rows`` predicted by ``T_pred``
        (T_field_camera) that ``which`` (per field row) names and whose ring, from ``ring_inner``
        disk radii (0: none, always), reaches the window
        (:func:`~service.core._kernels.roi_kernel.ring_masks_kernel`); NaN rows for the others."""
        T_cf = inv_T(T_pred)
        pose = (np.ascontiguousarray(T_cf[:3, :3]), np.ascontiguousarray(T_cf[:3, 3]))
        axes = self._plane_axes
        args = (self.field.xyz, *axes, self.radius_mm, which, rows, uv_pred, self._f_px, half, ring_inner)
        return roi_kernel.ring_masks_kernel(*pose, *args)
