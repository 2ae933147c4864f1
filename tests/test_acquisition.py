"""The acquisition thread survives a driver bug and reports a silent camera instead of calling it ok."""

from __future__ import annotations

import threading
import time

import numpy as np

from drivers.base import CameraInfo, CameraSettings, DriverTimeout, Frame
from service.runtime.acquisition import CameraChannel


class FlakyCamera:
    """A driver whose fetch fails with a programming error once, then delivers, then goes silent."""

    info = CameraInfo("flaky", "flaky", "0", 8, 8, "Mono8")

    def __init__(self) -> None:
        self.calls = 0
        self.silent = False

    def open(self) -> None: ...
    def configure(self, settings: CameraSettings) -> None: ...
    def trigger(self) -> None: ...
    def close(self) -> None: ...
    def try_fetch(self) -> Frame | None:
        return None

    def fetch(self, timeout_s: float) -> Frame:
        self.calls += 1
        if self.calls == 2:
            raise ZeroDivisionError("a bug in the driver")
        time.sleep(0.01)
        if self.silent:
            time.sleep(timeout_s)
            raise DriverTimeout("nothing")
        return Frame(np.zeros((8, 8), np.uint8), self.calls, time.monotonic_ns(), None, 100.0)


def test_channel_survives_a_driver_bug_and_flags_a_silent_camera():
    events = []
    cam = FlakyCamera()
    ch = CameraChannel(
        "c", cam, CameraSettings(frame_rate_hz=100.0), threading.Condition(), lambda *e: events.append(e)
    )
    ch.start()
    try:
        deadline = time.monotonic() + 5
        while ch.counters.frames < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert ch.counters.frames >= 5  # it went on after the exception
        assert any("driver error" in e[2] and "ZeroDivisionError" in e[2] for e in events)
        assert ch.snapshot()["state"] == "ok"
        cam.silent = True
        # stalled after 1 s of silence (service.acquisition.STALL_MIN_S): poll for it, within the 3.3 s
        deadline = time.monotonic() + 3.3
        while (snap := ch.snapshot())["state"] != "stalled" and time.monotonic() < deadline:
            time.sleep(0.02)
        assert snap["state"] == "stalled" and "no frame for" in snap["error"]
    finally:
        ch.stop()
