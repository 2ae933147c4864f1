"""The flange pose through the hand-eye, and the deviation from the reported pose (service/pipeline/flange.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.geometry.frames import inv_T, make_T
from service.pipeline.flange import deviation, flange_from_camera


def _pose(rng: np.random.Generator, scale_mm: float = 500.0) -> np.ndarray:
    return make_T(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-scale_mm, scale_mm, 3))


def test_the_camera_pose_the_flange_would_give_maps_back_onto_that_flange():
    rng = np.random.default_rng(3)
    he = SimpleNamespace(T_flange_camera=_pose(rng, 100.0), T_base_field=_pose(rng))
    T_base_flange = _pose(rng)
    T_field_camera = inv_T(he.T_base_field) @ T_base_flange @ he.T_flange_camera
    np.testing.assert_allclose(flange_from_camera(he, T_field_camera), T_base_flange, atol=1e-9)


def test_deviation_is_measured_minus_reported():
    rng = np.random.default_rng(4)
    T_rep = _pose(rng)
    small = make_T(Rotation.from_rotvec(np.radians([0.0, 0.0, 0.02])).as_matrix(), [0.3, -0.4, 1.2])
    T_meas = small @ T_rep  # 1.3 mm and 0.02 deg in the base frame
    d = deviation(T_meas, T_rep)
    np.testing.assert_allclose(d.vector_mm, T_meas[:3, 3] - T_rep[:3, 3], atol=1e-12)
    assert abs(d.position_mm - np.linalg.norm(d.vector_mm)) < 1e-9
    assert abs(d.angle_deg - 0.02) < 1e-9
    out = d.to_dict()
    assert out["position_mm"] == round(d.position_mm, 4) and len(out["vector_mm"]) == 3


def test_the_compiled_flange_part_equals_the_formulas_and_says_what_is_missing():
    from service.core.results import Reason
    from service.pipeline.flange import flange_part

    rng = np.random.default_rng(5)
    for _ in range(20):
        he = SimpleNamespace(T_flange_camera=_pose(rng, 100.0), T_base_field=_pose(rng))
        T_field_camera, T_rep = _pose(rng), _pose(rng)
        f = flange_part(he, T_field_camera, T_rep)
        np.testing.assert_allclose(f.T_base_flange_measured, flange_from_camera(he, T_field_camera), atol=1e-9)
        ref = deviation(flange_from_camera(he, T_field_camera), T_rep)
        assert abs(f.deviation.position_mm - ref.position_mm) < 1e-9
        assert abs(f.deviation.angle_deg - ref.angle_deg) < 1e-9
        np.testing.assert_allclose(f.deviation.vector_mm, ref.vector_mm, atol=1e-9)
        assert f.reason is None
    # a pose a hair apart: the angle is exact for tiny rotations (no arccos of a trace)
    tiny = make_T(Rotation.from_rotvec([1e-9, 0.0, 0.0]).as_matrix(), [0.0, 0.0, 0.0])
    T_rep = flange_from_camera(he, T_field_camera)
    f = flange_part(he, T_field_camera, tiny @ T_rep)
    assert abs(np.radians(f.deviation.angle_deg) - 1e-9) < 1e-12
    # no reported pose: the measured flange alone, with the robot's reason
    f = flange_part(he, T_field_camera, None, "the robot is disconnected")
    assert f.deviation is None and f.reason is Reason.robot_disconnected and f.T_base_flange_measured is not None
    # no hand-eye: nothing measured, said why
    f = flange_part(None, T_field_camera, T_rep)
    assert f.T_base_flange_measured is None and f.reason is Reason.not_calibrated
