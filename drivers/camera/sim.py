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
- an exposure step (a ``configure`` that changes only ``exposure_us`` and/or ``gain_db``, as the
  exposure control makes while the camera runs) keeps the frame grid, the frames asked for and
  the triggers waiting: a frame whose exposure had started before the step keeps the old
  exposure, as on a real camera, and every later one is asked of the renderer again with the new
  one (it may come late by that render; ``seq`` has no gap). Any other change starts afresh:
  the frames asked for and the triggers waiting are dropped, and the grid's next frame that can
  be rendered in time comes next (usually a gap in ``seq``, as a camera's restart loses frames);
- ``unplug()`` / ``plug()`` inject a lost link (``DriverDisconnected``); ``stall()`` keeps the
  link but delivers no frame (a stuck stream: only timeouts); ``garble()`` delivers frames of
  noise (a broken sensor or a wrong pixel format); ``plug()`` ends every fault.

Rendering (~30 ms a frame, ~12 ms for a pose rendered before) stands in for the camera's exposure
and readout; it runs in a child process (``sim_render.FrameRenderer``), not under the service's
GIL. Knowing its schedule, the camera asks for the next ``AHEAD_FRAMES`` frames at once and
copies each image out when due.
A frame's pose is the cell's at mid-exposure (program and commanded moves), computed when it is
asked for and checked again before and after it is taken: a move commanded after a frame was
asked for (the hand-eye session moving the arm) has it rendered again, so it may come late
(stamped with its scheduled arrival all the same). ``Frame.exposure_us`` is the exposure a frame
was rendered with, and its brightness follows it. A frame's noise comes from ``(seed, its exposure
start)``: the same image whichever process renders it. ``open()`` returns once the child is ready
(1-2 s; the camera boots, as a GigE camera's open takes seconds), so that no frame of the stream is
rendered more slowly than the rate and skipped; if the child is not ready within ``OPEN_WAIT_S``,
if it cannot start, or with ``render="inline"``, frames render in this process.

The arm's motion during the exposure smears the frame (one uniform smear, the median image motion
of the targets from the exposure's start to its end: :func:`service.sim.render.image_motion_px`).
What it does not model: a smear that differs across the image (a rotation), rolling shutter, packet loss, buffer
underruns, and how long rendering takes (a frame is handed over no earlier than its scheduled
arrival and stamped with it, even when rendering made it later). The ground truth of a frame
is in ``Frame.meta``: ``T_field_camera`` (mm), ``t_exposure_true_host_ns``, and ``render``
("child" or "inline": where it was rendered).
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

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
from drivers.camera.sim_render import FrameRenderer, RenderJob
from service.sim.cell import CellConfig, SimCell
from service.sim.render import RenderSettings, image_motion_px

_LIT_SOURCES = ("ExposureActive", "Timer0Active", "Timer1Active")
_BIT_DEPTH = {"Mono8": 8, "Mono12": 12, "Mono16": 16}
REFERENCE_EXPOSURE_US = 2000.0  # the exposure at which RenderSettings.target_dn is reached
MIN_SMEAR_PX = 0.05  # a slower image motion during the exposure is not rendered (the blur hides it)
AHEAD_FRAMES = 3  # free run: frames asked of the render process at once (the next one and two more)
STALE_NS = 500_000_000  # a frame due longer ago than this is dropped (the driver's buffers, ~10 frames at 20 Hz)
OPEN_WAIT_S = 15.0  # open() waits this long at most for the render child (a fresh install compiles it)
RENDER_MARGIN = 1.5  # a frame is asked for when it can be rendered in this many render times before it is due


@dataclass(frozen=True)
class _Planned:
    """A frame asked of the renderer: its exposure start and arrival (host ns), cell time s, pose (mm)."""

    t_start_ns: int
    t_arrival_ns: int
    t_cell_s: float
    T_field_camera: np.ndarray
    version: int  # of the settings it was asked for with
    ticket: int
    exposure_us: float  # what it is rendered with: an exposure step re-asks only the frames exposed after it
    gain_db: float | None


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
    render : "process" (a render process, the default) or "inline" (in the fetching thread)
    hot_pixels : share of the sensor's pixels that are hot (200 DN of dark current, lit or not; the
        same pixels in every frame, drawn from ``seed``); 0: none
    dead_pixels : share of the sensor's pixels that are dead (0 DN, lit or not; the same in every
        frame, drawn from ``seed``); 0: none
    """

    def __init__(
        self,
        cell: SimCell | None = None,
        cell_config: dict[str, Any] | None = None,
        epoch_ns: int | None = None,
        latency_s: float = 0.004,
        jitter_s: float = 0.0005,
        trigger_delay_us: float = 50.0,
        clock_offset_s: float = 1234.5,
        clock_drift_ppm: float = 30.0,
        seed: int = 1,
        serial: str = "SIM-0001",
        T_master_camera: list[list[float]] | None = None,
        render: str = "process",
        hot_pixels: float = 0.0,
        dead_pixels: float = 0.0,
    ) -> None:
        for name, share in (("hot_pixels", hot_pixels), ("dead_pixels", dead_pixels)):
            if not 0.0 <= float(share) <= 0.01:
                raise ValueError(f"{name} is a share of the sensor's pixels in [0, 0.01], got {share}")
        # the sensor's own, drawn from the seed: the same in every frame
        self._hot_pixels, self._dead_pixels = float(hot_pixels), float(dead_pixels)
        self._cell = cell if cell is not None else SimCell(CellConfig(**(cell_config or {})))
        self.epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)
        self.latency_ns = int(latency_s * 1e9)
        self.jitter_ns = float(jitter_s * 1e9)
        self.trigger_delay_ns = int(trigger_delay_us * 1e3)
        self.clock_offset_ns = float(clock_offset_s * 1e9)
        self.clock_rate = 1.0 + clock_drift_ppm * 1e-6
        self._seed = int(seed)
        self._rng = np.random.default_rng(seed)  # arrival jitter and garbled frames; each frame has its own noise
        self._serial = serial
        # a second camera of a rig: its pose relative to the cell's camera (the master), mm
        self.T_master_camera = None if T_master_camera is None else np.asarray(T_master_camera, dtype=np.float64)
        name, cam, field = f"simulated camera {serial}", self._cell.camera, self._cell.field
        self._renderer = FrameRenderer(cam, field, render, name, warmup_T_field_camera=self._T_field_camera(0.0))
        self._settings = CameraSettings(strobe=None)
        self._version = 0  # of the settings: frames asked for with older ones are dropped
        self._open = False
        self._plugged = True
        self._stalled = False
        self._garbled = False
        self._next_seq = 0
        self._last_exposure_start_ns: int | None = None
        self._last_version = -1  # the settings' version of the frame delivered last
        self._triggers: list[int] = []
        self._plan: collections.deque[_Planned] = collections.deque()  # asked for, in exposure order
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

    @property
    def render_status(self) -> dict[str, object]:
        """Where frames are rendered: ``FrameRenderer.status`` (state, pid, restarts, render_ms)."""
        return self._renderer.status

    def open(self) -> None:
        if not self._plugged:
            raise DriverInitError(f"simulated camera {self._serial} is unplugged")
        if not self._open:
            self._plan.clear()  # tickets of a closed renderer
            self._renderer.start()
            # rendered here meanwhile, frames would take longer than the period: the stream would
            # start with gaps in seq; a child that does not come leaves rendering here
            self._renderer.wait_ready(OPEN_WAIT_S)
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
            old, now_ns = self._settings, time.monotonic_ns()
            step = replace(settings, exposure_us=old.exposure_us, gain_db=old.gain_db) == old
            if step:  # a triggered exposure that has begun is taken with the old settings, as planned frames are
                while self._triggers and self._triggers[0] <= now_ns:
                    self._plan.append(self._ask(self._triggers.pop(0)))
            else:
                self._triggers.clear()
                self._version += 1
            self._settings = settings
        if step:
            self._expose_again(now_ns)

    def fetch(self, timeout_s: float) -> Frame:
        self._require_link()
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        none = f"no frame from simulated camera {self._serial} within {timeout_s:.3f} s"
        if self._stalled:
            time.sleep(timeout_s)
            raise DriverTimeout(f"{none} (stalled)")
        p = self._next_frame(deadline)
        if p is None:
            raise DriverTimeout(none)
        lead_ns = 0 if self._renderer.in_child(p.ticket) else int(self._renderer.render_s * 1e9)
        if p.t_arrival_ns - lead_ns > deadline:  # it would not even be rendering by then
            time.sleep(max(0.0, (deadline - time.monotonic_ns()) * 1e-9))
            raise DriverTimeout(none)
        image, by_child = self._take(deadline)
        if image is None:  # still being rendered: it stays the next frame
            raise DriverTimeout(f"{none} (still rendering)")
        p = self._plan[0]  # rendered again if the arm was commanded to move meanwhile
        if self._garbled:  # noise over the whole range: nothing in it may be measured as a target
            image = self._rng.integers(0, np.iinfo(image.dtype).max, image.shape, dtype=image.dtype, endpoint=True)
        wait_s = (p.t_arrival_ns - time.monotonic_ns()) * 1e-9
        if wait_s > 0:
            time.sleep(wait_s)
        self._plan.popleft()
        self._require_link()  # unplugged while "in flight": the frame is lost with the link
        seq = self._seq_of(p.t_start_ns)
        self._last_exposure_start_ns, self._last_version = p.t_start_ns, p.version
        exposure_ns = int(p.exposure_us * 1e3)
        return Frame(
            image=image,
            seq=seq,
            # the scheduled arrival: rendering stands in for the camera's readout, and a triggered
            # frame cannot be rendered before its trigger, so its render time is not latency
            t_host_ns=p.t_arrival_ns,
            t_device_ns=int((p.t_start_ns - self.clock_offset_ns) * self.clock_rate),
            exposure_us=p.exposure_us,
            meta={
                "T_field_camera": p.T_field_camera.tolist(),
                "t_exposure_true_host_ns": p.t_start_ns + exposure_ns // 2,
                "t_cell_s": p.t_cell_s,
                "lit": self._lit(),
                "render": "child" if by_child else "inline",
            },
        )

    def try_fetch(self) -> Frame | None:
        # "waiting" = due within the time it still takes to render it (the simulation's readout)
        self._require_link()
        now = time.monotonic_ns()
        mode = self._settings.trigger
        if mode is TriggerMode.HARDWARE:
            return None
        if mode is TriggerMode.FREE_RUN:
            self._revise_plan()
            self._fill_plan(now)
        if self._plan:
            due = self._plan[0].t_arrival_ns
            child = self._renderer.in_child(self._plan[0].ticket)
        else:
            with self._lock:
                if not self._triggers:
                    return None
                due = self._triggers[0] + int(self._exposure_us() * 1e3) + self.latency_ns
            child = False
        if due - now > (0 if child else self._renderer.render_s * RENDER_MARGIN * 1e9) + 1e6:
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
        self._renderer.close()  # its process ends within a second

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

    # --- the exposure schedule and the frames asked for -----------------------------------------

    def _next_frame(self, deadline_ns: int) -> _Planned | None:
        """The next frame to deliver (asked of the renderer), or None when none will be exposed by the deadline."""
        self._revise_plan()
        mode = self._settings.trigger
        if mode is TriggerMode.FREE_RUN:
            self._fill_plan(time.monotonic_ns())
        elif mode is TriggerMode.HARDWARE:
            time.sleep(max(0.0, (deadline_ns - time.monotonic_ns()) * 1e-9))
            return None  # no trigger line in the simulation
        while not self._plan:  # software trigger
            with self._lock:
                t_start_ns = self._triggers.pop(0) if self._triggers else None
            if t_start_ns is not None:
                self._plan.append(self._ask(t_start_ns))
            elif time.monotonic_ns() >= deadline_ns:
                return None
            else:
                time.sleep(0.0005)
        return self._plan[0]

    def _revise_plan(self) -> None:
        """Drop the frames asked for with older settings; ask again for those whose pose has changed since."""
        if any(p.version != self._version for p in self._plan):  # any: an exposure step may append behind stale ones
            for p in self._plan:
                if p.version != self._version:
                    self._renderer.cancel(p.ticket)
            self._plan = collections.deque(p for p in self._plan if p.version == self._version)
        for i in range(len(self._plan)):
            p = self._plan[i]
            if not np.array_equal(self._T_field_camera(p.t_cell_s), p.T_field_camera):  # a move was commanded
                self._renderer.cancel(p.ticket)
                self._plan[i] = self._ask(p.t_start_ns, p.t_arrival_ns, like=p)

    def _expose_again(self, now_ns: int) -> None:
        """An exposure step at ``now_ns``: the frames asked for whose exposure starts later are asked again with it.

        Their exposure start (so ``seq``) stays; the arrival moves by the change of the exposure.
        Those exposed before keep the old exposure, as a real camera's frames already taken do."""
        exposure_us, gain_db = self._exposure_us(), self._settings.gain_db
        for i, p in enumerate(self._plan):
            if (
                p.version != self._version
                or p.t_start_ns <= now_ns
                or (p.exposure_us, p.gain_db) == (exposure_us, gain_db)
            ):
                continue
            self._renderer.cancel(p.ticket)
            shift_ns = int(exposure_us * 1e3) - int(p.exposure_us * 1e3)
            self._plan[i] = self._ask(p.t_start_ns, p.t_arrival_ns + shift_ns)

    def _fill_plan(self, now_ns: int) -> None:
        """Free run: ask for the next frames on the grid that can be rendered before they are due (or that
        wait in the buffers for a consumer that came late)."""
        while self._plan and self._plan[0].t_arrival_ns < now_ns - STALE_NS:  # nobody fetched it in time
            self._renderer.cancel(self._plan.popleft().ticket)
        ahead = AHEAD_FRAMES if self._renderer.child_ready else 1  # in-process: rendered when taken
        if len(self._plan) >= ahead:
            return
        period = self._period_ns()
        exposure_ns = int(self._exposure_us() * 1e3)
        backlog = self._renderer.backlog() if ahead > 1 else 0
        while len(self._plan) < ahead:
            # the first frame that can still be rendered before it is due (after those asked for
            # already): rendering stands in for the camera's own exposure and readout, so it must
            # not make frames late; one after those asked for may be up to a period late (a render
            # slower than the rest) rather than not come at all
            late_ns = period if self._plan else 0
            ready_ns = now_ns + int(self._renderer.render_s * 1e9 * (backlog + RENDER_MARGIN)) - late_ns
            k = math.ceil((ready_ns - self.epoch_ns - exposure_ns - self.latency_ns) / period)
            last = self._plan[-1].t_start_ns if self._plan else self._last_exposure_start_ns
            if last is not None:  # once asked for, a frame stays the next one until delivered or stale
                k_next = (last - self.epoch_ns) // period + 1
                # a consumer that came late (a stalled thread) finds the frames since in the driver's
                # buffers, as a real camera's, and they come late; a renderer too slow for the rate
                # skips them instead, as before, so that its frames are never late
                buffered = (
                    (bool(self._plan) or self._last_version == self._version)
                    and self._renderer.render_s * 1e9 < period  # it catches up
                    and self.epoch_ns + k_next * period + exposure_ns + self.latency_ns >= now_ns - STALE_NS
                )
                k = k_next if buffered else max(k, k_next)
            self._plan.append(self._ask(self.epoch_ns + k * period))
            backlog += 1

    def _ask(self, t_start_ns: int, t_arrival_ns: int | None = None, like: _Planned | None = None) -> _Planned:
        """Ask the renderer for the frame exposed from ``t_start_ns``: the cell's pose at mid-exposure, now.

        With the current exposure and gain, or with those of ``like`` (the same frame asked again)."""
        exposure_us, gain_db = (
            (like.exposure_us, like.gain_db) if like else (self._exposure_us(), self._settings.gain_db)
        )
        exposure_ns = int(exposure_us * 1e3)
        if t_arrival_ns is None:
            t_arrival_ns = t_start_ns + exposure_ns + self.latency_ns + int(self._rng.exponential(self.jitter_ns))
        t_cell_s = (t_start_ns + exposure_ns // 2 - self.epoch_ns) * 1e-9
        T = self._T_field_camera(t_cell_s)
        settings = replace(self._render_settings(exposure_us, gain_db), lit=self._lit())
        # the arm's motion during the exposure smears the frame about its mid-exposure pose
        half_s = exposure_ns * 0.5e-9
        T0, T1 = self._T_field_camera(t_cell_s - half_s), self._T_field_camera(t_cell_s + half_s)
        if not np.array_equal(T0, T1):
            length_px, angle_deg = image_motion_px(self._cell.camera, self._cell.field, T0, T1)
            if length_px >= MIN_SMEAR_PX:
                settings = replace(settings, motion_blur_px=length_px, motion_angle_deg=angle_deg)
        job = RenderJob(T, settings, (self._seed, (t_start_ns - self.epoch_ns) % 2**63))
        ticket = self._renderer.submit(job)
        return _Planned(t_start_ns, t_arrival_ns, t_cell_s, T, self._version, ticket, exposure_us, gain_db)

    def _take(self, deadline_ns: int) -> tuple[np.ndarray | None, bool]:
        """The next frame's image (ROI), None if not rendered by the deadline, and whether the child rendered it.

        A move commanded while it was rendered has it rendered again (twice at most; then it comes as it is)."""
        for attempt in range(3):
            p = self._plan[0]
            by_child = self._renderer.in_child(p.ticket)
            image = self._renderer.take(p.ticket, deadline_ns, self._settings.roi)
            if image is None or attempt == 2 or np.array_equal(self._T_field_camera(p.t_cell_s), p.T_field_camera):
                break
            self._plan[0] = self._ask(p.t_start_ns, p.t_arrival_ns, like=p)
        return image, by_child

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

    def _seq_of(self, t_start_ns: int) -> int:
        if self._settings.trigger is TriggerMode.FREE_RUN:
            return round((t_start_ns - self.epoch_ns) / self._period_ns()) & 0xFFFF_FFFF
        self._next_seq += 1
        return self._next_seq

    def _lit(self) -> bool:
        s = self._settings.strobe
        return s is not None and s.enabled and s.source in _LIT_SOURCES and not s.inverted

    def _render_settings(self, exposure_us: float, gain_db: float | None) -> RenderSettings:
        gain = 10 ** ((gain_db or 0.0) / 20.0)
        depth = _BIT_DEPTH[self._settings.pixel_format or "Mono8"]
        return replace(
            RenderSettings(),
            exposure_scale=exposure_us / REFERENCE_EXPOSURE_US * gain,
            bit_depth=depth,
            hot_pixels=self._hot_pixels,
            hot_pixel_seed=self._seed,
            dead_pixels=self._dead_pixels,
            dead_pixel_seed=self._seed + 1,  # not the hot ones'
        )
