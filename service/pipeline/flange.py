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

from service.core._kernels.geometry_kernels import flange_kernel
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
    # compiled, once a frame: the measured flange and its deviation in one call
    reported = T_base_flange_reported is not None
    T_measured, dpos_mm, dang_rad, vector_mm = flange_kernel(
        _c(handeye.T_base_field),
        _c(T_field_camera),
        _c(handeye.T_flange_camera),
        _c(T_base_flange_reported) if reported else _EYE,
        reported,
    )
    dev = Deviation(float(dpos_mm), float(np.degrees(dang_rad)), vector_mm) if reported else None
    return Flange(T_base_flange_reported, T_measured, dev, reason, message)


_EYE = np.eye(4)


def _c(T: Array | None) -> Array:
    """A (4, 4) float64 C-contiguous array: the one type the kernel is compiled for at set-up."""
    return np.ascontiguousarray(T, dtype=np.float64)
