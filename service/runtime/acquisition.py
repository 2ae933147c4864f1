"""One camera's acquisition thread: the only caller of that camera's driver.

It opens the camera (and keeps re-opening it while it is gone), applies the
settings, and fetches frames into a one-frame slot: the processing worker
always takes the newest frame, and a frame it had no time for is counted as
dropped, never queued (a slow consumer must not build a backlog). Commands from
other threads (software trigger, new settings) run here between fetches. Given a
``stream_when`` event (the worker's "processing is ready"), it connects at once but
fetches only once it is set: frames nobody can measure yet are not counted as dropped.
Given an ``on_frame`` hand-over (the worker's), each frame is offered to it first, in this
thread: taken, it is already on its way to the measurement, one thread wake-up sooner than
through the slot; refused (the measurement is full or being set up), it goes to the slot.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

from drivers.base import (
    CameraDriver,
    CameraSettings,
    DriverDisconnected,
    DriverError,
    DriverTimeout,
    Frame,
    TriggerMode,
)

log = logging.getLogger(__name__)

FETCH_TIMEOUT_S = 0.1  # short, so that commands wait at most this long
# reconnection back-off: a camera is found again within ~1 s of its return, however long it was gone
RETRY_MIN_S, RETRY_MAX_S = 0.5, 1.0
STALLED = "stalled"  # reported state of a connected camera that delivers no frames
STALL_MIN_S, STALL_PERIODS = 1.0, 10  # silent for longer than both: stalled


class DeviceState(StrEnum):
    starting = "starting"
    ok = "ok"
    disconnected = "disconnected"
    failed = "failed"  # will not recover by retrying (bad configuration, missing SDK)
    absent = "absent"  # not configured
    stopped = "stopped"


@dataclass
class CameraCounters:
    frames: int = 0
    dropped: int = 0  # frames replaced in the slot before the worker took them
    timeouts: int = 0
    disconnects: int = 0
    seq_gaps: int = 0  # frames the camera skipped or lost (from its frame counter)
    fps: float = 0.0
    last_frame_host_ns: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


class Wakeup(threading.Condition):
    """The processing thread's wake-up on a new frame or a camera's change of state: a condition
    to wait on, and a pipe to select together with the measurement processes' answers
    (:meth:`fileno`, made on first use)."""

    def __init__(self) -> None:
        super().__init__()
        self._pipe: tuple[int, int] | None = None

    def fileno(self) -> int:
        if self._pipe is None:
            r, w = os.pipe()
            os.set_blocking(r, False)
            os.set_blocking(w, False)
            self._pipe = (r, w)
        return self._pipe[0]

    def notify_all(self) -> None:
        super().notify_all()
        if self._pipe is not None:
            with contextlib.suppress(BlockingIOError):  # full: it is readable, which is all it says
                os.write(self._pipe[1], b"\0")

    def notify_waiters(self) -> None:
        """Wake a thread waiting on the condition only: not one polling the pipe for the
        measurements' answers, which has nothing new to do (see ``HandOver.begin_at_once``)."""
        super().notify_all()

    def drain(self) -> None:
        if self._pipe is not None:
            with contextlib.suppress(BlockingIOError):
                while os.read(self._pipe[0], 4096):
                    pass

    def close(self) -> None:
        pipe, self._pipe = self._pipe, None
        for fd in pipe or ():
            os.close(fd)


class FrameSlot:
    """The newest frame of one camera; ``put`` replaces, ``take`` empties."""

    def __init__(self, wakeup: threading.Condition) -> None:
        self._frame: Frame | None = None
        self._cond = wakeup  # shared by all cameras so that one worker can wait on all of them

    def put(self, frame: Frame) -> bool:
        """Store the frame; True when an untaken frame was replaced (a drop)."""
        with self._cond:
            dropped = self._frame is not None
            self._frame = frame
            self._cond.notify_all()
        return dropped

    def take(self) -> Frame | None:
        with self._cond:
            frame, self._frame = self._frame, None
            return frame


class CameraChannel:
    """Owns one camera driver in its own thread (see the module docstring)."""

    def __init__(
        self,
        name: str,
        driver: CameraDriver,
        settings: CameraSettings,
        wakeup: threading.Condition,
        on_event: Callable[[str, str, str], None],
        stream_when: threading.Event | None = None,
        on_frame: Callable[[str, Frame], bool] | None = None,
    ) -> None:
        self.name = name
        self.driver = driver
        self.settings = settings
        self.slot = FrameSlot(wakeup)
        self._wakeup = wakeup
        self.state = DeviceState.starting
        self.last_error = ""
        self.counters = CameraCounters()
        self._on_event = on_event  # (level, kind, message)
        self._commands: queue.Queue[tuple[str, Any, threading.Event | None]] = queue.Queue()
        self._stop = threading.Event()
        self._stream_when = stream_when
        self._on_frame = on_frame  # (camera name, frame) -> taken
        self.tap: Callable[[Frame], None] | None = None  # a recording's, sees every frame delivered
        self._thread = threading.Thread(target=self._run, name=f"camera-{name}", daemon=True)
        self._last_seq: int | None = None
        self._connected_ns = time.monotonic_ns()
        self.command_error: dict[int, str] = {}
        self.exposure_refused = ""  # the driver's sentence when it refused an exposure step
        # what the camera delivers, as its driver says once it is configured (the measurement's full
        # scale: a Mono12 frame's values end at 4095, not at its uint16's 65535); None: not known yet
        self.pixel_format: str | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout=timeout_s)
        try:
            self.driver.close()
        except DriverError as e:
            log.warning("closing camera %s: %s", self.name, e)
        self.state = DeviceState.stopped

    # --- commands (any thread) -----------------------------------------------------------------

    def request_trigger(self) -> None:
        self._commands.put(("trigger", None, None))

    def request_exposure(self, exposure_us: float) -> None:
        """Change only the exposure, without waiting (the exposure control's step); a refusal is
        kept in :attr:`exposure_refused` (the device has no settable exposure: stop asking)."""
        self._commands.put(("exposure", float(exposure_us), None))

    def request_settings(self, settings: CameraSettings, timeout_s: float = 5.0) -> str:
        """Apply new settings in the owner thread; returns "" or the driver's error sentence."""
        done = threading.Event()
        self._commands.put(("configure", settings, done))
        if not done.wait(timeout_s):
            return f"camera {self.name} did not apply the settings within {timeout_s} s"
        return self.command_error.pop(id(done), "")

    # --- the thread ----------------------------------------------------------------------------

    def _set_state(self, state: DeviceState, error: str = "") -> None:
        if state != self.state:
            level = "info" if state is DeviceState.ok else "warning"
            self._on_event(level, f"camera_{state}", f"camera {self.name}: {error or state}")
        self.state, self.last_error = state, error
        with self._wakeup:  # wake the processing thread: it reports an outage at once
            self._wakeup.notify_all()

    def _connect(self) -> bool:
        try:
            self.driver.open()
            self.driver.configure(self.settings)
        except DriverError as e:
            try:
                self.driver.close()
            except DriverError:
                pass
            self._set_state(DeviceState.disconnected, str(e))
            return False
        self._connected_ns = time.monotonic_ns()
        self._note_pixel_format()
        self._set_state(DeviceState.ok)
        self._last_seq = None
        return True

    def _note_pixel_format(self) -> None:
        try:
            self.pixel_format = self.driver.info.pixel_format
        except (DriverError, AttributeError):  # a driver that cannot say: the frame's dtype decides
            self.pixel_format = None

    def _run_commands(self) -> None:
        while True:
            try:
                kind, arg, done = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                if kind == "trigger" and self.settings.trigger is TriggerMode.SOFTWARE:
                    self.driver.trigger()
                elif kind == "configure":
                    self.driver.configure(arg)
                    self.settings = arg
                    self._last_seq = None
                    self._note_pixel_format()
                elif kind == "exposure":  # an exposure step: the frame counter runs on, gaps are still gaps
                    new = replace(self.settings, exposure_us=arg)
                    self.driver.configure(new)
                    self.settings = new
            except DriverError as e:
                if kind == "exposure":
                    self.exposure_refused = str(e)
                if done is not None:
                    self.command_error[id(done)] = str(e)
                self._on_event("warning", f"camera_{kind}_failed", f"camera {self.name}: {e}")
            finally:
                if done is not None:
                    done.set()

    def _run(self) -> None:
        retry_s = RETRY_MIN_S
        while not self._stop.is_set():
            if self.state is not DeviceState.ok:
                if not self._connect():
                    self._stop.wait(retry_s)
                    retry_s = min(RETRY_MAX_S, retry_s * 2)
                    continue
                retry_s = RETRY_MIN_S
            self._run_commands()
            if self._stream_when is not None and not self._stream_when.is_set():
                self._stream_when.wait(0.05)
                self._connected_ns = time.monotonic_ns()  # not stalled: no frame was asked for yet
                continue
            try:
                frame = self.driver.fetch(FETCH_TIMEOUT_S)
            except DriverTimeout:
                if self.settings.trigger is TriggerMode.FREE_RUN:
                    self.counters.timeouts += 1
                continue
            except DriverDisconnected as e:
                self.counters.disconnects += 1
                try:
                    self.driver.close()
                except DriverError:
                    pass
                self._set_state(DeviceState.disconnected, str(e))
                continue
            except DriverError as e:
                self._set_state(DeviceState.disconnected, str(e))
                continue
            except Exception as e:  # a driver bug must not end acquisition silently: report, reopen
                log.exception("camera %s: fetch failed", self.name)
                self._set_state(DeviceState.disconnected, f"driver error: {e!r}")
                self._stop.wait(RETRY_MIN_S)
                continue
            self._account(frame)
            tap = self.tap
            if tap is not None:
                try:
                    tap(frame)  # queues a reference, never blocks
                except Exception:  # a recording's bug must not stop acquisition
                    log.exception("camera %s: recording a frame failed", self.name)
            if self._offer(frame):
                continue
            if self.slot.put(frame):
                self.counters.dropped += 1

    def _offer(self, frame: Frame) -> bool:
        """True when the hand-over took the frame; a failing hand-over leaves it to the slot."""
        if self._on_frame is None:
            return False
        try:
            return self._on_frame(self.name, frame)
        except Exception:  # a bug there must not stop acquisition: the slot still works
            log.exception("camera %s: handing a frame over failed", self.name)
            return False

    def _account(self, frame: Frame) -> None:
        c = self.counters
        if self._last_seq is not None and self.settings.trigger is TriggerMode.FREE_RUN:
            gap = (frame.seq - self._last_seq - 1) & 0xFFFF  # frame ids wrap (16 bit on GigE Vision 1.x)
            if 0 < gap < 1000:
                c.seq_gaps += gap
        self._last_seq = frame.seq
        if c.last_frame_host_ns:
            dt = (frame.t_host_ns - c.last_frame_host_ns) * 1e-9
            if dt > 0:
                c.fps = 1.0 / dt if c.fps == 0 else 0.9 * c.fps + 0.1 / dt
        c.last_frame_host_ns = frame.t_host_ns
        c.frames += 1

    def effective_state(self) -> tuple[str, str]:
        """(state, error) with ``stalled`` for a connected free-running camera that delivers nothing."""
        state, error, last_ns = str(self.state), self.last_error, self.counters.last_frame_host_ns
        if self.state is DeviceState.ok and self.settings.trigger is TriggerMode.FREE_RUN:
            silent_s = (time.monotonic_ns() - max(last_ns, self._connected_ns)) * 1e-9
            if silent_s > max(STALL_MIN_S, STALL_PERIODS / (self.settings.frame_rate_hz or 1.0)):
                return STALLED, f"camera {self.name} is connected but delivered no frame for {silent_s:.1f} s"
        return state, error

    def snapshot(self) -> dict[str, Any]:
        c = self.counters
        age_s = (time.monotonic_ns() - c.last_frame_host_ns) * 1e-9 if c.last_frame_host_ns else None
        state, error = self.effective_state()
        return {
            "state": state,
            "error": error,
            "fps": round(c.fps, 2) if age_s is not None and age_s < 2.0 else 0.0,
            "frames": c.frames,
            "dropped": c.dropped,
            "timeouts": c.timeouts,
            "disconnects": c.disconnects,
            "seq_gaps": c.seq_gaps,
            "last_frame_age_s": None if age_s is None else round(age_s, 3),
            "trigger": str(self.settings.trigger),
            "exposure_us": self.settings.exposure_us,
            "pixel_format": self.pixel_format,  # as the driver reports it: the measurement's bit depth
        }
