"""Kinematic identification on the simulated arm: a perturbed KR15 is the truth, the nominal KR15 the controller."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.results import Reason, SolveError
from service.core.robot.identification import identify_kinematics
from service.core.robot.kinematics import kr15
from service.sim.robot import perturbed

NOISE_MM = 0.02
NOISE_RAD = NOISE_MM / 1000.0  # what 0.02 mm means across a 1 m target field
N_TRAIN = 100

# with base and tool estimated: theta1/d1 are base rz/z, d3 is interchangeable with d2 (axes 2 || 3), the tool
# takes link 6's row, and a point measured on axis 6 cannot tell d5 from alpha5 or theta5 from a5
REDUNDANT_POSITIONS = {"d1", "theta1", "d3", "d5", "theta5", "a6", "alpha6", "d6", "theta6"}
REDUNDANT_POSES = {"d1", "theta1", "d3", "a6", "alpha6", "d6", "theta6"}


def _random_q(model, rng, n):
    lo = np.maximum(model.q_limits_rad[:, 0], -np.pi)
    hi = np.minimum(model.q_limits_rad[:, 1], np.pi)
    return rng.uniform(lo, hi, (n, 6))


@pytest.fixture
def cell(rng):
    nominal = kr15()
    truth = perturbed(nominal, rng)
    q = _random_q(nominal, rng, N_TRAIN)
    T_true = truth.fk(q)
    p_meas = T_true[:, :3, 3] + rng.normal(0.0, NOISE_MM, (N_TRAIN, 3))
    T_meas = T_true.copy()
    T_meas[:, :3, 3] = p_meas
    T_meas[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, NOISE_RAD, (N_TRAIN, 3))).as_matrix() @ T_true[:, :3, :3]
    q_fresh = _random_q(nominal, rng, 200)
    return nominal, truth, q, p_meas, T_meas, q_fresh


def _truth_equivalent(nominal, truth, poses):
    """The truth's errors in the identified parameterisation, to first order, for parameters with a clean mapping."""
    da, dal = truth.a_mm - nominal.a_mm, truth.alpha_rad - nominal.alpha_rad
    dd, dth = truth.d_mm - nominal.d_mm, truth.theta_offset_rad - nominal.theta_offset_rad
    tilt = Rotation.from_matrix(truth.T_base_j0[:3, :3]).as_rotvec()
    exp = {f"a{i}": da[i - 1] for i in range(1, 5)}
    exp |= {f"alpha{i}": dal[i - 1] for i in range(1, 5)}
    exp |= {f"theta{i}": dth[i - 1] for i in range(2, 5)}
    exp |= {"d2": dd[1] + dd[2], "d4": dd[3]}
    exp |= {"base_x": 0.0, "base_y": 0.0, "base_z": dd[0], "base_rx": tilt[0], "base_ry": tilt[1], "base_rz": dth[0]}
    exp |= {"tool_x": da[5], "tool_z": dd[5]}
    if poses:
        exp |= {"a5": da[4], "alpha5": dal[4], "d5": dd[4], "theta5": dth[4]}
        exp |= {"tool_y": 0.0, "tool_rx": dal[5], "tool_ry": 0.0, "tool_rz": dth[5]}
    return exp


@pytest.mark.parametrize("poses", [False, True], ids=["positions", "poses"])
def test_identified_kr15_predicts_fresh_configurations_within_0_05_mm(cell, poses):
    nominal, truth, q, p_meas, T_meas, q_fresh = cell
    res = identify_kinematics(nominal, q, T_meas if poses else p_meas)
    p_true = truth.fk(q_fresh)[:, :3, 3]
    err_before = np.linalg.norm(nominal.fk(q_fresh)[:, :3, 3] - p_true, axis=1)
    err_after = np.linalg.norm(res.predict(q_fresh) - p_true, axis=1)
    assert 0.3 < err_before.mean() < 5.0
    assert 0.0 < err_after.mean() < 0.05
    assert err_after.max() < 0.1
    noise_3d = NOISE_MM * np.sqrt(3.0)
    assert 0.5 * noise_3d < res.rms_after_mm < 2.0 * noise_3d
    assert res.rms_before_mm > 10 * res.rms_after_mm
    if poses:
        assert 0.5 * NOISE_RAD * np.sqrt(3) < res.rms_rotation_after_rad < 2.0 * NOISE_RAD * np.sqrt(3)
    else:
        assert res.rms_rotation_after_rad is None
    assert np.allclose(res.predict_T(q_fresh)[:, :3, 3], res.predict(q_fresh))


@pytest.mark.parametrize("poses", [False, True], ids=["positions", "poses"])
def test_identification_freezes_the_classic_dh_redundancies(cell, poses):
    nominal, _, q, p_meas, T_meas, _ = cell
    res = identify_kinematics(nominal, q, T_meas if poses else p_meas)
    assert set(res.fixed) == (REDUNDANT_POSES if poses else REDUNDANT_POSITIONS)
    assert set(res.unidentifiable) == set(res.fixed)
    for name in res.fixed:
        assert res.parameter(name) == (0.0, 0.0)
    assert all(s > 0 for _, s in res.as_dict().values())


def test_without_a_base_correction_joint_1_zero_and_d1_become_identifiable(cell):
    nominal, _, q, p_meas, _, _ = cell
    res = identify_kinematics(nominal, q, p_meas, estimate_base=False, fixed=("a2",))
    assert {"theta1", "d1"}.isdisjoint(res.fixed)
    assert "a2" in res.fixed and "a2" not in res.unidentifiable
    assert not any(n.startswith("base") for n in res.names)


@pytest.mark.parametrize("poses", [False, True], ids=["positions", "poses"])
def test_identified_parameters_match_the_truth_within_3_sigma(cell, poses):
    nominal, truth, q, p_meas, T_meas, _ = cell
    res = identify_kinematics(nominal, q, T_meas if poses else p_meas)
    expected = _truth_equivalent(nominal, truth, poses)
    z = {}
    for name, value in expected.items():
        est, sigma = res.parameter(name)
        assert sigma > 0, name
        z[name] = (est - value) / sigma
    bad = {n: round(v, 2) for n, v in z.items() if abs(v) > 3.0}
    assert not bad, f"parameters off by more than 3 sigma: {bad}"
    # sigma is honest, not inflated: the normalised errors scatter like N(0, 1)
    assert 0.4 < np.sqrt(np.mean(np.square(list(z.values())))) < 1.8


def test_compensated_command_puts_the_true_flange_on_target(cell, rng):
    nominal, truth, q, _, T_meas, _ = cell
    res = identify_kinematics(nominal, q, T_meas)
    q_seed = np.radians([0.0, -90.0, 90.0, 0.0, 45.0, 0.0])
    for _ in range(3):
        q_target = q_seed + rng.uniform(-0.3, 0.3, 6)
        T_target = truth.fk(q_target)
        T_cmd = res.compensate(nominal, T_target, q_seed)
        q_ctrl = nominal.ik(T_cmd, q_seed)  # what the controller does with the command
        miss_mm = np.linalg.norm(truth.fk(q_ctrl)[:3, 3] - T_target[:3, 3])
        naive_mm = np.linalg.norm(truth.fk(nominal.ik(T_target, q_seed))[:3, 3] - T_target[:3, 3])
        assert miss_mm < 0.05 < naive_mm


@pytest.mark.parametrize("n_configs", [5, 12])
def test_identification_refuses_too_few_configurations(cell, n_configs):
    nominal, _, q, p_meas, _, _ = cell
    with pytest.raises(SolveError) as e:
        identify_kinematics(nominal, q[:n_configs], p_meas[:n_configs])
    assert e.value.reason == Reason.poor_motion


def test_identification_refuses_motion_of_two_joints_only(cell, rng):
    nominal, truth, _, _, _, _ = cell
    q = np.tile(np.radians([0.0, -90.0, 90.0, 0.0, 45.0, 0.0]), (100, 1))
    q[:, :2] += rng.uniform(-0.5, 0.5, (100, 2))
    p = truth.fk(q)[:, :3, 3] + rng.normal(0.0, NOISE_MM, (100, 3))
    with pytest.raises(SolveError) as e:
        identify_kinematics(nominal, q, p)
    assert e.value.reason == Reason.poor_motion
    assert e.value.details["unidentifiable"]


def test_identification_rejects_unknown_fixed_names_and_non_finite_input(cell):
    nominal, _, q, p_meas, _, _ = cell
    with pytest.raises(SolveError) as e:
        identify_kinematics(nominal, q, p_meas, fixed=("tool_rx",))  # no orientation in position data
    assert e.value.reason == Reason.bad_input
    p_bad = p_meas.copy()
    p_bad[3, 1] = np.nan
    with pytest.raises(SolveError) as e:
        identify_kinematics(nominal, q, p_bad)
    assert e.value.reason == Reason.bad_input
