"""The simulated cell: geometry for measurement, reports with model errors, rendered frames the pipeline measures."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.geometry.frames import inv_T, pose_difference
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer
from service.sim.cell import CellConfig, SimCell
from service.sim.robot import JointTrajectory


@pytest.fixture(scope="module")
def cell() -> SimCell:
    return SimCell()


@pytest.fixture(scope="module")
def cell_ur() -> SimCell:
    return SimCell(CellConfig(robot="ur10e", seed=1))


def instants(cell: SimCell, n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, cell.duration_s, n)


def test_default_program_is_ten_laps_of_a_300_mm_circle(cell):
    c = cell.config
    assert (c.program, c.circle_laps, c.circle_radius_mm) == ("circle", 10, 300.0)
    assert cell.duration_s == pytest.approx(10 * c.circle_period_s)
    # the controller's (nominal) flange stays on the circle, in the plate's plane
    T = cell.T_base_flange_commanded(instants(cell, 300))
    p = (T[:, :3, 3] - cell.T_base_field[:3, 3]) @ cell.T_base_field[:3, :3]
    radius = np.linalg.norm(p[:, :2], axis=1)
    assert np.all(np.abs(radius - 300.0) < 0.01)
    assert np.ptp(p[:, 2]) < 0.01


@pytest.mark.parametrize("which", ["cell", "cell_ur"])
def test_program_stays_inside_joint_limits_and_away_from_singularities(which, request):
    cell = request.getfixturevalue(which)
    t = np.linspace(0.0, cell.duration_s, 400)
    q = cell.q_at(t)
    assert np.all(cell.nominal.within_limits(q, np.radians(5.0)))
    assert min(cell.nominal.dexterity_mm(qi) for qi in q[::4]) > 100.0
    assert all(cell.nominal.branch(qi) == cell.nominal.branch(q[0]) for qi in q[::4])


@pytest.mark.parametrize("which", ["cell", "cell_ur"])
def test_camera_sees_the_plate_from_about_1000_mm_along_the_whole_program(which, request):
    cell = request.getfixturevalue(which)
    T = cell.T_field_camera(instants(cell, 50))
    distance = np.linalg.norm(T[:, :3, 3], axis=1)
    assert np.all((900.0 < distance) & (distance < 1150.0))
    assert np.all(T[:, 2, 3] > 0) and np.all(T[:, 2, 2] < -0.9)  # above the plate, looking down
    for Ti in T:
        n_coded, n_uncoded = cell.targets_in_view(Ti)
        assert n_coded >= 20 and n_uncoded >= 150


def test_loop_point_is_continuous(cell):
    d = cell.duration_s
    assert np.allclose(cell.q_at(d - 1e-9), cell.q_at(0.0), atol=1e-8)
    assert np.allclose(cell.q_at(12.34 + 3 * d), cell.q_at(12.34), atol=1e-9)
    step = cell.q_at(np.array([d - 0.01, d, d + 0.01]))
    assert np.abs(np.diff(step, axis=0)).max() < 0.01


@pytest.mark.parametrize("which", ["cell", "cell_ur"])
def test_true_flange_differs_from_the_controllers_by_the_model_errors(which, request):
    cell = request.getfixturevalue(which)
    t = instants(cell, 300)
    d = np.linalg.norm(cell.T_base_flange_true(t)[:, :3, 3] - cell.T_base_flange_commanded(t)[:, :3, 3], axis=1)
    assert 0.5 < np.median(d) < 3.0 and d.max() < 5.0
    # the camera sees the truth: Z^-1 true X
    i = 17
    expected = inv_T(cell.T_base_field) @ cell.true.fk(cell.q_at(t[i])) @ cell.T_flange_camera
    assert np.allclose(cell.T_field_camera(t[i]), expected, atol=1e-9)


def test_robot_report_is_the_nominal_pose_of_noisy_encoders(cell):
    rng = np.random.default_rng(11)
    t = instants(cell, 400, seed=3)
    dq, dt_mm = [], []
    for ti in t:
        T_rep, q_meas = cell.robot_report(ti, rng)
        assert np.allclose(T_rep, cell.nominal.fk(q_meas), atol=1e-12)
        dq.append(q_meas - cell.q_at(ti))
        dt_mm.append(pose_difference(T_rep, cell.T_base_flange_commanded(ti))[0])
    rms = np.sqrt(np.mean(np.square(dq)))
    sigma = cell.config.encoder_noise_rad
    assert 0.9 * sigma < rms < 1.1 * sigma
    # the noise moves the reported flange by hundredths of a millimetre, far less than the model errors
    assert 0.002 < np.median(dt_mm) < 0.05
    T_quiet, q_quiet = cell.robot_report(5.0, None)
    assert np.array_equal(q_quiet, cell.q_at(5.0))


def test_rendered_frame_is_measured_at_the_true_camera_pose(cell):
    measurer = FrameMeasurer(cell.camera, cell.field)
    for t_s in (3.7, 61.2):
        frame = cell.render(t_s, np.random.default_rng(5))
        result = measurer.measure(frame.image).result
        assert isinstance(result, PoseResult), result
        assert result.n_coded >= 20 and result.n_uncoded >= 150
        dt_mm, dr_deg = pose_difference(result.T_field_camera, cell.T_field_camera(t_s))
        assert dt_mm < 0.1 and dr_deg < 0.01
    dark = cell.render(3.7, None, lit=False)
    assert dark.image.max() < 20


def test_targets_in_view_agrees_with_the_renderer(cell):
    for T_base_flange in cell.reachable_view_poses(4, np.random.default_rng(8)):
        q = cell.nominal.ik(T_base_flange, cell.q_home_rad)
        T = inv_T(cell.T_base_field) @ cell.true.fk(q) @ cell.T_flange_camera
        frame = cell.with_program(JointTrajectory(np.array([0.0, 1.0]), np.array([q, q]))).render(0.5)
        full = [i for i, f in zip(frame.ids, frame.fully_visible, strict=True) if f]
        n_coded = sum(i.startswith("C") for i in full)
        counted = cell.targets_in_view(T)
        assert abs(counted[0] - n_coded) <= 1 and abs(sum(counted) - len(full)) <= 2


@pytest.mark.parametrize("which", ["cell", "cell_ur"])
def test_reachable_view_poses_are_reachable_and_see_the_plate(which, request):
    cell = request.getfixturevalue(which)
    poses = cell.reachable_view_poses(12, np.random.default_rng(21))
    assert len(poses) == 12
    tilts, distances = [], []
    for T in poses:
        q = cell.nominal.ik(T, cell.q_home_rad)
        assert cell.nominal.within_limits(q)
        T_fc = inv_T(cell.T_base_field) @ T @ cell.T_flange_camera
        n_coded, n_uncoded = cell.targets_in_view(T_fc)
        assert n_coded >= 6 and n_coded + n_uncoded >= 30
        distances.append(np.linalg.norm(T_fc[:3, 3]))
        tilts.append(np.degrees(np.arccos(-T_fc[2, 2])))
    assert 650.0 < min(distances) and max(distances) < 1400.0
    assert max(tilts) < 45.0 and max(tilts) > 20.0
    # for hand-eye calibration the views turn about every axis
    R = np.array([T[:3, :3] for T in poses])
    angles = [pose_difference(poses[0], T)[1] for T in poses[1:]]
    assert max(angles) > 40.0 and np.linalg.matrix_rank(R.reshape(12, 9) - R.mean(axis=0).reshape(1, 9)) >= 3


def test_with_program_keeps_the_cell_and_moves_along_the_new_trajectory(cell):
    poses = cell.reachable_view_poses(2, np.random.default_rng(2))
    q = [cell.nominal.ik(T, cell.q_home_rad) for T in poses]
    other = cell.with_program(JointTrajectory(np.array([0.0, 4.0]), np.array(q)))
    assert other.duration_s == 4.0
    assert np.allclose(other.T_base_flange_commanded(0.0), poses[0], atol=1e-6)
    assert np.allclose(other.T_base_flange_commanded(4.0 - 1e-12), poses[1], atol=1e-6)
    assert np.array_equal(other.true.a_mm, cell.true.a_mm)
    assert np.array_equal(other.T_base_field, cell.T_base_field)


def test_random_program_rests_at_views_of_the_plate_and_loops():
    cell = SimCell(CellConfig(program="random", n_random_poses=5, dwell_s=0.5))
    traj = cell.trajectory
    assert np.allclose(traj.q_rad[-1], traj.q_rad[0])
    for t_s in traj.t_s:
        n_coded, n_uncoded = cell.targets_in_view(cell.T_field_camera(t_s))
        assert n_coded >= 6
    assert np.all(cell.nominal.within_limits(cell.q_at(np.linspace(0, cell.duration_s, 200))))


def test_hold_program_and_zero_error_cell_see_the_nominal_pose():
    cell = SimCell(CellConfig(program="hold", error_scale=0.0))
    assert np.allclose(cell.q_at(0.0), cell.q_at(123.4))
    assert np.allclose(cell.T_base_flange_true(0.3), cell.T_base_flange_commanded(0.3), atol=1e-12)
    T = cell.T_field_camera(0.0)
    # above the plate, the camera aimed at its centre
    miss_mm = np.linalg.norm(np.cross(T[:3, 2], -T[:3, 3]))
    assert miss_mm < 1.0 and 900.0 < T[2, 3] < 1100.0


def test_config_round_trips_through_a_dict_and_rejects_unknown_keys():
    config = CellConfig(seed=4, robot="ur10e", encoder_noise_rad=2e-5)
    assert CellConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown"):
        CellConfig.from_dict({"robot": "kr15", "speed": 3})
    with pytest.raises(ValueError):
        CellConfig(robot="abb")


def test_same_seed_gives_the_same_cell():
    a, b = SimCell(CellConfig(seed=9, program="hold")), SimCell(CellConfig(seed=9, program="hold"))
    assert np.array_equal(a.T_base_flange_true(0.2), b.T_base_flange_true(0.2))
    c = SimCell(CellConfig(seed=10, program="hold"))
    assert not np.allclose(a.true.a_mm, c.true.a_mm)
