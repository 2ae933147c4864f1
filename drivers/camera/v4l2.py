"""USB/V4L2 cameras through OpenCV's ``CAP_V4L2`` backend.

For set-up, demos and cheap cells: a UVC camera has no strobe output and no
device timestamps that map to exposure, so frames carry the arrival time only
and pairing falls back to "arrival minus exposure and latency". Colour frames
are converted to grey (the targets are measured in intensity). Exposure is set
where the device allows manual exposure (``CAP_PROP_AUTO_EXPOSURE`` = 1 is
"manual" in V4L2's menu, and ``CAP_PROP_EXPOSURE`` is in units of 100 µs).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from drivers.base import (
    CameraInfo,
    CameraSettings,
    DriverDisconnected,
    DriverInitError,
    DriverTimeout,
    FeatureUnsupported,
    Frame,
    TriggerMode,
)

_V4L2_MANUAL_EXPOSURE = 1  # the V4L2 exposure_auto menu: 1 manual, 3 aperture priority


class V4L2Camera:
    """A V4L2 device, e.g. ``/dev/video0`` (or its index ``0``)."""

    def __init__(self, device: str | int = "/dev/video0", width: int | None = None, height: int | None = None) -> None:
        self.device = device
        self._size = (width, height)
        self._cap: cv2.VideoCapture | None = None
        self._settings = CameraSettings()
        self._seq = 0
        self._info: CameraInfo | None = None

    @property
    def info(self) -> CameraInfo:
        if self._info is None:
            raise DriverDisconnected(f"V4L2 camera {self.device} is not open")
        return self._info

    def open(self) -> None:
        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise DriverInitError(f"no V4L2 camera could be opened at {self.device!r} (missing, busy or no permission)")
        w, h = self._size
        if w and h:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
        self._cap = cap
        self._info = CameraInfo(
            driver="v4l2",
            model=cap.getBackendName(),
            serial=str(self.device),
            width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            pixel_format="Mono8",
            features=("frame_rate",),
        )

    def configure(self, settings: CameraSettings) -> None:
        cap = self._require()
        if settings.strobe is not None and settings.strobe.enabled:
            raise FeatureUnsupported(
                "LineSource", f"the V4L2 camera {self.device} has no strobe output for a ring light"
            )
        if settings.trigger is not TriggerMode.FREE_RUN:
            raise FeatureUnsupported("TriggerMode", f"the V4L2 camera {self.device} runs free only (no trigger)")
        if settings.roi is not None or settings.pixel_format not in (None, "Mono8"):
            raise FeatureUnsupported("ROI", "V4L2 cameras deliver full 8-bit frames only")
        if settings.exposure_us is not None:
            manual = cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _V4L2_MANUAL_EXPOSURE)
            if not (manual and cap.set(cv2.CAP_PROP_EXPOSURE, settings.exposure_us / 100.0)):
                raise FeatureUnsupported("ExposureTime", f"the V4L2 camera {self.device} refuses manual exposure")
        if settings.gain_db is not None and not cap.set(cv2.CAP_PROP_GAIN, settings.gain_db):
            raise FeatureUnsupported("Gain", f"the V4L2 camera {self.device} has no gain control")
        if settings.frame_rate_hz is not None:
            cap.set(cv2.CAP_PROP_FPS, settings.frame_rate_hz)  # a request; UVC picks the nearest mode
        self._settings = settings

    def fetch(self, timeout_s: float) -> Frame:
        cap = self._require()
        t0 = time.monotonic()
        ok, image = cap.read()  # blocks for one frame period; OpenCV has no per-call timeout
        if not ok or image is None:
            if time.monotonic() - t0 > timeout_s:
                raise DriverTimeout(f"no frame from V4L2 camera {self.device} within {timeout_s:.3f} s")
            self.close()
            raise DriverDisconnected(f"V4L2 camera {self.device} stopped delivering frames")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        self._seq += 1
        exposure_us = self._settings.exposure_us or 0.0
        return Frame(np.ascontiguousarray(image), self._seq, time.monotonic_ns(), None, exposure_us)

    def try_fetch(self) -> Frame | None:
        return None  # OpenCV cannot poll without blocking; the worker calls fetch

    def trigger(self) -> None:
        raise FeatureUnsupported("TriggerSoftware", f"the V4L2 camera {self.device} has no software trigger")

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None

    def _require(self) -> cv2.VideoCapture:
        if self._cap is None:
            try:
                self.open()  # reconnect on the next call after a loss
            except DriverInitError as e:
                raise DriverDisconnected(str(e)) from e
        assert self._cap is not None
        return self._cap
