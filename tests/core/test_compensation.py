"""Compensated commands: corrected-model IK, the nominal command, refusals, and the simulated cell's true arm."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.results import Reason, SolveError
from service.core.robot.compensation import compensate_targets
from service.core.robot.identification import identify_kinematics
from service.core.robot.kinematics import kr15, ur5
from service.sim.cell import CellConfig, SimCell
from service.sim.robot import perturbed

HOME_UR_DEG = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)


@pytest.fixture
def arm(rng):
    nominal = ur5()
    corrected = replace(perturbed(nominal, rng), beta_rad=np.radians([0, 0.02, -0.03, 0, 0, 0]))
    return nominal, corrected


def _targets(model, q_center, rng, n, spread_rad=0.4):
    q = q_center + rng.uniform(-spread_rad, spread_rad, (n, 6))
    return model.fk(q), q


def test_compensated_joints_put_the_corrected_flange_on_target_and_the_command_is_their_nominal_pose(arm, rng):
    nominal, corrected = arm
    home = np.radians(HOME_UR_DEG)
    T_t, q_t = _targets(nominal, home, rng, 12)
    seeds = np.full((12, 6), np.nan)
    seeds[::3] = q_t[::3] + 0.05  # some rows seeded, the others follow the previous row
    res = compensate_targets(corrected, nominal, T_t, seeds, q_neutral_rad=home)
    T_fit = corrected.fk(res.q_rad)
    assert np.abs(T_fit[:, :3, 3] - T_t[:, :3, 3]).max() < 1e-3  # mm
    assert np.abs(Rotation.from_matrix(np.swapaxes(T_fit[:, :3, :3], 1, 2) @ T_t[:, :3, :3]).magnitude()).max() < 1e-6
    assert res.residual_mm.max() < 1e-3
    assert np.allclose(res.T_base_flange_command, nominal.fk(res.q_rad), atol=1e-12)
    # the controller's own IK of the command, from a nearby seed, gives back the compensated joints
    for k in range(12):
        assert np.allclose(nominal.ik(res.T_base_flange_command[k], q_t[k]), res.q_rad[k], atol=1e-8)
    # the correction is the arm's error: ~mm, and it is what the command and the target differ by
    assert 0.3 < res.correction_mm.mean() < 5.0
    assert np.allclose(res.correction_mm, np.linalg.norm(res.T_base_flange_command[:, :3, 3] - T_t[:, :3, 3], axis=1))
    assert np.isfinite(res.seed_distance_rad[::3]).all() and np.isnan(res.seed_distance_rad[1::3]).all()


def test_a_first_row_without_a_seed_starts_from_the_neutral_seed_even_far_away(arm, rng):
    nominal, corrected = arm
    home = np.radians(HOME_UR_DEG)
    T_t, q_t = _targets(nominal, home + np.radians([40, 20, -30, 10, 20, 30]), rng, 3, spread_rad=0.05)
    res = compensate_targets(corrected, nominal, T_t, q_neutral_rad=home)
    assert res.residual_mm.max() < 1e-3
    assert np.abs(res.q_rad - q_t).max() < np.radians(2.0)  # the same configuration as the targets'


def test_unreachable_targets_are_refused_naming_the_row_and_the_distance(arm, rng):
    nominal, corrected = arm
    home = np.radians(HOME_UR_DEG)
    T_t, _ = _targets(nominal, home, rng, 4)
    T_t[2, :3, 3] *= 4.0  # ~2 m out: beyond the UR5's 850 mm reach
    with pytest.raises(SolveError) as e:
        compensate_targets(corrected, nominal, T_t, q_neutral_rad=home)
    assert e.value.reason == Reason.bad_input and e.value.details["rows"] == [3]
    msg = e.value.message
    assert msg.startswith("target 3 is out of reach of the corrected model: the nearest pose is ")
    far_mm = float(msg.split("nearest pose is ")[1].split(" mm")[0])
    assert 500.0 < far_mm < 3000.0, msg


def test_a_solution_far_from_its_seed_is_refused(arm, rng):
    nominal, corrected = arm
    home = np.radians(HOME_UR_DEG)
    T_t, q_t = _targets(nominal, home, rng, 3, spread_rad=0.05)
    seeds = q_t.copy()
    seeds[1, 5] += np.radians(40.0)  # wrist 3 seeded 40 deg off: the same pose, far from the seed
    with pytest.raises(SolveError) as e:
        compensate_targets(corrected, nominal, T_t, seeds, q_neutral_rad=home)
    assert e.value.details["rows"] == [2]
    assert "target 2 needs joint 6 40.0 deg from its seed (at most 30.0 deg allowed)" in e.value.message
    # with a wider allowance the same file passes
    res = compensate_targets(corrected, nominal, T_t, seeds, q_neutral_rad=home, max_seed_distance_rad=np.radians(45))
    assert np.degrees(res.seed_distance_rad[1]) == pytest.approx(40.0, abs=0.5)


def test_a_target_needing_a_joint_beyond_its_limits_is_refused(rng):
    nominal = kr15()
    corrected = perturbed(nominal, rng)
    home = np.radians([0.0, -90.0, 90.0, 0.0, 45.0, 0.0])
    narrow = replace(corrected, q_limits_rad=np.radians([[-30, 30], *np.degrees(nominal.q_limits_rad[1:]).tolist()]))
    T_t = nominal.fk(np.array([home, home + np.radians([60.0, 0, 0, 0, 0, 0])]))
    with pytest.raises(SolveError) as e:
        compensate_targets(narrow, nominal, T_t, q_neutral_rad=home)
    assert e.value.details["rows"] == [2]
    assert e.value.message.startswith("target 2 is out of reach of the corrected model: the pose needs joint 1")


def test_compensation_brings_the_simulated_cells_true_arm_to_its_targets():
    # identify from measured flange poses of the simulated cell (what camera + hand-eye give), compensate,
    # then ask the cell's TRUE arm where the compensated joints put the flange
    cell = SimCell(CellConfig(seed=0, robot="kr15"))
    nominal, true = cell.nominal, cell.true
    rng = np.random.default_rng(7)
    lo, hi = nominal.q_limits_rad[:, 0] * 0.6, nominal.q_limits_rad[:, 1] * 0.6
    q = rng.uniform(lo, hi, (120, 6))
    T_meas = true.fk(q)
    T_meas[:, :3, 3] += rng.normal(0.0, 0.02, (120, 3))
    T_meas[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 2e-5, (120, 3))).as_matrix() @ T_meas[:, :3, :3]
    q_meas = q + rng.normal(0.0, cell.config.encoder_noise_rad, q.shape)
    res = identify_kinematics(nominal, q_meas, T_meas, parameterisation="hayati")

    home = cell.q_home_rad
    q_goal = home + rng.uniform(-0.4, 0.4, (30, 6))
    T_target = nominal.fk(q_goal)  # poses the user wants: anywhere around home
    comp = compensate_targets(res.model, nominal, T_target, np.tile(home, (30, 1)), q_neutral_rad=home)
    q_plain = np.array([nominal.ik(T, home) for T in T_target])  # what the controller does uncompensated
    miss = np.linalg.norm(true.fk(comp.q_rad)[:, :3, 3] - T_target[:, :3, 3], axis=1)
    miss_plain = np.linalg.norm(true.fk(q_plain)[:, :3, 3] - T_target[:, :3, 3], axis=1)
    print(
        f"\nsimulated kr15: true flange off target {miss_plain.mean():.3f} mm uncompensated, "
        f"{miss.mean():.4f} mm compensated"
    )
    assert 0.5 < miss_plain.mean() < 3.0
    assert 0.0 < miss.mean() < 0.05 and miss.max() < 0.1
