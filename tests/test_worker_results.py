"""The worker's newest results: marked stale by age, outages as results (no devices started)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import Frame
from service.core.measurement import Measurement
from service.core.results import Failure, PoseResult, Reason
from service.runtime.worker import STALE_MIN_S, STALE_PERIODS, Worker
from service.settings import load_settings


@pytest.fixture
def worker(tmp_path):
    settings = load_settings(None, state_dir=str(tmp_path))
    camera = settings.cameras[0].model_copy(update={"frame_rate_hz": 20.0})
    return Worker(settings.model_copy(update={"cameras": [camera]}))


def _frame(age_s: float) -> Frame:
    t = time.monotonic_ns() - int(age_s * 1e9)
    return Frame(image=np.zeros((4, 4), np.uint8), seq=1, t_device_ns=0, t_host_ns=t, exposure_us=1000.0)


def _pose() -> PoseResult:
    return PoseResult(np.eye(4), np.full(3, 0.01), np.full(3, 0.001), 0.05, 0.05, ())


def _result(frame: Frame, result: PoseResult | Failure | None = None) -> Measurement:
    return Measurement("cam0", result or _pose(), time.time_ns(), frame.t_host_ns, seq=frame.seq)


def test_a_result_older_than_a_few_frame_periods_is_served_as_stale_with_its_pose(worker):
    assert worker.stale_after_s("cam0") == max(STALE_MIN_S, STALE_PERIODS / 20.0)
    fresh = _frame(0.01)
    worker._publish("cam0", _result(fresh), fresh)
    r = worker.current().to_dict()
    assert r["ok"] is True and r["stale"] is False and 0.0 <= r["age_s"] < 0.2
    old = _frame(2.0)
    worker._publish("cam0", _result(old, Failure(Reason.too_few_targets, "3 targets")), old)
    r = worker.current("cam0").to_dict()
    assert r["ok"] is False and r["stale"] is True and r["reason"] == "stale" and r["age_s"] >= 2.0
    assert r["measured_reason"] == "too_few_targets"
    assert worker.latest["cam0"].reason == "too_few_targets"  # the stored result is not changed
    worker._publish("cam0", _result(old), old)
    r = worker.current("cam0").to_dict()
    assert r["reason"] == "stale" and r["T_field_camera"] is not None  # the values are kept for diagnosis


def test_an_outage_result_is_current_whatever_its_age(worker):
    old = _frame(5.0)
    worker._publish("cam0", _result(old), old)
    worker._publish("cam0", worker._failure("cam0", Reason.camera_disconnected, "unplugged"), None)
    r = worker.current("cam0").to_dict()
    assert r["stale"] is False and r["reason"] == "camera_disconnected" and r["age_s"] < 0.5
    assert worker.counters["results"] == 1  # an outage is not a measured frame
