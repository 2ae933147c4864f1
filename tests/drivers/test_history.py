"""The robot history's time queries: the samples in a span, oldest first, across the ring's wrap."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.base import RobotSample
from drivers.history import RobotHistory


def _filled(capacity: int, total: int, rng: np.random.Generator) -> tuple[RobotHistory, list[tuple[int, float]]]:
    h, t, kept = RobotHistory(capacity), 0, []
    for i in range(total):
        t += int(rng.integers(0, 3))  # equal stamps happen (two samples in one host tick)
        h.append(RobotSample(np.eye(4) * (i + 1), np.zeros(6), t, float(i)))
        kept.append((t, float(i)))
    return h, kept[-capacity:]


@pytest.mark.parametrize(("capacity", "total"), [(10, 0), (10, 5), (10, 10), (10, 37), (7, 1000), (500, 1234)])
def test_the_samples_between_two_times_are_those_of_the_newest_capacity_in_arrival_order(capacity, total):
    rng = np.random.default_rng(capacity * 1000 + total)
    h, kept = _filled(capacity, total, rng)
    t_max = kept[-1][0] if kept else 0
    for _ in range(200):
        t0 = int(rng.integers(-5, t_max + 5))
        t1 = t0 + int(rng.integers(-2, 20))
        expected = [(t, i) for t, i in kept if t0 <= t <= t1]
        t_host, t_robot, T = h.arrays_between(t0, t1)
        assert list(zip(t_host.tolist(), t_robot.tolist())) == expected
        assert [s.t_robot_s for s in h.samples_between(t0, t1)] == [i for _, i in expected]
        assert all(T[k][0, 0] == i + 1 for k, (_, i) in enumerate(expected))
