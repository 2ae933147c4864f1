"""Results and failures shared by the engine, the worker, the API and the CLI.

A failed measurement is a value (DESIGN section 4): ``ok = False`` with a
machine-readable :class:`Reason` and a sentence for a person. Solvers in the
core raise :class:`SolveError` for input they cannot solve; the pipeline turns
it into a :class:`Failure`. Programmer errors (wrong shapes) stay exceptions.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any


class Reason(StrEnum):
    """Why a measurement or a solve failed; the same codes in CLI, REST, WebSocket and database."""

    too_few_targets = "too_few_targets"
    degenerate_geometry = "degenerate_geometry"
    behind_camera = "behind_camera"
    no_convergence = "no_convergence"
    bad_image = "bad_image"
    bad_input = "bad_input"
    no_frame = "no_frame"
    camera_disconnected = "camera_disconnected"
    robot_disconnected = "robot_disconnected"
    not_calibrated = "not_calibrated"
    poor_motion = "poor_motion"
    initializing = "initializing"
    timeout = "timeout"


class SolveError(Exception):
    """A solver could not produce a trustworthy answer from its input."""

    def __init__(self, reason: Reason, message: str, details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message
        self.details = details or {}


@dataclass(frozen=True)
class Failure:
    """A measurement that did not give a pose."""

    reason: Reason
    message: str
    details: dict[str, Any] | None = None

    ok: bool = False

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"ok": False, "reason": str(self.reason), "message": self.message}
        if self.details:
            d.update(self.details)
        return d

    @classmethod
    def from_error(cls, e: SolveError) -> Failure:
        return cls(reason=e.reason, message=e.message, details=e.details or None)
