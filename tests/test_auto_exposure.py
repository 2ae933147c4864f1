"""The exposure control on the targets' peaks: the pure control law, the measurement's brightness,
and the running worker bringing an over- and an under-exposed simulated camera to a measurable frame."""

from __future__ import annotations

import time

import numpy as np
import pytest

from service.pipeline.brightness import Brightness
from service.pipeline.measure import FrameMeasurer
from service.runtime.exposure import SETTLE_FRAMES, ExposureControl, ExposureLimits
from service.runtime.worker import Worker
from service.settings import load_settings
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

FULL = 255.0


def _b(n: int, peak: float, n_saturated: int = 0, background: float = 12.0) -> Brightness:
    return Brightness(n, peak, background, n_saturated, FULL)


def _settled(control: ExposureControl) -> None:
    for _ in range(SETTLE_FRAMES):
        assert control.observe(control.exposure_us, _b(200, 120.0)) is None


def test_saturated_targets_halve_the_exposure_but_a_glint_or_two_do_not():
    control = ExposureControl(ExposureLimits(), 8000.0)
    assert control.observe(8000.0, _b(200, 200.0, n_saturated=2)) is None  # two glints among 200 disks
    step = control.observe(8000.0, _b(20, 250.0, n_saturated=180))
    assert step is not None and step.exposure_us == 4000.0 and "180 of 200 targets saturated" in step.why
    # frames still of the old exposure are not judged, nor the next SETTLE_FRAMES of the new one
    assert control.observe(8000.0, _b(0, 0.0, n_saturated=200)) is None
    _settled(control)
    step = control.observe(4000.0, _b(0, 0.0, n_saturated=200))
    assert step is not None and step.exposure_us == 2000.0


def test_dim_targets_are_brought_to_the_aim_in_one_step_within_the_factor_limit():
    limits = ExposureLimits(target_peak=0.75)
    control = ExposureControl(limits, 1000.0)
    level = 0.3  # peak above background, share of (full - background)
    step = control.observe(1000.0, _b(150, 12.0 + level * (FULL - 12.0)))
    assert step is not None and step.exposure_us == pytest.approx(1000.0 * 0.75 / level, rel=1e-3)
    control = ExposureControl(limits, 100.0)
    step = control.observe(100.0, _b(150, 14.0))  # barely visible: at most 4x a step
    assert step is not None and step.exposure_us == 400.0


def test_within_the_band_and_with_nothing_seen_the_exposure_stays():
    control = ExposureControl(ExposureLimits(), 2000.0)
    for peak in (130.0, 190.0, 235.0):  # 0.47 .. 0.92 of the span
        assert control.observe(2000.0, _b(200, peak)) is None
    assert control.observe(2000.0, _b(0, 0.0)) is None  # looking away from the field
    assert control.observe(2000.0, None) is None  # an unreadable image
    assert control.steps == 0


def test_the_limits_hold_and_a_step_at_a_limit_is_not_repeated():
    control = ExposureControl(ExposureLimits(min_us=500.0, max_us=3000.0), 1000.0)
    step = control.observe(1000.0, _b(0, 0.0, n_saturated=100))
    assert step is not None and step.exposure_us == 500.0
    _settled(control)
    assert control.observe(500.0, _b(0, 0.0, n_saturated=100)) is None  # already at the minimum
    control.restart(2500.0)
    assert control.observe(2500.0, _b(100, 20.0)).exposure_us == 3000.0


def test_the_measurement_reports_the_targets_brightness_following_the_exposure():
    camera, field = reference_camera(), reference_field()
    T = reference_pose(view_angle_deg=80.0, distance_mm=1000.0)
    measured = {}
    for scale in (0.5, 1.0, 2.5):
        frame = render_frame(camera, field, T, RenderSettings(exposure_scale=scale), np.random.default_rng(3))
        measured[scale] = FrameMeasurer(camera, field).measure(frame.image).brightness
    half, one, over = measured[0.5], measured[1.0], measured[2.5]
    assert half.n_measured > 100 and one.n_measured > 100 and half.n_saturated == 0 == one.n_saturated
    above = {k: b.peak_dn - b.background_dn for k, b in measured.items()}
    assert above[0.5] == pytest.approx(0.5 * above[1.0], rel=0.1)  # the disks' light scales with the exposure
    assert over.n_saturated > 0.5 * (over.n_measured + over.n_saturated)
    assert over.full_dn == FULL


def _worker(tmp_path, exposure_us: float, auto: bool) -> Worker:
    settings = load_settings(None, state_dir=str(tmp_path))
    cam = settings.cameras[0]
    cam = cam.model_copy(
        update={
            "frame_rate_hz": 20.0,
            "exposure_us": exposure_us,
            "auto_exposure": cam.auto_exposure.model_copy(update={"enabled": auto}),
        }
    )
    return Worker(settings.model_copy(update={"cameras": [cam]}))


@pytest.mark.parametrize("exposure_us", [8000.0, 250.0])
def test_the_running_cell_steers_an_over_or_under_exposed_camera_to_poses(tmp_path, exposure_us):
    worker = _worker(tmp_path, exposure_us, auto=True)
    got: list = []
    worker.subscribe(got.append)
    worker.start()
    try:
        deadline = time.monotonic() + 60.0  # a busy host: the kernels load, the renderer starts
        while time.monotonic() < deadline and not (len(got) >= 20 and all(m.ok for m in got[-20:])):
            time.sleep(0.1)
        health = worker.health()["cameras"]["cam0"]
    finally:
        worker.stop()
    tail = got[-20:]
    assert len(tail) == 20 and all(m.ok for m in tail), [m.reason for m in tail]
    assert health["auto_exposure"]["on"] and 1 <= health["auto_exposure"]["steps"] <= 4
    assert 1000.0 <= health["exposure_us"] <= 4000.0  # the reference scene's exposure is 2000 us
    # the simulated cell's optics: sharp (blur 0.6 px and the pixel's width), nothing said of the focus
    assert 0.4 < health["blur_px"] < 1.0 and health["focus"] is None, health


def test_without_the_control_an_over_exposed_camera_is_said_to_saturate(tmp_path):
    worker = _worker(tmp_path, 8000.0, auto=False)
    got: list = []
    worker.subscribe(got.append)
    worker.start()
    try:
        deadline = time.monotonic() + 60.0
        while len(got) < 20 and time.monotonic() < deadline:
            time.sleep(0.1)
        health = worker.health()["cameras"]["cam0"]
    finally:
        worker.stop()
    results = [m for m in got if m.t_exposure_host_ns is not None]
    assert health["auto_exposure"] == {"on": False, "steps": 0, "held": None} and health["exposure_us"] == 8000.0
    # four times the exposure clips most disks: measured all the same (they gave no pose before
    # clipped disks were measured), and said
    assert len(results) >= 10 and all(m.ok for m in results)
    assert health["targets_saturated"] >= 100 and "shorten the exposure" in health["saturation"]


def test_a_camera_refusing_the_exposure_step_has_the_control_switched_off(tmp_path, caplog):
    # a replay of the simulated cell rendered at 8000 us: its frames clip, the control asks for less,
    # and the replay (recorded images) refuses another exposure than its frames were taken with
    settings = load_settings(None, state_dir=str(tmp_path))
    cam = settings.cameras[0].model_copy(
        update={"driver": "replay", "options": {"source": "sim", "n_frames": 20}, "exposure_us": 8000.0}
    )
    worker = Worker(settings.model_copy(update={"cameras": [cam]}))
    got: list = []
    worker.subscribe(got.append)
    with caplog.at_level("WARNING"):
        worker.start()
        try:
            deadline = time.monotonic() + 60.0  # the replay renders its frames first (seconds on a busy host)
            while worker.health()["cameras"]["cam0"]["auto_exposure"]["on"] and time.monotonic() < deadline:
                time.sleep(0.1)
            n_before = len(got)
            time.sleep(1.0)
            health = worker.health()["cameras"]["cam0"]
        finally:
            worker.stop()
    assert health["auto_exposure"]["on"] is False and health["exposure_us"] == 8000.0
    assert health["state"] == "ok" and len(got) > n_before  # the camera itself runs on
    assert any("automatic exposure off" in r.getMessage() and "8000" in r.getMessage() for r in caplog.records)


def test_a_held_exposure_control_takes_no_step_until_released(tmp_path):
    # as while an accuracy test runs (service/runtime/accuracy_test.py holds it): every stop alike
    worker = _worker(tmp_path, 8000.0, auto=True)
    worker.hold_exposure("accuracy test 1 (table1) is running")
    got: list = []
    worker.subscribe(got.append)
    worker.start()
    try:
        deadline = time.monotonic() + 60.0
        while len(got) < 15 and time.monotonic() < deadline:
            time.sleep(0.1)
        held = worker.health()["cameras"]["cam0"]
        n_held = len(got)
        worker.hold_exposure("")
        deadline = time.monotonic() + 60.0
        # a step is counted when it is decided, and the camera takes it after: wait for both
        while time.monotonic() < deadline:
            released = worker.health()["cameras"]["cam0"]
            if released["auto_exposure"]["steps"] >= 1 and released["exposure_us"] < 8000.0:
                break
            time.sleep(0.1)
    finally:
        worker.stop()
    assert held["auto_exposure"] == {"on": True, "steps": 0, "held": "accuracy test 1 (table1) is running"}
    assert held["exposure_us"] == 8000.0
    assert n_held >= 15 and held["targets_saturated"] >= 100  # 8000 us clips most targets
    assert released["auto_exposure"]["held"] is None and released["auto_exposure"]["steps"] >= 1
    assert released["exposure_us"] < 8000.0


@pytest.mark.parametrize("n", [1, 2, 7, 230])
def test_the_frame_background_is_the_median_of_the_disks_backgrounds(n):
    from service.pipeline.brightness import _median

    x = np.random.default_rng(n).uniform(5.0, 40.0, n)
    assert _median(x) == pytest.approx(float(np.median(x)), abs=1e-12)
