"""Rotations (SO(3)): the helpers every solver shares, each written once.

A rotation vector ``w`` (axis times angle, rad) is the parametrisation of every adjustment
here and the UR convention: ``R_from_rotvec(w) = exp([w]x)`` and ``rotvec_from_R`` is its
inverse (the logarithm, angle in [0, pi]). The conversions go through
``scipy.spatial.transform.Rotation``: it works by quaternions, so it stays exact for tiny
angles and at pi, where the trace formula ``arccos((tr R - 1) / 2)`` loses every digit.

Written by hand is only what scipy does not offer: the cross-product matrix :func:`skew`
and the left Jacobian of SO(3) with its inverse (:func:`left_jacobian`,
:func:`left_jacobian_inv`), the adjustments' own method (bundle, hand-eye): they turn a step
in a rotation vector into a small rotation about fixed axes,
``exp([w + dw]x) = exp([Jl(w) dw]x) exp([w]x)`` to first order, and back. And one matrix's
logarithm, compiled (the same quaternion method): the service takes a few per frame (pairing,
deviation), and scipy's fixed cost per call was a tenth of the hot path's interpreter time.

All functions take stacks: a leading ``...`` of any shape, also empty.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.core._kernels.geometry_kernels import rotation_from_rotvec_kernel, rotvec_from_matrix_kernel

Array = NDArray[np.float64]

#: Below this angle (rad) the Jacobians use their Taylor series (exact to 1e-17 there); above it
#: the closed forms lose at most 1e-11 relative to cancellation.
SMALL_ANGLE_RAD = 1e-2


def skew(v: ArrayLike) -> Array:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``skew(a) @ b == cross(a, b)``.

    >>> skew([1.0, 2.0, 3.0]) @ [4.0, 5.0, 6.0]
    array([-3.,  6., -3.])
    """
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros((*v.shape[:-1], 3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def R_from_rotvec(rotvec: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) rad: ``exp([w]x)``.

    >>> np.round(R_from_rotvec([0.0, 0.0, np.pi / 2]) @ [1.0, 0.0, 0.0], 12).tolist()
    [0.0, 1.0, 0.0]
    """
    w = np.asarray(rotvec, dtype=np.float64)
    if w.shape == (3,):  # one vector: compiled Rodrigues, as rotvec_from_R
        return np.asarray(rotation_from_rotvec_kernel(np.array(w, order="C")))  # a writable copy: one signature
    return np.asarray(Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix()).reshape(*w.shape[:-1], 3, 3)


def rotvec_from_R(R: ArrayLike) -> Array:
    """Rotation vectors (..., 3) rad, angle in [0, pi], of rotation matrices (..., 3, 3): ``log R``.

    A matrix that is not quite orthonormal gives the rotation nearest to it.

    >>> np.round(rotvec_from_R(R_from_rotvec([0.1, -0.2, 0.3])), 12).tolist()
    [0.1, -0.2, 0.3]
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):  # one matrix: compiled, ~40x less per call; equal to 1e-15 on rotations
        return np.asarray(rotvec_from_matrix_kernel(np.array(R, order="C")))  # (a read-only one compiles anew)
    return np.asarray(Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()).reshape(*R.shape[:-2], 3)


def T_from_rotvec(rotvec: ArrayLike, t: ArrayLike) -> Array:
    """Transforms (..., 4, 4) from rotation vectors (..., 3) rad and translations (..., 3) mm.

    >>> T_from_rotvec([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])[:3, 3].tolist()
    [1.0, 2.0, 3.0]
    """
    R = R_from_rotvec(rotvec)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros((*np.broadcast_shapes(R.shape[:-2], t.shape[:-1]), 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def rotvec_from_T(T: ArrayLike) -> Array:
    """Rotation vectors (..., 3) rad of the rotation blocks of transforms (..., 4, 4)."""
    return rotvec_from_R(np.asarray(T, dtype=np.float64)[..., :3, :3])


def rotvec_between(R_a: ArrayLike, R_b: ArrayLike) -> Array:
    """``log(R_a^T R_b)`` (..., 3) rad: ``R_b = R_a @ exp([w]x)``, the rotation from a to b in a's own axes.

    >>> np.round(rotvec_between(np.eye(3), R_from_rotvec([0.0, 0.0, 0.25])), 12).tolist()
    [0.0, 0.0, 0.25]
    """
    R_a = np.asarray(R_a, dtype=np.float64)
    R_b = np.asarray(R_b, dtype=np.float64)
    return rotvec_from_R(np.swapaxes(R_a, -1, -2) @ R_b)


def angle(R: ArrayLike) -> Array:
    """Rotation angles (...) rad, in [0, pi], of rotation matrices (..., 3, 3)."""
    return np.asarray(np.linalg.norm(rotvec_from_R(R), axis=-1))


def angle_between(R_a: ArrayLike, R_b: ArrayLike) -> Array:
    """Angles (...) rad, in [0, pi], of the rotations between ``R_a`` and ``R_b`` (..., 3, 3).

    Exact for tiny angles (no arccos of a trace):

    >>> float(angle_between(np.eye(3), R_from_rotvec([1e-9, 0.0, 0.0])))
    1e-09
    """
    return np.asarray(np.linalg.norm(rotvec_between(R_a, R_b), axis=-1))


def R_mean(R: ArrayLike) -> Array:
    """The chordal L2 mean (3, 3) of rotations (n, 3, 3) (``Rotation.mean``): the rotation nearest
    to their arithmetic mean matrix, which for rotations close together is their average."""
    return np.asarray(Rotation.from_matrix(np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)).mean().as_matrix())


def _angle_terms(rotvec: ArrayLike) -> tuple[Array, Array, Array]:
    """``W = [w]x`` (..., 3, 3), the angle theta (..., 1, 1) and theta with 1 in place of the small ones."""
    w = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    small = theta < SMALL_ANGLE_RAD
    return skew(w), theta, np.where(small, 1.0, theta)


def left_jacobian(rotvec: ArrayLike) -> Array:
    """Left Jacobians (..., 3, 3) of SO(3) at rotation vectors (..., 3) rad.

    ``R(w + dw) = exp([Jl(w) dw]x) R(w)`` to first order, with
    ``Jl = I + (1 - cos t) / t^2 [w]x + (t - sin t) / t^3 [w]x^2`` (t = |w|); it is the
    identity at 0, and invertible for every t < 2 pi.
    """
    W, theta, t = _angle_terms(rotvec)
    small = theta < SMALL_ANGLE_RAD
    t2 = theta * theta
    a = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * np.sin(t / 2.0) ** 2 / t**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / t**3)
    return np.asarray(np.eye(3) + a * W + b * (W @ W))


def left_jacobian_inv(rotvec: ArrayLike) -> Array:
    """Inverses (..., 3, 3) of :func:`left_jacobian`: ``dw = Jl(w)^-1 d`` for a left rotation ``d``.

    ``Jl^-1 = I - [w]x / 2 + (1 - (t / 2) cot(t / 2)) / t^2 [w]x^2``, written with
    ``cot(t / 2)`` so that it stays finite at pi (where ``(1 + cos t) / (2 t sin t)`` is 0/0).
    """
    W, theta, t = _angle_terms(rotvec)
    small = theta < SMALL_ANGLE_RAD
    t2 = theta * theta
    half = t / 2.0
    b = np.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0, (1.0 - half * np.cos(half) / np.sin(half)) / t**2)
    return np.asarray(np.eye(3) - 0.5 * W + b * (W @ W))
