"""The simulated camera smears its frames by the arm's motion during the exposure, about the
mid-exposure pose it stamps as the frame's truth."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.base import CameraSettings, StrobeSettings
from drivers.camera.sim import REFERENCE_EXPOSURE_US, SimCamera
from service.core.geometry.frames import apply_T, inv_T
from service.core.targets.detect import detect_blobs
from service.sim.cell import CellConfig, SimCell
from service.sim.render import image_motion_px
from service.sim.scene import reference_camera, reference_field, reference_pose

LIT = StrobeSettings(enabled=True, line="Line1", source="ExposureActive")
SPEED_MM_PER_S = 500.0  # along the camera's own x: 2 mm in a 4 ms exposure, ~3.6 px at 1 m
PERIOD_S = 0.4  # back and forth, +-50 mm about the reference pose


class _Sliding(SimCell):
    """The cell's camera sliding to and fro along its own x axis at a constant speed."""

    def T_field_camera(self, t_s):  # type: ignore[override]
        phase = (float(t_s) / PERIOD_S) % 1.0
        x_mm = SPEED_MM_PER_S * PERIOD_S * (min(phase, 1.0 - phase) - 0.25)
        T = reference_pose().copy()
        T[:3, 3] += T[:3, :3] @ np.array([x_mm, 0.0, 0.0])
        return T


def _clear_of_turns(t_s: float, half_exposure_s: float) -> bool:
    phase = (t_s / PERIOD_S) % 0.5  # turns at phases 0 and 1/2
    return min(phase, 0.5 - phase) * PERIOD_S > half_exposure_s + 1e-3


def test_image_motion_is_the_targets_median_motion():
    T0 = reference_pose()
    T1 = T0.copy()
    T1[:3, 3] += T0[:3, :3] @ np.array([1.0, 0.0, 0.0])  # 1 mm to the camera's right
    length_px, angle_deg = image_motion_px(reference_camera(), reference_field(), T0, T1)
    assert length_px == pytest.approx(12.0 / 0.0067 / 1000.0, rel=0.05)  # c / pixel / distance
    assert abs(abs(angle_deg) - 180.0) < 0.5  # the image moves the other way
    assert image_motion_px(reference_camera(), reference_field(), T0, T0) == (0.0, 0.0)
    behind = T0.copy()
    behind[:3, 3] += T0[:3, :3] @ np.array([0.0, 0.0, 3000.0])  # past the plate: nothing in view
    assert image_motion_px(reference_camera(), reference_field(), T0, behind) == (0.0, 0.0)


def _frame(exposure_us: float):
    cam = SimCamera(_Sliding(CellConfig(program="hold")), seed=3, render="inline")
    cam.open()
    try:
        gain_db = 20.0 * np.log10(REFERENCE_EXPOSURE_US / exposure_us)  # the same brightness
        cam.configure(CameraSettings(exposure_us=exposure_us, gain_db=gain_db, frame_rate_hz=10.0, strobe=LIT))
        for _ in range(5):  # a frame whose exposure does not hold a turn: one smear
            frame = cam.fetch(timeout_s=5.0)
            if _clear_of_turns(frame.meta["t_cell_s"], exposure_us * 0.5e-6):
                return frame
    finally:
        cam.close()
    raise AssertionError("five frames in a row held a turn of the slide")


def _measured(frame):
    """The frame's blobs, and the median distance of each from the targets' projection at the
    frame's mid-exposure pose (its truth), px."""
    blobs, _ = detect_blobs(frame.image)
    uv = reference_camera().pixel_from_camera(apply_T(inv_T(frame.meta["T_field_camera"]), reference_field().xyz))
    return blobs, float(np.median(np.linalg.norm(blobs.uv[:, None, :] - uv[None], axis=2).min(axis=1)))


def test_a_moving_arm_smears_the_frame_about_its_mid_exposure_pose():
    moving, still = _frame(4000.0), _frame(50.0)  # 2 mm and 0.025 mm of motion during the exposure
    (b1, d1), (b0, d0) = _measured(moving), _measured(still)
    assert len(b1) > 200 and len(b0) > 200
    assert d1 < 0.1 and d0 < 0.1  # measured where the mid-exposure pose puts them
    # the smear's variance L^2 / 12 adds to the disks' along the motion (u): (a^2 - b^2) / 4 grows by it
    smear_px = SPEED_MM_PER_S * 4000e-6 * 12.0 / 0.0067 / 1000.0  # c / pixel / distance: ~3.6 px

    def stretch(b):
        return float(np.median((b.ellipse[:, 2] ** 2 - b.ellipse[:, 3] ** 2) / 4.0))

    assert 0.7 < (stretch(b1) - stretch(b0)) / (smear_px**2 / 12) < 1.3
    assert np.mean(np.abs(np.cos(b1.ellipse[:, 4])) > 0.9) > 0.9  # the long axes along u, the motion
