"""The flange pose a measurement gives, and its deviation from the pose the controller reports.

With the hand-eye calibration (``X = T_flange_camera``, ``Z = T_base_field``) a camera pose in
the field is the flange's true pose in the robot's base: ``T_base_flange = Z @ T_field_camera @
X^-1`` (the paper's outer loop); its difference from the controller's reported pose at the same
exposure is the robot's error there. One place for both, for a single camera and for the rig.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.frames import inv_T, pose_difference

Array = NDArray[np.float64]


class HandEye(Protocol):
    T_flange_camera: Array  # X, mm
    T_base_field: Array  # Z, mm


@dataclass(frozen=True)
class Deviation:
    """Measured minus reported flange pose: distance mm, angle deg, and the position vector mm (base)."""

    position_mm: float
    angle_deg: float
    vector_mm: Array

    def to_dict(self) -> dict[str, Any]:
        return {
            "position_mm": round(self.position_mm, 4),
            "angle_deg": round(self.angle_deg, 5),
            "vector_mm": [round(float(v), 4) for v in self.vector_mm],
        }


def flange_from_camera(handeye: HandEye, T_field_camera: Array) -> Array:
    """``T_base_flange`` (4, 4) mm measured through the hand-eye calibration."""
    return handeye.T_base_field @ np.asarray(T_field_camera, dtype=np.float64) @ inv_T(handeye.T_flange_camera)


def deviation(T_base_flange_measured: Array, T_base_flange_reported: Array) -> Deviation:
    """The robot's error at one exposure: the measured flange against the reported one."""
    T_meas = np.asarray(T_base_flange_measured, dtype=np.float64)
    T_rep = np.asarray(T_base_flange_reported, dtype=np.float64)
    dpos, dang = pose_difference(T_meas, T_rep)
    return Deviation(float(dpos), float(dang), T_meas[:3, 3] - T_rep[:3, 3])
