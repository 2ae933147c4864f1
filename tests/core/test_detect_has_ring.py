"""The detector marks the blobs it found ring pieces around: the coded targets, and only them."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from service.core.targets.detect import detect_blobs, measure_windows
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose


def _frame(view_angle_deg: float, seed: int):
    pose = reference_pose(view_angle_deg=view_angle_deg, roll_deg=15.0, azimuth_deg=30.0)
    return render_frame(reference_camera(), reference_field(), pose, RenderSettings(), np.random.default_rng(seed))


def test_coded_targets_and_only_they_have_ring_pieces_head_on_and_oblique():
    field = reference_field()
    for view_angle_deg, seed in ((90.0, 1), (60.0, 2)):
        frame = _frame(view_angle_deg, seed)
        blobs, _ = detect_blobs(frame.image)
        d, k = cKDTree(frame.uv_disk_centroid).query(blobs.uv)
        assert np.all(d < 0.5)
        coded = field.codes[field.indices_of([frame.ids[i] for i in k])] >= 0
        assert 20 <= coded.sum() <= 30
        assert np.array_equal(blobs.has_ring, coded)


def test_measure_windows_does_not_look_for_rings():
    frame = _frame(90.0, 3)
    blobs, found = measure_windows(frame.image, frame.uv_disk_centroid, 8)
    assert (found >= 0).sum() > 150
    assert blobs.has_ring.dtype == bool and not blobs.has_ring.any()
