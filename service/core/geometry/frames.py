"""Rigid transforms between frames, named ``T_a_b`` (maps frame b into frame a).

``p_a = T_a_b @ p_b`` for homogeneous points, so chains read left to right:
``T_base_camera = T_base_flange @ T_flange_camera``. Lengths are mm, angles rad
unless a name says ``_deg``. Rotation vectors and the angle between two rotations come from
:mod:`service.core.geometry.so3` (re-exported here: :func:`T_from_rotvec`, :func:`rotvec_from_T`);
the Euler conventions below go through ``scipy.spatial.transform.Rotation``.

Orientation conventions offered for people (DESIGN section 1):

- rotation vector (axis * angle, rad): the UR convention;
- KUKA A, B, C: intrinsic Z-Y'-X'' Euler angles in degrees;
- the paper's omega, phi, kappa: the classical photogrammetric sequence
  ``R = R_x(omega) @ R_y(phi) @ R_z(kappa)`` (intrinsic X-Y'-Z''), rad, applied
  to ``R_field_camera``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.core._kernels.geometry_kernels import predict_kernel
from service.core.geometry import so3
from service.core.geometry.so3 import T_from_rotvec as T_from_rotvec
from service.core.geometry.so3 import rotvec_from_T as rotvec_from_T

Array = NDArray[np.float64]


def check_T(T: ArrayLike, name: str = "T", atol: float = 1e-6) -> Array:
    """Return ``T`` as a float (4, 4) array or raise ``ValueError`` saying what is wrong.

    >>> check_T(np.eye(4)).shape
    (4, 4)
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} contains non-finite values")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} rotation block is not a proper rotation")
    return T


def assert_T(T: ArrayLike, atol: float = 1e-6) -> None:
    """Test helper: fail with an ``AssertionError`` unless ``T`` is a rigid transform."""
    try:
        check_T(T, atol=atol)
    except ValueError as e:
        raise AssertionError(str(e)) from None


def make_T(R: ArrayLike, t: ArrayLike) -> Array:
    """Homogeneous transform from rotation ``R`` (3, 3) and translation ``t`` (3,) mm.

    >>> make_T(np.eye(3), [1, 2, 3])[:3, 3].tolist()
    [1.0, 2.0, 3.0]
    """
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T_a_b: ArrayLike) -> Array:
    """``T_b_a`` from ``T_a_b`` using the rigid-body structure (no general inverse).

    >>> T = T_from_rotvec([0, 0, np.pi / 2], [1, 0, 0])
    >>> np.allclose(inv_T(T) @ T, np.eye(4))
    True
    """
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    R_b_a = T_a_b[:3, :3].T
    T_b_a = np.zeros((4, 4))  # not make_T: np.eye and its conversions were half of this, twice an ROI frame
    T_b_a[:3, :3] = R_b_a
    T_b_a[:3, 3] = -R_b_a @ T_a_b[:3, 3]
    T_b_a[3, 3] = 1.0
    return T_b_a


def apply_T(T_a_b: ArrayLike, p_b: ArrayLike) -> Array:
    """Map points ``p_b`` (N, 3) or (3,) mm from frame b into frame a.

    >>> apply_T(make_T(np.eye(3), [0, 0, 10]), [[1.0, 2.0, 3.0]]).tolist()
    [[1.0, 2.0, 13.0]]
    """
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    p_b = np.asarray(p_b, dtype=np.float64)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def T_from_ur_pose(pose_m_rotvec: ArrayLike) -> Array:
    """UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector rad) to a transform in mm.

    >>> T_from_ur_pose([0.1, 0.0, 0.5, 0, 0, 0])[:3, 3].tolist()
    [100.0, 0.0, 500.0]
    """
    p = np.asarray(pose_m_rotvec, dtype=np.float64).reshape(6)
    return T_from_rotvec(p[3:], p[:3] * 1000.0)


def ur_pose_from_T(T: ArrayLike) -> Array:
    """Inverse of :func:`T_from_ur_pose`: ``[x, y, z, rx, ry, rz]`` in m and rad."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[:3, 3] / 1000.0, rotvec_from_T(T)])


def kuka_abc_deg_from_R(R: ArrayLike) -> Array:
    """KUKA A, B, C (intrinsic Z-Y'-X'', degrees) of a rotation matrix.

    >>> np.round(kuka_abc_deg_from_R(Rotation.from_euler("ZYX", [30, 20, 10], degrees=True).as_matrix()), 9).tolist()
    [30.0, 20.0, 10.0]
    """
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_euler("ZYX", degrees=True)


def R_from_kuka_abc_deg(abc_deg: ArrayLike) -> Array:
    """Rotation matrix from KUKA A, B, C in degrees (intrinsic Z-Y'-X'')."""
    return Rotation.from_euler("ZYX", np.asarray(abc_deg, dtype=np.float64), degrees=True).as_matrix()


def opk_from_R(R: ArrayLike) -> Array:
    """The paper's omega, phi, kappa (rad) with ``R = R_x(omega) R_y(phi) R_z(kappa)``.

    >>> np.round(opk_from_R(R_from_opk([0.1, -0.2, 0.3])), 12).tolist()
    [0.1, -0.2, 0.3]
    """
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_euler("XYZ")


def R_from_opk(opk: ArrayLike) -> Array:
    """Rotation matrix from omega, phi, kappa (rad), intrinsic X-Y'-Z''."""
    return Rotation.from_euler("XYZ", np.asarray(opk, dtype=np.float64)).as_matrix()


def rotation_angle_deg(R: ArrayLike) -> float:
    """Angle (deg) of the rotation ``R``; used for pose differences.

    >>> round(rotation_angle_deg(so3.R_from_rotvec([0, 0.5, 0])), 6)
    28.64789
    """
    return float(np.degrees(so3.angle(R)))


def pose_difference(T_a_b1: ArrayLike, T_a_b2: ArrayLike) -> tuple[float, float]:
    """Distance (mm) between the origins and angle (deg) between two poses of the same frame."""
    T1 = np.asarray(T_a_b1, dtype=np.float64)
    T2 = np.asarray(T_a_b2, dtype=np.float64)
    dt = float(np.linalg.norm(T1[:3, 3] - T2[:3, 3]))
    return dt, float(np.degrees(so3.angle_between(T1[:3, :3], T2[:3, :3])))


def interpolate_T(T_a_b0: ArrayLike, T_a_b1: ArrayLike, s: float) -> Array:
    """Pose at fraction ``s`` between two poses: linear in position, slerp in rotation."""
    T0 = np.asarray(T_a_b0, dtype=np.float64)
    T1 = np.asarray(T_a_b1, dtype=np.float64)
    if T0.shape == T1.shape == (4, 4):
        # compiled, the pairing's per-frame call (~0.1 ms of numpy calls on the service's hot path):
        # moving T1 on by s - 1 of the motion from T0 is T0 moved by s of it (the same geodesic)
        return np.asarray(
            predict_kernel(np.array(T0, order="C"), np.array(T1, order="C"), float(s) - 1.0)
        )  # writable C copies: the one signature compiled at set-up
    R = T0[:3, :3] @ so3.R_from_rotvec(s * so3.rotvec_between(T0[:3, :3], T1[:3, :3]))
    return make_T(R, (1.0 - s) * T0[:3, 3] + s * T1[:3, 3])


def orientation_report(T: ArrayLike) -> dict[str, list[float]]:
    """What a person reads of a pose: position mm, rotation vector rad, KUKA A,B,C deg, omega-phi-kappa deg."""
    T = check_T(T)
    return {
        "xyz_mm": T[:3, 3].tolist(),
        "rotvec": rotvec_from_T(T).tolist(),
        "kuka_abc_deg": kuka_abc_deg_from_R(T[:3, :3]).tolist(),
        "omega_phi_kappa_deg": np.degrees(opk_from_R(T[:3, :3])).tolist(),
    }
