"""Faults injected into the simulated cell (``POST /sim/faults``): which device object takes which action."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

FAULT_ACTIONS = {"camera": ("unplug", "plug", "stall", "garble"), "robot": ("unplug", "plug")}


def fault_target(
    device: str, action: str, camera: str | None, cameras: Mapping[str, Any], robot: Any, transport: str
) -> tuple[Any, str]:
    """The simulated device to call ``action`` on and its name in sentences.

    ``cameras``: the running camera channels by name (each with its ``driver``). Raises LookupError
    when there is no simulated device to act on, ValueError for an unknown action.
    """
    if action not in FAULT_ACTIONS.get(device, ()):
        raise ValueError(f"device {device!r} takes the actions {FAULT_ACTIONS.get(device, ())}, not {action!r}")
    if device == "camera":
        name = camera or next(iter(cameras), None)
        ch = cameras.get(name) if name is not None else None
        if ch is None:
            raise LookupError(f"no running camera named {name!r}; cameras: {sorted(cameras)}")
        target, what = ch.driver, f"camera {name}"
    else:
        target, what = robot, "robot"
    if not callable(getattr(target, action, None)):
        raise LookupError(
            f"the {what} is not simulated in this process (sim.transport = {transport!r}): faults are "
            "injected into the direct simulated cell"
        )
    return target, what
