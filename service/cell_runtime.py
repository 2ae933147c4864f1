"""The simulated cell as the service runs it: one SimCell shared by the simulated drivers.

With ``sim.transport = "direct"`` the simulated drivers (``drivers/camera/sim.py``,
``drivers/robot/sim.py``) read the cell in-process. Both share the cell and its
epoch (the host monotonic time of the cell's t = 0), so the camera sees the arm
where the controller says it is, up to the arm's model errors.

With ``sim.transport = "standins"`` the service runs its *real* drivers against
protocol stand-ins of the same cell: the Aravis driver against Aravis's fake
GigE Vision camera on 127.0.0.1 (in this process, as Aravis requires an
interface address), and the UR driver (ur_rtde in its child process) against
the RTDE stand-in in a process of its own (``drivers.standins.sim_cell``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

from service.formats import field_to_json
from service.settings import CameraConfig, Settings
from service.sim.cell import CellConfig, SimCell

GV_ADDRESS = "127.0.0.1"  # Aravis's fake camera needs an address of an interface: lo has only this one
RTDE_ADDRESS = "127.0.0.20"  # ur_rtde's port is fixed (30004): an address of its own, clear of the tests'


class CellRuntime:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.active = settings.uses_sim
        self.epoch_ns = time.monotonic_ns()
        self._cell: SimCell | None = None
        self._gv: Any = None
        self._rtde: subprocess.Popen[str] | None = None

    @property
    def cell(self) -> SimCell:
        if self._cell is None:
            s = self.settings.sim
            self._cell = SimCell(CellConfig(seed=s.seed, robot=s.robot, program=s.program, error_scale=s.error_scale))
        return self._cell

    @property
    def standins(self) -> bool:
        return self.active and self.settings.sim.transport == "standins"

    def start(self) -> None:
        if not self.active:
            return
        cell = self.cell  # build it (inverse kinematics of the program) before the drivers need it
        if not self.standins:
            return
        from drivers.standins.gv_camera import GvStandIn, cell_frame_source  # needs PyGObject + Aravis

        source = cell_frame_source(cell, self.epoch_ns, ahead=True)
        self._gv = GvStandIn(source, address=GV_ADDRESS, serial="POSECELL-SIM",
                             width=cell.camera.width, height=cell.camera.height)
        self._gv.start()
        self._rtde = subprocess.Popen(
            [sys.executable, "-m", "drivers.standins.sim_cell", "--host", RTDE_ADDRESS,
             "--epoch-ns", str(self.epoch_ns), "--cell", json.dumps(cell.config.to_dict())],
            stdout=subprocess.PIPE, text=True,
        )
        assert self._rtde.stdout is not None
        line = self._rtde.stdout.readline()  # "ready" once it listens (or "" if it died)
        if line.strip() != "ready":
            raise RuntimeError(f"the RTDE stand-in did not start (exit code {self._rtde.poll()})")

    def stop(self) -> None:
        if self._rtde is not None:
            self._rtde.terminate()
            try:
                self._rtde.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._rtde.kill()
            self._rtde = None
        if self._gv is not None:
            self._gv.stop()
            self._gv = None

    def camera_driver(self, cfg: CameraConfig) -> tuple[str, dict[str, Any]]:
        """The registry name and options of a configured camera (the simulated one is substituted here)."""
        if cfg.driver != "sim":
            return cfg.driver, dict(cfg.options)
        if self.standins:
            # frames rendered ahead leave only the copy and the loopback transfer as latency
            cfg.transport_latency_s = 0.0005
            return "aravis", {"device": GV_ADDRESS, "packet_size": 8192}
        return "sim", {"cell": self.cell, "epoch_ns": self.epoch_ns, **cfg.options}

    def robot_driver(self) -> tuple[str, dict[str, Any]]:
        r = self.settings.robot
        if r.driver != "sim":
            return r.driver, dict(r.options)
        if self.standins:
            return "ur", {"host": RTDE_ADDRESS, "frequency_hz": 500.0}
        return "sim", {"cell": self.cell, "epoch_ns": self.epoch_ns, **r.options}

    def defaults(self) -> dict[str, Any]:
        """Calibrations the simulated cell knows exactly (used when nothing else is stored)."""
        cell = self.cell
        out: dict[str, Any] = {"camera": cell.camera.to_dict(), "field": field_to_json(cell.field)}
        if self.settings.sim.preload_handeye:
            out["handeye"] = {
                "T_flange_camera": cell.T_flange_camera.tolist(),
                "T_base_field": cell.T_base_field.tolist(),
                "note": "the simulated cell's true hand-eye (preload_handeye = true)",
            }
        return out
