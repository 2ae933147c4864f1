"""A hand-eye sample taken through a camera's ROI keeps the whole sensor's pixels.

The frames of a window of the sensor are measured in the window's pixels (``tests/test_camera_roi.py``);
the session's samples feed the image-level hand-eye refinement and the camera's self-calibration,
which project with the whole sensor's camera, so a sample records its targets in the sensor's pixels.
"""

from __future__ import annotations

import numpy as np

from service.core.geometry.frames import apply_T, inv_T
from tests.api.conftest import live_settings, run_server
from tests.api.test_handeye_workflow import _capture

WINDOW = [200, 100, 1000, 800]  # x, y, width, height px


def test_a_sample_taken_through_a_camera_roi_keeps_the_sensors_pixels(tmp_path):
    settings = live_settings(
        tmp_path, sim__program="hold", sim__preload_handeye=False, cameras=[{"frame_rate_hz": 15.0, "roi": WINDOW}]
    )
    for server in run_server(settings):
        server.wait_for(lambda h: h["processing"]["ok"] >= 2, 180.0, "the cell running")
        with server.client() as c:
            assert c.post("/calibration/handeye/session", json={"n_poses": 6}).status_code == 200
            r = _capture(c)
            assert r.status_code == 200, r.text
            sample = c.get("/calibration/handeye/session/export").json()["samples"][0]
        cell = server.worker.cell.cell
        ids = [p["id"] for p in sample["points"]]
        uv = np.array([p["uv"] for p in sample["points"]])
        assert len(ids) >= 20
        T_camera_field = inv_T(np.array(sample["T_field_camera"]))
        projected = cell.camera.pixel_from_camera(apply_T(T_camera_field, cell.field.xyz[cell.field.indices_of(ids)]))
        assert np.abs(projected - uv).max() < 0.5  # in the window's pixels they would be (200, 100) px off
        assert uv[:, 0].min() >= WINDOW[0] and uv[:, 1].min() >= WINDOW[1]
