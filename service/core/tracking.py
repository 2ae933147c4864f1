"""Pose prediction for ROI tracking: where will every target be in the next frame?

The paper's route to control-loop rates is to measure "only those parts of an
image containing targets". After a good frame, the next pose is predicted from
the last two (constant velocity: the last relative motion, scaled by the time
step, linear in position and along the geodesic in rotation), every field
target is projected with it, and only small windows around those predictions
are measured. The caller falls back to full-frame detection when too few
targets are found or the adjustment disagrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core.frames import make_T
from service.core.geometry_kernels import rotation_from_rotvec_kernel

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PoseSample:
    """A measured ``T_field_camera`` (4, 4) at time ``t_s`` (s, any monotonic origin)."""

    T_field_camera: Array
    t_s: float


def _rotvec_from_matrix(R: Array) -> Array:
    """Rotation vector (3,) rad of a rotation matrix, through its unit quaternion (Shepperd's
    method, stable at any angle); by hand because scipy's Rotation costs a tenth of a frame."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    k = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + tr)
        f = 0.25 / w
        q = np.array([(R[2, 1] - R[1, 2]) * f, (R[0, 2] - R[2, 0]) * f, (R[1, 0] - R[0, 1]) * f, w])
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        v = np.empty(3)
        v[i] = 0.5 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[m, m])
        f = 0.25 / v[i]
        v[j], v[m] = (R[j, i] + R[i, j]) * f, (R[m, i] + R[i, m]) * f
        q = np.array([v[0], v[1], v[2], (R[m, j] - R[j, m]) * f])
    if q[3] < 0:
        q = -q
    n = float(np.sqrt(q[:3] @ q[:3]))
    if n < 1e-12:
        return 2.0 * q[:3]
    return (2.0 * np.arctan2(n, q[3]) / n) * q[:3]


def predict_pose(history: list[PoseSample] | tuple[PoseSample, ...], t_s: float, max_gap_s: float = 0.5) -> Array | None:
    """Constant-velocity prediction of ``T_field_camera`` at ``t_s``; None without a usable history.

    With one sample (or a gap over ``max_gap_s``) the last pose is returned as is.

    >>> T0, T1 = np.eye(4), make_T(np.eye(3), [1.0, 0, 0])
    >>> predict_pose([PoseSample(T0, 0.0), PoseSample(T1, 0.01)], 0.02)[:3, 3].tolist()
    [2.0, 0.0, 0.0]
    """
    if not history:
        return None
    last = history[-1]
    if t_s - last.t_s > max_gap_s:
        return None
    if len(history) < 2:
        return last.T_field_camera
    prev = history[-2]
    dt = last.t_s - prev.t_s
    if dt <= 0 or last.t_s - prev.t_s > max_gap_s:
        return last.T_field_camera
    s = (t_s - last.t_s) / dt
    T0, T1 = prev.T_field_camera, last.T_field_camera
    dR = _rotvec_from_matrix(T0[:3, :3].T @ T1[:3, :3])
    R = T1[:3, :3] @ rotation_from_rotvec_kernel(s * dR)
    return make_T(R, T1[:3, 3] + s * (T1[:3, 3] - T0[:3, 3]))
