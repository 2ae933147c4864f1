"""The online correction: from each frame's flange deviation, the offset an external control applies.

The paper's outer loop (its Figure 1) made continuous: the camera measures where the flange really
is, the controller says where it believes it is, and their deviation ``measured - reported`` (base
frame) is what the arm is off by. An external-control interface (UR's RTDE ``servoj``/``speedl``
offsets, KUKA RSI, a PLC's correction registers) adds ``-deviation`` to its commands so that the
*real* flange lands where it is commanded.

What keeps it safe, by hand here because it is the product's own rule, not a filter library's:

- **smoothing**: a first-order filter with ``gain`` per frame (0 < gain <= 1; 1 = each frame's
  own deviation), so one noisy frame moves the offset by ``gain`` of its noise;
- **a bound**: a deviation beyond ``max_mm`` / ``max_deg`` is not a correction but a fault (a
  wrong calibration, a collision, a misidentified target): the state turns ``hold`` with the
  reason, the offset is not applied, never clipped silently;
- **a watchdog**: a frame without a pose keeps the last offset, but no usable frame for
  ``watchdog_s`` and the state is ``hold`` (``stale``); a client must stop applying offsets while
  it holds. A hold resets the filter: the next usable frame starts it again from its own deviation.

Pure: no clock of its own (the caller passes the times), no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

APPLY, HOLD = "apply", "hold"


@dataclass(frozen=True)
class CorrectionLimits:
    max_mm: float = 2.0  # a larger deviation is a fault, not a correction
    max_deg: float = 0.5
    gain: float = 0.5  # of each frame's deviation taken into the offset
    watchdog_s: float = 0.25  # no usable frame for this long: hold

    def __post_init__(self) -> None:
        if not (self.max_mm > 0 and self.max_deg > 0 and self.watchdog_s > 0):
            raise ValueError("max_mm, max_deg and watchdog_s must be positive")
        if not 0 < self.gain <= 1:
            raise ValueError(f"gain must be in (0, 1], not {self.gain}")


@dataclass(frozen=True)
class Correction:
    """The offset to add to the commanded flange position (base frame, mm), or a hold and why."""

    state: str  # APPLY or HOLD
    offset_mm: NDArray[np.float64]  # (3,), zeros while holding
    reason: str = ""  # why it holds: no_pose, no_flange, beyond_bound, stale
    message: str = ""


class CorrectionFilter:
    """Turns each frame's deviation into the offset to apply (see the module docstring)."""

    def __init__(self, limits: CorrectionLimits) -> None:
        self.limits = limits
        self._offset_mm: NDArray[np.float64] | None = None
        self._last_ok_s: float | None = None

    def update(
        self, t_s: float, deviation_mm: NDArray[np.float64] | None, angle_deg: float | None, why_not: str = ""
    ) -> Correction:
        """One frame at ``t_s`` (s): its deviation vector (mm, base) and angle, or None with ``why_not``."""
        lim = self.limits
        dev = None if deviation_mm is None else np.asarray(deviation_mm, dtype=np.float64)
        if dev is None or angle_deg is None or not (np.all(np.isfinite(dev)) and np.isfinite(angle_deg)):
            # a frame without a pose is ridden out on the last offset until the watchdog says stale
            if self._offset_mm is not None and (stale := self.check(t_s)) is not None:
                return stale
            if self._offset_mm is not None:
                return Correction(APPLY, self._offset_mm.copy())
            return self._hold("no_flange", why_not or "the frame gave no flange deviation")
        size_mm = float(np.linalg.norm(dev))
        if size_mm > lim.max_mm or angle_deg > lim.max_deg:
            return self._hold(
                "beyond_bound",
                f"the deviation of {size_mm:.3f} mm / {angle_deg:.4f} deg is beyond the bound of "
                f"{lim.max_mm:g} mm / {lim.max_deg:g} deg: a fault, not a correction",
            )
        target = -dev
        self._offset_mm = target if self._offset_mm is None else self._offset_mm + lim.gain * (target - self._offset_mm)
        self._last_ok_s = t_s
        return Correction(APPLY, self._offset_mm.copy())

    def check(self, now_s: float) -> Correction | None:
        """The watchdog at ``now_s``: a ``stale`` hold when no usable frame came for ``watchdog_s``
        while applying, else None."""
        if self._offset_mm is None or self._last_ok_s is None:
            return None
        if now_s - self._last_ok_s <= self.limits.watchdog_s:
            return None
        late_ms = (now_s - self._last_ok_s) * 1e3
        return self._hold(
            "stale", f"no usable frame for {late_ms:.0f} ms (watchdog {self.limits.watchdog_s * 1e3:.0f} ms)"
        )

    def _hold(self, reason: str, message: str) -> Correction:
        self._offset_mm = None
        self._last_ok_s = None
        return Correction(HOLD, np.zeros(3), reason, message)
