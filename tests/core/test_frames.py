from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.geometry import frames as F


def random_T(rng):
    return F.make_T(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(0, 500, 3))


def test_chains_compose_left_to_right(rng):
    T_base_flange, T_flange_camera = random_T(rng), random_T(rng)
    p_camera = rng.normal(0, 100, (5, 3))
    T_base_camera = T_base_flange @ T_flange_camera
    assert np.allclose(
        F.apply_T(T_base_camera, p_camera), F.apply_T(T_base_flange, F.apply_T(T_flange_camera, p_camera))
    )
    assert np.allclose(F.inv_T(T_base_camera) @ T_base_camera, np.eye(4))


def test_check_T_rejects_non_rigid_input():
    with pytest.raises(ValueError, match="shape"):
        F.check_T(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2
    with pytest.raises(ValueError, match="rotation"):
        F.check_T(bad)
    with pytest.raises(AssertionError):
        F.assert_T(np.diag([1, 1, -1, 1.0]))


def test_ur_pose_round_trip_converts_metres_to_mm(rng):
    pose = np.r_[rng.normal(0, 0.5, 3), Rotation.random(random_state=1).as_rotvec()]
    T = F.T_from_ur_pose(pose)
    assert np.allclose(T[:3, 3], pose[:3] * 1000)
    assert np.allclose(F.ur_pose_from_T(T), pose)


def test_kuka_abc_is_intrinsic_zyx():
    A, B, C = 30.0, -20.0, 10.0
    Rz = Rotation.from_rotvec([0, 0, np.radians(A)]).as_matrix()
    Ry = Rotation.from_rotvec([0, np.radians(B), 0]).as_matrix()
    Rx = Rotation.from_rotvec([np.radians(C), 0, 0]).as_matrix()
    assert np.allclose(F.R_from_kuka_abc_deg([A, B, C]), Rz @ Ry @ Rx)
    assert np.allclose(F.kuka_abc_deg_from_R(Rz @ Ry @ Rx), [A, B, C])


def test_opk_is_the_classical_photogrammetric_sequence():
    o, p, k = 0.1, -0.3, 1.2
    Rx = Rotation.from_rotvec([o, 0, 0]).as_matrix()
    Ry = Rotation.from_rotvec([0, p, 0]).as_matrix()
    Rz = Rotation.from_rotvec([0, 0, k]).as_matrix()
    assert np.allclose(F.R_from_opk([o, p, k]), Rx @ Ry @ Rz)


def test_interpolate_T_is_linear_and_slerp(rng):
    T0, T1 = random_T(rng), random_T(rng)
    mid = F.interpolate_T(T0, T1, 0.5)
    assert np.allclose(mid[:3, 3], (T0[:3, 3] + T1[:3, 3]) / 2)
    d0 = F.pose_difference(T0, mid)[1]
    d1 = F.pose_difference(mid, T1)[1]
    assert d0 == pytest.approx(d1, rel=1e-9)
    assert np.allclose(F.interpolate_T(T0, T1, 1.0), T1)
