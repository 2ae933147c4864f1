"""GigE Vision and USB3 Vision cameras through Aravis 0.8 (PyGObject, Debian's ``gir1.2-aravis-0.8``).

The driver owns one ``Aravis.Camera``, one stream with a fixed pool of
buffers and nothing else: ``fetch`` pops a buffer, checks its status, copies
the image out and pushes the buffer back at once (harvesters' and Aravis'
own pattern). Feature names are GenICam SFNC; where cameras differ (the
older ``ExposureTimeAbs``/``GainRaw``/``AcquisitionFrameRateAbs``) the driver
takes whichever exists, and a feature the configuration needs but the camera
lacks raises :class:`FeatureUnsupported` *before* anything is changed.

Loss and recovery: Aravis' heartbeat thread reads the control register of a
GigE Vision camera every second and emits ``control-lost`` when the camera
stops answering (after ~5 s of retries) or answers without our control bit
(it was power-cycled, or another host took it). The driver notes that, the
next ``fetch`` raises :class:`DriverDisconnected`, and every later
``fetch``/``try_fetch`` tries to reopen the camera at most every
``reconnect_interval_s`` and re-applies the last settings. A lost camera's
Aravis objects are released in a background thread: their finalisers wait
for GVCP timeouts (~10 s) and must not block the caller.

Settings: ``configure`` stops the acquisition, writes everything and starts it again on a new
stream, which costs a GigE Vision camera hundreds of milliseconds of frames, except for an
exposure step (only ``exposure_us`` and/or ``gain_db`` differ from the settings in force, as the
exposure control makes a few times a second): that is written to the acquiring camera and the
stream runs on, frame ids without a gap. Where the camera's GenICam description makes the feature
read-only or locked while acquiring, or the camera refuses the write, the step takes the full path.
``Frame.exposure_us`` is the camera's ``ExposureTime`` read back after each change (the driver
enables no chunk data, so no per-frame ``ChunkExposureTime``): which exposure a buffer was taken
with cannot be known, and frames not yet fetched at a step (exposed, in transit or waiting in the
pool), and on sensors that pipeline their exposures the next one or two, carry the new value.

Clocks: ``t_device_ns`` is the buffer's device timestamp; ``t_host_ns`` is when the frame's
leader reached Aravis' stream thread, put on the monotonic clock, not when it was popped (which
waits for the GIL); :mod:`drivers.camera.aravis_stream` says how, and how late the stamps may be.

The driver in three modules, one idea each: this one is the camera's life (open, fetch, lose,
reopen, close) and discovery; :mod:`drivers.camera.aravis_genicam` the GenICam features and the
settings written to them; :mod:`drivers.camera.aravis_stream` the buffer pool and the frames
copied out of it.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace
from typing import Any

from drivers.base import (
    CameraInfo,
    CameraSettings,
    DriverDisconnected,
    DriverError,
    DriverInitError,
    DriverTimeout,
    FeatureUnsupported,
    Frame,
    StrobeSettings,
)
from drivers.camera.aravis_genicam import (
    Aravis,
    Features,
    GLib,
    apply_exposure_step,
    apply_settings,
    apply_strobe,
    check_settings,
    read_exposure_us,
    read_info,
)
from drivers.camera.aravis_stream import FrameCopier, make_stream

log = logging.getLogger(__name__)

__all__ = ["AravisCamera", "discover"]

_POP_SLICE_S = 0.1  # fetch waits in slices this long so that a lost camera is noticed within it
_MiB = 1 << 20


def discover() -> list[dict[str, str]]:
    """Cameras Aravis finds on every interface (GigE Vision broadcast, USB3 Vision enumeration).

    Returns
    -------
    list of dict with ``id`` (what ``device`` accepts), ``model``, ``serial``, ``address`` (IP or
    USB path) and ``protocol`` (``"GigEVision"``, ``"USB3Vision"``, ...). Takes about a second.
    """
    Aravis.update_device_list()
    return [
        {
            "id": Aravis.get_device_id(i) or "",
            "model": Aravis.get_device_model(i) or "",
            "serial": Aravis.get_device_serial_nbr(i) or "",
            "address": Aravis.get_device_address(i) or "",
            "protocol": Aravis.get_device_protocol(i) or "",
        }
        for i in range(Aravis.get_n_devices())
    ]


class AravisCamera:
    """A GenICam camera through Aravis.

    Parameters
    ----------
    device : Aravis device id, serial number or IP address; None opens the first camera found.
        Open GigE Vision cameras by IP address where you can: it binds the right interface.
    n_buffers : stream buffers in the pool (each of the payload size).
    packet_size : GigE Vision packet size in bytes (``GevSCPSPacketSize``); None lets Aravis
        negotiate it with the camera's test packet (it keeps the camera's value when the camera
        has none). Jumbo frames (8192 or more) need the interface's MTU raised too.
    socket_buffer_bytes : the stream's receive socket buffer; None lets Aravis size it by payload.
    packet_resend : ask the camera to resend lost packets (GigE Vision).
    reconnect_interval_s : the least time between two reconnection attempts after a loss.
    packet_socket : receive through Aravis' packet-socket ring (the default: less CPU per packet,
        arrival stamps up to 5 ms late; see the module note) rather than a UDP socket.

    ``CameraSettings.strobe = None`` puts out the ring light this driver switched on earlier
    (that line's ``LineSource`` goes ``Off``) and otherwise leaves the camera's lines alone, as
    the simulated camera and the contract suite expect; ``StrobeSettings(enabled=False, line=...)``
    switches a given line off.
    """

    def __init__(
        self,
        device: str | None = None,
        n_buffers: int = 8,
        packet_size: int | None = None,
        socket_buffer_bytes: int | None = 4 * _MiB,
        packet_resend: bool = True,
        reconnect_interval_s: float = 1.0,
        packet_socket: bool = True,
    ) -> None:
        if n_buffers < 2:
            raise ValueError(f"n_buffers must be at least 2, got {n_buffers}")
        self.device = device
        self.n_buffers = int(n_buffers)
        self.packet_size = packet_size
        self.socket_buffer_bytes = socket_buffer_bytes
        self.packet_resend = packet_resend
        self.reconnect_interval_s = float(reconnect_interval_s)
        self.packet_socket = bool(packet_socket)

        self._camera: Any = None  # Aravis.Camera
        self._device: Any = None  # Aravis.Device (GvDevice for GigE Vision)
        self._stream: Any = None  # Aravis.Stream
        self._handler_id: int | None = None
        self._generation = 0  # tells a late control-lost of a replaced connection from a current one
        self._lost = threading.Event()
        self._opened = False
        self._last_attempt_s = -float("inf")
        self._settings: CameraSettings | None = None  # the last configured (re-applied after a reconnection)
        self._applied: CameraSettings | None = None  # what the connected camera holds, when written whole
        self._info: CameraInfo | None = None
        self._features: Any = None  # Features of the connection's device
        self._exposure_us = float("nan")
        self._frames = FrameCopier()  # counts good frames and failed buffers across reconnections
        self._n_reconnects = 0
        self._releasers: list[threading.Thread] = []
        self._lit_line: str | None = None  # the output line this driver set up as the strobe

    # --- the CameraDriver protocol ---------------------------------------------------------

    @property
    def info(self) -> CameraInfo:
        if self._info is None:
            raise DriverDisconnected(f"the Aravis camera {self._name()} is not open")
        return self._info

    @property
    def stats(self) -> dict[str, Any]:
        """Counters for health reports: good frames, failed buffers by status, reconnections."""
        frames = self._frames
        return {"frames": frames.n_ok, "failed_buffers": dict(frames.failed), "reconnects": self._n_reconnects}

    def read_feature(self, name: str) -> bool | int | float | str:
        """The current value of any GenICam feature, for diagnostics and tests (enumerations as strings)."""
        self._ensure_connected()
        return self._features.read(name)

    def open(self) -> None:
        if self._camera is not None:
            return
        self._connect()
        self._opened = True
        self._start()

    def configure(self, settings: CameraSettings) -> None:
        self._ensure_connected()
        check_settings(self._features, settings)
        if self._step_exposure(settings):
            return
        self._stop()
        previous, self._settings = self._settings, settings  # a reconnection mid-way applies the new ones
        try:
            self._apply(settings)
        except DriverDisconnected:
            raise
        except DriverError:
            self._settings = previous  # refused by the camera: do not retry it on every reconnection
            raise
        finally:
            if self._camera is not None and not self._is_lost():
                # a new stream (new socket, new pool of the new payload size): packets of a frame taken
                # before the change, still queued in the old socket, cannot come out as the first new frame
                self._make_stream()
                self._start()

    def fetch(self, timeout_s: float) -> Frame:
        deadline = time.monotonic() + max(0.0, timeout_s)
        self._ensure_connected(budget_s=timeout_s)
        while True:
            remaining_s = deadline - time.monotonic()
            if remaining_s > 0:
                buffer = self._stream.timeout_pop_buffer(int(min(remaining_s, _POP_SLICE_S) * 1e6))
            else:
                buffer = self._stream.try_pop_buffer()
            if buffer is not None:
                frame = self._frame_from(buffer)
                if frame is not None:
                    return frame
                continue
            if self._is_lost():
                raise self._mark_lost("stopped answering")
            if remaining_s <= 0:
                raise DriverTimeout(f"no frame from the camera {self._name()} within {timeout_s:.3g} s")

    def try_fetch(self) -> Frame | None:
        self._ensure_connected()
        while (buffer := self._stream.try_pop_buffer()) is not None:
            frame = self._frame_from(buffer)
            if frame is not None:
                return frame
        if self._is_lost():
            raise self._mark_lost("stopped answering")
        return None

    def trigger(self) -> None:
        self._ensure_connected()
        f = self._features
        if not f.has("TriggerSoftware"):
            raise FeatureUnsupported("TriggerSoftware", f"the camera {self._model()} has no software trigger")
        f.call(lambda: f.device.execute_command("TriggerSoftware"), "fire a software trigger")

    def close(self) -> None:
        self._opened = False
        self._info = None
        if self._camera is not None:
            lost = self._is_lost()
            if not lost:
                try:
                    self._camera.stop_acquisition()
                except GLib.Error as e:
                    log.warning("camera %s: stopping the acquisition on close failed: %s", self._name(), e.message)
                    lost = True
            self._release(background=lost)
        for thread in self._releasers:  # a camera that answers lets go in milliseconds; a lost one may not
            thread.join(timeout=1.0)
        self._releasers = [t for t in self._releasers if t.is_alive()]

    # --- connection -----------------------------------------------------------------------

    def _connect(self) -> None:
        try:
            camera = Aravis.Camera.new(self.device)
        except GLib.Error as e:
            where = f"at {self.device!r}" if self.device else "on any interface"
            raise DriverInitError(
                f"no GigE Vision or USB3 Vision camera answers {where} ({e.message}); check the address, "
                "the cable and that no other program holds the camera"
            ) from e
        device = camera.get_device()
        if camera.is_gv_device() and not device.is_controller():
            raise DriverInitError(f"the camera {self.device!r} is controlled by another program or host")
        self._generation += 1
        self._lost.clear()
        self._camera, self._device = camera, device
        self._features = Features(device, self._lost, self._name, self._model)
        self._handler_id = device.connect("control-lost", self._on_control_lost, self._generation)
        try:
            self._make_stream()
            self._info = read_info(self._features, camera)
            self._exposure_us = read_exposure_us(self._features)
        except DriverError as e:
            self._release(background=True)
            raise DriverInitError(f"the camera {self._name()} opened but cannot stream: {e}") from e

    def _make_stream(self) -> None:
        """A stream with ``n_buffers`` buffers of the current payload (a new one replaces the old)."""
        self._stream = None
        self._stream = make_stream(
            self._camera,
            self._features,
            n_buffers=self.n_buffers,
            packet_size=self.packet_size,
            socket_buffer_bytes=self.socket_buffer_bytes,
            packet_resend=self.packet_resend,
            packet_socket=self.packet_socket,
        )

    def _ensure_connected(self, budget_s: float = 0.0) -> None:
        """Return when the camera is usable; after a loss, reopen it (rate-limited) or raise.

        ``budget_s`` is how long the caller may block: a ``fetch`` sleeps until the next attempt
        is due (or its timeout ends) instead of returning at once, so a worker loop cannot spin.
        """
        if self._camera is not None:
            if not self._is_lost():
                return
            raise self._mark_lost("stopped answering")
        if not self._opened:
            raise DriverDisconnected(f"the Aravis camera {self._name()} is not open")
        wait_s = self._last_attempt_s + self.reconnect_interval_s - time.monotonic()
        if wait_s > 0:
            time.sleep(min(wait_s, max(0.0, budget_s)))
            if wait_s > budget_s:
                raise DriverDisconnected(
                    f"the camera {self._name()} is lost; reconnecting every {self.reconnect_interval_s:g} s"
                )
        self._last_attempt_s = time.monotonic()
        try:
            self._connect()
            if self._settings is not None:
                check_settings(self._features, self._settings)
                self._stop()
                self._apply(self._settings)
                self._make_stream()
            self._start()
        except DriverError as e:
            self._release(background=True)
            raise DriverDisconnected(f"the camera {self._name()} is lost and could not be reopened yet: {e}") from e
        self._n_reconnects += 1
        log.info("camera %s reconnected (settings re-applied: %s)", self._name(), self._settings is not None)

    def _on_control_lost(self, _device: Any, generation: int) -> None:
        # runs in Aravis' heartbeat thread: only set a flag
        if generation == self._generation:
            self._lost.set()

    def _is_lost(self) -> bool:
        if self._lost.is_set():
            return True
        # the heartbeat also clears the controller flag; reading it is local (no GVCP traffic)
        return bool(self._camera.is_gv_device() and not self._device.is_controller())

    def _mark_lost(self, why: str) -> DriverDisconnected:
        """Drop the lost connection (in the background) and say so; the next call reconnects."""
        name = self._name()
        if self._camera is not None:
            log.warning("camera %s %s; it will be reopened every %.1f s", name, why, self.reconnect_interval_s)
            self._release(background=True)
            self._last_attempt_s = time.monotonic()
        return DriverDisconnected(f"the camera {name} {why} (control lost); reconnecting")

    def _release(self, background: bool) -> None:
        """Drop stream and camera; a lost camera's finalisers wait on GVCP timeouts, so off this thread."""
        if self._device is not None and self._handler_id is not None:
            self._device.disconnect(self._handler_id)
        objects = [self._stream, self._camera, self._device, self._features]
        self._stream = self._camera = self._device = self._features = None
        self._applied = None
        self._handler_id = None
        if background:
            thread = threading.Thread(target=objects.clear, name="aravis-release", daemon=True)
            thread.start()
            self._releasers = [t for t in self._releasers if t.is_alive()] + [thread]
        else:
            objects.clear()

    def _start(self) -> None:
        self._features.call(self._camera.start_acquisition, "start the acquisition")

    def _stop(self) -> None:
        self._features.call(self._camera.stop_acquisition, "stop the acquisition")

    # --- frames and settings (the work is in aravis_stream and aravis_genicam) ----------------

    def _frame_from(self, buffer: Any) -> Frame | None:
        """An owned frame from a popped buffer, or None for a failed one; the buffer goes back at once."""
        return self._frames.frame_from(self._stream, buffer, self._exposure_us, self._name())

    def _step_exposure(self, s: CameraSettings) -> bool:
        """An exposure step written to the acquiring camera; False when ``s`` needs the full path."""
        old = self._applied
        if old is None or replace(s, exposure_us=old.exposure_us, gain_db=old.gain_db) != old:
            return False
        try:
            if not apply_exposure_step(self._features, old, s):
                return False
        except DriverDisconnected:
            raise
        except DriverError as e:  # said no while acquiring, without saying so in its description
            log.info("camera %s refused an exposure step while acquiring (%s); stopping to write it", self._name(), e)
            return False
        self._settings = self._applied = s
        self._exposure_us = read_exposure_us(self._features)
        return True

    def _apply(self, s: CameraSettings) -> None:
        """Write ``s`` to the stopped camera (checked by ``check_settings``); the caller makes a new stream."""
        f = self._features
        self._applied = None  # a write that fails part-way leaves the camera's state unknown
        apply_settings(f, s)
        if s.strobe is not None:
            self._lit_line = apply_strobe(f, s.strobe)
        elif self._lit_line is not None:  # no strobe now: put out the ring light this driver lit
            self._lit_line = apply_strobe(f, StrobeSettings(enabled=False, line=self._lit_line))
        if f.has("AcquisitionMode"):
            f.set("AcquisitionMode", "Continuous")
        self._exposure_us = read_exposure_us(f)
        self._info = read_info(f, self._camera)
        self._applied = s

    def _model(self) -> str:
        return self._info.model if self._info is not None and self._info.model else self._name()

    def _name(self) -> str:
        return repr(self.device) if self.device else "(first found)"

    def __repr__(self) -> str:
        state = "open" if self._camera is not None else ("lost" if self._opened else "closed")
        return f"AravisCamera(device={self.device!r}, {state})"
