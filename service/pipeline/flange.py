"""The flange pose a measurement gives, and its deviation from the pose the controller reports.

With the hand-eye calibration (``X = T_flange_camera``, ``Z = T_base_field``) a camera pose in
the field is the flange's true pose in the robot's base: ``T_base_flange = Z @ T_field_camera @
X^-1`` (the paper's outer loop); its difference from the controller's reported pose at the same
exposure is the robot's error there. One place for both, for a single camera and for the rig.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.frames import inv_T, pose_difference
from service.core.measurement import Deviation, Flange
from service.core.results import Reason

Array = NDArray[np.float64]


class HandEye(Protocol):
    T_flange_camera: Array  # X, mm
    T_base_field: Array  # Z, mm


def flange_from_camera(handeye: HandEye, T_field_camera: Array) -> Array:
    """``T_base_flange`` (4, 4) mm measured through the hand-eye calibration."""
    return handeye.T_base_field @ np.asarray(T_field_camera, dtype=np.float64) @ inv_T(handeye.T_flange_camera)


def deviation(T_base_flange_measured: Array, T_base_flange_reported: Array) -> Deviation:
    """The robot's error at one exposure: the measured flange against the reported one."""
    T_meas = np.asarray(T_base_flange_measured, dtype=np.float64)
    T_rep = np.asarray(T_base_flange_reported, dtype=np.float64)
    dpos, dang = pose_difference(T_meas, T_rep)
    return Deviation(float(dpos), float(dang), T_meas[:3, 3] - T_rep[:3, 3])


NO_HANDEYE = "no hand-eye calibration: the flange pose cannot be measured"


def flange_part(
    handeye: HandEye | None,
    T_field_camera: Array,
    T_base_flange_reported: Array | None,
    why_unreported: str = "no robot pose at the exposure",
) -> Flange:
    """The robot's part of one pose; what is missing says why (the robot's reason first)."""
    reason, message = None, ""
    if T_base_flange_reported is None:
        reason, message = Reason.robot_disconnected, why_unreported
    elif handeye is None:
        reason, message = Reason.not_calibrated, NO_HANDEYE
    if handeye is None:
        return Flange(T_base_flange_reported, None, None, reason or Reason.not_calibrated, message or NO_HANDEYE)
    T_measured = flange_from_camera(handeye, T_field_camera)
    dev = None if T_base_flange_reported is None else deviation(T_measured, T_base_flange_reported)
    return Flange(T_base_flange_reported, T_measured, dev, reason, message)
