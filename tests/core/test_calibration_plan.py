"""Planning a kinematic calibration: views the camera measures, chosen to make the errors observable."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.geometry.frames import inv_T
from service.core.robot.calibration_plan import plan_calibration, select_d_optimal, view_candidates
from service.core.robot.identification import identify_kinematics, observability
from service.sim.cell import CellConfig, SimCell


@pytest.fixture(scope="module")
def cell():
    return SimCell(CellConfig(seed=0, robot="kr15"))


@pytest.fixture(scope="module")
def candidates(cell):
    rng = np.random.default_rng(5)
    return view_candidates(
        cell.nominal, cell.camera, cell.field, cell.T_base_field, cell.T_flange_camera, cell.q_home_rad, 120, rng
    )


def test_every_candidate_is_a_view_of_the_field_reached_by_those_joints(cell, candidates):
    T, q = candidates
    assert len(T) == 120
    assert np.allclose(cell.nominal.fk(q), T, atol=1e-6)
    for k in range(0, 120, 10):  # the simulation's own (stricter, ring-aware) count of what the camera sees
        n_coded, n_uncoded = cell.targets_in_view(inv_T(cell.T_base_field) @ T[k] @ cell.T_flange_camera)
        assert n_coded >= 6 and n_coded + n_uncoded >= 30
    assert np.degrees(np.ptp(q, axis=0)).min() > 20.0  # spread over every joint, not one corner


def test_d_optimal_poses_are_better_conditioned_than_the_first_ones(cell, candidates):
    _, q = candidates
    pick = select_d_optimal(cell.nominal, q, 20)
    assert len(set(pick)) == 20
    chosen, first = observability(cell.nominal, q[pick]), observability(cell.nominal, q[:20])
    assert chosen.blind == () and chosen.condition < first.condition
    assert chosen.names == first.names or len(chosen.names) >= len(first.names)


def test_observability_freezes_what_the_identification_freezes(cell, candidates):
    _, q = candidates
    ob = observability(cell.nominal, q[:24])
    res = identify_kinematics(cell.nominal, q[:24], cell.true.fk(q[:24]), parameterisation="hayati", fixed=ob.blind)
    assert set(res.unidentifiable) == set(ob.structural)
    assert {"theta1", "d1"} <= set(ob.structural)  # the base transform takes them
    assert set(res.as_dict()) == set(ob.names)
    assert res.condition == pytest.approx(ob.condition, rel=0.2)  # at the solution vs at zero error


def test_a_plan_puts_the_hold_out_poses_last_and_they_are_not_in_the_fit(cell):
    rng = np.random.default_rng(8)
    plan = plan_calibration(
        cell.nominal, cell.camera, cell.field, cell.T_base_field, cell.T_flange_camera, cell.q_home_rad, 16, 4, rng
    )
    assert plan.q_rad.shape == (20, 6) and plan.n_holdout == 4 and plan.n_candidates >= 20
    assert len({tuple(np.round(q, 9)) for q in plan.q_rad}) == 20  # no pose twice
