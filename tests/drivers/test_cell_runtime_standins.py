"""The stand-ins of the simulated cell, as ``service.runtime.cell_runtime`` runs them: their own processes, watched.

A stand-in whose process dies (here: SIGKILL) is started again on the same address with the same cell
and epoch, so the real UR driver reading it finds samples of the same motion again within seconds, and
the runtime says so in its events. A service that dies takes its stand-ins with it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_receive", reason="ur-rtde is installed by deploy/dev.sh (test extras)")
pytest.importorskip("drivers.standins.gv_camera", reason="PyGObject and Aravis 0.8 (deploy/dev.sh)")

from drivers.base import DriverDisconnected  # noqa: E402
from drivers.robot.ur import URRobot  # noqa: E402
from service.core.geometry.frames import pose_difference  # noqa: E402
from service.runtime.cell_runtime import CellRuntime  # noqa: E402
from service.settings import load_settings  # noqa: E402

RTDE_ADDRESS = "127.0.0.16"  # this file's own (see test_ur_rtde.py for the others)


def _wait_for(predicate: Callable[[], bool], timeout_s: float) -> float | None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if predicate():
            return time.monotonic() - t0
        time.sleep(0.02)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_killed_rtde_standin_is_restarted_and_robot_samples_flow_again(tmp_path: Path) -> None:
    events: list[tuple[str, str, str]] = []
    runtime = CellRuntime(
        load_settings(None, state_dir=tmp_path, sim__transport="standins"), on_event=lambda *e: events.append(e)
    )
    runtime.rtde_address = RTDE_ADDRESS
    runtime.start()
    robot = URRobot(RTDE_ADDRESS, frequency_hz=125.0, reconnect_interval_s=0.2)
    try:
        robot.open()
        old_pid = runtime.standin_processes["rtde"].pid
        assert old_pid is not None
        os.kill(old_pid, signal.SIGKILL)
        t_kill_ns = time.monotonic_ns()
        assert _wait_for(lambda: not robot.connected, 3.0) is not None

        def fresh() -> bool:
            try:
                return robot.latest().t_host_ns > t_kill_ns + 0.1e9
            except DriverDisconnected:
                return False

        t_back_s = _wait_for(fresh, 15.0)
        assert t_back_s is not None, f"no robot sample since the kill; events: {events}"
        assert runtime.standin_processes["rtde"].pid != old_pid
        assert runtime.standin_processes["rtde"].restarts == 1
        kinds = [kind for _, kind, _ in events]
        assert kinds[:2] == ["standin_died", "standin_restarted"], events
        assert str(old_pid) in events[0][2]
        # the same cell and epoch: the restarted controller reports where the arm is now
        s = robot.latest()
        t_cell_s = (s.t_host_ns - runtime.epoch_ns) * 1e-9
        errors = [
            pose_difference(s.T_base_flange, runtime.cell.robot_report(t_cell_s - dt, None)[0])[0]
            for dt in np.linspace(0.0, 0.005, 11)
        ]
        assert min(errors) < 0.2
    finally:
        robot.close()
        runtime.stop()
    assert all(p.proc is None for p in runtime.standin_processes.values())


def test_the_standins_stop_with_the_service_that_started_them(tmp_path: Path) -> None:
    # a service killed outright (no stop()) must not leave its stand-ins holding their addresses
    script = (
        "import sys, time\n"
        "from service.runtime.cell_runtime import CellRuntime\n"
        "from service.settings import load_settings\n"
        f"r = CellRuntime(load_settings(None, state_dir={str(tmp_path)!r}, sim__transport='standins'))\n"
        f"r.rtde_address = {RTDE_ADDRESS!r}\n"
        "r.start()\n"
        "print(*(p.pid for p in r.standin_processes.values()), flush=True)\n"
        "time.sleep(60)\n"
    )
    service = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2]
    )
    try:
        assert service.stdout is not None
        pids = [int(p) for p in service.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
    finally:
        service.kill()
        service.wait()
    assert _wait_for(lambda: not any(_alive(p) for p in pids), 15.0) is not None, "the stand-ins outlived it"
