"""Automatic exposure on the targets: keep the brightest disks just below full scale.

A camera's own auto-exposure steers by the mean of the image, which for retro-reflective
targets on a dark cell is mostly background: it would open up until every disk clips. A
disk's image is the LED ring's light returned by the target, so its brightness above the
background scales with the exposure and with 1/range² — near the plate (under ~750 mm at
the default exposure) the disks saturate and are rejected, far away they fade into the
noise. This control therefore steers by the measured disks' peaks (:class:`Brightness`
from the measurement): the 90th percentile of their peaks above background is brought to
``target_peak`` of full scale, with a dead band so that it does not hunt, at most one step
per settling time, and within the configured limits. A frame that shows no disks at all
changes nothing: the camera may simply be looking away from the field.

Pure logic (no device, no clock of its own): the worker feeds it each frame's exposure
and brightness and applies what it returns.
"""

from __future__ import annotations

from dataclasses import dataclass

from service.pipeline.brightness import Brightness

#: a step smaller than this share is not worth a camera write
MIN_STEP = 0.05
#: the most one step may change the exposure by (factor): a wrong reading cannot throw it far
MAX_FACTOR = 4.0
#: blobs rejected as saturated, as a share of all disks, that make the frame over-exposed: a glint
#: or two (a shiny bolt) must not drive the exposure to its minimum
SATURATED_SHARE = 0.1
#: frames after a change that are not judged: frames already exposed with the old value may still
#: be on their way (a driver that cannot tell says the new value)
SETTLE_FRAMES = 2


@dataclass(frozen=True)
class ExposureLimits:
    """The control's settings: the aim and the band as shares of full scale, the limits in µs."""

    target_peak: float = 0.75
    low: float = 0.45
    high: float = 0.92
    min_us: float = 20.0
    max_us: float = 10_000.0


@dataclass(frozen=True)
class ExposureStep:
    """A new exposure and why (a sentence for the event log)."""

    exposure_us: float
    why: str


class ExposureControl:
    """One camera's exposure control (see the module docstring); called from one thread."""

    def __init__(self, limits: ExposureLimits, exposure_us: float) -> None:
        self.limits = limits
        self.exposure_us = float(exposure_us)  # what was last asked of the camera
        self.steps = 0
        self._settle = 0

    def restart(self, exposure_us: float, limits: ExposureLimits | None = None) -> None:
        """Start again from ``exposure_us`` (the configuration changed)."""
        self.limits = limits or self.limits
        self.exposure_us, self._settle = float(exposure_us), 0

    def observe(self, frame_exposure_us: float, brightness: Brightness | None) -> ExposureStep | None:
        """The step to take after a frame taken with ``frame_exposure_us``, or None."""
        if brightness is None or abs(frame_exposure_us - self.exposure_us) > 0.01 * self.exposure_us:
            return None  # not yet a frame of the exposure asked for (or an unreadable image)
        if self._settle > 0:
            self._settle -= 1
            return None
        factor, why = self._factor(brightness)
        if factor is None:
            return None
        lim = self.limits
        new_us = round(min(lim.max_us, max(lim.min_us, self.exposure_us * factor)), 1)
        if abs(new_us - self.exposure_us) < MIN_STEP * self.exposure_us:
            return None  # at a limit already, or a step too small to matter
        self.exposure_us, self._settle = new_us, SETTLE_FRAMES
        self.steps += 1
        return ExposureStep(new_us, why)

    def _factor(self, b: Brightness) -> tuple[float | None, str]:
        lim = self.limits
        span = b.full_dn - b.background_dn
        if span <= 0:
            return None, ""
        seen = b.n_measured + b.n_saturated
        if b.n_saturated >= 2 and b.n_saturated >= SATURATED_SHARE * seen:
            # how far over is unknowable from a clipped disk: halve, or less when the unclipped ones say so
            factor = 0.5
            if b.n_measured:
                factor = min(factor, (lim.target_peak * span) / max(b.peak_dn - b.background_dn, 1e-9))
            return max(factor, 1.0 / MAX_FACTOR), f"{b.n_saturated} of {seen} targets saturated"
        if b.n_measured == 0:
            return None, ""  # nothing to go by
        level = (b.peak_dn - b.background_dn) / span
        if lim.low <= level <= lim.high:
            return None, ""
        factor = min(MAX_FACTOR, max(1.0 / MAX_FACTOR, lim.target_peak / max(level, 1e-9)))
        return factor, f"the targets' peaks at {100 * level:.0f} % of full scale"
