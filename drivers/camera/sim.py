"""The simulated camera: frames rendered from the simulated cell, on a real clock.

It behaves like a GigE Vision camera in the ways the worker depends on:

- free run on a fixed frame grid; a consumer that falls behind gets the next
  frame to be exposed, and the skipped ones show as gaps in ``seq``;
- a software trigger starts one exposure ``trigger_delay_us`` later;
- the device clock is its own (an offset and a drift against the host), and a
  frame reaches the host ``latency_s`` (+ exponential jitter) after its exposure
  ends, so time alignment has real work to do;
- exposure, gain, bit depth and ROI change the rendered image; the ring light is
  lit only while the strobe output is configured to fire during the exposure;
- ``unplug()`` / ``plug()`` inject a lost link (``DriverDisconnected``); ``stall()`` keeps the
  link but delivers no frame (a stuck stream: only timeouts); ``garble()`` delivers frames of
  noise (a broken sensor or a wrong pixel format); ``plug()`` ends every fault.

What it does not model: motion blur within the exposure, rolling shutter,
packet loss, buffer underruns, and how long rendering takes (a frame is
handed over no earlier than its scheduled arrival and stamped with it, even
when rendering made it later).
The ground truth of every frame is in ``Frame.meta``: ``T_field_camera`` (mm)
and ``t_exposure_true_host_ns``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace

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
from service.sim.cell import CellConfig, SimCell
from service.sim.render import RenderSettings, render_frame

_LIT_SOURCES = ("ExposureActive", "Timer0Active", "Timer1Active")
_BIT_DEPTH = {"Mono8": 8, "Mono12": 12, "Mono16": 16}
REFERENCE_EXPOSURE_US = 2000.0  # the exposure at which RenderSettings.target_dn is reached


class SimCamera:
    """A camera in the simulated cell.

    Parameters
    ----------
    cell : the shared simulated cell (the robot driver must see the same one); built from
        ``cell_config`` (CellConfig fields) when None
    epoch_ns : host monotonic time of the cell's t = 0; shared with the robot driver
    latency_s : transfer delay after the exposure ends (readout + network)
    jitter_s : mean of the extra exponential delay
    clock_offset_s, clock_drift_ppm : the device clock against the host clock
    """

    def __init__(
        self,
        cell: SimCell | None = None,
        cell_config: dict[str, object] | None = None,
        epoch_ns: int | None = None,
        latency_s: float = 0.004,
        jitter_s: float = 0.0005,
        trigger_delay_us: float = 50.0,
        clock_offset_s: float = 1234.5,
        clock_drift_ppm: float = 30.0,
        seed: int = 1,
        serial: str = "SIM-0001",
        T_master_camera: list[list[float]] | None = None,
    ) -> None:
        self._cell = cell if cell is not None else SimCell(CellConfig(**(cell_config or {})))
        self.epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)
        self.latency_ns = int(latency_s * 1e9)
        self.jitter_ns = float(jitter_s * 1e9)
        self.trigger_delay_ns = int(trigger_delay_us * 1e3)
        self.clock_offset_ns = float(clock_offset_s * 1e9)
        self.clock_rate = 1.0 + clock_drift_ppm * 1e-6
        self._rng = np.random.default_rng(seed)
        self._serial = serial
        # a second camera of a rig: its pose relative to the cell's camera (the master), mm
        self.T_master_camera = None if T_master_camera is None else np.asarray(T_master_camera, dtype=np.float64)
        self._settings = CameraSettings(strobe=None)
        self._open = False
        self._plugged = True
        self._stalled = False
        self._garbled = False
        self._next_seq = 0
        self._last_exposure_start_ns: int | None = None
        self._triggers: list[int] = []
        self._render_s = 0.03  # running estimate of the time one frame takes to render
        self._pending_start_ns: int | None = None
        self._lock = threading.Lock()  # trigger() may come from another thread than fetch()

    # --- CameraDriver -------------------------------------------------------------------------

    @property
    def info(self) -> CameraInfo:
        cam = self._cell.camera
        w, h = (self._settings.roi[2], self._settings.roi[3]) if self._settings.roi else (cam.width, cam.height)
        return CameraInfo(
            driver="sim",
            model="posecell simulated camera",
            serial=self._serial,
            width=w,
            height=h,
            pixel_format=self._settings.pixel_format or "Mono8",
            features=("strobe", "gain", "timer", "frame_rate", "trigger", "roi"),
        )

    @property
    def cell(self) -> SimCell:
        return self._cell

    def open(self) -> None:
        if not self._plugged:
            raise DriverInitError(f"simulated camera {self._serial} is unplugged")
        self._open = True

    def configure(self, settings: CameraSettings) -> None:
        self._require_link()
        if settings.pixel_format is not None and settings.pixel_format not in _BIT_DEPTH:
            raise FeatureUnsupported("PixelFormat", f"the simulated camera has no pixel format {settings.pixel_format}")
        if settings.roi is not None:
            x, y, w, h = settings.roi
            cam = self._cell.camera
            if x < 0 or y < 0 or w <= 0 or h <= 0 or x + w > cam.width or y + h > cam.height:
                raise FeatureUnsupported("ROI", f"ROI {settings.roi} is outside the {cam.width} x {cam.height} sensor")
        if settings.frame_rate_hz is not None and not 0 < settings.frame_rate_hz <= 200:
            raise FeatureUnsupported(
                "AcquisitionFrameRate", f"frame rate {settings.frame_rate_hz} Hz is outside 0..200"
            )
        strobe = settings.strobe
        if strobe is not None and strobe.enabled and strobe.source not in (*_LIT_SOURCES, "Off", "UserOutput0"):
            raise FeatureUnsupported("LineSource", f"the simulated camera has no line source {strobe.source}")
        with self._lock:
            self._settings = settings
            self._triggers.clear()
            self._pending_start_ns = None

    def fetch(self, timeout_s: float) -> Frame:
        self._require_link()
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        if self._stalled:
            time.sleep(timeout_s)
            raise DriverTimeout(f"no frame from simulated camera {self._serial} within {timeout_s:.3f} s (stalled)")
        t_start_ns = self._next_exposure_start(deadline)
        if t_start_ns is None:
            raise DriverTimeout(f"no frame from simulated camera {self._serial} within {timeout_s:.3f} s")
        exposure_ns = int(self._exposure_us() * 1e3)
        t_arrival_ns = t_start_ns + exposure_ns + self.latency_ns + int(self._rng.exponential(self.jitter_ns))
        if t_arrival_ns - self._render_s * 1e9 > deadline:  # it would not even be rendering by then
            time.sleep(max(0.0, (deadline - time.monotonic_ns()) * 1e-9))
            raise DriverTimeout(f"no frame from simulated camera {self._serial} within {timeout_s:.3f} s")
        t_mid_ns = t_start_ns + exposure_ns // 2
        t_cell_s = (t_mid_ns - self.epoch_ns) * 1e-9
        t_render = time.perf_counter()
        if self.T_master_camera is None:
            rendered = self._cell.render(t_cell_s, self._rng, self._render_settings(), lit=self._lit())
        else:
            s = replace(self._render_settings(), lit=self._lit())
            rendered = render_frame(self._cell.camera, self._cell.field, self._T_field_camera(t_cell_s), s, self._rng)
        self._render_s = min(0.5, 0.8 * self._render_s + 0.2 * (time.perf_counter() - t_render))
        image = rendered.image
        if self._garbled:  # noise over the whole range: nothing in it may be measured as a target
            image = self._rng.integers(0, np.iinfo(image.dtype).max, image.shape, dtype=image.dtype, endpoint=True)
        if self._settings.roi is not None:
            x, y, w, h = self._settings.roi
            image = np.ascontiguousarray(image[y : y + h, x : x + w])
        wait_s = (t_arrival_ns - time.monotonic_ns()) * 1e-9
        if wait_s > 0:
            time.sleep(wait_s)
        self._require_link()  # unplugged while "in flight": the frame is lost with the link
        seq = self._seq_of(t_start_ns)
        self._last_exposure_start_ns = t_start_ns
        self._pending_start_ns = None
        return Frame(
            image=image,
            seq=seq,
            # the scheduled arrival: rendering stands in for the camera's readout, and a triggered
            # frame cannot be rendered before its trigger, so its render time is not latency
            t_host_ns=t_arrival_ns,
            t_device_ns=int((t_start_ns - self.clock_offset_ns) * self.clock_rate),
            exposure_us=self._exposure_us(),
            meta={
                "T_field_camera": self._T_field_camera(t_cell_s).tolist(),
                "t_exposure_true_host_ns": t_mid_ns,
                "t_cell_s": t_cell_s,
                "lit": self._lit(),
            },
        )

    def try_fetch(self) -> Frame | None:
        # "waiting" = due within the time it takes to render it (the simulation's readout)
        self._require_link()
        now = time.monotonic_ns()
        start = self._peek_exposure_start(now)
        if start is None:
            return None
        due = start + int(self._exposure_us() * 1e3) + self.latency_ns
        if due - now > self._render_s * 1.5e9 + 1e6:
            return None
        return self.fetch(timeout_s=1.0)

    def trigger(self) -> None:
        self._require_link()
        if self._settings.trigger is not TriggerMode.SOFTWARE:
            raise FeatureUnsupported("TriggerSoftware", "software trigger needs trigger mode 'software'")
        with self._lock:
            self._triggers.append(time.monotonic_ns() + self.trigger_delay_ns)

    def close(self) -> None:
        self._open = False

    def _T_field_camera(self, t_cell_s: float) -> np.ndarray:
        T = self._cell.T_field_camera(t_cell_s)
        return T if self.T_master_camera is None else T @ self.T_master_camera

    # --- fault injection for tests and the demo -----------------------------------------------

    def unplug(self) -> None:
        self._plugged = False

    def plug(self) -> None:
        self._plugged = True
        self._stalled = self._garbled = False

    def stall(self) -> None:
        self._stalled = True

    def garble(self) -> None:
        self._garbled = True

    # --- internals ----------------------------------------------------------------------------

    def _require_link(self) -> None:
        if not self._open:
            raise DriverDisconnected(f"simulated camera {self._serial} is not open")
        if not self._plugged:
            raise DriverDisconnected(f"simulated camera {self._serial} does not answer (unplugged)")

    def _exposure_us(self) -> float:
        return self._settings.exposure_us if self._settings.exposure_us is not None else REFERENCE_EXPOSURE_US

    def _period_ns(self) -> int:
        return int(1e9 / (self._settings.frame_rate_hz or 30.0))

    def _peek_exposure_start(self, now_ns: int) -> int | None:
        mode = self._settings.trigger
        if mode is TriggerMode.SOFTWARE:
            with self._lock:
                return self._triggers[0] if self._triggers else None
        if mode is TriggerMode.HARDWARE:
            return None  # no trigger line in the simulation
        if self._pending_start_ns is not None:
            return self._pending_start_ns
        period = self._period_ns()
        exposure_ns = int(self._exposure_us() * 1e3)
        # the next frame that can still be rendered before it is due: rendering stands in for the
        # camera's own exposure and readout, so it must not make frames late
        ready_ns = now_ns + int(self._render_s * 1e9 * 1.5)
        k = math.ceil((ready_ns - self.epoch_ns - exposure_ns - self.latency_ns) / period)
        start = self.epoch_ns + k * period
        last = self._last_exposure_start_ns
        # once chosen, a frame stays the next one until delivered: re-choosing on every short
        # fetch would push it ahead for ever when rendering is slow
        self._pending_start_ns = start if last is None or start > last else last + period
        return self._pending_start_ns

    def _next_exposure_start(self, deadline_ns: int) -> int | None:
        if self._settings.trigger is TriggerMode.SOFTWARE:
            while True:
                with self._lock:
                    if self._triggers:
                        return self._triggers.pop(0)
                if time.monotonic_ns() >= deadline_ns:
                    return None
                time.sleep(0.0005)
        if self._settings.trigger is TriggerMode.HARDWARE:
            time.sleep(max(0.0, (deadline_ns - time.monotonic_ns()) * 1e-9))
            return None
        return self._peek_exposure_start(time.monotonic_ns())

    def _seq_of(self, t_start_ns: int) -> int:
        if self._settings.trigger is TriggerMode.FREE_RUN:
            return round((t_start_ns - self.epoch_ns) / self._period_ns()) & 0xFFFF_FFFF
        self._next_seq += 1
        return self._next_seq

    def _lit(self) -> bool:
        s = self._settings.strobe
        return s is not None and s.enabled and s.source in _LIT_SOURCES and not s.inverted

    def _render_settings(self) -> RenderSettings:
        gain = 10 ** ((self._settings.gain_db or 0.0) / 20.0)
        depth = _BIT_DEPTH[self._settings.pixel_format or "Mono8"]
        return replace(
            RenderSettings(),
            exposure_scale=self._exposure_us() / REFERENCE_EXPOSURE_US * gain,
            bit_depth=depth,
        )
