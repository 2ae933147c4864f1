"""Hayati's beta on near-parallel links: the chain, its Jacobian, its conditioning and its identification."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.results import Reason, SolveError
from service.core.robot.identification import (
    BASE_NAMES,
    TOOL_NAMES,
    dh_parameter_names,
    hayati_parameter_names,
    identification_jacobian,
    identify_kinematics,
)
from service.core.robot.kinematics import kr15, near_parallel_links, nominal_model, ur5
from service.sim.robot import perturbed

ROBOTS = ("kr15", "ur10e", "ur5")
NOISE_MM = 0.02


def _classic_fk(model, q):
    """An independent classic-DH chain, one 4x4 product per link, for one configuration q (6,)."""

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def rx(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def ry(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])

    def tr(x, z):
        T = np.eye(4)
        T[0, 3], T[2, 3] = x, z
        return T

    T = model.T_base_j0.copy()
    for i in range(6):
        th = q[i] + model.theta_offset_rad[i]
        T = T @ rz(th) @ tr(0.0, model.d_mm[i]) @ tr(model.a_mm[i], 0.0) @ rx(model.alpha_rad[i])
        T = T @ ry(model.beta_rad[i])
    return T @ model.T_j6_flange


def _random_q(model, rng, n):
    lo = np.maximum(model.q_limits_rad[:, 0], -np.pi)
    hi = np.minimum(model.q_limits_rad[:, 1], np.pi)
    return rng.uniform(lo, hi, (n, 6))


def test_near_parallel_links_are_found_from_the_nominal_model():
    assert near_parallel_links(ur5()) == (2, 3)  # axes 2, 3, 4 parallel
    assert near_parallel_links(kr15()) == (2,)  # axes 2, 3 parallel
    assert near_parallel_links(nominal_model("ur10e")) == (2, 3)
    # a link 4 deg from parallel counts, one 6 deg from it does not
    for eps_deg, expected in ((4.0, (2,)), (6.0, ())):
        tilted = replace(kr15(), alpha_rad=kr15().alpha_rad + np.radians([0, eps_deg, 0, 0, 0, 0]))
        assert near_parallel_links(tilted) == expected


@pytest.mark.parametrize("robot", ROBOTS)
def test_hayati_chain_at_zero_errors_is_the_classic_model(robot, rng):
    nominal = nominal_model(robot)
    names = hayati_parameter_names(nominal)
    assert {n for n in names if n.startswith("beta")} == {f"beta{i}" for i in near_parallel_links(nominal)}
    res_model = replace(nominal, beta_rad=np.zeros(6))
    q = _random_q(nominal, rng, 20)
    T_fast = res_model.fk(q)
    for k in range(20):
        assert np.allclose(T_fast[k], _classic_fk(nominal, q[k]), atol=1e-9)
    assert np.array_equal(T_fast, nominal.fk(q))


@pytest.mark.parametrize("robot", ROBOTS)
def test_hayati_chain_with_beta_matches_the_link_by_link_product(robot, rng):
    nominal = nominal_model(robot)
    model = replace(nominal, beta_rad=rng.normal(0.0, 0.01, 6))
    q = _random_q(nominal, rng, 10)
    T = model.fk(q)
    for k in range(10):
        assert np.allclose(T[k], _classic_fk(model, q[k]), atol=1e-9)
    # and beta moves the flange: not a silent no-op
    assert np.linalg.norm(T[:, :3, 3] - nominal.fk(q)[:, :3, 3], axis=1).min() > 0.5


@pytest.mark.parametrize("robot", ROBOTS)
def test_jacobian_of_a_hayati_model_matches_finite_differences(robot, rng):
    model = replace(nominal_model(robot), beta_rad=rng.normal(0.0, 0.01, 6))
    h = 1e-6
    for q in _random_q(model, rng, 5):
        J = model.jacobian(q)
        T0 = model.fk(q)
        J_fd = np.empty((6, 6))
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = h
            Tp, Tm = model.fk(q + dq), model.fk(q - dq)
            J_fd[:3, j] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            # angular velocity in the base frame: log(R(q + h) R(q - h)^T) / 2h
            J_fd[3:, j] = Rotation.from_matrix(Tp[:3, :3] @ Tm[:3, :3].T).as_rotvec() / (2 * h)
        assert np.allclose(J[:3], J_fd[:3], atol=1e-5 * max(1.0, np.abs(J[:3]).max()))
        assert np.allclose(J[3:], J_fd[3:], atol=1e-7)
        assert np.isfinite(T0).all()


def test_classic_dh_is_ill_conditioned_for_near_parallel_axes_and_hayati_is_not(rng):
    # a KR15 whose axes 2 and 3 are eps off parallel; the free parameters are the ones classic DH
    # identifies on a clearly non-parallel arm (only the base, tool and link-6 redundancies frozen)
    generic_redundant = {"d1", "theta1", "d5", "theta5", "a6", "alpha6", "d6", "theta6"}
    dh = [n for n in [*BASE_NAMES, *TOOL_NAMES[:3], *dh_parameter_names()] if n not in generic_redundant]
    hayati = [n for n in dh if n != "d2"] + ["beta2"]  # beta replaces d on the near-parallel link
    cond = {}
    for eps_deg in (4.0, 1.0, 0.25):
        nom = replace(kr15(), alpha_rad=kr15().alpha_rad + np.radians([0, eps_deg, 0, 0, 0, 0]))
        q = _random_q(nom, rng, 100)
        cond[eps_deg] = (
            np.linalg.cond(identification_jacobian(nom, q, dh)),
            np.linalg.cond(identification_jacobian(nom, q, hayati)),
        )
    print("\n| axes 2-3 off parallel | cond classic DH | cond Hayati |\n|---|---|---|")
    for eps_deg, (c_dh, c_h) in cond.items():
        print(f"| {eps_deg} deg | {c_dh:.3g} | {c_h:.3g} |")
    # classic grows like 1 / eps^2 (x16 per factor 4 here); Hayati stays where a well-posed fit is
    assert cond[0.25][0] > 1e5 and cond[0.25][0] > 100 * cond[4.0][0] / 4
    assert all(c_h < 50 for _, c_h in cond.values())
    assert max(c_h for _, c_h in cond.values()) < 1.5 * min(c_h for _, c_h in cond.values())


def _ur5_with_tilted_parallel_axes(rng):
    """A true UR5: the simulator's DH errors plus a tilt beta of axes 3 and 4 (links 2 and 3) by 0.02-0.03 deg."""
    truth = perturbed(ur5(), rng)
    beta = np.zeros(6)
    beta[[1, 2]] = np.radians([0.025, -0.03])
    return replace(truth, beta_rad=beta)


@pytest.mark.parametrize("poses", [False, True], ids=["positions", "poses"])
def test_hayati_identification_recovers_tilted_parallel_axes_that_classic_dh_cannot(rng, poses):
    nominal = ur5()
    truth = _ur5_with_tilted_parallel_axes(rng)
    q = _random_q(nominal, rng, 150)
    T_true = truth.fk(q)
    p_meas = T_true[:, :3, 3] + rng.normal(0.0, NOISE_MM, (150, 3))
    meas = p_meas
    if poses:
        meas = T_true.copy()
        meas[:, :3, 3] = p_meas
        meas[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, NOISE_MM / 1000, (150, 3))).as_matrix() @ T_true[:, :3, :3]
    res = identify_kinematics(nominal, q, meas, parameterisation="hayati")
    classic = identify_kinematics(nominal, q, meas, parameterisation="dh")
    noise_3d = NOISE_MM * np.sqrt(3.0)
    q_fresh = _random_q(nominal, rng, 200)
    p_fresh = truth.fk(q_fresh)[:, :3, 3]
    err = np.linalg.norm(res.predict(q_fresh) - p_fresh, axis=1)
    err_classic = np.linalg.norm(classic.predict(q_fresh) - p_fresh, axis=1)
    print(
        f"\nfresh poses, mean error: Hayati {err.mean():.4f} mm, classic DH {err_classic.mean():.4f} mm; "
        f"fit RMS {res.rms_after_mm:.4f} vs {classic.rms_after_mm:.4f} mm; cond {res.condition:.3g}"
    )
    assert res.parameterisation == "hayati" and {"d2", "d3"} <= set(res.unidentifiable)
    assert 0.5 * noise_3d < res.rms_after_mm < 2.0 * noise_3d  # down to the noise, not below it
    assert 0.0 < err.mean() < 0.03
    assert classic.rms_after_mm > 3.0 * noise_3d  # classic DH has no parameter for the tilt
    assert err_classic.mean() > 3.0 * err.mean()
    for name, k in (("beta2", 1), ("beta3", 2)):
        est, sigma = res.parameter(name)
        assert 0 < sigma < 0.2 * abs(truth.beta_rad[k]), name
        assert abs(est - truth.beta_rad[k]) < 3.5 * sigma, (name, est, truth.beta_rad[k], sigma)


def test_hayati_identification_of_an_arm_without_tilt_finds_beta_zero(rng):
    nominal = kr15()
    truth = perturbed(nominal, rng)
    q = _random_q(nominal, rng, 100)
    p = truth.fk(q)[:, :3, 3] + rng.normal(0.0, NOISE_MM, (100, 3))
    res = identify_kinematics(nominal, q, p, parameterisation="hayati")
    est, sigma = res.parameter("beta2")
    assert sigma > 0 and abs(est) < 4 * sigma
    p_fresh = truth.fk(q_f := _random_q(nominal, rng, 100))[:, :3, 3]
    assert np.linalg.norm(res.predict(q_f) - p_fresh, axis=1).mean() < 0.05


def test_ik_of_a_hayati_model_round_trips_and_respects_limits(rng):
    model = replace(perturbed(kr15(), rng), beta_rad=np.radians([0, 0.02, 0, 0, 0, 0]))
    q_seed = np.radians([0.0, -90.0, 90.0, 0.0, 45.0, 0.0])
    for _ in range(5):
        q_t = q_seed + rng.uniform(-0.3, 0.3, 6)
        q = model.ik(model.fk(q_t), q_seed)
        assert np.linalg.norm(model.fk(q)[:3, 3] - model.fk(q_t)[:3, 3]) < 1e-6
        assert model.within_limits(q)
    limits_deg = [[-185, 185], [-155, 35], [-130, 154], [-350, 350], [-10, 10], [-350, 350]]  # A5 within +-10
    narrow = replace(model, q_limits_rad=np.radians(limits_deg))
    with pytest.raises(SolveError, match=r"joint 5 .* beyond its limits") as e:
        narrow.ik(model.fk(q_seed), q_seed)
    assert e.value.reason == Reason.bad_input
