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

Clocks: ``t_device_ns`` is the buffer's device timestamp (GigE Vision ticks
scaled to ns by Aravis). ``t_host_ns`` is when the leader reached Aravis' stream
thread (its ``CLOCK_REALTIME`` system timestamp, ``meta["system_timestamp_ns"]``,
put on the monotonic clock by ``drivers.timing.arrival_ns``), not the pop
(``meta["t_popped_ns"]``), which waits for the GIL that numba kernels hold for
milliseconds. That thread runs at nice -10 where allowed. By default it reads
Aravis' packet-socket ring (its fast path), which hands packets over every 5 ms
or 2 MiB, so stamps may be up to 5 ms late; ``packet_socket=False`` reads a UDP
socket instead (stamps within ~0.3 ms; the simulated cell's stand-ins use it), at
more CPU per packet and, under load, with triggered frames lost here to the
socket's small default buffer.
"""

from __future__ import annotations

import ctypes
import logging
import threading
import time
from collections import Counter
from typing import Any

import numpy as np

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib
except (ImportError, ValueError) as e:  # ValueError: gi is there but the Aravis typelib is not
    raise ImportError(f"Aravis 0.8 for Python is missing (Debian: python3-gi gir1.2-aravis-0.8): {e}") from e

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
    TriggerMode,
)
from drivers.timing import arrival_ns, thread_nice

log = logging.getLogger(__name__)

__all__ = ["AravisCamera", "discover"]

# pixel formats posecell reads, with their PFNC codes and array types (GigE Vision pixels are little-endian)
_PIXEL_FORMATS: dict[str, tuple[int, np.dtype[Any]]] = {
    "Mono8": (Aravis.PIXEL_FORMAT_MONO_8, np.dtype(np.uint8)),
    "Mono12": (Aravis.PIXEL_FORMAT_MONO_12, np.dtype("<u2")),
    "Mono16": (Aravis.PIXEL_FORMAT_MONO_16, np.dtype("<u2")),
}
_DTYPE_BY_CODE = {code: dtype for code, dtype in _PIXEL_FORMATS.values()}
_NAME_BY_CODE = {code: name for name, (code, _) in _PIXEL_FORMATS.items()}

_DEVICE_ERROR = "arv-device-error-quark"
_GC_ERROR = "arv-gc-error-quark"
_LINK_ERRORS = {
    int(Aravis.DeviceError.TIMEOUT),
    int(Aravis.DeviceError.NOT_CONNECTED),
    int(Aravis.DeviceError.TRANSFER_ERROR),
    int(Aravis.DeviceError.NOT_CONTROLLER),
}
# PyGObject hands buffer data out as an immutable bytes copy; ctypes copies it once into a writable array
_lib = ctypes.CDLL("libaravis-0.8.so.0")  # the library gi loaded (same soname, same handle)
_lib.arv_buffer_get_image_data.restype = ctypes.c_void_p
_lib.arv_buffer_get_image_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype, _capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]

_POP_SLICE_S = 0.1  # fetch waits in slices this long so that a lost camera is noticed within it
_CLOCK_STEP_NS = 1_000_000  # a change of CLOCK_REALTIME - CLOCK_MONOTONIC larger than this is a step
_MiB = 1 << 20
_STREAM_THREAD_NICE = -10  # the stream thread stamps arrivals: it runs ahead of image processing when allowed


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
        self._settings: CameraSettings | None = None
        self._info: CameraInfo | None = None
        self._exposure_us = float("nan")
        self._failed: Counter[str] = Counter()  # failed buffers by Aravis status nick
        self._n_ok = 0
        self._n_reconnects = 0
        self._releasers: list[threading.Thread] = []
        self._lit_line: str | None = None  # the output line this driver set up as the strobe
        self._real_minus_mono_ns: int | None = None  # CLOCK_REALTIME - CLOCK_MONOTONIC at the last pop

    # --- the CameraDriver protocol ---------------------------------------------------------

    @property
    def info(self) -> CameraInfo:
        if self._info is None:
            raise DriverDisconnected(f"the Aravis camera {self._name()} is not open")
        return self._info

    @property
    def stats(self) -> dict[str, Any]:
        """Counters for health reports: good frames, failed buffers by status, reconnections."""
        return {"frames": self._n_ok, "failed_buffers": dict(self._failed), "reconnects": self._n_reconnects}

    def read_feature(self, name: str) -> bool | int | float | str:
        """The current value of any GenICam feature, for diagnostics and tests (enumerations as strings)."""
        self._ensure_connected()
        node = self._device.get_feature(name)
        if node is None:
            raise FeatureUnsupported(name, f"the camera {self._model()} has no {name}")
        d = self._device
        for kind, getter in (
            (Aravis.GcEnumeration, d.get_string_feature_value),
            (Aravis.GcBoolean, d.get_boolean_feature_value),
            (Aravis.GcFloat, d.get_float_feature_value),
            (Aravis.GcInteger, d.get_integer_feature_value),
            (Aravis.GcString, d.get_string_feature_value),
        ):
            if isinstance(node, kind):
                value: bool | int | float | str = self._call(lambda g=getter: g(name), f"read {name}", name)
                return value
        raise FeatureUnsupported(name, f"{name} of the camera {self._model()} is a {type(node).__name__}, not a value")

    def open(self) -> None:
        if self._camera is not None:
            return
        self._connect()
        self._opened = True
        self._start()

    def configure(self, settings: CameraSettings) -> None:
        self._ensure_connected()
        self._check(settings)
        self._call(self._camera.stop_acquisition, "stop the acquisition")
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
        if not self._has("TriggerSoftware"):
            raise FeatureUnsupported("TriggerSoftware", f"the camera {self._model()} has no software trigger")
        self._call(lambda: self._device.execute_command("TriggerSoftware"), "fire a software trigger")

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
        self._handler_id = device.connect("control-lost", self._on_control_lost, self._generation)
        try:
            self._make_stream()
            self._info = self._read_info()
            self._exposure_us = self._read_exposure()
        except DriverError as e:
            self._release(background=True)
            raise DriverInitError(f"the camera {self._name()} opened but cannot stream: {e}") from e

    def _make_stream(self) -> None:
        """A stream with ``n_buffers`` buffers of the current payload (a new one replaces the old)."""
        self._stream = None
        camera = self._camera
        if camera.is_gv_device() and self.packet_size is not None:
            self._call(lambda: camera.gv_set_packet_size(int(self.packet_size)), "set the packet size")
            self._device.set_packet_size_adjustment(Aravis.GvPacketSizeAdjustment.NEVER)
        if isinstance(self._device, Aravis.GvDevice):  # the option is read when the stream is created
            self._device.set_stream_options(
                Aravis.GvStreamOption.NONE if self.packet_socket else Aravis.GvStreamOption.PACKET_SOCKET_DISABLED
            )
        # Aravis starts the stream's receiving thread here: it inherits this thread's priority
        with thread_nice(_STREAM_THREAD_NICE):
            stream = self._call(lambda: camera.create_stream(None, None), "create a stream")
        if stream is None:
            raise DriverError(f"the camera {self._name()} gave no stream channel")
        if isinstance(stream, Aravis.GvStream):
            if self.socket_buffer_bytes is None:
                stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
            else:
                stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", int(self.socket_buffer_bytes))
            resend = Aravis.GvStreamPacketResend.ALWAYS if self.packet_resend else Aravis.GvStreamPacketResend.NEVER
            stream.set_property("packet-resend", resend)
        payload = int(self._call(camera.get_payload, "read the payload size"))
        for _ in range(self.n_buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._stream = stream

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
                self._check(self._settings)
                self._call(self._camera.stop_acquisition, "stop the acquisition")
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
        objects = [self._stream, self._camera, self._device]
        self._stream = self._camera = self._device = None
        self._handler_id = None
        if background:
            thread = threading.Thread(target=objects.clear, name="aravis-release", daemon=True)
            thread.start()
            self._releasers = [t for t in self._releasers if t.is_alive()] + [thread]
        else:
            objects.clear()

    def _start(self) -> None:
        self._call(self._camera.start_acquisition, "start the acquisition")

    # --- frames ---------------------------------------------------------------------------

    def _frame_from(self, buffer: Any) -> Frame | None:
        """An owned frame from a popped buffer, or None for a failed one; the buffer goes back at once."""
        t_pop_ns = time.monotonic_ns()
        real_minus_mono_ns = time.time_ns() - t_pop_ns
        try:
            status = buffer.get_status()
            if status != Aravis.BufferStatus.SUCCESS:
                self._failed[status.value_nick] += 1
                return None
            width, height = buffer.get_image_width(), buffer.get_image_height()
            code = buffer.get_image_pixel_format()
            dtype = _DTYPE_BY_CODE.get(code)
            if dtype is None:
                raise DriverError(
                    f"the camera {self._name()} sent pixel format 0x{code:08x}; posecell reads "
                    f"{', '.join(_PIXEL_FORMATS)} only"
                )
            x_padding, _ = buffer.get_image_padding()
            seq, t_device_ns = buffer.get_frame_id(), buffer.get_timestamp()
            t_system_ns = buffer.get_system_timestamp()
            image = self._copy_image(buffer, width, height, dtype, x_padding)
        finally:
            self._stream.push_buffer(buffer)
        if image is None:
            self._failed["size-mismatch"] += 1
            return None
        self._n_ok += 1
        previous, self._real_minus_mono_ns = self._real_minus_mono_ns, real_minus_mono_ns
        stepped = previous is not None and abs(real_minus_mono_ns - previous) > _CLOCK_STEP_NS
        return Frame(
            image=image,
            seq=int(seq),
            t_host_ns=t_pop_ns if stepped else arrival_ns(t_pop_ns, int(t_system_ns), real_minus_mono_ns),
            t_device_ns=int(t_device_ns) if t_device_ns else None,
            exposure_us=self._exposure_us,
            meta={
                "system_timestamp_ns": int(t_system_ns),
                "t_popped_ns": t_pop_ns,
                "failed_buffers": dict(self._failed),
                "pixel_format": _NAME_BY_CODE[code],
            },
        )

    @staticmethod
    def _copy_image(buffer: Any, width: int, height: int, dtype: np.dtype[Any], x_padding: int) -> np.ndarray | None:
        """The buffer's pixels in a new (height, width) array: one copy, or two for padded rows."""
        size = ctypes.c_size_t(0)
        data = _lib.arv_buffer_get_image_data(_capsule_pointer(buffer.__gpointer__, None), ctypes.byref(size))
        stride = width * dtype.itemsize + x_padding
        if not data or size.value < stride * height - x_padding:
            return None
        if not x_padding:
            image = np.empty((height, width), dtype)
            ctypes.memmove(image.ctypes.data, data, image.nbytes)
            return image
        rows = np.zeros((height, stride), np.uint8)
        ctypes.memmove(rows.ctypes.data, data, min(size.value, rows.nbytes))
        return np.ascontiguousarray(rows[:, : width * dtype.itemsize]).view(dtype)

    # --- settings -------------------------------------------------------------------------

    def _check(self, s: CameraSettings) -> None:
        """Raise FeatureUnsupported for anything in ``s`` the camera lacks, before changing anything."""
        model = self._model()
        if s.pixel_format is not None:
            if s.pixel_format not in _PIXEL_FORMATS:
                raise FeatureUnsupported(
                    "PixelFormat", f"posecell reads {', '.join(_PIXEL_FORMATS)}, not {s.pixel_format}"
                )
            self._need_entry("PixelFormat", s.pixel_format, "pixel format")
        if s.roi is not None:
            x, y, w, h = s.roi
            for name in ("OffsetX", "OffsetY", "Width", "Height"):
                self._need(name, "the region of interest cannot be set")
            if min(x, y) < 0 or w <= 0 or h <= 0:
                raise DriverError(f"the region of interest {s.roi} is not a valid x, y, width, height")
            if self._has("SensorWidth") and self._has("SensorHeight"):
                sw, sh = self._get_int("SensorWidth"), self._get_int("SensorHeight")
                if x + w > sw or y + h > sh:
                    raise DriverError(f"the region of interest {s.roi} exceeds the {sw} x {sh} sensor of {model}")
        if s.exposure_us is not None:
            self._first("exposure time", "ExposureTime", "ExposureTimeAbs")
        if s.gain_db is not None:
            self._first("gain", "Gain", "GainRaw")
        if s.frame_rate_hz is not None and s.trigger is TriggerMode.FREE_RUN:
            self._first("frame rate", "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
        if s.trigger is not TriggerMode.FREE_RUN:
            self._need("TriggerMode", "it cannot be triggered")
            source = "Software" if s.trigger is TriggerMode.SOFTWARE else s.trigger_line
            self._need_entry("TriggerSource", source, "trigger source")
            if s.trigger is TriggerMode.SOFTWARE:
                self._need("TriggerSoftware", "it cannot be triggered by software")
        if s.strobe is not None and s.strobe.enabled:
            self._check_strobe(s.strobe)

    def _check_strobe(self, st: StrobeSettings) -> None:
        why = (
            f"the ring light cannot be strobed from its line {st.line} (use a camera with SFNC digital I/O, "
            "or set strobe.enabled = false)"
        )
        for name in ("LineSelector", "LineMode", "LineSource"):
            self._need(name, why)
        self._need_entry("LineSelector", st.line, "I/O line", why)
        self._need_entry("LineMode", "Output", "line mode", why)
        self._need_entry("LineSource", st.source, "line source", why)
        if st.inverted:
            self._need("LineInverter", "the strobe cannot be inverted")
        if st.source.startswith("Timer"):
            for name in ("TimerSelector", "TimerDuration", "TimerTriggerSource"):
                self._need(name, f"the strobe source {st.source} cannot be used")
            self._need_entry("TimerSelector", st.source.removesuffix("Active"), "timer")
            if st.delay_us:
                self._need("TimerDelay", "the strobe cannot be delayed")
            if st.duration_us is None or st.duration_us <= 0:
                raise DriverError(f"the strobe source {st.source} needs strobe.duration_us > 0")

    def _apply(self, s: CameraSettings) -> None:
        """Write ``s`` to the stopped camera (checked by ``_check``); the caller makes a new stream."""
        if s.roi is not None:
            x, y, w, h = s.roi
            self._set("OffsetX", 0)  # offsets first to 0, so that the new size always fits the sensor
            self._set("OffsetY", 0)
            self._set("Width", int(w))
            self._set("Height", int(h))
            self._set("OffsetX", int(x))
            self._set("OffsetY", int(y))
        if s.pixel_format is not None:
            self._set("PixelFormat", s.pixel_format)
        if s.exposure_us is not None:
            self._set_if_entry("ExposureAuto", "Off")
            self._set_if_entry("ExposureMode", "Timed")
            self._set(self._first("exposure time", "ExposureTime", "ExposureTimeAbs"), float(s.exposure_us))
        if s.gain_db is not None:
            self._set_if_entry("GainAuto", "Off")
            self._set_if_entry("GainSelector", "All")
            if self._has("Gain"):
                self._set("Gain", float(s.gain_db))
            else:
                log.warning(
                    "camera %s has GainRaw only (device units, not dB); writing %d", self._model(), round(s.gain_db)
                )
                self._set("GainRaw", round(s.gain_db))
        self._apply_trigger(s)
        if s.strobe is not None:
            self._apply_strobe(s.strobe)
        elif self._lit_line is not None:  # no strobe now: put out the ring light this driver lit
            self._apply_strobe(StrobeSettings(enabled=False, line=self._lit_line))
        if self._has("AcquisitionMode"):
            self._set("AcquisitionMode", "Continuous")
        self._exposure_us = self._read_exposure()
        self._info = self._read_info()

    def _apply_trigger(self, s: CameraSettings) -> None:
        selectors = self._entries("TriggerSelector") if self._has("TriggerSelector") else []
        for selector in selectors:  # every trigger off first: a left-over AcquisitionStart trigger stalls a free run
            self._set("TriggerSelector", selector)
            self._set("TriggerMode", "Off")
        if not selectors and self._has("TriggerMode"):
            self._set("TriggerMode", "Off")
        if s.trigger is TriggerMode.FREE_RUN:
            if s.frame_rate_hz is not None:
                if self._has("AcquisitionFrameRateEnable"):
                    self._set("AcquisitionFrameRateEnable", True)
                name = self._first("frame rate", "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
                self._set(name, float(s.frame_rate_hz))
            return
        if self._has("AcquisitionFrameRateEnable"):
            self._set("AcquisitionFrameRateEnable", False)  # a rate limit would swallow triggers
        if "FrameStart" in selectors:
            self._set("TriggerSelector", "FrameStart")
        if s.trigger is TriggerMode.SOFTWARE:
            self._set("TriggerSource", "Software")
        else:
            self._set("TriggerSource", s.trigger_line)
            self._set_if_entry("TriggerActivation", "RisingEdge")
        self._set("TriggerMode", "On")

    def _apply_strobe(self, st: StrobeSettings) -> None:
        if not st.enabled:
            # switch the line's source off where the camera allows it; leave a camera without lines alone
            if self._has("LineSelector") and st.line in self._entries("LineSelector"):
                self._set("LineSelector", st.line)
                self._set_if_entry("LineSource", "Off")
            self._lit_line = None
            return
        self._set("LineSelector", st.line)
        self._set("LineMode", "Output")
        if st.source.startswith("Timer"):
            self._set("TimerSelector", st.source.removesuffix("Active"))
            self._set("TimerDuration", float(st.duration_us or 0.0))
            if self._has("TimerDelay"):
                self._set("TimerDelay", float(st.delay_us))
            self._set("TimerTriggerSource", "ExposureStart")
        elif st.delay_us or st.duration_us is not None:
            log.warning(
                "camera %s: strobe delay/duration apply to timer sources only; %s follows the exposure",
                self._model(),
                st.source,
            )
        self._set("LineSelector", st.line)  # timer nodes may share selectors on some cameras: select again
        self._set("LineSource", st.source)
        if self._has("LineInverter"):
            self._set("LineInverter", bool(st.inverted))
        self._lit_line = st.line

    # --- feature access -------------------------------------------------------------------

    def _has(self, name: str) -> bool:
        try:
            return bool(self._device.is_feature_available(name))
        except GLib.Error:
            return False

    def _need(self, name: str, consequence: str) -> None:
        if not self._has(name):
            raise FeatureUnsupported(name, f"the camera {self._model()} has no {name}; {consequence}")

    def _need_entry(self, name: str, entry: str, what: str, consequence: str | None = None) -> None:
        consequence = consequence or f"the {what} {entry} cannot be set"
        self._need(name, consequence)
        entries = self._entries(name)
        if entry not in entries:
            raise FeatureUnsupported(
                name,
                f"the camera {self._model()} has no {what} {entry} "
                f"(it offers {', '.join(entries) or 'none'}); {consequence}",
            )

    def _first(self, what: str, *names: str) -> str:
        for name in names:
            if self._has(name):
                return name
        raise FeatureUnsupported(names[0], f"the camera {self._model()} has no {what} ({' or '.join(names)})")

    def _entries(self, name: str) -> list[str]:
        return list(
            self._call(
                lambda: self._device.dup_available_enumeration_feature_values_as_strings(name),
                f"read the entries of {name}",
                name,
            )
            or []
        )

    def _set(self, name: str, value: bool | int | float | str) -> None:
        d = self._device
        setter = (
            d.set_boolean_feature_value
            if isinstance(value, bool)
            else d.set_integer_feature_value
            if isinstance(value, int)
            else d.set_float_feature_value
            if isinstance(value, float)
            else d.set_string_feature_value
        )
        self._call(lambda: setter(name, value), f"set {name} to {value}", name)

    def _set_if_entry(self, name: str, entry: str) -> None:
        if self._has(name) and entry in self._entries(name):
            self._set(name, entry)

    def _get_int(self, name: str) -> int:
        return int(self._call(lambda: self._device.get_integer_feature_value(name), f"read {name}", name))

    def _call(self, fn: Any, what: str, feature: str | None = None) -> Any:
        """Run an Aravis call; a GLib error becomes a DriverError subclass naming the feature."""
        try:
            return fn()
        except GLib.Error as e:
            if e.domain == _DEVICE_ERROR and e.code in _LINK_ERRORS:
                self._lost.set()
                raise DriverDisconnected(
                    f"the camera {self._name()} did not answer while trying to {what} ({e.message})"
                ) from e
            if feature is not None and (
                (e.domain == _DEVICE_ERROR and e.code == int(Aravis.DeviceError.FEATURE_NOT_FOUND))
                or (e.domain == _GC_ERROR and e.code == int(Aravis.GcError.ENUM_ENTRY_NOT_FOUND))
            ):
                raise FeatureUnsupported(
                    feature, f"the camera {self._model()} has no {feature} (trying to {what})"
                ) from e
            raise DriverError(f"the camera {self._name()} refused to {what}: {e.message}") from e

    def _read_exposure(self) -> float:
        for name in ("ExposureTime", "ExposureTimeAbs"):
            if self._has(name):
                return float(self._call(lambda n=name: self._device.get_float_feature_value(n), f"read {name}", name))
        return float("nan")

    def _read_info(self) -> CameraInfo:
        camera = self._camera
        has = self._has
        features = [
            ("strobe", has("LineSelector") and has("LineMode") and has("LineSource")),
            ("gain", has("Gain") or has("GainRaw")),
            ("timer", has("TimerSelector") and has("TimerDuration")),
            ("frame_rate", has("AcquisitionFrameRate") or has("AcquisitionFrameRateAbs")),
            ("trigger", has("TriggerMode")),
        ]
        return CameraInfo(
            driver="aravis",
            model=self._call(camera.get_model_name, "read the model name") or "",
            serial=self._call(camera.get_device_serial_number, "read the serial number") or "",
            width=self._get_int("Width"),
            height=self._get_int("Height"),
            pixel_format=str(
                self._call(
                    lambda: self._device.get_string_feature_value("PixelFormat"), "read PixelFormat", "PixelFormat"
                )
            )
            if has("PixelFormat")
            else "",
            features=tuple(name for name, present in features if present),
        )

    def _model(self) -> str:
        return self._info.model if self._info is not None and self._info.model else self._name()

    def _name(self) -> str:
        return repr(self.device) if self.device else "(first found)"

    def __repr__(self) -> str:
        state = "open" if self._camera is not None else ("lost" if self._opened else "closed")
        return f"AravisCamera(device={self.device!r}, {state})"
