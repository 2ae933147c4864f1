"""Hand-eye refinement on image observations in the simulated cell: robot model errors as nuisance."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.calib.handeye import calibrate_handeye
from service.core.calib.handeye_images import ImageSample, refine_handeye_on_images
from service.core.geometry.frames import inv_T, make_T, pose_difference
from service.core.pose.resection import resect
from service.core.results import SolveError
from service.core.targets.identify import project_field
from service.sim.cell import CellConfig, SimCell


@pytest.fixture(scope="module")
def scene():
    cell = SimCell(CellConfig(program="hold"))
    rng = np.random.default_rng(5)
    poses = cell.reachable_view_poses(10, rng)
    samples, C = [], []
    for T in poses:
        q = cell.nominal.ik(T, cell.q_home_rad)
        T_true = cell.true.fk(q)  # where the arm really is; the controller reports T
        T_fc = inv_T(cell.T_base_field) @ T_true @ cell.T_flange_camera
        rows, uv = project_field(cell.camera, cell.field, T_fc, margin_px=5.0)
        uv = uv + rng.normal(0.0, 0.02, uv.shape)
        samples.append(ImageSample(T, cell.field.xyz[rows], uv))
        C.append(resect(cell.camera, cell.field.xyz[rows], uv).T_field_camera)
    return cell, samples, np.array(poses), np.array(C)


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_image_refinement_recovers_the_hand_eye_within_what_the_arm_errors_allow(scene):
    cell, samples, P, C = scene
    pose_level = calibrate_handeye(P, C)
    res = refine_handeye_on_images(
        cell.camera, samples, pose_level.T_flange_camera, pose_level.T_base_field, sigma_px=0.02
    )
    dX = pose_difference(res.T_flange_camera, cell.T_flange_camera)
    dZ = pose_difference(res.T_base_field, cell.T_base_field)
    assert dX[0] < 3.0 and dX[1] < 0.2, dX
    assert dZ[0] < 3.0 and dZ[1] < 0.2, dZ
    # the robot's errors go into the per-sample corrections, so the images fit to their noise
    assert 0.01 < float(np.median(res.rms_px)) < 0.04
    assert 0.05 < float(np.median(res.robot_error_position_mm)) < 5.0
    assert np.all(res.sigma_flange_camera_position_mm > 0) and res.converged


def test_image_refinement_is_exact_without_robot_errors_or_noise():
    cell = SimCell(CellConfig(program="hold", error_scale=0.0))
    rng = np.random.default_rng(2)
    samples = []
    for T in cell.reachable_view_poses(6, rng):
        T_fc = inv_T(cell.T_base_field) @ T @ cell.T_flange_camera
        rows, uv = project_field(cell.camera, cell.field, T_fc, margin_px=5.0)
        samples.append(ImageSample(T, cell.field.xyz[rows], uv))
    X0 = cell.T_flange_camera @ make_T(np.eye(3), [2.0, -1.5, 1.0])  # a few mm off
    res = refine_handeye_on_images(cell.camera, samples, X0, cell.T_base_field, sigma_px=0.02)
    assert pose_difference(res.T_flange_camera, cell.T_flange_camera)[0] < 0.01
    assert float(np.max(res.rms_px)) < 1e-3


def test_image_refinement_needs_three_samples(scene):
    cell, samples, *_ = scene
    with pytest.raises(SolveError, match="at least 3"):
        refine_handeye_on_images(cell.camera, samples[:2], np.eye(4), np.eye(4))
