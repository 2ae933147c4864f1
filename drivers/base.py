"""What the service expects of a camera and of a robot: two small Protocols, their data and one error tree.

The worker is the only caller of a driver and calls it from one thread per
device, so drivers need not be thread-safe towards their caller; a driver that
runs a thread of its own (a robot reader) keeps that thread's state private.

Clocks: every ``t_host_ns`` is ``time.monotonic_ns()`` of this process, the one
clock that pairs frames with robot poses (``service/timesync.py``). Device
clocks (a camera's tick counter, the robot controller's seconds) are reported
beside it, unconverted, so that the offset and drift can be estimated.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from drivers.history import RobotHistory

_EMPTY: Mapping[str, Any] = MappingProxyType({})


# --- errors -------------------------------------------------------------------------------------


class DriverError(Exception):
    """Base of every error a driver raises; the message is one sentence for an operator."""


class DriverUnavailable(DriverError):
    """The driver's SDK or system package is not installed (the import error is in the message)."""


class DriverInitError(DriverError):
    """The device could not be found or opened (wrong id, busy, no permission)."""


class DriverTimeout(DriverError):
    """No frame or sample arrived within the timeout; the device may still be there."""


class DriverDisconnected(DriverError):
    """The link to the device is lost; the driver tries to reconnect on the next call."""


class FeatureUnsupported(DriverError):
    """The device lacks a feature the configuration asks for (the feature's name is in ``feature``)."""

    def __init__(self, feature: str, message: str) -> None:
        super().__init__(message)
        self.feature = feature


# --- camera -------------------------------------------------------------------------------------


class TriggerMode(enum.StrEnum):
    FREE_RUN = "free_run"  # the camera runs at frame_rate_hz
    SOFTWARE = "software"  # one frame per trigger() call
    HARDWARE = "hardware"  # one frame per edge on trigger_line


@dataclass(frozen=True)
class StrobeSettings:
    """The IR ring light, driven by a camera output line (GenICam SFNC names).

    ``source`` is an SFNC ``LineSource`` value: ``ExposureActive`` fires the LED
    for exactly the exposure; ``Timer0Active`` fires it for ``duration_us``
    after ``delay_us`` from the exposure start (a timer the camera must have).
    """

    enabled: bool = True
    line: str = "Line1"
    source: str = "ExposureActive"
    inverted: bool = False
    delay_us: float = 0.0
    duration_us: float | None = None


@dataclass(frozen=True)
class CameraSettings:
    """What the configuration sets on a camera; a ``None`` number leaves the device's value unchanged."""

    exposure_us: float | None = 2000.0
    gain_db: float | None = None
    frame_rate_hz: float | None = 30.0
    trigger: TriggerMode = TriggerMode.FREE_RUN
    trigger_line: str = "Line0"
    pixel_format: str | None = None  # "Mono8", "Mono12", "Mono16"
    roi: tuple[int, int, int, int] | None = None  # x, y, width, height in px
    strobe: StrobeSettings | None = None  # None: no strobe (a line the driver had lit is switched off)


@dataclass(frozen=True)
class CameraInfo:
    driver: str
    model: str
    serial: str
    width: int
    height: int
    pixel_format: str
    features: tuple[str, ...] = ()  # optional features this device supports, e.g. ("strobe", "gain")


@dataclass(frozen=True, eq=False)
class Frame:
    """One image and when it was taken.

    image : (H, W) uint8 or uint16, C-contiguous, owned by the frame: never a view into a buffer
        the driver reuses (a replay lends read-only views of its recording, which nothing rewrites);
        consumers only read it
    seq : the device's frame counter (may wrap; compare for gaps, not order)
    t_host_ns : host monotonic clock when the frame reached this process
    t_device_ns : the device's timestamp of the exposure start in device ticks as ns, or None
    exposure_us : the exposure that was used
    t_exposure_host_ns : mid-exposure on the host clock when the driver knows it exactly
        (a simulation, or a hardware trigger the host fired), else None and time alignment estimates it
    meta : driver extras (ground truth in simulation, buffer status counters), JSON-friendly
    """

    image: NDArray[Any]
    seq: int
    t_host_ns: int
    t_device_ns: int | None
    exposure_us: float
    t_exposure_host_ns: int | None = None
    meta: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)


@runtime_checkable
class CameraDriver(Protocol):
    """A camera as the worker sees it. ``open`` then ``configure`` then ``fetch`` in a loop."""

    @property
    def info(self) -> CameraInfo: ...

    def open(self) -> None:
        """Connect and allocate buffers; raises ``DriverInitError``/``DriverUnavailable``."""

    def configure(self, settings: CameraSettings) -> None:
        """Apply settings (stops and restarts acquisition as needed); raises ``FeatureUnsupported``.

        An exposure step, settings that differ from those in force only in ``exposure_us`` and/or
        ``gain_db`` (the exposure control's, a few times a second), is applied without restarting
        the acquisition wherever the device allows: the frame counter runs on without a gap and
        waiting triggers stay. ``Frame.exposure_us`` is the exposure a frame was taken with, as
        well as the driver can know it (a driver that cannot tell says which frames around a step
        may carry the new value while taken with the old one).
        """

    def fetch(self, timeout_s: float) -> Frame:
        """The next frame; raises ``DriverTimeout`` or ``DriverDisconnected``."""

    def try_fetch(self) -> Frame | None:
        """A frame that is already waiting, or None at once."""

    def trigger(self) -> None:
        """Fire a software trigger (``TriggerMode.SOFTWARE``)."""

    def close(self) -> None:
        """Release the device; idempotent."""


# --- robot --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RobotSample:
    """The controller's belief of where the flange is, at one instant.

    T_base_flange : (4, 4) float, mm — the flange (tool flange, no TCP offset) in the base frame
    q_rad : (n_joints,) float, rad — encoder joint positions
    t_host_ns : host monotonic clock when the sample reached this process
    t_robot_s : the controller's own timestamp, s since its start (None if it has none)
    """

    T_base_flange: NDArray[np.float64]
    q_rad: NDArray[np.float64]
    t_host_ns: int
    t_robot_s: float | None = None
    meta: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)


@dataclass(frozen=True)
class RobotInfo:
    driver: str
    model: str
    address: str
    rate_hz: float
    T_flange_tcp: tuple[tuple[float, ...], ...] | None = None  # the TCP offset removed at the boundary, mm


@runtime_checkable
class RobotDriver(Protocol):
    """A robot as the worker sees it: a background reader filling a time-indexed history."""

    @property
    def info(self) -> RobotInfo: ...

    @property
    def connected(self) -> bool: ...

    @property
    def history(self) -> RobotHistory:
        """The time-indexed ring buffer the reader fills (pairing interpolates in it)."""

    def open(self) -> None:
        """Connect and start reading; raises ``DriverInitError``/``DriverUnavailable``."""

    def latest(self) -> RobotSample:
        """The newest sample; raises ``DriverDisconnected`` when the link is down or stale."""

    def samples_between(self, t0_host_ns: int, t1_host_ns: int) -> list[RobotSample]:
        """Buffered samples with ``t0 <= t_host_ns <= t1`` in time order (for interpolation)."""

    def close(self) -> None:
        """Stop the reader and disconnect; idempotent."""
