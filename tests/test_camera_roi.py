"""A camera that delivers a window of its sensor (its ``roi``): the frames are measured with the
camera of that window.

The calibration is the whole sensor's. A window's pixel (0, 0) is the sensor's (x, y), so its
principal point, given from the image's centre, moves (``BrownFraser.cropped``). Before, the
service measured such frames with the whole sensor's camera: a pose off by the window's offset, or
a failure that blamed the targets. A frame of another size than the camera model is now refused
with a sentence that says so.
"""

from __future__ import annotations

import json

import numpy as np
from websockets.sync.client import connect

from service.core.geometry.frames import pose_difference
from service.core.results import Failure, PoseResult, Reason
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose
from tests.api.conftest import live_settings, run_server

WINDOW = (200, 100, 1000, 800)  # x, y, width, height px


def test_a_window_of_the_frame_is_measured_with_the_camera_of_that_window():
    frame = render_frame(
        reference_camera(),
        reference_field(),
        reference_pose(),
        RenderSettings(exposure_scale=0.8),
        np.random.default_rng(2),
    )
    x, y, w, h = WINDOW
    window = np.ascontiguousarray(frame.image[y : y + h, x : x + w])
    settings = MeasureSettings(roi=False)
    whole = FrameMeasurer(reference_camera(), reference_field(), settings).measure(frame.image).result
    part = FrameMeasurer(reference_camera().cropped(*WINDOW), reference_field(), settings).measure(window).result
    assert isinstance(whole, PoseResult) and isinstance(part, PoseResult), part
    assert len(part.targets) < len(whole.targets)  # the window holds some of them
    assert pose_difference(part.T_field_camera, frame.T_field_camera)[0] < 0.1
    # with the whole sensor's camera: refused, saying why (not a pose off by the window's offset)
    refused = FrameMeasurer(reference_camera(), reference_field(), settings).measure(window).result
    assert isinstance(refused, Failure) and refused.reason == Reason.bad_image
    assert "1000 x 800 px but the camera model is for 1300 x 1030 px" in refused.message


def test_the_service_measures_a_camera_roi_with_the_camera_of_its_window(tmp_path):
    settings = live_settings(tmp_path, cameras=[{"frame_rate_hz": 15.0, "roi": list(WINDOW)}])
    for server in run_server(settings):
        server.wait_for(lambda h: h["processing"]["ok"] >= 5, 120.0, "poses from the camera's window")
        with connect(f"{server.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
            for _ in range(5):
                msg = json.loads(ws.recv(timeout=10))
                assert msg["ok"], msg
                # the simulation's truth: the pose is right, not off by the window's offset
                d_mm = pose_difference(np.array(msg["T_field_camera"]), np.array(msg["truth"]["T_field_camera"]))[0]
                assert d_mm < 0.5, d_mm
