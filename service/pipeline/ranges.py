"""The detector's area limits for the targets a field can show at a working range (:class:`MeasureSettings`'s
``range_mm``): pure geometry of the field's disks and the camera's focal length."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.core.geometry.camera_model import BrownFraser
from service.core.targets.detect import DetectSettings
from service.core.targets.field import Field

#: A target's image at the far end of the range is at least this share of its head-on disk (seen at up
#: to 75 deg, thresholded); at the near end at most this many times it (blur and the threshold's growth)
MIN_AREA_SHARE, MAX_AREA_FACTOR = 0.25, 1.5


def detect_settings_for_range(
    detect: DetectSettings, field: Field, camera: BrownFraser, range_mm: tuple[float, float]
) -> DetectSettings:
    """``detect`` with its area limits narrowed to the targets ``field`` can show at ``range_mm``
    (nearest, farthest; mm) through ``camera``: the smallest disk at the far end seen obliquely,
    the largest at the near end plus 2 px of blur (unknown diameters: 10 mm coded, 6 mm uncoded).
    Narrower limits reject stickers, labels and specks before they are measured, and keep the
    search for ring pieces short."""
    near, far = (float(v) for v in range_mm)
    if not 0 < near <= far:
        raise ValueError(f"range_mm must be (nearest, farthest) with 0 < nearest <= farthest, got {range_mm}")
    d = np.where(np.isfinite(field.diameters_mm), field.diameters_mm, np.where(field.is_coded, 10.0, 6.0))
    px = camera.c_mm / camera.mean_pixel_size_mm  # image radius px per mm of disk radius at 1 mm range
    r_small, r_big = 0.5 * float(d.min()) * px / far, 0.5 * float(d.max()) * px / near
    min_area = max(3, int(MIN_AREA_SHARE * np.pi * r_small**2))
    max_area = int(np.ceil(MAX_AREA_FACTOR * np.pi * (r_big + 2.0) ** 2))
    return replace(
        detect,
        min_area_px=max(detect.min_area_px, min_area),
        max_area_px=max(min(detect.max_area_px, max_area), min_area + 1),
    )
