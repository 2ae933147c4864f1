"""One clock for the replay of a recording: its cameras and its robot played in step.

A recording (``service/runtime/recorder.py``) stamps the frames (``<camera>/timestamps.csv``) and
the robot's samples (``robot.csv``) on one clock, the recording host's monotonic clock. The
``replay`` camera (``timing = "recorded"``) and the ``replay`` robot map those times onto this
host's clock with the same offset, so the service pairs each replayed frame with the robot samples
it was recorded with, whatever order and moment the two drivers open in: both take the
:class:`ReplayClock` of the recording's folder, made once per process by the first to ask.

The recording loops with the span of its frames (the first frame to the last plus one frame
interval): a pass ``p`` plays recorded time ``t`` at ``anchor + (t - t0) + p * span``.
"""

from __future__ import annotations

import csv
import io
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.base import DriverInitError

LEAD_S = 0.5  # the first frame plays this long after the clock is made: both drivers are open by then
_clocks: dict[Path, ReplayClock] = {}
_lock = threading.Lock()


@dataclass(frozen=True)
class ReplayClock:
    """Recorded time ``t`` (ns) of pass ``p`` plays at ``anchor_ns + (t - t0_ns) + p * span_ns`` (host, ns)."""

    anchor_ns: int
    t0_ns: int
    span_ns: int
    step_ns: int  # the frames' interval (the median)

    def host_ns(self, t_recorded_ns: int | np.ndarray, n_pass: int = 0) -> int | np.ndarray:
        return self.anchor_ns + (t_recorded_ns - self.t0_ns) + n_pass * self.span_ns


def frame_times_ns(folder: Path) -> np.ndarray:
    """The ``t_ns`` column of a camera folder's ``timestamps.csv`` (recorded exposure instants)."""
    path = folder / "timestamps.csv"
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))))
        return np.array([int(r["t_ns"]) for r in rows], dtype=np.int64)
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise DriverInitError(f"{path} cannot be read as a recording's frame times ({e})") from None


def recording_of(path: Path) -> Path:
    """The recording folder of a camera folder or of a robot.csv (the one holding ``recording.json``)."""
    p = path.expanduser().resolve()
    for candidate in (p, p.parent):
        if (candidate / "recording.json").is_file():
            return candidate
    raise DriverInitError(f"{path} is not in a recording (no recording.json beside it or above it)")


def clock_of(recording: Path) -> ReplayClock:
    """The process's clock for ``recording`` (made by the first caller; see the module docstring)."""
    key = recording.resolve()
    with _lock:
        clock = _clocks.get(key)
        if clock is None:
            cameras = [d for d in sorted(key.iterdir()) if (d / "timestamps.csv").is_file()]
            times = [t for t in (frame_times_ns(d) for d in cameras) if t.size]
            if not times:
                raise DriverInitError(f"recording {key} holds no frame times (no camera's timestamps.csv has a row)")
            t0 = min(int(t[0]) for t in times)
            t1 = max(int(t[-1]) for t in times)
            step = int(np.median(np.diff(times[0]))) if times[0].size > 1 else 1_000_000
            clock = ReplayClock(time.monotonic_ns() + int(LEAD_S * 1e9), t0, t1 - t0 + step, step)
            _clocks[key] = clock
        return clock


def forget(recording: Path) -> None:
    """Drop the clock (tests; a replay opened afterwards starts a new one)."""
    with _lock:
        _clocks.pop(recording.resolve(), None)
