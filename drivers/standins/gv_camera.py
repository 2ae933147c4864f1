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
* image content from ``frame_source(t_host_ns, lit)``: libaravis' fill-pattern
  hook is set through ctypes, because the PyGObject binding of
  ``arv_fake_camera_set_fill_pattern`` crashes the process (Aravis 0.8.26);
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
clock, µs resolution), exposure time or gain in the image (``frame_source``
decides), partial strobe overlap (the light is on or off for a whole frame),
hardware triggers (with ``TriggerSource = Line0`` no frame comes), packed pixel
formats. Frame ids start near 65400 and wrap at 65535 (Aravis' choice).

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

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis
except (ImportError, ValueError) as e:  # ValueError: gi is there but the Aravis typelib is not
    raise ImportError(f"Aravis 0.8 for Python is missing (Debian: python3-gi gir1.2-aravis-0.8): {e}") from e

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_XML", "FrameSource", "GvStandIn", "cell_frame_source", "contract_camera"]

DEFAULT_XML = Path(__file__).with_name("gv_camera.xml")

FrameSource = Callable[[int, bool], np.ndarray]
"""``frame_source(t_host_ns, lit) -> (H, W) uint8`` (or uint16): the whole sensor at that instant."""

_GVCP_PORT = 3956

# ArvFakeCamera's register map (arvfakecamera.h, Aravis 0.8) and the additions of gv_camera.xml
_REG_WIDTH, _REG_HEIGHT = 0x100, 0x104
_REG_SENSOR_HEIGHT, _REG_SENSOR_WIDTH = 0x118, 0x11C
_REG_OFFSET_X, _REG_OFFSET_Y = 0x130, 0x134
_REG_MODEL_NAME, _MODEL_NAME_SIZE = 0x68, 32  # GigE Vision bootstrap string
_REG_LINE_MODE, _REG_LINE_SOURCE, _REG_LINE_INVERTER, _LINE_STRIDE = 0xA100, 0xA104, 0xA108, 0x10
_REG_TIMER_DURATION, _REG_TIMER_TRIGGER_SOURCE = 0xA310, 0xA318
_LINE_MODE_OUTPUT = 1
_SOURCE_EXPOSURE_ACTIVE, _SOURCE_TIMER0_ACTIVE = 1, 2
_TIMER_TRIGGER_EXPOSURE_START = 1

_FillPattern = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
                                ctypes.c_uint32)


def _libaravis() -> ctypes.CDLL:
    lib = ctypes.CDLL("libaravis-0.8.so.0")  # CDLL: calls release the GIL, so the fake's thread can call back
    sigs: dict[str, tuple[Any, list[Any]]] = {
        "arv_fake_camera_set_fill_pattern": (None, [ctypes.c_void_p, _FillPattern, ctypes.c_void_p]),
        "arv_fake_camera_read_register": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint32,
                                                          ctypes.POINTER(ctypes.c_uint32)]),
        "arv_fake_camera_write_register": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32]),
        "arv_fake_camera_write_memory": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
                                                         ctypes.c_char_p]),
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
    frame_source : ``(t_host_ns, lit) -> (height, width) uint8`` (uint16 is taken as is for the
        16-bit formats, uint8 is shifted up to them). Called in the fake camera's thread once per
        frame; ``t_host_ns`` is ``time.monotonic_ns()`` when the frame is filled.
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

        self.frames_served = 0
        self.lit_frames = 0
        self.errors: list[str] = []  # exceptions raised in the fill callback (it must not raise into C)

        self._line = int(ring_light_line[4:])
        self._gv: Any = None
        self._fake: Any = None
        self._fake_ptr = 0
        self._callback: Any = None
        self._lock_fd: int | None = None
        self._mutex = threading.Lock()

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
        gv = Aravis.GvFakeCamera.new_full(self.address, self.serial, self.xml_path)
        if not gv.is_running():
            raise RuntimeError(
                f"Aravis' fake camera cannot listen on {self.address}: it binds only addresses of a network "
                "interface (127.0.0.1 on a stock host; add others with `ip addr add 127.0.0.N/8 dev lo`)")
        if self.lost_packet_ratio:
            gv.set_property("gvsp-lost-ratio", self.lost_packet_ratio)
        fake = gv.get_fake_camera()
        ptr = _gobject_pointer(fake)
        for address, value in ((_REG_SENSOR_WIDTH, self.width), (_REG_SENSOR_HEIGHT, self.height),
                               (_REG_WIDTH, self.width), (_REG_HEIGHT, self.height)):
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

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
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

    def _fill(self, buffer: int, _data: int, _exposure_us: int, _gain: int, pixel_format: int) -> None:
        # called by libaravis with its fill mutex held; exceptions must not escape into C
        try:
            t_host_ns = time.monotonic_ns()
            width = _lib.arv_buffer_get_image_width(buffer)
            height = _lib.arv_buffer_get_image_height(buffer)
            size = ctypes.c_size_t(0)
            data = _lib.arv_buffer_get_data(buffer, ctypes.byref(size))  # size reads 0 here: use the payload
            payload = _lib.arv_fake_camera_get_payload(self._fake_ptr)
            lit = self._lit()
            got = self.frame_source(t_host_ns, lit)
            if isinstance(got, tuple):
                # the source drew the scene at another instant (a frame rendered ahead): stamp the
                # buffer with that instant, so that the device clock and the content agree
                got, t_content_ns = got
                stamp = _lib.arv_buffer_get_timestamp(buffer)
                _lib.arv_buffer_set_timestamp(buffer, max(0, stamp + (int(t_content_ns) - t_host_ns)))
            sensor = np.asarray(got)
            window = self._window(sensor, self._register(_REG_OFFSET_X), self._register(_REG_OFFSET_Y),
                                  width, height, pixel_format)
            ctypes.memmove(data, window.ctypes.data, min(window.nbytes, payload))
            self.frames_served += 1
            self.lit_frames += lit
        except Exception as e:  # a bug in frame_source: keep serving (black frames) and record it
            if len(self.errors) < 100:
                self.errors.append(f"{type(e).__name__}: {e}")
            log.exception("GigE Vision stand-in %s: frame_source failed", self.serial)

    @staticmethod
    def _window(sensor: np.ndarray, x0: int, y0: int, width: int, height: int, pixel_format: int) -> np.ndarray:
        """The ROI of ``sensor`` in the camera's pixel format, zero where the source image ends."""
        bits = (pixel_format >> 16) & 0xFF  # PFNC: bits per pixel in the code's third byte
        if sensor.ndim != 2 or bits not in (8, 16):
            raise ValueError(f"frame_source must give a 2D image for Mono8/Mono12/Mono16, got shape "
                             f"{sensor.shape} for pixel format 0x{pixel_format:08x}")
        dtype = np.dtype(np.uint8) if bits == 8 else np.dtype("<u2")
        out = np.zeros((height, width), dtype)
        part = sensor[y0: y0 + height, x0: x0 + width]
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
                    raise RuntimeError(f"another GigE Vision stand-in has held {self.address} for "
                                       f"{self.lock_timeout_s:.0f} s ({path})") from None
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
                raise RuntimeError(f"UDP port {_GVCP_PORT} on {self.address} is taken by another GigE Vision "
                                   f"device or program ({e.strerror})") from e


def cell_frame_source(cell: Any, t0_ns: int | None = None, ahead: bool = False) -> FrameSource:
    """A ``frame_source`` showing a :class:`service.sim.cell.SimCell` at ``(t_host_ns - t0_ns)`` s.

    Noise-free renders; a cell whose program holds still is rendered once per ring-light state.
    With ``ahead`` a background thread renders the next frame for the instant the fake camera
    is expected to fill it (its frame period, learnt from the calls), and the frame goes out at
    once with that instant as its device timestamp: the fake camera renders inside its
    exposure, and tens of milliseconds of rendering would otherwise look like transfer latency.
    """
    t0 = time.monotonic_ns() if t0_ns is None else t0_ns
    still = getattr(cell.config, "program", None) == "hold"
    cache: dict[bool, np.ndarray] = {}

    def render(t_host_ns: int, lit: bool) -> np.ndarray:
        if still and lit in cache:
            return cache[lit]
        image: np.ndarray = cell.render((t_host_ns - t0) * 1e-9, None, lit=lit).image
        if still:
            cache[lit] = image
        return image

    if not ahead:
        return render
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="gv-prerender")
    calls: collections.deque[int] = collections.deque(maxlen=9)
    pending: dict[str, Any] = {}

    def source(t_host_ns: int, lit: bool) -> Any:
        calls.append(t_host_ns)
        fut = pending.pop("future", None)
        image, t_content = None, t_host_ns
        if fut is not None and fut.done():
            t_pred, lit_pred, img = fut.result()
            if lit_pred == lit and len(calls) >= 3:
                period = float(np.median(np.diff(np.array(calls))))
                if abs(t_pred - t_host_ns) < 0.5 * period:
                    image, t_content = img, t_pred
        if image is None:
            image = render(t_host_ns, lit)
        if len(calls) >= 3:
            t_next = t_host_ns + int(np.median(np.diff(np.array(calls))))
            pending["future"] = pool.submit(lambda t=t_next, lt=lit: (t, lt, render(t, lt)))
        return image, t_content

    return source


@contextlib.contextmanager
def contract_camera(address: str = "127.0.0.1", **camera_options: Any) -> Iterator[Any]:
    """The Aravis driver (not yet opened) on a stand-in showing the simulated cell, for contract suites."""
    from drivers.camera.aravis import AravisCamera
    from service.sim.cell import CellConfig, SimCell

    camera_options.setdefault("packet_size", 8192)  # loopback: the fake's 1400-byte default loses frames
    cell = SimCell(CellConfig(program="hold"))
    with GvStandIn(cell_frame_source(cell), address=address, serial="POSECELL-CT",
                   width=cell.camera.width, height=cell.camera.height):
        camera = AravisCamera(address, **camera_options)
        try:
            yield camera
        finally:
            camera.close()
