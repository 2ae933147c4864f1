"""Driver names → classes, imported on demand (python-can style).

The cell PC needs PyGObject/Aravis only when ``aravis`` is chosen and ur_rtde
only when ``ur`` is, and CI can run the simulated drivers with neither.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers.base import CameraDriver, DriverUnavailable, RobotDriver

CAMERAS: dict[str, str] = {
    "sim": "drivers.camera.sim:SimCamera",
    "aravis": "drivers.camera.aravis:AravisCamera",
    "v4l2": "drivers.camera.v4l2:V4L2Camera",
    "replay": "drivers.camera.replay:ReplayCamera",
}

ROBOTS: dict[str, str] = {
    "replay": "drivers.robot.replay:ReplayRobot",
    "sim": "drivers.robot.sim:SimRobot",
    "ur": "drivers.robot.ur:URRobot",
}


def _load(table: dict[str, str], kind: str, name: str) -> type[Any]:
    try:
        target = table[name]
    except KeyError:
        raise ValueError(f"unknown {kind} driver {name!r}; choose one of {sorted(table)}") from None
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise DriverUnavailable(f"the {kind} driver {name!r} cannot be loaded: {e}") from e
    cls: type[Any] = getattr(module, class_name)
    return cls


def camera_class(name: str) -> type[CameraDriver]:
    return _load(CAMERAS, "camera", name)


def robot_class(name: str) -> type[RobotDriver]:
    return _load(ROBOTS, "robot", name)


def make_camera(name: str, **options: Any) -> CameraDriver:
    """A camera driver by registry name, constructed with driver-specific options (not yet opened)."""
    return camera_class(name)(**options)


def make_robot(name: str, **options: Any) -> RobotDriver:
    """A robot driver by registry name, constructed with driver-specific options (not yet opened)."""
    return robot_class(name)(**options)
