"""The simulated cell behind the real protocols: its arm read by the real ur_rtde client through the
RTDE stand-in, its camera read by the Aravis driver from the fake GigE Vision camera."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import CameraSettings, StrobeSettings
from service.core.geometry.frames import pose_difference
from service.sim.cell import CellConfig, SimCell

pytest.importorskip("rtde_receive", reason="ur-rtde is installed by deploy/dev.sh (test extras)")


def test_ur_driver_reads_the_simulated_arm_at_125_hz_through_the_rtde_stand_in():
    from drivers.robot.ur import URRobot
    from drivers.standins.rtde_server import RtdeServer
    from drivers.standins.sim_cell import CellArm

    cell = SimCell(CellConfig(program="circle"))
    epoch = time.monotonic_ns()
    with RtdeServer(CellArm(cell, epoch), host="127.0.0.11"):
        robot = URRobot("127.0.0.11", frequency_hz=125.0)
        try:
            robot.open()
            time.sleep(1.5)
            # the last second's samples, looked at for up to 10 s: this VM has stalled for over a
            # second at times (a whole-suite run on 2026-12-06 saw none in one second, the link lost)
            counts = []
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                now = time.monotonic_ns()
                window = robot.samples_between(now - int(1e9), now)
                counts.append(len(window))
                if len(window) >= 0.8 * 125:
                    break
                time.sleep(0.5)
            assert len(window) >= 0.8 * 125, f"samples in the last second, every 0.5 s: {counts}"
            s = window[-1]
            # the controller's nominal belief at that instant (encoder noise ~0.01 mm, delivery < 5 ms)
            t_cell = (s.t_host_ns - epoch) * 1e-9
            errors = [
                pose_difference(s.T_base_flange, cell.robot_report(t_cell - dt, None)[0])[0]
                for dt in np.linspace(0.0, 0.005, 11)
            ]
            assert min(errors) < 0.2
        finally:
            robot.close()


def test_aravis_driver_sees_the_simulated_cell_through_the_fake_gige_camera():
    pytest.importorskip("gi", reason="PyGObject is linked into the venv by deploy/dev.sh")
    from drivers.camera.aravis import AravisCamera
    from drivers.standins.gv_camera import GvStandIn, cell_frame_source
    from service.pipeline.measure import FrameMeasurer

    cell = SimCell(CellConfig(program="hold"))
    with GvStandIn(cell_frame_source(cell), width=cell.camera.width, height=cell.camera.height):
        cam = AravisCamera("127.0.0.1", packet_size=8192)
        try:
            cam.open()
            cam.configure(CameraSettings(strobe=StrobeSettings(), frame_rate_hz=10.0))
            frame = cam.fetch(timeout_s=5.0)
        finally:
            cam.close()
    out = FrameMeasurer(cell.camera, cell.field).measure(frame.image)
    assert out.result.ok, out.result
    assert pose_difference(out.result.T_field_camera, cell.T_field_camera(0.0))[0] < 0.1
