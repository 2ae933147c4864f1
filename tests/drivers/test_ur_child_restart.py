"""The UR driver's ur_rtde child process killed under it: the link reads as down at once, and a new child takes over.

Against the RTDE stand-in on an address of its own (``ur_rtde`` always uses port 30004; see
``test_ur_rtde.py`` for the addresses the other tests take).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable

import pytest

pytest.importorskip("rtde_receive", reason="ur-rtde is installed by deploy/dev.sh (test extras)")

from drivers.base import DriverDisconnected  # noqa: E402
from drivers.robot.ur import URRobot  # noqa: E402
from drivers.standins.demo_arm import DemoArm  # noqa: E402
from drivers.standins.rtde_server import RtdeServer  # noqa: E402

HOST = "127.0.0.12"


def _wait_for(predicate: Callable[[], bool], timeout_s: float) -> float | None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if predicate():
            return time.monotonic() - t0
        time.sleep(0.005)
    return None


def _fresh_after(robot: URRobot, t_ns: int) -> bool:
    try:
        return robot.latest().t_host_ns > t_ns
    except DriverDisconnected:
        return False


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killing_the_rtde_child_drops_the_link_at_once_and_a_new_child_recovers_it(sig: signal.Signals) -> None:
    with RtdeServer(DemoArm(), host=HOST):
        robot = URRobot(HOST, frequency_hz=125.0, reconnect_interval_s=0.2)
        try:
            robot.open()
            assert robot.connected
            pid = robot._proc.pid
            os.kill(pid, sig)
            t_kill_ns = time.monotonic_ns()
            t_down_s = _wait_for(lambda: not robot.connected, 2.0)
            assert t_down_s is not None and t_down_s < 0.25, "the dead child's link still reads as up"
            with pytest.raises(DriverDisconnected, match="RTDE child process ended"):
                robot.latest()
            t_back_s = _wait_for(lambda: _fresh_after(robot, t_kill_ns), 10.0)
            assert t_back_s is not None, "no sample from a new child"
            assert robot.connected
            assert robot._proc is not None and robot._proc.pid != pid
            assert robot.stats["child_restarts"] == 1 and robot.stats["links_up"] == 2
        finally:
            robot.close()


def test_the_worker_reports_a_killed_rtde_child_before_it_reconnects(tmp_path) -> None:
    from service.runtime.acquisition import DeviceState
    from service.runtime.worker import Worker
    from service.settings import load_settings

    host = "127.0.0.18"  # this test's own address
    settings = load_settings(
        None, state_dir=str(tmp_path), robot__driver="ur", robot__options={"host": host, "frequency_hz": 125.0}
    )
    with RtdeServer(DemoArm(), host=host):
        worker = Worker(settings)
        worker.start()
        try:
            assert _wait_for(lambda: worker.robot_state is DeviceState.ok, 20.0) is not None
            seen: list[str] = []
            os.kill(worker.robot._proc.pid, signal.SIGKILL)
            t_down = _wait_for(
                lambda: seen.append(str(worker.robot_state)) or worker.robot_state is DeviceState.disconnected, 1.0
            )
            assert t_down is not None, f"the outage never showed: {sorted(set(seen))}"
            assert _wait_for(lambda: worker.robot_state is DeviceState.ok, 10.0) is not None
        finally:
            worker.stop()
