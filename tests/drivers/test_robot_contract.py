"""One contract, every robot driver: simulated, the UR driver on the RTDE stand-in, and hardware on request."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import DriverDisconnected, RobotDriver
from service.core.geometry.frames import check_T
from tests.drivers.conftest import robot_factories, use

FACTORIES = robot_factories()


@pytest.fixture(params=sorted(FACTORIES))
def robot(request):
    with use(FACTORIES[request.param], request.param) as r:
        r.open()
        yield r


def test_robot_satisfies_the_protocol(robot):
    assert isinstance(robot, RobotDriver)
    assert robot.connected
    assert robot.info.rate_hz >= 100


def test_samples_are_valid_poses_in_mm_at_the_reporting_rate(robot):
    time.sleep(1.0)
    s = robot.latest()
    check_T(s.T_base_flange)
    assert 100.0 < np.linalg.norm(s.T_base_flange[:3, 3]) < 5000.0  # mm, not m
    assert s.q_rad.shape == (6,)
    now = time.monotonic_ns()
    assert 0 <= now - s.t_host_ns < 0.5e9
    window = robot.samples_between(now - int(0.8e9), now)
    t = np.array([x.t_host_ns for x in window])
    assert np.all(np.diff(t) >= 0)
    rate = (len(t) - 1) / ((t[-1] - t[0]) * 1e-9)
    assert 0.7 * robot.info.rate_hz < rate < 1.3 * robot.info.rate_hz
    if window[0].t_robot_s is not None:
        t_robot = np.array([x.t_robot_s for x in window])
        assert np.all(np.diff(t_robot) > 0)


def test_close_is_idempotent_and_a_closed_robot_says_so(robot):
    robot.close()
    robot.close()
    assert not robot.connected
    with pytest.raises(DriverDisconnected):
        robot.latest()
