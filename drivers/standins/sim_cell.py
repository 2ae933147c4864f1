"""The simulated cell behind the real protocols: its arm over RTDE, its camera over GigE Vision.

``CellArm`` is an RTDE stand-in state source: the arm's *nominal* flange pose
(the controller's belief, with encoder noise) as ``actual_TCP_pose`` with a zero
TCP offset, and its joints. It reads the cell at host monotonic time minus the
shared epoch, as the camera's frame source does, so a camera and a robot served
in different processes see one consistent motion (CLOCK_MONOTONIC is system-wide).
With ``controller_origin_ns`` (the server's ``origin_ns``) that time is the
controller tick's own instant, the one its ``timestamp`` names, not the moment
the server got round to the tick, which is later by its scheduling delay (a
pose and its timestamp must agree, as on a real controller).

Each stand-in runs in a process of its own (``python -m drivers.standins.sim_cell
--serve rtde|camera``), started and watched by ``service.runtime.cell_runtime``: the
ur_rtde client must not share a process with the service's event loop, and a
stand-in inside the service would live under the service's GIL. For the camera
that matters most: the fake camera's thread needs the GIL to end each exposure
on time and to hand the frame to libaravis, and the service's numba kernels hold
it for milliseconds at a time, so its frames would leave late by however long
(``gv_camera.GvStandIn(render_ahead=True)``; its own process also renders on a
core of its own). The camera process shortens its GIL switch interval, since
its render thread and its fake camera's thread compete for its GIL, and both
raise the priority of the threads that keep time (the controller clock, the
fake camera's exposures) when they may, as the UR driver's reader does: a real
controller or camera keeps time in hardware, whatever the host's load.

Both print ``ready`` on stdout once they serve, and stop on SIGTERM, or with
``--parent-stdin`` when their stdin reaches end-of-file: the parent holds the
other end, so a service that dies without stopping them (SIGKILL, a crash) takes
its stand-ins with it instead of leaving them on their addresses.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading
import time

import numpy as np

from drivers.standins.rtde_protocol import RobotState
from drivers.standins.rtde_server import RtdeServer
from service.core.geometry.frames import ur_pose_from_T
from service.sim.cell import CellConfig, SimCell

log = logging.getLogger(__name__)


class CellArm:
    """RTDE state source of the simulated cell's arm (see the module docstring)."""

    def __init__(self, cell: SimCell, epoch_ns: int, seed: int = 3) -> None:
        self.cell = cell
        self.epoch_ns = int(epoch_ns)
        self._rng = np.random.default_rng(seed)
        self.controller_origin_ns: int | None = None

    def __call__(self, t_s: float) -> RobotState:
        origin = self.controller_origin_ns
        t_host_ns = time.monotonic_ns() if origin is None else origin + round(t_s * 1e9)
        t_cell_s = (t_host_ns - self.epoch_ns) * 1e-9
        T_base_flange, q = self.cell.robot_report(t_cell_s, self._rng)
        pose = tuple(float(v) for v in ur_pose_from_T(T_base_flange))
        qt = tuple(float(v) for v in q)
        return RobotState(actual_TCP_pose=pose, target_TCP_pose=pose, actual_q=qt, target_q=qt)


CAMERA_SWITCH_INTERVAL_S = 0.0005  # the camera process: its fake camera's thread gets the GIL back this soon
TIMING_NICE = -10  # the threads that keep the stand-ins' time (when the process may raise their priority)


def _serve_rtde(cell: SimCell, epoch_ns: int, host: str, done: threading.Event) -> None:
    try:
        os.nice(TIMING_NICE)  # this process only ticks the controller clock: all of it keeps time
    except OSError:
        pass
    arm = CellArm(cell, epoch_ns)
    with RtdeServer(arm, host=host) as server:
        arm.controller_origin_ns = server.origin_ns  # before any client: no tick reads it earlier
        log.info("RTDE stand-in of the simulated cell on %s:30004", host)
        print("ready", flush=True)  # noqa: T201 -- the parent waits for this line
        done.wait()


def _serve_camera(cell: SimCell, epoch_ns: int, host: str, serial: str, done: threading.Event) -> None:
    import sys

    from drivers.standins.gv_camera import GvStandIn, cell_frame_source  # needs PyGObject + Aravis

    sys.setswitchinterval(CAMERA_SWITCH_INTERVAL_S)
    with GvStandIn(
        cell_frame_source(cell, epoch_ns),
        address=host,
        serial=serial,
        width=cell.camera.width,
        height=cell.camera.height,
        render_ahead=True,
        readout_nice=TIMING_NICE,
    ) as camera:
        log.info("GigE Vision stand-in of the simulated cell on %s", host)
        print("ready", flush=True)  # noqa: T201 -- the parent waits for this line
        while not done.wait(60.0):
            d = np.array(camera.readout_delays_s) * 1e3
            if d.size:
                log.debug(
                    "frames %d (%d rendered ahead); readout after the exposure: min %.2f, median %.2f ms",
                    camera.frames_served,
                    camera.frames_rendered_ahead,
                    d.min(),
                    np.median(d),
                )


def _stop_at_eof(done: threading.Event) -> None:
    # os.read on the descriptor: sys.stdin's buffer lock held by this daemon thread at exit aborts Python
    while os.read(0, 4096):
        pass
    log.info("the parent process is gone: stopping")
    done.set()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="a stand-in of the simulated cell on loopback: its arm or its camera")
    p.add_argument(
        "--serve",
        choices=("rtde", "camera"),
        default="rtde",
        help="rtde: the arm on port 30004; camera: the GigE Vision camera",
    )
    p.add_argument("--host", default="127.0.0.2", help="address to serve on (the camera: an interface's)")
    p.add_argument("--epoch-ns", type=int, required=True, help="host monotonic time of the cell's t = 0")
    p.add_argument("--cell", default="{}", help="CellConfig as JSON")
    p.add_argument("--serial", default="POSECELL-SIM", help="the camera's serial number")
    p.add_argument("--parent-stdin", action="store_true", help="stop when stdin closes (the parent is gone)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    import json

    cell = SimCell(CellConfig.from_dict(json.loads(args.cell)))
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    if args.parent_stdin:
        threading.Thread(target=_stop_at_eof, args=(done,), name="parent-watch", daemon=True).start()
    if args.serve == "rtde":
        _serve_rtde(cell, args.epoch_ns, args.host, done)
    else:
        _serve_camera(cell, args.epoch_ns, args.host, args.serial, done)


if __name__ == "__main__":
    main()
