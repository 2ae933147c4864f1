"""A time-indexed ring buffer of robot samples, shared by the robot drivers.

One reader thread appends, the worker queries; a lock keeps a query from
seeing half a sample. Preallocated arrays: at 500 Hz a 10 s history is 5000
poses, appended without allocation and searched by bisection.
"""

from __future__ import annotations

import threading
from typing import Literal

import numpy as np

from drivers.base import RobotSample


class RobotHistory:
    """The last ``capacity`` samples in arrival order (``t_host_ns`` must not decrease)."""

    def __init__(self, capacity: int, n_joints: int = 6) -> None:
        if capacity < 2:
            raise ValueError("a robot history needs room for at least 2 samples")
        self.capacity = capacity
        self._t_host = np.zeros(capacity, dtype=np.int64)
        self._t_robot = np.full(capacity, np.nan)
        self._T = np.zeros((capacity, 4, 4))
        self._q = np.zeros((capacity, n_joints))
        self._n = 0  # samples ever appended
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    @property
    def n_total(self) -> int:
        return self._n

    def append(self, sample: RobotSample) -> None:
        with self._lock:
            if self._n and sample.t_host_ns < self._t_host[(self._n - 1) % self.capacity]:
                return  # out of order (a clock step): dropped, never reorders the buffer
            i = self._n % self.capacity
            self._t_host[i] = sample.t_host_ns
            self._t_robot[i] = np.nan if sample.t_robot_s is None else sample.t_robot_s
            self._T[i] = sample.T_base_flange
            self._q[i] = sample.q_rad
            self._n += 1

    def clear(self) -> None:
        with self._lock:
            self._n = 0

    def _sample(self, i: int) -> RobotSample:
        t_robot = float(self._t_robot[i])
        return RobotSample(
            T_base_flange=self._T[i].copy(),
            q_rad=self._q[i].copy(),
            t_host_ns=int(self._t_host[i]),
            t_robot_s=None if np.isnan(t_robot) else t_robot,
        )

    def latest(self) -> RobotSample | None:
        with self._lock:
            return self._sample((self._n - 1) % self.capacity) if self._n else None

    def _span(self, t0_host_ns: int, t1_host_ns: int) -> tuple[slice, ...]:
        """Buffer slices of the samples with t0 <= t_host <= t1, oldest first (the lock held): one,
        or two where the span crosses the buffer's end.

        The ring holds its samples in arrival order as at most two sorted runs (before and after the
        wrap), each searched by ``np.searchsorted``: at 500 Hz the pairing asks this for every frame,
        under the lock the reader's appends wait for (a bisection in Python over the ring took 30 us
        of it, sorting out all 5000 slots far more). Slices, not an index array: the pairing's copy of
        a window took 17 us with
        fancy indexing and np.searchsorted, 8-11 us now.
        """
        n, cap = len(self), self.capacity
        start = (self._n - n) % cap  # the oldest sample's slot
        t = self._t_host
        first = t[start : min(start + n, cap)]  # up to the buffer's end
        second = t[: n - first.size]  # after the wrap (empty when there is none)

        def position(value: int, side: Literal["left", "right"]) -> int:
            # the arrays' method: np.searchsorted's wrapper cost 2.7 against 0.7 us here
            k = int(first.searchsorted(value, side))
            return k if k < first.size else first.size + int(second.searchsorted(value, side))

        lo = position(t0_host_ns, "left")
        hi = max(lo, position(t1_host_ns, "right"))
        a, b = start + lo, start + hi
        if b <= cap:
            return (slice(a, b),)
        if a >= cap:
            return (slice(a - cap, b - cap),)
        return slice(a, cap), slice(0, b - cap)

    @staticmethod
    def _copy(values: np.ndarray, span: tuple[slice, ...]) -> np.ndarray:
        return values[span[0]].copy() if len(span) == 1 else np.concatenate([values[s] for s in span])

    def samples_between(self, t0_host_ns: int, t1_host_ns: int) -> list[RobotSample]:
        with self._lock:
            return [
                self._sample(i)
                for part in self._span(t0_host_ns, t1_host_ns)
                for i in range(*part.indices(self.capacity))
            ]

    def arrays_between(self, t0_host_ns: int, t1_host_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_host_ns (K,), t_robot_s (K,), T_base_flange (K, 4, 4)) copies, for vectorised pairing."""
        with self._lock:
            span = self._span(t0_host_ns, t1_host_ns)
            return self._copy(self._t_host, span), self._copy(self._t_robot, span), self._copy(self._T, span)

    def columns_between(
        self, t0_host_ns: int, t1_host_ns: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`arrays_between` and the joints, q_rad (K, n_joints): a recording's copy of the samples."""
        with self._lock:
            span = self._span(t0_host_ns, t1_host_ns)
            return tuple(self._copy(values, span) for values in (self._t_host, self._t_robot, self._T, self._q))  # type: ignore[return-value]
