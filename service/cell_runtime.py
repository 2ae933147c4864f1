"""The simulated cell as the service runs it: one SimCell shared by the simulated drivers.

With ``sim.transport = "direct"`` the simulated drivers (``drivers/camera/sim.py``,
``drivers/robot/sim.py``) read the cell in-process. Both share the cell and its
epoch (the host monotonic time of the cell's t = 0), so the camera sees the arm
where the controller says it is, up to the arm's model errors.
"""

from __future__ import annotations

import time
from typing import Any

from service.formats import field_to_json
from service.settings import CameraConfig, Settings
from service.sim.cell import CellConfig, SimCell


class CellRuntime:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.active = settings.uses_sim
        self.epoch_ns = time.monotonic_ns()
        self._cell: SimCell | None = None

    @property
    def cell(self) -> SimCell:
        if self._cell is None:
            s = self.settings.sim
            self._cell = SimCell(CellConfig(seed=s.seed, robot=s.robot, program=s.program, error_scale=s.error_scale))
        return self._cell

    def start(self) -> None:
        if self.active:
            _ = self.cell  # build it (inverse kinematics of the program) before the drivers need it

    def stop(self) -> None:
        pass

    def camera_options(self, cfg: CameraConfig) -> dict[str, Any]:
        if cfg.driver == "sim":
            return {"cell": self.cell, "epoch_ns": self.epoch_ns, **cfg.options}
        return dict(cfg.options)

    def robot_options(self) -> dict[str, Any]:
        if self.settings.robot.driver == "sim":
            return {"cell": self.cell, "epoch_ns": self.epoch_ns, **self.settings.robot.options}
        return dict(self.settings.robot.options)

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
