"""The simulated cell's arm behind the real RTDE protocol (its camera: ``gv_camera.cell_frame_source``).

``CellArm`` is an RTDE stand-in state source: the arm's *nominal* flange pose
(the controller's belief, with encoder noise) as ``actual_TCP_pose`` with a zero
TCP offset, and its joints. It reads the cell at host monotonic time minus the
shared epoch, as the camera's frame source does, so a camera and a robot served
in different processes see one consistent motion (CLOCK_MONOTONIC is system-wide).

The RTDE stand-in runs in its own process (``python -m drivers.standins.sim_cell``)
because the ur_rtde client must not share a process with the service's event
loop, and a stand-in in the client's process would starve under its GIL.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time

import numpy as np

from drivers.standins.rtde_server import RobotState, RtdeServer
from service.core.frames import ur_pose_from_T
from service.sim.cell import CellConfig, SimCell

log = logging.getLogger(__name__)


class CellArm:
    """RTDE state source of the simulated cell's arm (see the module docstring)."""

    def __init__(self, cell: SimCell, epoch_ns: int, seed: int = 3) -> None:
        self.cell = cell
        self.epoch_ns = int(epoch_ns)
        self._rng = np.random.default_rng(seed)

    def __call__(self, t_s: float) -> RobotState:
        t_cell_s = (time.monotonic_ns() - self.epoch_ns) * 1e-9
        T_base_flange, q = self.cell.robot_report(t_cell_s, self._rng)
        pose = tuple(float(v) for v in ur_pose_from_T(T_base_flange))
        qt = tuple(float(v) for v in q)
        return RobotState(actual_TCP_pose=pose, target_TCP_pose=pose, actual_q=qt, target_q=qt)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="RTDE stand-in serving the simulated cell's arm on loopback")
    p.add_argument("--host", default="127.0.0.2")
    p.add_argument("--epoch-ns", type=int, required=True, help="host monotonic time of the cell's t = 0")
    p.add_argument("--cell", default="{}", help="CellConfig as JSON")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    import json

    cell = SimCell(CellConfig.from_dict(json.loads(args.cell)))
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with RtdeServer(CellArm(cell, args.epoch_ns), host=args.host):
        log.info("RTDE stand-in of the simulated cell on %s:30004", args.host)
        print("ready", flush=True)  # noqa: T201 -- the parent waits for this line
        done.wait()


if __name__ == "__main__":
    main()
