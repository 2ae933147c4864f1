"""A GigE Vision camera on loopback: Aravis' own fake GV camera, serving images we render.

``GvStandIn`` runs libaravis' ``ArvGvFakeCamera`` in this process. It answers
GVCP and streams GVSP on a loopback address like a real network camera, so the
real :class:`drivers.camera.aravis.AravisCamera` opens it by IP address and
goes through discovery, GenICam XML, register access, packets, heartbeat and
control privilege exactly as with hardware.

What it adds to Aravis' fake camera:

* a GenICam description (``gv_camera.xml``) with the SFNC strobe features
  (``LineSelector/LineMode/LineSource/LineInverter``), ``Gain`` in dB,
  ``ExposureTime``, a timer and Mono12, which the fake camera stores and reads
  back; ``xml_path=None`` keeps Aravis' built-in description (no lines);
* image content from ``frame_source(t_host_ns, lit, exposure_us)``: libaravis'
  fill-pattern hook is set through ctypes, because the PyGObject binding of
  ``arv_fake_camera_set_fill_pattern`` crashes the process (Aravis 0.8.26);
* exposure: ``ExposureTime`` may be written while the camera acquires (as SFNC allows and
  cameras do); the fake reads it as it fills each frame, so the change holds from the next
  frame exposed, and ``frame_source`` is told it: :func:`cell_frame_source` renders the cell's
  targets brighter or dimmer with it, as the simulated camera does (gain is not in the image);
* exposure timing: a frame's exposure starts when the fake camera fills it (or, rendering
  ahead, at the instant its image was rendered for), its device timestamp is that start on the
  host's real-time clock (ns), the image shows the scene at mid-exposure, and the frame leaves
  no earlier than the end of its exposure, as a camera reads out after exposing. With
  ``render_ahead`` a background thread renders each next frame for the fake camera's next
  frame slot (``AcquisitionFramePeriod`` on the real-time clock) that it can finish in time;
  a frame with nothing rendered for it (the first, a software trigger, a changed exposure)
  starts its exposure later by the expected render time. So a frame always leaves a small,
  steady delay after its exposure, as from a camera, rather than tens or hundreds of
  milliseconds of rendering later, which a clock mapping would take for transfer latency;
* ``lit``: True only while the camera's registers say the ring-light line is
  an output driven by ``ExposureActive`` (or by ``Timer0Active`` with the timer
  started by the exposure and a duration > 0) and not inverted, so a test can
  show that the targets stay dark until the driver configures the strobe;
* ROI: ``frame_source`` draws the whole sensor; the stand-in cuts the window
  at ``OffsetX/OffsetY`` of ``Width x Height`` the driver set;
* a lock file per address, so that test suites in parallel processes wait
  for each other instead of talking to each other's camera.

What it does not model: packet loss unless asked (``lost_packet_ratio``),
network latency, clock drift (device timestamps are the host's real-time
clock), motion blur, gain in the image, partial strobe overlap (the light is
on or off for a whole frame), hardware triggers (with ``TriggerSource = Line0``
no frame comes), packed pixel formats. Frame ids start near 65400 and wrap at
65535 (Aravis' choice).

Addresses: Aravis' fake camera listens only on an address assigned to a
network interface; on a stock Linux host that is 127.0.0.1 alone (binding
127.0.0.2 fails, ``is_running()`` is false). Use another loopback address only
after adding it (``ip addr add 127.0.0.2/8 dev lo``).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import ctypes
import fcntl
import logging
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from drivers.timing import thread_nice

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis
except (ImportError, ValueError) as e:  # ValueError: gi is there but the Aravis typelib is not
    raise ImportError(f"Aravis 0.8 for Python is missing (Debian: python3-gi gir1.2-aravis-0.8): {e}") from e

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_XML", "FrameSource", "GvStandIn", "cell_frame_source", "contract_camera"]

DEFAULT_XML = Path(__file__).with_name("gv_camera.xml")

FrameSource = Callable[[int, bool, float], np.ndarray]
"""``frame_source(t_host_ns, lit, exposure_us) -> (H, W) uint8`` (or uint16): the whole sensor at
that instant (``time.monotonic_ns()``; the stand-in asks for mid-exposure), exposed that long."""

_GVCP_PORT = 3956

# ArvFakeCamera's register map (arvfakecamera.h, Aravis 0.8) and the additions of gv_camera.xml
_REG_WIDTH, _REG_HEIGHT = 0x100, 0x104
_REG_SENSOR_HEIGHT, _REG_SENSOR_WIDTH = 0x118, 0x11C
_REG_OFFSET_X, _REG_OFFSET_Y = 0x130, 0x134
_REG_FRAME_PERIOD_US, _REG_TRIGGER_MODE = 0x138, 0x300  # the fake's free-run period; 1 = triggered
_REG_MODEL_NAME, _MODEL_NAME_SIZE = 0x68, 32  # GigE Vision bootstrap string
_REG_LINE_MODE, _REG_LINE_SOURCE, _REG_LINE_INVERTER, _LINE_STRIDE = 0xA100, 0xA104, 0xA108, 0x10
_REG_TIMER_DURATION, _REG_TIMER_TRIGGER_SOURCE = 0xA310, 0xA318
_LINE_MODE_OUTPUT = 1
_SOURCE_EXPOSURE_ACTIVE, _SOURCE_TIMER0_ACTIVE = 1, 2
_TIMER_TRIGGER_EXPOSURE_START = 1
_STALE_AHEAD_NS = 500_000_000  # a frame rendered ahead for an exposure longer ago than this is dropped
_RESULT_TIMEOUT_S = 5.0  # the longest a fill waits for the frame being rendered ahead for it
_STILL_RENDERS_KEPT = 8  # cell_frame_source: renders of a still cell kept (by ring light and exposure)

_FillPattern = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


def _libaravis() -> ctypes.CDLL:
    lib = ctypes.CDLL("libaravis-0.8.so.0")  # CDLL: calls release the GIL, so the fake's thread can call back
    sigs: dict[str, tuple[Any, list[Any]]] = {
        "arv_fake_camera_set_fill_pattern": (None, [ctypes.c_void_p, _FillPattern, ctypes.c_void_p]),
        "arv_fake_camera_read_register": (
            ctypes.c_int,
            [ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint32)],
        ),
        "arv_fake_camera_write_register": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32]),
        "arv_fake_camera_write_memory": (
            ctypes.c_int,
            [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_char_p],
        ),
        "arv_fake_camera_get_payload": (ctypes.c_size_t, [ctypes.c_void_p]),
        "arv_buffer_get_image_width": (ctypes.c_int, [ctypes.c_void_p]),
        "arv_buffer_get_image_height": (ctypes.c_int, [ctypes.c_void_p]),
        "arv_buffer_get_data": (ctypes.c_void_p, [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]),
        "arv_buffer_get_timestamp": (ctypes.c_uint64, [ctypes.c_void_p]),
        "arv_buffer_set_timestamp": (None, [ctypes.c_void_p, ctypes.c_uint64]),
    }
    for name, (restype, argtypes) in sigs.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes
    return lib


_lib = _libaravis()
_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype, _capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]


def _gobject_pointer(obj: Any) -> int:
    """The C pointer behind a PyGObject wrapper (for the ctypes calls PyGObject cannot make)."""
    return int(_capsule_pointer(obj.__gpointer__, None))


class GvStandIn:
    """Aravis' fake GigE Vision camera on a loopback address, showing ``frame_source``'s images.

    Parameters
    ----------
    frame_source : ``(t_host_ns, lit, exposure_us) -> (height, width) uint8`` (uint16 is taken as
        is for the 16-bit formats, uint8 is shifted up to them): the scene at mid-exposure,
        ``t_host_ns`` on ``time.monotonic_ns()``, exposed for the camera's ``ExposureTime`` in us.
        Called once per frame in the fake camera's thread, or with ``render_ahead`` mostly in the
        stand-in's render thread (so it must be thread-safe).
    address : IPv4 address to listen on (one stand-in per address; see the module note).
    serial : serial number the camera reports (at most 15 characters).
    width, height : sensor size in px; also the initial ROI.
    xml_path : GenICam XML served by the camera; None serves Aravis' built-in one (no strobe lines,
        no Gain, ExposureTimeAbs) for tests of cameras that lack features.
    model : DeviceModelName (at most 31 characters).
    ring_light_line : the output line the ring light is wired to (``"Line1"``).
    trigger_rate_hz : how often the fake looks for a software trigger (Aravis' default is 25 Hz).
    lost_packet_ratio : fraction of GVSP packets the fake drops on purpose (0 = none).
    lock_timeout_s : how long ``start`` waits for another process using the same address.
    render_ahead : render each frame before the fake camera asks for it (see the module note);
        for sources that take longer than a frame period to draw.
    readout_nice : nice value for the fake camera's thread (it times the exposures and sends the
        frames), when the process may lower it; the render thread keeps the caller's. None: no change.
    """

    def __init__(
        self,
        frame_source: FrameSource,
        address: str = "127.0.0.1",
        serial: str = "POSECELL-SIM",
        width: int = 1300,
        height: int = 1030,
        xml_path: str | os.PathLike[str] | None = DEFAULT_XML,
        model: str = "posecell GV stand-in",
        ring_light_line: str = "Line1",
        trigger_rate_hz: float = 100.0,
        lost_packet_ratio: float = 0.0,
        lock_timeout_s: float = 60.0,
        render_ahead: bool = False,
        readout_nice: int | None = None,
    ) -> None:
        if not (ring_light_line.startswith("Line") and ring_light_line[4:].isdigit()):
            raise ValueError(f"ring_light_line must be LineN, got {ring_light_line!r}")
        if not 0 < len(serial.encode()) < 16:
            raise ValueError(f"a GigE Vision serial number has 1 to 15 characters, got {serial!r}")
        if width <= 0 or height <= 0:
            raise ValueError(f"the sensor size must be positive, got {width} x {height}")
        self.frame_source = frame_source
        self.address = address
        self.serial = serial
        self.width, self.height = int(width), int(height)
        self.xml_path = None if xml_path is None else str(xml_path)
        self.model = model
        self.ring_light_line = ring_light_line
        self.trigger_rate_hz = float(trigger_rate_hz)
        self.lost_packet_ratio = float(lost_packet_ratio)
        self.lock_timeout_s = float(lock_timeout_s)
        self.render_ahead = bool(render_ahead)
        self.readout_nice = readout_nice

        self.frames_served = 0
        self.frames_rendered_ahead = 0  # frames served from the render thread (the rest rendered in the fill)
        # how long after its exposure ended each recent frame went out, s (its scheduling delay)
        self.readout_delays_s: collections.deque[float] = collections.deque(maxlen=200)
        self.lit_frames = 0
        self.errors: list[str] = []  # exceptions raised in the fill callback (it must not raise into C)

        self._line = int(ring_light_line[4:])
        self._gv: Any = None
        self._fake: Any = None
        self._fake_ptr = 0
        self._callback: Any = None
        self._lock_fd: int | None = None
        self._mutex = threading.Lock()
        # rendering ahead: the render thread, the frame it renders (exposure start ns, lit, exposure
        # ns, future), the last exposure start served, and recent render durations (s)
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: tuple[int, bool, int, concurrent.futures.Future[np.ndarray]] | None = None
        self._last_start_ns = -1
        self._render_s: collections.deque[float] = collections.deque(maxlen=8)

    # --- lifecycle -------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._gv is not None

    def start(self) -> None:
        """Listen on the address and serve frames; idempotent."""
        with self._mutex:
            if self._gv is not None:
                return
            locked_here = self._lock_fd is None
            self._acquire_lock()
            try:
                self._start_fake()
            except BaseException:
                if locked_here:
                    self._release_lock()
                raise
        log.info("GigE Vision stand-in %s listening on %s", self.serial, self.address)

    def _start_fake(self) -> None:
        self._check_port_free()
        if self.xml_path is not None and not os.path.isfile(self.xml_path):
            raise FileNotFoundError(f"no GenICam XML at {self.xml_path}")
        if self.render_ahead:  # its thread starts here, at this thread's priority
            self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="gv-render-ahead")
            self._pool.submit(lambda: None).result()
            self._pending, self._last_start_ns = None, -1
        with thread_nice(self.readout_nice):  # the fake's thread starts here and inherits it
            gv = Aravis.GvFakeCamera.new_full(self.address, self.serial, self.xml_path)
        if not gv.is_running():
            raise RuntimeError(
                f"Aravis' fake camera cannot listen on {self.address}: it binds only addresses of a network "
                "interface (127.0.0.1 on a stock host; add others with `ip addr add 127.0.0.N/8 dev lo`)"
            )
        if self.lost_packet_ratio:
            gv.set_property("gvsp-lost-ratio", self.lost_packet_ratio)
        fake = gv.get_fake_camera()
        ptr = _gobject_pointer(fake)
        for address, value in (
            (_REG_SENSOR_WIDTH, self.width),
            (_REG_SENSOR_HEIGHT, self.height),
            (_REG_WIDTH, self.width),
            (_REG_HEIGHT, self.height),
        ):
            _lib.arv_fake_camera_write_register(ptr, address, value)
        name = self.model.encode()[: _MODEL_NAME_SIZE - 1].ljust(_MODEL_NAME_SIZE, b"\0")
        _lib.arv_fake_camera_write_memory(ptr, _REG_MODEL_NAME, _MODEL_NAME_SIZE, name)
        fake.set_trigger_frequency(self.trigger_rate_hz)
        self._callback = _FillPattern(self._fill)  # referenced until the pattern is reset
        _lib.arv_fake_camera_set_fill_pattern(ptr, self._callback, None)
        self._gv, self._fake, self._fake_ptr = gv, fake, ptr

    def stop(self) -> None:
        """Stop answering (as a camera pulled off the network); the address stays reserved for ``start``."""
        with self._mutex:
            if self._gv is None:
                return
            _lib.arv_fake_camera_set_fill_pattern(self._fake_ptr, ctypes.cast(None, _FillPattern), None)
            # the reset takes the fake's fill mutex: no callback runs past this line, so both can go
            self._callback = None
            self._gv = self._fake = None  # joins the fake's thread and closes its sockets
            self._fake_ptr = 0
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool, self._pending = None, None
        log.info("GigE Vision stand-in %s on %s stopped", self.serial, self.address)

    def close(self) -> None:
        """Stop and give the address back to other processes."""
        self.stop()
        self._release_lock()

    def __enter__(self) -> GvStandIn:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"GvStandIn({self.address}, serial={self.serial!r}, {'running' if self.running else 'stopped'})"

    # --- introspection for tests -----------------------------------------------------------

    def read_register(self, address: int) -> int:
        """A 32-bit register of the running fake camera, as the camera itself sees it."""
        if not self._fake_ptr:
            raise RuntimeError("the stand-in is not running")
        return self._register(address)

    def strobe_lit(self) -> bool:
        """Whether the ring light fires with the camera's current line configuration."""
        if not self._fake_ptr:
            return False
        return self._lit()

    # --- the fake camera's thread ------------------------------------------------------------

    def _fill(self, buffer: int, _data: int, exposure_us: int, _gain: int, pixel_format: int) -> None:
        # called by libaravis with its fill mutex held; exceptions must not escape into C
        try:
            t_call_ns = time.monotonic_ns()
            exposure_ns = int(exposure_us) * 1000
            width = _lib.arv_buffer_get_image_width(buffer)
            height = _lib.arv_buffer_get_image_height(buffer)
            size = ctypes.c_size_t(0)
            data = _lib.arv_buffer_get_data(buffer, ctypes.byref(size))  # size reads 0 here: use the payload
            payload = _lib.arv_fake_camera_get_payload(self._fake_ptr)
            lit = self._lit()
            if self._pool is not None:
                t_start_ns, sensor, ahead = self._take_ahead(t_call_ns, lit, exposure_ns)
                self._prepare_ahead(t_start_ns, lit, exposure_ns)  # renders while this frame waits
            else:
                t_start_ns, ahead = t_call_ns, False
                sensor = self.frame_source(t_start_ns + exposure_ns // 2, lit, exposure_ns * 1e-3)
            window = self._window(
                np.asarray(sensor),
                self._register(_REG_OFFSET_X),
                self._register(_REG_OFFSET_Y),
                width,
                height,
                pixel_format,
            )
            ctypes.memmove(data, window.ctypes.data, min(window.nbytes, payload))
            # the device clock is the host's real-time clock; the stamp is the exposure start
            _lib.arv_buffer_set_timestamp(buffer, max(0, t_start_ns + time.time_ns() - time.monotonic_ns()))
            wait_ns = t_start_ns + exposure_ns - time.monotonic_ns()
            if wait_ns > 0:  # read out after the exposure ends, not before
                time.sleep(wait_ns * 1e-9)
            self.readout_delays_s.append((time.monotonic_ns() - t_start_ns - exposure_ns) * 1e-9)
            self.frames_served += 1
            self.frames_rendered_ahead += ahead
            self.lit_frames += lit
        except Exception as e:  # a bug in frame_source: keep serving (black frames) and record it
            if len(self.errors) < 100:
                self.errors.append(f"{type(e).__name__}: {e}")
            log.exception("GigE Vision stand-in %s: frame_source failed", self.serial)

    # --- rendering ahead (the fake camera's thread, but for the renders themselves) ------------

    def _render(self, t_start_ns: int, lit: bool, exposure_ns: int) -> np.ndarray:
        t0 = time.perf_counter()
        image = self.frame_source(t_start_ns + exposure_ns // 2, lit, exposure_ns * 1e-3)
        self._render_s.append(time.perf_counter() - t0)
        return image

    def _lead_ns(self) -> int:
        """How long before an exposure its rendering must start: the recent worst render time and a margin."""
        worst_s = max(self._render_s) if self._render_s else 0.2
        return int((1.25 * worst_s + 0.003) * 1e9)

    def _take_ahead(self, t_call_ns: int, lit: bool, exposure_ns: int) -> tuple[int, np.ndarray, bool]:
        """The frame to serve now: the one rendered ahead for about now, else one exposed a render time from now."""
        pending, self._pending = self._pending, None
        if pending is not None:
            t_start_ns, p_lit, p_exposure_ns, future = pending
            usable = (
                p_lit == lit
                and p_exposure_ns == exposure_ns
                and t_start_ns > self._last_start_ns
                and t_call_ns - t_start_ns < _STALE_AHEAD_NS
            )
            if usable:
                try:
                    image = future.result(timeout=_RESULT_TIMEOUT_S)
                except Exception:  # late, cancelled or failed: draw it here (a failure is recorded then)
                    image = None
                if image is not None:
                    self._last_start_ns = t_start_ns
                    return t_start_ns, image, True
            future.cancel()
        # nothing rendered for this frame (the first one, a trigger, new settings): expose it once it
        # can be drawn, so that it still leaves right after its exposure
        t_start_ns = max(t_call_ns + self._lead_ns(), self._last_start_ns + 1)
        image = self._render(t_start_ns, lit, exposure_ns)
        self._last_start_ns = t_start_ns
        return t_start_ns, image, False

    def _prepare_ahead(self, t_served_ns: int, lit: bool, exposure_ns: int) -> None:
        """Render the next frame for the fake's first frame slot after this one that rendering can make."""
        period_us = self._register(_REG_FRAME_PERIOD_US)
        if self._pool is None or self._register(_REG_TRIGGER_MODE) != 0 or period_us == 0:
            return  # triggered: the next exposure's instant is not known in advance
        period_ns = period_us * 1000
        now_ns = time.monotonic_ns()
        real_minus_mono_ns = time.time_ns() - now_ns
        # the fake starts frames at multiples of the period on the real-time clock
        earliest_ns = max(now_ns + self._lead_ns(), t_served_ns + period_ns // 2) + real_minus_mono_ns
        t_start_ns = -(-earliest_ns // period_ns) * period_ns - real_minus_mono_ns
        future = self._pool.submit(self._render, t_start_ns, lit, exposure_ns)
        self._pending = (t_start_ns, lit, exposure_ns, future)

    @staticmethod
    def _window(sensor: np.ndarray, x0: int, y0: int, width: int, height: int, pixel_format: int) -> np.ndarray:
        """The ROI of ``sensor`` in the camera's pixel format, zero where the source image ends."""
        bits = (pixel_format >> 16) & 0xFF  # PFNC: bits per pixel in the code's third byte
        if sensor.ndim != 2 or bits not in (8, 16):
            raise ValueError(
                f"frame_source must give a 2D image for Mono8/Mono12/Mono16, got shape "
                f"{sensor.shape} for pixel format 0x{pixel_format:08x}"
            )
        dtype = np.dtype(np.uint8) if bits == 8 else np.dtype("<u2")
        out = np.zeros((height, width), dtype)
        part = sensor[y0 : y0 + height, x0 : x0 + width]
        h, w = part.shape
        if bits == 8:
            out[:h, :w] = np.clip(part, 0, 255) if part.dtype != np.uint8 else part
        elif part.dtype == np.uint8:
            shift = 4 if pixel_format == Aravis.PIXEL_FORMAT_MONO_12 else 8
            out[:h, :w] = part.astype(np.uint16) << shift
        else:
            out[:h, :w] = part
        return out

    def _lit(self) -> bool:
        line = self._line * _LINE_STRIDE
        if self._register(_REG_LINE_MODE + line) != _LINE_MODE_OUTPUT:
            return False
        if self._register(_REG_LINE_INVERTER + line) != 0:
            return False
        source = self._register(_REG_LINE_SOURCE + line)
        if source == _SOURCE_EXPOSURE_ACTIVE:
            return True
        if source == _SOURCE_TIMER0_ACTIVE:
            duration_us = np.frombuffer(self._register(_REG_TIMER_DURATION).to_bytes(4, "big"), ">f4")[0]
            started = self._register(_REG_TIMER_TRIGGER_SOURCE) == _TIMER_TRIGGER_EXPOSURE_START
            return bool(started and duration_us > 0)
        return False

    def _register(self, address: int) -> int:
        value = ctypes.c_uint32(0)
        _lib.arv_fake_camera_read_register(self._fake_ptr, address, ctypes.byref(value))
        return int(value.value)

    # --- one stand-in per address --------------------------------------------------------------

    def _acquire_lock(self) -> None:
        if self._lock_fd is not None:
            return
        path = Path(tempfile.gettempdir()) / f"posecell-gv-standin-{self.address}.lock"
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        deadline = time.monotonic() + self.lock_timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise RuntimeError(
                        f"another GigE Vision stand-in has held {self.address} for {self.lock_timeout_s:.0f} s ({path})"
                    ) from None
                time.sleep(0.05)
        self._lock_fd = fd

    def _release_lock(self) -> None:
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def _check_port_free(self) -> None:
        # a second fake camera on a taken address reports running but never answers: say so instead
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((self.address, _GVCP_PORT))
            except OSError as e:
                raise RuntimeError(
                    f"UDP port {_GVCP_PORT} on {self.address} is taken by another GigE Vision "
                    f"device or program ({e.strerror})"
                ) from e


def cell_frame_source(cell: Any, t0_ns: int | None = None) -> FrameSource:
    """A ``frame_source`` showing a :class:`service.sim.cell.SimCell` at ``(t_host_ns - t0_ns)`` s.

    Noise-free renders whose targets' brightness follows the exposure as the simulated camera's
    do (``target_dn`` at ``REFERENCE_EXPOSURE_US``); a cell whose program holds still is rendered
    once per ring-light state and exposure (the last few kept). Safe to call from several threads
    (the cell is read only). A moving cell takes tens of milliseconds per frame: serve it with
    ``GvStandIn(..., render_ahead=True)``.
    """
    from drivers.camera.sim import REFERENCE_EXPOSURE_US
    from service.sim.render import RenderSettings

    t0 = time.monotonic_ns() if t0_ns is None else t0_ns
    still = getattr(cell.config, "program", None) == "hold"
    cache: dict[tuple[bool, float], np.ndarray] = {}
    cache_lock = threading.Lock()  # the render thread and the fake camera's thread both ask

    def render(t_host_ns: int, lit: bool, exposure_us: float) -> np.ndarray:
        key = (lit, exposure_us)
        with cache_lock:
            cached = cache.get(key) if still else None
        if cached is not None:
            return cached
        settings = RenderSettings(exposure_scale=exposure_us / REFERENCE_EXPOSURE_US)
        image: np.ndarray = cell.render((t_host_ns - t0) * 1e-9, None, settings, lit=lit).image
        if still:
            with cache_lock:
                if len(cache) >= _STILL_RENDERS_KEPT:  # an exposure control's steps: keep the newest
                    del cache[next(iter(cache))]
                cache[key] = image
        return image

    return render


@contextlib.contextmanager
def contract_camera(address: str = "127.0.0.1", **camera_options: Any) -> Iterator[Any]:
    """The Aravis driver (not yet opened) on a stand-in showing the simulated cell, for contract suites."""
    from drivers.camera.aravis import AravisCamera
    from service.sim.cell import CellConfig, SimCell

    camera_options.setdefault("packet_size", 8192)  # loopback: the fake's 1400-byte default loses frames
    cell = SimCell(CellConfig(program="hold"))
    with GvStandIn(
        cell_frame_source(cell),
        address=address,
        serial="POSECELL-CT",
        width=cell.camera.width,
        height=cell.camera.height,
    ):
        camera = AravisCamera(address, **camera_options)
        try:
            yield camera
        finally:
            camera.close()
