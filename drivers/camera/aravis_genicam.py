"""GenICam features of an Aravis camera, and :class:`~drivers.base.CameraSettings` written to them.

:class:`Features` is one connected device's feature access by SFNC name: whether a feature
exists, its enumeration entries, typed reads and writes, and every Aravis call turned into the
driver's error tree (a lost link sets the connection's ``lost`` flag and raises
:class:`~drivers.base.DriverDisconnected`; a missing node raises
:class:`~drivers.base.FeatureUnsupported` naming it). On top of it, the settings: where cameras
differ (the older ``ExposureTimeAbs``/``GainRaw``/``AcquisitionFrameRateAbs``) whichever exists is
taken; :func:`check_settings` raises for anything the camera lacks *before* :func:`apply_settings`
and :func:`apply_strobe` change anything. :func:`apply_exposure_step` is the one write made to a
camera that is acquiring: a new exposure time and gain (SFNC lets both change while acquiring,
and practically every camera does), unless the camera's GenICam description says they are
read-only or locked now.

A module of its own because it is the GenICam side of the driver: what it writes and in which
order (offsets before sizes, every trigger off before one goes on) matters for every camera model,
and none of it depends on how frames are streamed (:mod:`drivers.camera.aravis_stream`) or how
a lost camera is reopened (:mod:`drivers.camera.aravis`). This module also imports ``gi`` for
its siblings, with the error message that says what to install.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
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
    FeatureUnsupported,
    StrobeSettings,
    TriggerMode,
)

log = logging.getLogger(__name__)

__all__ = [
    "PIXEL_FORMATS",
    "Aravis",
    "Features",
    "GLib",
    "apply_exposure_step",
    "apply_settings",
    "apply_strobe",
    "check_settings",
    "read_exposure_us",
    "read_info",
]

# pixel formats posecell reads, with their PFNC codes and array types (GigE Vision pixels are little-endian)
PIXEL_FORMATS: dict[str, tuple[int, np.dtype[Any]]] = {
    "Mono8": (Aravis.PIXEL_FORMAT_MONO_8, np.dtype(np.uint8)),
    "Mono12": (Aravis.PIXEL_FORMAT_MONO_12, np.dtype("<u2")),
    "Mono16": (Aravis.PIXEL_FORMAT_MONO_16, np.dtype("<u2")),
}

_DEVICE_ERROR = "arv-device-error-quark"
_GC_ERROR = "arv-gc-error-quark"
_LINK_ERRORS = {
    int(Aravis.DeviceError.TIMEOUT),
    int(Aravis.DeviceError.NOT_CONNECTED),
    int(Aravis.DeviceError.TRANSFER_ERROR),
    int(Aravis.DeviceError.NOT_CONTROLLER),
}


class Features:
    """The GenICam features of one connected ``Aravis.Device``, by SFNC name.

    Parameters
    ----------
    device : the connection's ``Aravis.Device``; dropped with the connection.
    lost : the driver's flag, set when a call finds the link gone.
    name, model : how messages name the camera (its address; its model once known).
    """

    def __init__(self, device: Any, lost: threading.Event, name: Callable[[], str], model: Callable[[], str]) -> None:
        self.device = device
        self._lost = lost
        self.name = name
        self.model = model

    def read(self, name: str) -> bool | int | float | str:
        """The current value of any GenICam feature (enumerations as strings)."""
        node = self.device.get_feature(name)
        if node is None:
            raise FeatureUnsupported(name, f"the camera {self.model()} has no {name}")
        d = self.device
        for kind, getter in (
            (Aravis.GcEnumeration, d.get_string_feature_value),
            (Aravis.GcBoolean, d.get_boolean_feature_value),
            (Aravis.GcFloat, d.get_float_feature_value),
            (Aravis.GcInteger, d.get_integer_feature_value),
            (Aravis.GcString, d.get_string_feature_value),
        ):
            if isinstance(node, kind):
                value: bool | int | float | str = self.call(lambda g=getter: g(name), f"read {name}", name)
                return value
        raise FeatureUnsupported(name, f"{name} of the camera {self.model()} is a {type(node).__name__}, not a value")

    def has(self, name: str) -> bool:
        try:
            return bool(self.device.is_feature_available(name))
        except GLib.Error:
            return False

    def need(self, name: str, consequence: str) -> None:
        if not self.has(name):
            raise FeatureUnsupported(name, f"the camera {self.model()} has no {name}; {consequence}")

    def need_entry(self, name: str, entry: str, what: str, consequence: str | None = None) -> None:
        consequence = consequence or f"the {what} {entry} cannot be set"
        self.need(name, consequence)
        entries = self.entries(name)
        if entry not in entries:
            raise FeatureUnsupported(
                name,
                f"the camera {self.model()} has no {what} {entry} "
                f"(it offers {', '.join(entries) or 'none'}); {consequence}",
            )

    def first(self, what: str, *names: str) -> str:
        for name in names:
            if self.has(name):
                return name
        raise FeatureUnsupported(names[0], f"the camera {self.model()} has no {what} ({' or '.join(names)})")

    def entries(self, name: str) -> list[str]:
        return list(
            self.call(
                lambda: self.device.dup_available_enumeration_feature_values_as_strings(name),
                f"read the entries of {name}",
                name,
            )
            or []
        )

    def set(self, name: str, value: bool | int | float | str) -> None:
        d = self.device
        setter = (
            d.set_boolean_feature_value
            if isinstance(value, bool)
            else d.set_integer_feature_value
            if isinstance(value, int)
            else d.set_float_feature_value
            if isinstance(value, float)
            else d.set_string_feature_value
        )
        self.call(lambda: setter(name, value), f"set {name} to {value}", name)

    def writable(self, name: str) -> bool:
        """Whether ``name`` may be written now: its access mode (of its node and the registers behind it)
        is RW or WO and its ``pIsLocked`` (often ``TLParamsLocked`` while acquiring) is not set."""
        node = self.device.get_feature(name)
        if not isinstance(node, Aravis.GcFeatureNode):
            return False
        # the node's own call: arv_device_get_feature_access_mode returns a truth value, not the mode (0.8.26)
        mode = node.get_actual_access_mode()
        locked = self.call(node.is_locked, f"read whether {name} is locked", name)
        return mode in (Aravis.GcAccessMode.RW, Aravis.GcAccessMode.WO) and not locked

    def set_if_entry(self, name: str, entry: str) -> None:
        if self.has(name) and entry in self.entries(name):
            self.set(name, entry)

    def get_int(self, name: str) -> int:
        return int(self.call(lambda: self.device.get_integer_feature_value(name), f"read {name}", name))

    def call(self, fn: Any, what: str, feature: str | None = None) -> Any:
        """Run an Aravis call; a GLib error becomes a DriverError subclass naming the feature."""
        try:
            return fn()
        except GLib.Error as e:
            if e.domain == _DEVICE_ERROR and e.code in _LINK_ERRORS:
                self._lost.set()
                raise DriverDisconnected(
                    f"the camera {self.name()} did not answer while trying to {what} ({e.message})"
                ) from e
            if feature is not None and (
                (e.domain == _DEVICE_ERROR and e.code == int(Aravis.DeviceError.FEATURE_NOT_FOUND))
                or (e.domain == _GC_ERROR and e.code == int(Aravis.GcError.ENUM_ENTRY_NOT_FOUND))
            ):
                raise FeatureUnsupported(
                    feature, f"the camera {self.model()} has no {feature} (trying to {what})"
                ) from e
            raise DriverError(f"the camera {self.name()} refused to {what}: {e.message}") from e


# --- settings ---------------------------------------------------------------------------------


def check_settings(f: Features, s: CameraSettings) -> None:
    """Raise FeatureUnsupported for anything in ``s`` the camera lacks, before changing anything."""
    model = f.model()
    if s.pixel_format is not None:
        if s.pixel_format not in PIXEL_FORMATS:
            raise FeatureUnsupported("PixelFormat", f"posecell reads {', '.join(PIXEL_FORMATS)}, not {s.pixel_format}")
        f.need_entry("PixelFormat", s.pixel_format, "pixel format")
    if s.roi is not None:
        x, y, w, h = s.roi
        for name in ("OffsetX", "OffsetY", "Width", "Height"):
            f.need(name, "the region of interest cannot be set")
        if min(x, y) < 0 or w <= 0 or h <= 0:
            raise DriverError(f"the region of interest {s.roi} is not a valid x, y, width, height")
        if f.has("SensorWidth") and f.has("SensorHeight"):
            sw, sh = f.get_int("SensorWidth"), f.get_int("SensorHeight")
            if x + w > sw or y + h > sh:
                raise DriverError(f"the region of interest {s.roi} exceeds the {sw} x {sh} sensor of {model}")
    if s.exposure_us is not None:
        f.first("exposure time", "ExposureTime", "ExposureTimeAbs")
    if s.gain_db is not None:
        f.first("gain", "Gain", "GainRaw")
    if s.frame_rate_hz is not None and s.trigger is TriggerMode.FREE_RUN:
        f.first("frame rate", "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
    if s.trigger is not TriggerMode.FREE_RUN:
        f.need("TriggerMode", "it cannot be triggered")
        source = "Software" if s.trigger is TriggerMode.SOFTWARE else s.trigger_line
        f.need_entry("TriggerSource", source, "trigger source")
        if s.trigger is TriggerMode.SOFTWARE:
            f.need("TriggerSoftware", "it cannot be triggered by software")
    if s.strobe is not None and s.strobe.enabled:
        _check_strobe(f, s.strobe)


def _check_strobe(f: Features, st: StrobeSettings) -> None:
    why = (
        f"the ring light cannot be strobed from its line {st.line} (use a camera with SFNC digital I/O, "
        "or set strobe.enabled = false)"
    )
    for name in ("LineSelector", "LineMode", "LineSource"):
        f.need(name, why)
    f.need_entry("LineSelector", st.line, "I/O line", why)
    f.need_entry("LineMode", "Output", "line mode", why)
    f.need_entry("LineSource", st.source, "line source", why)
    if st.inverted:
        f.need("LineInverter", "the strobe cannot be inverted")
    if st.source.startswith("Timer"):
        for name in ("TimerSelector", "TimerDuration", "TimerTriggerSource"):
            f.need(name, f"the strobe source {st.source} cannot be used")
        f.need_entry("TimerSelector", st.source.removesuffix("Active"), "timer")
        if st.delay_us:
            f.need("TimerDelay", "the strobe cannot be delayed")
        if st.duration_us is None or st.duration_us <= 0:
            raise DriverError(f"the strobe source {st.source} needs strobe.duration_us > 0")


def apply_settings(f: Features, s: CameraSettings) -> None:
    """Write ``s`` but its strobe to the stopped camera (checked by :func:`check_settings`): region,
    pixel format, exposure, gain and trigger, in that order."""
    if s.roi is not None:
        x, y, w, h = s.roi
        f.set("OffsetX", 0)  # offsets first to 0, so that the new size always fits the sensor
        f.set("OffsetY", 0)
        f.set("Width", int(w))
        f.set("Height", int(h))
        f.set("OffsetX", int(x))
        f.set("OffsetY", int(y))
    if s.pixel_format is not None:
        f.set("PixelFormat", s.pixel_format)
    if s.exposure_us is not None:
        f.set_if_entry("ExposureAuto", "Off")
        f.set_if_entry("ExposureMode", "Timed")
        f.set(f.first("exposure time", "ExposureTime", "ExposureTimeAbs"), float(s.exposure_us))
    if s.gain_db is not None:
        f.set_if_entry("GainAuto", "Off")
        f.set_if_entry("GainSelector", "All")
        name, value = _gain_write(f, s.gain_db)
        if name == "GainRaw":
            log.warning("camera %s has GainRaw only (device units, not dB); writing %d", f.model(), value)
        f.set(name, value)
    _apply_trigger(f, s)


def apply_exposure_step(f: Features, old: CameraSettings, new: CameraSettings) -> bool:
    """Write the exposure time and gain of ``new`` that differ from ``old`` to the acquiring camera.

    ``new`` differs from ``old`` (written whole by :func:`apply_settings`) in ``exposure_us`` and
    ``gain_db`` only. Returns False, having written nothing, when the change needs the camera
    stopped: a feature is read-only or locked while acquiring, or manual exposure (gain) is to be
    taken over from the camera's own (``old`` left it alone: ``ExposureAuto`` may be on). A camera
    that refuses the write itself raises :class:`~drivers.base.DriverError`, as any write does.
    """
    writes: list[tuple[str, float | int]] = []
    if new.exposure_us is not None and new.exposure_us != old.exposure_us:
        if old.exposure_us is None:
            return False
        writes.append((f.first("exposure time", "ExposureTime", "ExposureTimeAbs"), float(new.exposure_us)))
    if new.gain_db is not None and new.gain_db != old.gain_db:
        if old.gain_db is None:
            return False
        writes.append(_gain_write(f, new.gain_db))
    if not all(f.writable(name) for name, _ in writes):
        return False
    for name, value in writes:
        f.set(name, value)
    return True


def _gain_write(f: Features, gain_db: float) -> tuple[str, float | int]:
    """The gain feature and the value to write: ``Gain`` in dB, else ``GainRaw`` in device units."""
    return ("Gain", float(gain_db)) if f.has("Gain") else ("GainRaw", round(gain_db))


def _apply_trigger(f: Features, s: CameraSettings) -> None:
    selectors = f.entries("TriggerSelector") if f.has("TriggerSelector") else []
    for selector in selectors:  # every trigger off first: a left-over AcquisitionStart trigger stalls a free run
        f.set("TriggerSelector", selector)
        f.set("TriggerMode", "Off")
    if not selectors and f.has("TriggerMode"):
        f.set("TriggerMode", "Off")
    if s.trigger is TriggerMode.FREE_RUN:
        if s.frame_rate_hz is not None:
            if f.has("AcquisitionFrameRateEnable"):
                f.set("AcquisitionFrameRateEnable", True)
            name = f.first("frame rate", "AcquisitionFrameRate", "AcquisitionFrameRateAbs")
            f.set(name, float(s.frame_rate_hz))
        return
    if f.has("AcquisitionFrameRateEnable"):
        f.set("AcquisitionFrameRateEnable", False)  # a rate limit would swallow triggers
    if "FrameStart" in selectors:
        f.set("TriggerSelector", "FrameStart")
    if s.trigger is TriggerMode.SOFTWARE:
        f.set("TriggerSource", "Software")
    else:
        f.set("TriggerSource", s.trigger_line)
        f.set_if_entry("TriggerActivation", "RisingEdge")
    f.set("TriggerMode", "On")


def apply_strobe(f: Features, st: StrobeSettings) -> str | None:
    """Switch the ring light's line to ``st``; returns the line now lit by the driver (None: none)."""
    if not st.enabled:
        # switch the line's source off where the camera allows it; leave a camera without lines alone
        if f.has("LineSelector") and st.line in f.entries("LineSelector"):
            f.set("LineSelector", st.line)
            f.set_if_entry("LineSource", "Off")
        return None
    f.set("LineSelector", st.line)
    f.set("LineMode", "Output")
    if st.source.startswith("Timer"):
        f.set("TimerSelector", st.source.removesuffix("Active"))
        f.set("TimerDuration", float(st.duration_us or 0.0))
        if f.has("TimerDelay"):
            f.set("TimerDelay", float(st.delay_us))
        f.set("TimerTriggerSource", "ExposureStart")
    elif st.delay_us or st.duration_us is not None:
        log.warning(
            "camera %s: strobe delay/duration apply to timer sources only; %s follows the exposure",
            f.model(),
            st.source,
        )
    f.set("LineSelector", st.line)  # timer nodes may share selectors on some cameras: select again
    f.set("LineSource", st.source)
    if f.has("LineInverter"):
        f.set("LineInverter", bool(st.inverted))
    return st.line


def read_exposure_us(f: Features) -> float:
    """The exposure time the camera reports, us (NaN if it has none)."""
    for name in ("ExposureTime", "ExposureTimeAbs"):
        if f.has(name):
            return float(f.call(lambda n=name: f.device.get_float_feature_value(n), f"read {name}", name))
    return float("nan")


def read_info(f: Features, camera: Any) -> CameraInfo:
    """What ``camera`` (the ``Aravis.Camera`` of ``f``) is and which optional features it has."""
    has = f.has
    features = [
        ("strobe", has("LineSelector") and has("LineMode") and has("LineSource")),
        ("gain", has("Gain") or has("GainRaw")),
        ("timer", has("TimerSelector") and has("TimerDuration")),
        ("frame_rate", has("AcquisitionFrameRate") or has("AcquisitionFrameRateAbs")),
        ("trigger", has("TriggerMode")),
    ]
    return CameraInfo(
        driver="aravis",
        model=f.call(camera.get_model_name, "read the model name") or "",
        serial=f.call(camera.get_device_serial_number, "read the serial number") or "",
        width=f.get_int("Width"),
        height=f.get_int("Height"),
        pixel_format=str(
            f.call(lambda: f.device.get_string_feature_value("PixelFormat"), "read PixelFormat", "PixelFormat")
        )
        if has("PixelFormat")
        else "",
        features=tuple(name for name, present in features if present),
    )
