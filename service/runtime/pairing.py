"""Pair every frame with the robot's reported pose at the frame's mid-exposure instant.

Both devices' clocks are mapped onto the host clock with a lower-envelope fit
(``service.core.pose.timesync``): the camera's exposure-start stamps and the robot
controller's seconds. The transport latencies the envelope cannot see (the
smallest delay from event to arrival) come from the configuration; what is
left of them shows up as a time offset between measured and reported motion,
which the worker estimates and reports (``estimate_time_offset_s``). Each
frame is one clock event, however often it is asked about. A clock's rate is
fitted only over a long enough span (the camera's from 30 s on, the robot's
4 s window never): over a short one a delay floor that moves with the host's
load reads as a drift of hundreds of ppm.

Fallbacks, in order of preference: the driver's own exact exposure time
(``Frame.t_exposure_host_ns``), the mapped device stamp, the arrival time
minus exposure and latency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.base import Frame
from drivers.history import RobotHistory
from service.core.pose.timesync import ClockMapper, pose_at

CAMERA_CLOCK_WINDOW = 1200  # frames: a minute at 20 processed frames per second, four at 5
CAMERA_RATE_SPAN_S = 30.0  # see timesync.fit_lower_envelope: a floor moving by 1 ms then reads as 33 ppm
CAMERA_OFFSET_SPAN_S = 10.0  # meanwhile a 50 ppm drift errs by at most 0.5 ms
ROBOT_RATE_SPAN_S = 30.0
ROBOT_OFFSET_SPAN_S = 2.0


@dataclass(frozen=True)
class Pairing:
    """The robot pose paired with one frame.

    t_exposure_host_ns : mid-exposure on the host clock, as estimated
    T_base_flange : (4, 4) mm, the robot's reported pose interpolated to that instant, or None
    source : how the exposure instant was found: "driver", "device_clock" or "arrival"
    reason : why there is no pose, when T_base_flange is None
    """

    t_exposure_host_ns: int
    T_base_flange: np.ndarray | None
    source: str
    reason: str = ""


class FramePairer:
    """Holds the two clock mappings; one per camera–robot pair, fed by the worker thread."""

    def __init__(
        self,
        camera_transport_latency_s: float = 0.0,
        robot_transport_latency_s: float = 0.0,
        max_sample_gap_s: float = 0.05,
    ) -> None:
        # a camera's delay floor moves with the host's load (its arrival stamps are the host's): its rate
        # is fitted over half a minute or more only, and until then the offset follows the last 10 s
        self.camera_clock = ClockMapper(
            window=CAMERA_CLOCK_WINDOW,
            min_latency_ns=camera_transport_latency_s * 1e9,
            min_rate_span_ns=CAMERA_RATE_SPAN_S * 1e9,
            offset_span_ns=CAMERA_OFFSET_SPAN_S * 1e9,
        )
        # the robot's window (2000 reports: 4 s at 500 Hz) is too short for a rate when the floor moves
        # (it swung by hundreds of ppm on a loaded host): the offset follows the last 2 s instead, where a
        # controller drifting by 50 ppm errs by 0.1 ms at most
        self.robot_clock = ClockMapper(
            window=2000,
            min_latency_ns=robot_transport_latency_s * 1e9,
            refit_every=50,
            min_rate_span_ns=ROBOT_RATE_SPAN_S * 1e9,
            offset_span_ns=ROBOT_OFFSET_SPAN_S * 1e9,
        )
        self.camera_latency_ns = camera_transport_latency_s * 1e9
        self.max_gap_ns = max_sample_gap_s * 1e9
        self._robot_fed_until_ns = -1
        self._last: tuple[tuple[int, int | None, int], tuple[int, str]] | None = None

    def exposure_instant_ns(self, frame: Frame) -> tuple[int, str]:
        """Mid-exposure on the host clock and where it came from; feeds the camera clock mapping.

        A frame is one clock event however often it is asked about (the processor asks, then
        ``pair`` does): the same frame again returns the same instant and adds no point.
        """
        key = (frame.seq, frame.t_device_ns, frame.t_host_ns)
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        half_ns = frame.exposure_us * 500.0
        if frame.t_exposure_host_ns is not None:
            out = int(frame.t_exposure_host_ns), "driver"
        elif frame.t_device_ns is not None:
            # exposure ended before the readout and transfer began: remove it from the arrival
            self.camera_clock.add(frame.t_device_ns, frame.t_host_ns - 2 * half_ns)
            out = int(self.camera_clock.host_from_device(frame.t_device_ns) + half_ns), "device_clock"
        else:
            out = int(frame.t_host_ns - half_ns - self.camera_latency_ns), "arrival"
        self._last = (key, out)
        return out

    def _feed_robot(self, t_host: np.ndarray, t_robot_s: np.ndarray) -> None:
        # only the samples not fed yet (one or two a frame of the ~0.5 s window asked for): a
        # Python loop over the whole window was a tenth of the processing thread's time at 500 Hz
        new = np.flatnonzero((t_host > self._robot_fed_until_ns) & np.isfinite(t_robot_s))
        for k in new.tolist():
            th = int(t_host[k])
            if th > self._robot_fed_until_ns:
                self.robot_clock.add(float(t_robot_s[k]) * 1e9, float(th))
                self._robot_fed_until_ns = th

    def pair(self, frame: Frame, history: RobotHistory, exposure: tuple[int, str] | None = None) -> Pairing:
        """The robot's pose at the frame's exposure; ``exposure``: its :meth:`exposure_instant_ns`,
        when it was asked for already (perhaps before newer frames were)."""
        t_exp, source = exposure or self.exposure_instant_ns(frame)
        window_ns = int(max(self.max_gap_ns, 0.25e9))
        t_host, t_robot_s, T = history.arrays_between(t_exp - window_ns, t_exp + window_ns)
        if t_host.size == 0:
            return Pairing(t_exp, None, source, "no robot sample near the exposure")
        self._feed_robot(t_host, t_robot_s)
        if np.all(np.isfinite(t_robot_s)) and self.robot_clock.fit is not None:
            t_samples = np.asarray(self.robot_clock.fit.host_from_device(t_robot_s * 1e9))
        else:
            t_samples = t_host.astype(np.float64)
        T_pose = pose_at(float(t_exp), t_samples, T, max_gap=self.max_gap_ns)
        if T_pose is None:
            return Pairing(t_exp, None, source, "the robot's samples do not cover the exposure instant")
        return Pairing(t_exp, T_pose, source)
