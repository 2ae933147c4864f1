"""The stream of an Aravis camera: a fixed pool of buffers, and owned frames copied out of them.

:func:`make_stream` creates the stream with ``n_buffers`` buffers of the payload size (and the
GigE Vision options: packet size, socket buffer, packet resend, packet socket or UDP).
:class:`FrameCopier` turns each popped buffer into a :class:`~drivers.base.Frame`: it checks the
buffer's status, copies the image out (one ``memmove``, two for padded rows) and pushes the
buffer back at once, counting good frames and failed buffers by status (harvesters' and Aravis'
own pattern). Popping, and noticing a lost camera between pops, is the driver's
(:mod:`drivers.camera.aravis`).

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
socket's small default buffer. Where ``CLOCK_REALTIME`` steps between two pops, the
pop's time stands in for the arrival.
"""

from __future__ import annotations

import ctypes
import time
from collections import Counter
from typing import Any

import numpy as np

from drivers.base import DriverError, Frame
from drivers.camera.aravis_genicam import PIXEL_FORMATS, Aravis, Features
from drivers.timing import arrival_ns, thread_nice

_DTYPE_BY_CODE = {code: dtype for code, dtype in PIXEL_FORMATS.values()}
_NAME_BY_CODE = {code: name for name, (code, _) in PIXEL_FORMATS.items()}

# PyGObject hands buffer data out as an immutable bytes copy; ctypes copies it once into a writable array
_lib = ctypes.CDLL("libaravis-0.8.so.0")  # the library gi loaded (same soname, same handle)
_lib.arv_buffer_get_image_data.restype = ctypes.c_void_p
_lib.arv_buffer_get_image_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype, _capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]

_CLOCK_STEP_NS = 1_000_000  # a change of CLOCK_REALTIME - CLOCK_MONOTONIC larger than this is a step
_STREAM_THREAD_NICE = -10  # the stream thread stamps arrivals: it runs ahead of image processing when allowed


def make_stream(
    camera: Any,
    f: Features,
    *,
    n_buffers: int,
    packet_size: int | None,
    socket_buffer_bytes: int | None,
    packet_resend: bool,
    packet_socket: bool,
) -> Any:
    """A new ``Aravis.Stream`` of ``camera`` with ``n_buffers`` buffers of the current payload
    (the options as :class:`~drivers.camera.aravis.AravisCamera` takes them)."""
    if camera.is_gv_device() and packet_size is not None:
        f.call(lambda: camera.gv_set_packet_size(int(packet_size)), "set the packet size")
        f.device.set_packet_size_adjustment(Aravis.GvPacketSizeAdjustment.NEVER)
    if isinstance(f.device, Aravis.GvDevice):  # the option is read when the stream is created
        f.device.set_stream_options(
            Aravis.GvStreamOption.NONE if packet_socket else Aravis.GvStreamOption.PACKET_SOCKET_DISABLED
        )
    # Aravis starts the stream's receiving thread here: it inherits this thread's priority
    with thread_nice(_STREAM_THREAD_NICE):
        stream = f.call(lambda: camera.create_stream(None, None), "create a stream")
    if stream is None:
        raise DriverError(f"the camera {f.name()} gave no stream channel")
    if isinstance(stream, Aravis.GvStream):
        if socket_buffer_bytes is None:
            stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
        else:
            stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.FIXED)
            stream.set_property("socket-buffer-size", int(socket_buffer_bytes))
        resend = Aravis.GvStreamPacketResend.ALWAYS if packet_resend else Aravis.GvStreamPacketResend.NEVER
        stream.set_property("packet-resend", resend)
    payload = int(f.call(camera.get_payload, "read the payload size"))
    for _ in range(n_buffers):
        stream.push_buffer(Aravis.Buffer.new_allocate(payload))
    return stream


class FrameCopier:
    """Owned frames out of popped buffers, and the count of good frames and failed buffers."""

    def __init__(self) -> None:
        self.failed: Counter[str] = Counter()  # failed buffers by Aravis status nick
        self.n_ok = 0
        self._real_minus_mono_ns: int | None = None  # CLOCK_REALTIME - CLOCK_MONOTONIC at the last pop

    def frame_from(self, stream: Any, buffer: Any, exposure_us: float, name: str) -> Frame | None:
        """An owned frame from a ``buffer`` popped off ``stream``, or None for a failed one; the
        buffer goes back to ``stream`` at once. ``name`` is the camera's, for the error message."""
        t_pop_ns = time.monotonic_ns()
        real_minus_mono_ns = time.time_ns() - t_pop_ns
        try:
            status = buffer.get_status()
            if status != Aravis.BufferStatus.SUCCESS:
                self.failed[status.value_nick] += 1
                return None
            width, height = buffer.get_image_width(), buffer.get_image_height()
            code = buffer.get_image_pixel_format()
            dtype = _DTYPE_BY_CODE.get(code)
            if dtype is None:
                raise DriverError(
                    f"the camera {name} sent pixel format 0x{code:08x}; posecell reads {', '.join(PIXEL_FORMATS)} only"
                )
            x_padding, _ = buffer.get_image_padding()
            seq, t_device_ns = buffer.get_frame_id(), buffer.get_timestamp()
            t_system_ns = buffer.get_system_timestamp()
            image = copy_image(buffer, width, height, dtype, x_padding)
        finally:
            stream.push_buffer(buffer)
        if image is None:
            self.failed["size-mismatch"] += 1
            return None
        self.n_ok += 1
        previous, self._real_minus_mono_ns = self._real_minus_mono_ns, real_minus_mono_ns
        stepped = previous is not None and abs(real_minus_mono_ns - previous) > _CLOCK_STEP_NS
        return Frame(
            image=image,
            seq=int(seq),
            t_host_ns=t_pop_ns if stepped else arrival_ns(t_pop_ns, int(t_system_ns), real_minus_mono_ns),
            t_device_ns=int(t_device_ns) if t_device_ns else None,
            exposure_us=exposure_us,
            meta={
                "system_timestamp_ns": int(t_system_ns),
                "t_popped_ns": t_pop_ns,
                "failed_buffers": dict(self.failed),
                "pixel_format": _NAME_BY_CODE[code],
            },
        )


def copy_image(buffer: Any, width: int, height: int, dtype: np.dtype[Any], x_padding: int) -> np.ndarray | None:
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
