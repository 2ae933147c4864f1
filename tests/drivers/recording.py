"""A small recording, written as ``service/runtime/recorder.py`` writes one, for the replay drivers' tests."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np

from service.core.geometry.so3 import T_from_rotvec, rotvec_from_R

FRAME_PERIOD_NS = 10_000_000
ROBOT_PERIOD_NS = 2_000_000
T0_NS = 5_000_000_000_000  # the recording host's monotonic clock, ns
EXPOSURE_LEAD_NS = 4_000_000  # a frame arrives 4 ms after its exposure (on the robot samples' 2 ms grid)


def robot_pose(t_ns: int) -> np.ndarray:
    """The recorded flange pose at recorded time ``t_ns``: moving 0.1 mm and 0.1 mrad a sample."""
    m = (t_ns - T0_NS) / ROBOT_PERIOD_NS
    return T_from_rotvec([0.1, -0.2, 0.3 + 1e-4 * m], [400.0 + 0.1 * m, -100.0, 600.0])


def make_recording(folder: Path, n_frames: int = 5) -> Path:
    """A recording of ``n_frames`` 64 x 48 frames 10 ms apart (each frame's pixels hold its index) and
    500 Hz robot samples from 20 ms before the first to 20 ms after the last."""
    cam = folder / "cam0"
    cam.mkdir(parents=True)
    with (cam / "timestamps.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(("file", "t_ns", "seq", "t_device_ns", "t_exposure_host_ns", "exposure_us"))
        for k in range(n_frames):
            name = f"frame-{k + 1:06d}.pgm"
            cv2.imwrite(str(cam / name), np.full((48, 64), 10 + k, dtype=np.uint8))
            # arrivals 10 ms apart, exposed 4 ms before; a device clock 1 s behind the host's
            t = T0_NS + k * FRAME_PERIOD_NS
            w.writerow((name, t, k + 1, t - EXPOSURE_LEAD_NS - 1_000_000_000, t - EXPOSURE_LEAD_NS, "1500"))
    with (folder / "robot.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(("t_host_ns", "t_robot_s", "x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")
                   + tuple(f"q{i}_rad" for i in range(1, 7)))  # fmt: skip
        t_end = T0_NS + (n_frames - 1) * FRAME_PERIOD_NS + 20_000_000
        for t in range(T0_NS - 20_000_000, t_end + 1, ROBOT_PERIOD_NS):
            T = robot_pose(t)
            w.writerow((t, f"{t * 1e-9 - 4000:.6f}", *T[:3, 3], *rotvec_from_R(T[:3, :3]), *[1e-6 * (t - T0_NS)] * 6))
    (folder / "recording.json").write_text(json.dumps({"id": folder.name, "state": "complete"}))
    return folder
