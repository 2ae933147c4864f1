"""Time alignment: device clocks onto the host clock, and the robot's pose at a frame's exposure.

A camera stamps each frame with its own tick counter at the exposure start; the
robot controller stamps each state with its own seconds. Both arrive at the host
later by a transport delay that is never negative but jitters. So the host
arrival time is an *upper bound* of the event's host time, and the best line
``t_host = offset + rate * t_device`` lies under all points, touching the
lowest ones: the lower convex hull, the classic one-way clock synchronisation
(Moon, Skelly, Towsley 1999). Written by hand because it is the method, not a
library routine: a least-squares fit would carry the mean jitter into the
offset, the lower envelope carries only the minimum delay, which is the
transport latency a caller can state (``min_latency_ns``) or measure
(``estimate_time_offset_s`` from the poses themselves).

All times are integers or floats in ns unless a name says ``_s``.
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core._kernels.geometry_kernels import pose_at_kernel

Array = NDArray[np.float64]

MAX_DRIFT = 1e-3  # 1000 ppm: a crystal drifts < 100 ppm; larger means a wrong clock unit or a reset
RESET_JUMP_NS = 1e9  # a device clock going back further than this was reset; less: events out of order


@dataclass(frozen=True)
class ClockFit:
    """``t_host = t_host_ref + rate * (t_device - t_device_ref)``, valid near the fitted window.

    jitter_ns : median height of the points above the envelope (the typical transport jitter)
    """

    t_device_ref: float
    t_host_ref: float
    rate: float
    jitter_ns: float
    n: int

    @property
    def drift_ppm(self) -> float:
        return (self.rate - 1.0) * 1e6

    def host_from_device(self, t_device: ArrayLike) -> NDArray[np.float64] | float:
        t = np.asarray(t_device, dtype=np.float64)
        out = self.t_host_ref + self.rate * (t - self.t_device_ref)
        return float(out) if out.ndim == 0 else out


def _lower_hull(x: Array, y: Array) -> list[int]:
    """Indices of the lower convex hull of points sorted by x (Andrew's monotone chain)."""
    hull: list[int] = []
    for i in range(len(x)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            # keep b only if a -> b -> i turns left (b lies strictly below the chord a -> i)
            if (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a]) > 0:
                break
            hull.pop()
        hull.append(i)
    return hull


def fit_lower_envelope(
    t_device: ArrayLike,
    t_host: ArrayLike,
    min_latency_ns: float = 0.0,
    min_rate_span_ns: float = 0.0,
    offset_span_ns: float = np.inf,
) -> ClockFit:
    """Fit the clock line under all (device, host-arrival) points.

    Parameters
    ----------
    t_device : (N,) float, ns — event times on the device clock
    t_host : (N,) float, ns — arrival times on the host clock (event + delay, delay >= min_latency)
    min_latency_ns : the smallest transport delay, subtracted from the envelope
    min_rate_span_ns : fit a rate only over at least this much device time; shorter: rate 1
    offset_span_ns : with rate 1 for want of span, the line touches the lowest point of only the
        newest this much device time (a drift of d ppm then errs by at most d * offset_span)

    The chosen hull edge is the one spanning the window's mean device time,
    which maximises the line's mean height (the LP optimum), so it is the
    most accurate over the window. A rate outside 1 ± MAX_DRIFT falls back to
    rate 1 (too few points to see drift, or a clock that was reset). Over a
    short window the slope is mostly the delay floor's own change (delays
    settling after a start, a host's load coming and going): a floor 1 ms
    lower 5 s later reads as 200 ppm, extrapolated to the newest events; a
    caller whose floor may move asks for ``min_rate_span_ns`` (30 s makes
    that 33 ppm), and meanwhile for a recent ``offset_span_ns``.
    """
    d = np.asarray(t_device, dtype=np.float64).ravel()
    h = np.asarray(t_host, dtype=np.float64).ravel()
    if d.size == 0 or d.size != h.size:
        raise ValueError(f"need matching non-empty time arrays, got {d.size} device and {h.size} host times")
    order = np.argsort(d, kind="stable")
    d, h = d[order], h[order]
    d_ref, h_ref = d[0], h[0]
    x, y = d - d_ref, h - h_ref  # small numbers: no precision loss in the cross products
    rate = 1.0
    intercept = float(np.min(y - x))
    if d.size >= 3 and x[-1] > 0 and x[-1] < min_rate_span_ns:
        recent = x >= x[-1] - offset_span_ns
        intercept = float(np.min(y[recent] - x[recent]))
    elif d.size >= 3 and x[-1] > 0:
        hull = _lower_hull(x, y)
        x_mean = float(np.mean(x))
        for a, b in itertools.pairwise(hull):
            if x[a] <= x_mean <= x[b] and x[b] > x[a]:
                slope = (y[b] - y[a]) / (x[b] - x[a])
                if abs(slope - 1.0) < MAX_DRIFT:
                    rate = float(slope)
                    intercept = float(y[a] - slope * x[a])
                break
        intercept = float(np.min(y - rate * x))  # touch the lowest point (guards the fallback branch)
    above = y - (intercept + rate * x)
    return ClockFit(
        t_device_ref=float(d_ref),
        t_host_ref=float(h_ref + intercept - min_latency_ns),
        rate=rate,
        jitter_ns=float(np.median(above)),
        n=int(d.size),
    )


class ClockMapper:
    """Online device → host clock mapping over a sliding window of recent events.

    A pure, deterministic accumulator: the caller feeds (device time, arrival
    time) pairs and asks for host times; no clock is read here.
    """

    def __init__(
        self,
        window: int = 300,
        min_latency_ns: float = 0.0,
        refit_every: int = 10,
        min_rate_span_ns: float = 0.0,
        offset_span_ns: float = np.inf,
    ) -> None:
        if window < 2:
            raise ValueError("window must hold at least 2 events")
        self._d: deque[float] = deque(maxlen=window)
        self._h: deque[float] = deque(maxlen=window)
        self.min_latency_ns = float(min_latency_ns)
        self.min_rate_span_ns = float(min_rate_span_ns)
        self.offset_span_ns = float(offset_span_ns)
        self._refit_every = max(1, refit_every)
        self._since_fit = 0
        self._fit: ClockFit | None = None

    def add(self, t_device: float, t_host_arrival: float) -> None:
        """Record one event; a device clock that jumps back (a camera reset) restarts the window.

        An event less than ``RESET_JUMP_NS`` older than the newest is one that arrived out of order
        (a package overtaken by the next): it is left out, not taken for a reset. Compared as
        stored (float): an integer stamp above 2**53 ns (a device clock counting from 1970 does)
        rounds, and Python compares an int with the float it rounded to exactly, so the same stamp
        given twice would otherwise read as a jump back.
        """
        d = float(t_device)
        if self._d and d < self._d[-1]:
            if self._d[-1] - d < RESET_JUMP_NS:
                return
            self.reset()
        self._d.append(d)
        self._h.append(float(t_host_arrival))
        self._since_fit += 1
        # the envelope only moves when a new low point arrives or the window slides; refitting every
        # few events keeps the cost at a fraction of a millisecond per frame
        if self._fit is None or self._since_fit >= self._refit_every or len(self._d) < 20:
            self._refit()

    def _refit(self) -> None:
        self._fit = fit_lower_envelope(
            np.fromiter(self._d, float),
            np.fromiter(self._h, float),
            self.min_latency_ns,
            self.min_rate_span_ns,
            self.offset_span_ns,
        )
        self._since_fit = 0

    def reset(self) -> None:
        self._d.clear()
        self._h.clear()
        self._fit = None
        self._since_fit = 0

    @property
    def fit(self) -> ClockFit | None:
        return self._fit

    @property
    def n(self) -> int:
        return len(self._d)

    def host_from_device(self, t_device: float) -> float:
        if self._fit is None:
            raise ValueError("no clock events recorded yet")
        return float(self._fit.host_from_device(t_device))


def pose_at(t: float, t_samples: ArrayLike, T_samples: ArrayLike, max_gap: float) -> NDArray[np.float64] | None:
    """The pose at time ``t`` interpolated between the two samples around it.

    Parameters
    ----------
    t : the query time (any unit, the same as ``t_samples``)
    t_samples : (N,) increasing sample times
    T_samples : (N, 4, 4) poses, mm
    max_gap : the largest bracketing interval (and the largest extrapolation past the
        newest sample, for a query a little ahead of the robot's next report) accepted

    Returns None when ``t`` is not covered: the caller reports the frame as not
    paired rather than pairing it with a stale pose. Linear in position, slerp
    in rotation (``frames.interpolate_T``).
    """
    ts = np.ascontiguousarray(t_samples, dtype=np.float64).reshape(-1)
    Ts = np.ascontiguousarray(T_samples, dtype=np.float64).reshape(-1, 4, 4)
    # compiled: the pairing's per-frame call (a dozen numpy calls, each a wait for the interpreter
    # lock on the service's busy processing thread)
    covered, T = pose_at_kernel(float(t), ts, Ts, float(max_gap))
    return T if covered else None


@dataclass(frozen=True)
class TimeOffsetFit:
    """How much later the measured motion happened than the reported one says.

    offset_s : a pose measured at a frame time t matches the robot's report at t - offset_s,
        i.e. the frame times are offset_s too late (subtract it from them)
    sigma_s : its standard deviation
    bias_mm : (3,) the constant position difference (model errors), fitted alongside
    rms_mm : the residual after removing both
    """

    offset_s: float
    sigma_s: float
    bias_mm: Array
    rms_mm: float
    n: int


def estimate_time_offset_s(t_s: ArrayLike, p_measured_mm: ArrayLike, p_reported_mm: ArrayLike) -> TimeOffsetFit:
    """Estimate the residual latency between camera-measured and robot-reported positions in motion.

    Model: ``p_measured(t) = p_reported(t - offset) + bias ≈ p_reported(t) - v(t) * offset + bias``
    with ``v`` the reported velocity (finite differences), solved by linear least
    squares. The robot's geometric errors change slowly along a path and go into
    ``bias``; the fit needs motion (speed) to see the offset.

    Parameters
    ----------
    t_s : (N,) s — the paired instants, increasing
    p_measured_mm, p_reported_mm : (N, 3) mm — flange (or camera) positions in one frame
    """
    t = np.asarray(t_s, dtype=np.float64)
    pm = np.asarray(p_measured_mm, dtype=np.float64).reshape(-1, 3)
    pr = np.asarray(p_reported_mm, dtype=np.float64).reshape(-1, 3)
    n = t.size
    if n < 5 or pm.shape[0] != n or pr.shape[0] != n:
        raise ValueError(f"need >= 5 paired positions with matching times, got {n}")
    v = np.asarray(np.gradient(pr, t, axis=0))  # mm/s
    A = np.zeros((3 * n, 4))
    A[:, 0] = -v.ravel()
    A[:, 1:] = np.tile(np.eye(3), (n, 1))
    b = (pm - pr).ravel()
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ x
    dof = max(1, 3 * n - 4)
    s2 = float(r @ r) / dof
    AtA = A.T @ A
    if np.linalg.cond(AtA) > 1e12:
        raise ValueError("the robot hardly moved: a time offset cannot be seen without motion")
    cov = s2 * np.linalg.inv(AtA)
    return TimeOffsetFit(
        offset_s=float(x[0]),
        sigma_s=float(np.sqrt(cov[0, 0])),
        bias_mm=np.array(x[1:], dtype=np.float64),
        rms_mm=float(np.sqrt(np.mean(r.reshape(n, 3) ** 2) * 3)),
        n=n,
    )
