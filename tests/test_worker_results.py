"""The worker's newest results: marked stale by age, outages as results (no devices started)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import Frame
from service.runtime.worker import STALE_MIN_S, STALE_PERIODS, Worker
from service.settings import load_settings


@pytest.fixture
def worker(tmp_path):
    settings = load_settings(None, state_dir=str(tmp_path))
    settings.cameras[0].frame_rate_hz = 20.0
    return Worker(settings)


def _frame(age_s: float) -> Frame:
    t = time.monotonic_ns() - int(age_s * 1e9)
    return Frame(image=np.zeros((4, 4), np.uint8), seq=1, t_device_ns=0, t_host_ns=t, exposure_us=1000.0)


def _result(frame: Frame) -> dict:
    return {"ok": True, "camera": "cam0", "t_exposure_host_ns": frame.t_host_ns, "T_field_camera": np.eye(4).tolist()}


def test_a_result_older_than_a_few_frame_periods_is_served_as_stale_with_its_pose(worker):
    assert worker.stale_after_s("cam0") == max(STALE_MIN_S, STALE_PERIODS / 20.0)
    fresh = _frame(0.01)
    worker._publish("cam0", _result(fresh), fresh)
    r = worker.current()
    assert r["ok"] is True and r["stale"] is False and 0.0 <= r["age_s"] < 0.2
    old = _frame(2.0)
    worker._publish("cam0", {**_result(old), "ok": False, "reason": "too_few_targets"}, old)
    r = worker.current("cam0")
    assert r["ok"] is False and r["stale"] is True and r["reason"] == "stale" and r["age_s"] >= 2.0
    assert r["measured_reason"] == "too_few_targets" and r["T_field_camera"] is not None
    assert worker.latest["cam0"]["reason"] == "too_few_targets"  # the stored result is not changed


def test_an_outage_result_is_current_whatever_its_age(worker):
    old = _frame(5.0)
    worker._publish("cam0", _result(old), old)
    worker._publish("cam0", worker._failure("cam0", "camera_disconnected", "unplugged"), None)
    r = worker.current("cam0")
    assert r["stale"] is False and r["reason"] == "camera_disconnected" and r["age_s"] < 0.5
    assert worker.counters["results"] == 1  # an outage is not a measured frame
