"""The rotation helpers: against scipy, against finite differences, round trips, and the edge cases
where rotation formulas break (tiny angles, a half turn)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.geometry import so3
from service.core.geometry.frames import make_T


def random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = np.pi) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, max_angle, (n, 1))


#: Angles (rad) that cover the tiny ones, both sides of the series' threshold, the middle and pi.
EDGE_ANGLES = [0.0, 1e-12, 1e-8, 0.5 * so3.SMALL_ANGLE_RAD, 2.0 * so3.SMALL_ANGLE_RAD, 0.7, 2.0, np.pi - 1e-6, np.pi]


def test_skew_is_the_cross_product_for_stacks(rng):
    a, b = rng.normal(size=(2, 5, 4, 3))
    S = so3.skew(a)
    assert S.shape == (5, 4, 3, 3)
    assert np.allclose(np.einsum("...ij,...j->...i", S, b), np.cross(a, b), atol=1e-14)
    assert np.array_equal(S, -np.swapaxes(S, -1, -2))


def test_rotvec_and_matrix_agree_with_scipy_for_any_stack_shape(rng):
    w = random_rotvecs(rng, 24).reshape(2, 4, 3, 3)
    R = so3.R_from_rotvec(w)
    assert R.shape == (2, 4, 3, 3, 3)
    assert np.allclose(R.reshape(-1, 3, 3), Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix(), atol=1e-15)
    assert np.allclose(so3.rotvec_from_R(R), w, atol=1e-12)
    assert so3.R_from_rotvec(np.zeros((0, 3))).shape == (0, 3, 3)
    assert so3.rotvec_from_R(np.zeros((0, 3, 3))).shape == (0, 3)
    assert so3.R_from_rotvec([0.0, 0.0, 0.0]).shape == (3, 3)


@pytest.mark.parametrize("theta", EDGE_ANGLES)
def test_rotvec_round_trips_from_tiny_angles_to_a_half_turn(rng, theta):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    w = theta * axis
    R = so3.R_from_rotvec(w)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-15) and np.isclose(np.linalg.det(R), 1.0)
    back = so3.rotvec_from_R(R)
    if theta < np.pi:
        assert np.allclose(back, w, rtol=1e-9, atol=1e-15)  # exact to the last digits even at 1e-12 rad
    else:
        assert np.allclose(back, w, atol=1e-12) or np.allclose(back, -w, atol=1e-12)  # a half turn: either sign
    assert np.allclose(so3.R_from_rotvec(back), R, atol=1e-14)


def test_transforms_from_rotation_vectors_are_make_T_of_the_matrices(rng):
    w, t = random_rotvecs(rng, 6), rng.normal(0.0, 100.0, (6, 3))
    T = so3.T_from_rotvec(w, t)
    assert T.shape == (6, 4, 4)
    for k in range(6):
        assert np.allclose(T[k], make_T(Rotation.from_rotvec(w[k]).as_matrix(), t[k]), atol=1e-15)
    assert np.allclose(so3.rotvec_from_T(T), w, atol=1e-12)
    assert np.allclose(so3.T_from_rotvec(w[0], t[0]), T[0])
    assert so3.T_from_rotvec(w, [1.0, 2.0, 3.0]).shape == (6, 4, 4)  # one translation for every rotation


def test_rotation_between_and_its_angle(rng):
    R_a, R_b = so3.R_from_rotvec(random_rotvecs(rng, 2))
    w = so3.rotvec_between(R_a, R_b)
    assert np.allclose(R_a @ so3.R_from_rotvec(w), R_b, atol=1e-14)
    assert np.isclose(so3.angle_between(R_a, R_b), np.linalg.norm(w))
    assert np.isclose(so3.angle_between(R_b, R_a), so3.angle_between(R_a, R_b))
    assert np.isclose(so3.angle(so3.R_from_rotvec([0.0, 3.0, 0.0])), 3.0)
    # beyond a half turn the angle folds back into [0, pi]
    assert np.isclose(so3.angle(so3.R_from_rotvec([0.0, 0.0, 4.0])), 2 * np.pi - 4.0)


@pytest.mark.parametrize("theta", [1e-12, 1e-9, 1e-6])
def test_the_angle_between_nearly_equal_rotations_keeps_its_digits(rng, theta):
    # the trace formula arccos((tr R - 1) / 2) gives 0 at 1e-12 rad and ~1e-4 relative error at 1e-6;
    # the quaternion one keeps the angle to the rounding of the matrix product (~1e-16 rad)
    R_a = so3.R_from_rotvec(random_rotvecs(rng, 1)[0])
    axis = np.array([0.6, -0.8, 0.0])
    R_b = R_a @ so3.R_from_rotvec(theta * axis)
    assert abs(so3.angle_between(R_a, R_b) - theta) < 1e-15
    assert abs(so3.angle_between(np.eye(3), so3.R_from_rotvec(theta * axis)) / theta - 1.0) < 1e-12


def test_the_angle_of_a_half_turn_is_pi():
    for axis in np.eye(3):
        assert np.isclose(so3.angle(so3.R_from_rotvec(np.pi * axis)), np.pi, atol=1e-15)
    R = np.diag([1.0, -1.0, -1.0])  # a half turn about x, built directly
    assert np.isclose(so3.angle(R), np.pi) and np.isclose(so3.angle_between(np.eye(3), R), np.pi)


def numeric_left_jacobian(w: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of ``log(R(w + dw) R(w)^T)``: the left rotation a step of w makes."""
    R0 = so3.R_from_rotvec(w)
    J = np.empty((3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        J[:, i] = (
            so3.rotvec_from_R(so3.R_from_rotvec(w + e) @ R0.T) - so3.rotvec_from_R(so3.R_from_rotvec(w - e) @ R0.T)
        ) / (2 * h)
    return J


@pytest.mark.parametrize("theta", [*EDGE_ANGLES, 4.0])  # 4 rad: adjusted rotation vectors are not wrapped
def test_left_jacobian_is_the_derivative_of_the_exponential(rng, theta):
    axis = rng.normal(size=3)
    w = theta * axis / np.linalg.norm(axis)
    assert np.allclose(so3.left_jacobian(w), numeric_left_jacobian(w), atol=1e-8)


@pytest.mark.parametrize("theta", EDGE_ANGLES)
def test_left_jacobian_inverse_inverts_it_up_to_a_half_turn(rng, theta):
    axis = rng.normal(size=3)
    w = theta * axis / np.linalg.norm(axis)
    Ji = so3.left_jacobian_inv(w)
    assert np.all(np.isfinite(Ji))  # at pi the old (1 + cos t) / (2 t sin t) was 0 / 0
    assert np.allclose(Ji @ so3.left_jacobian(w), np.eye(3), atol=1e-12)


def reference_jacobians(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jl and its inverse from their Taylor series to t^8 (Bernoulli numbers for the inverse):
    exact to 1e-20 at the series threshold, where both of the helper's branches must meet them."""
    t2 = float(w @ w)
    a = sum((-1) ** k * t2**k / math.factorial(2 * k + 2) for k in range(5))
    b = sum((-1) ** k * t2**k / math.factorial(2 * k + 3) for k in range(5))
    b_inv = 1 / 12 + t2 / 720 + t2**2 / 30240 + t2**3 / 1209600 + t2**4 / 47900160
    W = so3.skew(w)
    return np.eye(3) + a * W + b * W @ W, np.eye(3) - 0.5 * W + b_inv * W @ W


def test_jacobians_are_exact_on_both_sides_of_the_series_threshold_and_take_stacks(rng):
    axis = np.array([2.0, -1.0, 2.0]) / 3.0
    for side in (1 - 1e-9, 1 + 1e-9):  # the series, then the closed forms
        w = so3.SMALL_ANGLE_RAD * side * axis
        J, J_inv = reference_jacobians(w)
        assert np.allclose(so3.left_jacobian(w), J, rtol=0.0, atol=1e-15)
        assert np.allclose(so3.left_jacobian_inv(w), J_inv, rtol=0.0, atol=1e-15)
    for f in (so3.left_jacobian, so3.left_jacobian_inv):
        assert np.array_equal(f(np.zeros(3)), np.eye(3))
        w = random_rotvecs(rng, 8).reshape(2, 4, 3)
        J = f(w)
        assert J.shape == (2, 4, 3, 3) and np.allclose(J[1, 2], f(w[1, 2]))


def test_the_mean_of_rotations_spread_around_one_is_that_one(rng):
    centre = so3.R_from_rotvec([0.3, -0.2, 1.1])
    d = random_rotvecs(rng, 5, 0.05)
    R = np.array([centre @ so3.R_from_rotvec(s * v) for v in d for s in (1.0, -1.0)])  # symmetric pairs
    assert so3.angle_between(so3.R_mean(R), centre) < 1e-4
    assert np.allclose(so3.R_mean(R[:1]), R[0])
