"""A recording's frames and robot samples replayed in step: each frame meets the samples it was recorded with."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import CameraSettings, DriverInitError
from drivers.registry import make_camera, make_robot
from drivers.replay_clock import forget
from tests.drivers.recording import EXPOSURE_LEAD_NS, FRAME_PERIOD_NS, T0_NS, make_recording, robot_pose


@pytest.fixture
def recording(tmp_path):
    folder = make_recording(tmp_path / "20261205-101500")
    yield folder
    forget(folder)


def test_frames_and_robot_samples_play_on_one_clock_pass_after_pass(recording):
    robot = make_robot("replay", source=str(recording))
    robot.open()  # the robot first: the order does not matter, the clock is the recording's
    cam = make_camera("replay", source=str(recording / "cam0"), timing="recorded", n_buffers=100)
    cam.open()
    cam.configure(CameraSettings(frame_rate_hz=1.0))  # not used: recorded time sets the pace
    try:
        frames = [cam.fetch(timeout_s=2.0) for _ in range(12)]  # two passes and a bit
        time.sleep(0.05)  # the samples just after the last frame
        span_ns = 5 * FRAME_PERIOD_NS
        for j, f in enumerate(frames):
            k, n_pass = j % 5, j // 5
            assert int(f.image[0, 0]) == 10 + k  # the recorded frame, in order
            # the frames arrive with their recorded spacing on this host's clock, their stamps as recorded
            if j:
                assert f.t_host_ns - frames[j - 1].t_host_ns == (
                    FRAME_PERIOD_NS if k else span_ns - 4 * FRAME_PERIOD_NS
                )
            assert f.t_exposure_host_ns == f.t_host_ns - EXPOSURE_LEAD_NS
            assert f.t_device_ns == T0_NS + k * FRAME_PERIOD_NS - EXPOSURE_LEAD_NS - 1_000_000_000 + n_pass * span_ns
            # the robot sample at the frame's exposure is the one recorded with it
            (sample,) = robot.samples_between(f.t_exposure_host_ns, f.t_exposure_host_ns)
            t_rec = T0_NS + k * FRAME_PERIOD_NS - EXPOSURE_LEAD_NS
            np.testing.assert_allclose(sample.T_base_flange, robot_pose(t_rec), atol=1e-6)
            assert sample.t_robot_s == pytest.approx(t_rec * 1e-9 - 4000 + n_pass * 0.05)
        # between passes the samples run on in order, none twice
        t = np.array([s.t_host_ns for s in robot.samples_between(frames[0].t_host_ns, frames[-1].t_host_ns)])
        assert np.all(np.diff(t) > 0) and np.all(np.diff(t) <= 2_000_000)
        assert robot.info.driver == "replay" and robot.info.rate_hz == pytest.approx(500.0)
    finally:
        cam.close()
        robot.close()


def test_recorded_timing_needs_a_recording(tmp_path, recording):
    with pytest.raises(ValueError, match="timing"):
        make_camera("replay", source="sim", timing="recorded")
    with pytest.raises(ValueError, match="timing"):
        make_camera("replay", source=str(recording / "cam0"), timing="live")
    (recording / "recording.json").unlink()
    with pytest.raises(DriverInitError, match="not in a recording"):
        make_robot("replay", source=str(recording)).open()
    with pytest.raises(DriverInitError, match="not in a recording"):
        make_camera("replay", source=str(recording / "cam0"), timing="recorded").open()
