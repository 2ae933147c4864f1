"""3-D similarity / rigid transform between two point sets: closed form (Umeyama 1991) and refined.

The paper (section 4.4) finds the camera pose from forward intersection as the
transform between the model frame (here the master camera of a rig) and the
field frame, "carried out" in closed form. Umeyama's SVD solution is that
closed form: it minimises ``sum_i w_i |p_a_i - (s R p_b_i + t)|^2`` (the same
optimum as Horn's quaternion form), with the scale and with the sign guard that
keeps the plain SVD method (Arun 1987) from returning a reflection for noisy or
coplanar points (the usual floor plate). It is written by hand because neither
scipy nor OpenCV offers the weighted similarity (``Rotation.align_vectors`` has
no translation or scale, ``cv2.estimateAffine3D`` is not rigid).

When the points of one set carry a full 3x3 covariance each (points from
forward intersection are much weaker in depth than across),
:func:`rigid_transform_with_covariance` refines the closed form by Gauss-Newton
weighted with those covariances and returns the transform's 6x6 covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.geometry.so3 import R_from_rotvec, skew
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

# Relative spread below which a point set counts as collinear (second singular
# value over the first); a roll about the line is then undetermined.
COLLINEAR_RATIO = 1e-6


@dataclass(frozen=True)
class SimilarityResult:
    """The transform ``p_a = scale * R_a_b @ p_b + t_a_b`` fitted to point pairs.

    Attributes
    ----------
    T_a_b : (4, 4) float
        ``[[scale * R_a_b, t_a_b], [0, 0, 0, 1]]``, so ``apply_T(T_a_b, p_b)``
        maps b into a; it is a rigid transform exactly when ``scale == 1``.
    R_a_b : (3, 3) float
        Proper rotation (det +1).
    t_a_b : (3,) float, mm
    scale : float
        1.0 unless fitted with ``with_scale=True``.
    residuals_mm : (N, 3) float, mm
        ``p_a - (scale * R_a_b @ p_b + t_a_b)`` for every pair, also those
        with zero weight (so outliers can be seen).
    rms_mm : float, mm
        Weighted root-mean-square length of the residual vectors of the points
        with positive weight.
    n_points : int
        Pairs with positive weight.
    """

    T_a_b: Array
    R_a_b: Array
    t_a_b: Array
    scale: float
    residuals_mm: Array
    rms_mm: float
    n_points: int


def _check_pairs(p_a: ArrayLike, p_b: ArrayLike, weights: ArrayLike | None) -> tuple[Array, Array, Array]:
    a = np.asarray(p_a, dtype=np.float64)
    b = np.asarray(p_b, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or b.shape != a.shape:
        raise ValueError(f"p_a and p_b must both have shape (N, 3), got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("p_a and p_b must be finite")
    if weights is None:
        w = np.ones(len(a))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(a),):
            raise ValueError(f"weights must have shape ({len(a)},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
    return a, b, w


def rigid_transform(
    p_a: ArrayLike,
    p_b: ArrayLike,
    with_scale: bool = False,
    weights: ArrayLike | None = None,
) -> SimilarityResult:
    """Closed-form least-squares transform mapping points ``p_b`` onto ``p_a``.

    Parameters
    ----------
    p_a : (N, 3) float, mm
        The points in frame a (e.g. ``p_field``).
    p_b : (N, 3) float, mm
        The same points in frame b (e.g. ``p_master`` from intersection).
    with_scale : bool
        Also fit a scale factor (a similarity transform); otherwise rigid.
    weights : (N,) float, optional
        Non-negative weight of each pair (for example ``1 / trace(covariance)``);
        zero drops a pair from the fit but keeps its residual.

    Returns
    -------
    SimilarityResult

    Raises
    ------
    SolveError
        ``too_few_targets`` with fewer than 3 weighted pairs;
        ``degenerate_geometry`` when the weighted points of b are (nearly)
        collinear or coincident.

    Examples
    --------
    >>> p_b = np.array([[0.0, 0, 0], [100, 0, 0], [0, 50, 0], [0, 0, 20]])
    >>> fit = rigid_transform(p_b + [1.0, 2.0, 3.0], p_b)
    >>> np.round(fit.t_a_b, 9).tolist(), round(fit.rms_mm, 9)
    ([1.0, 2.0, 3.0], 0.0)
    """
    a, b, w = _check_pairs(p_a, p_b, weights)
    used = w > 0
    n = int(np.count_nonzero(used))
    if n < 3:
        raise SolveError(
            Reason.too_few_targets,
            f"a 3-D transform needs at least 3 point pairs, got {n}.",
            {"n_points": n},
        )
    W = float(w.sum())
    mu_a = w @ a / W
    mu_b = w @ b / W
    A = a - mu_a
    B = b - mu_b
    sqrt_w = np.sqrt(w)[:, None]
    spread = np.linalg.svd(B * sqrt_w, compute_uv=False)
    if spread[0] <= 0 or spread[1] < COLLINEAR_RATIO * spread[0]:
        raise SolveError(
            Reason.degenerate_geometry,
            "the points are collinear or coincident, so the rotation about their line is undetermined.",
            {"n_points": n, "singular_values_mm": spread.tolist()},
        )
    cross = (A * w[:, None]).T @ B / W  # Sigma_ab of Umeyama, (3, 3)
    U, S, Vt = np.linalg.svd(cross)
    D = np.ones(3)
    # Umeyama's reflection guard: holds also for coplanar points (rank 2).
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2] = -1.0
    R = (U * D) @ Vt
    if with_scale:
        var_b = float(np.sum(w * np.sum(B * B, axis=1)) / W)
        scale = float(np.sum(S * D) / var_b)
    else:
        scale = 1.0
    t = mu_a - scale * R @ mu_b
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = t
    residuals = a - (scale * b @ R.T + t)
    rms = float(np.sqrt(np.sum(w * np.sum(residuals**2, axis=1)) / W))
    return SimilarityResult(T_a_b=T, R_a_b=R, t_a_b=t, scale=scale, residuals_mm=residuals, rms_mm=rms, n_points=n)


@dataclass(frozen=True)
class RigidFitResult:
    """A rigid ``T_a_b`` fitted to points of b with covariances, and its own covariance.

    Attributes
    ----------
    T_a_b : (4, 4) float, mm
    covariance : (6, 6) float
        Over ``[wx, wy, wz]`` (rad, a small rotation about a's axes applied on
        the left, ``R_a_b <- exp([w]x) R_a_b``, about b's origin) and
        ``[dx, dy, dz]`` (mm, the origin of b in a): the order and
        perturbation of ``ResectionResult.covariance``.
    residuals_mm : (N, 3) float, mm
        ``p_a - T_a_b @ p_b``; NaN for unused rows.
    rms_mm : float, mm
        Root mean square length of the residual vectors of the used rows.
    sigma0 : float
        ``sqrt(chi^2 / (3 n - 6))`` of the covariance-weighted fit; about 1
        when the covariances describe the data.
    used : (N,) bool
        Rows that entered the fit (all of p_a, p_b and covariance finite).
    n_points : int
    n_iter : int
    """

    T_a_b: Array
    covariance: Array
    residuals_mm: Array
    rms_mm: float
    sigma0: float
    used: NDArray[np.bool_]
    n_points: int
    n_iter: int


def _rigid_linearise(R: Array, t: Array, a: Array, b: Array, info_b: Array) -> tuple[Array, Array, Array]:
    """Residuals (n, 3) of ``a - (R b + t)``, Jacobian (n, 3, 6), weights (n, 3, 3) in frame a."""
    Rb = b @ R.T
    r = a - (Rb + t)
    J = np.concatenate([skew(Rb), np.broadcast_to(-np.eye(3), Rb.shape + (3,))], axis=2)
    return r, J, R @ info_b @ R.T


def rigid_transform_with_covariance(
    p_a: ArrayLike,
    p_b: ArrayLike,
    covariance_b: ArrayLike,
    max_iter: int = 20,
) -> RigidFitResult:
    """Rigid ``T_a_b`` from points ``p_a`` (error-free) and ``p_b`` with a 3x3 covariance each.

    Closed-form start (:func:`rigid_transform`, weights ``1 / trace``), then
    Gauss-Newton on ``p_a - (R p_b + t)`` weighted by each covariance rotated
    into a. Hand-written rather than ``least_squares`` so that the
    perturbation, and hence the covariance, is the one documented in
    :class:`RigidFitResult`. The covariance is ``(J^T W J)^-1``, not rescaled
    by ``sigma0``.

    Parameters
    ----------
    p_a : (N, 3) float, mm
        E.g. field coordinates; NaN rows are ignored.
    p_b : (N, 3) float, mm
        E.g. intersected points in the master camera frame; NaN rows are ignored.
    covariance_b : (N, 3, 3) float, mm^2
        Covariance of each ``p_b``; positive definite where used.

    Raises
    ------
    SolveError
        As :func:`rigid_transform`, and ``no_convergence`` if the refinement
        does not settle within ``max_iter`` iterations.
    """
    a = np.asarray(p_a, dtype=np.float64)
    b = np.asarray(p_b, dtype=np.float64)
    C = np.asarray(covariance_b, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or b.shape != a.shape or C.shape != (len(a), 3, 3):
        raise ValueError(f"need p_a (N, 3), p_b (N, 3), covariance_b (N, 3, 3); got {a.shape}, {b.shape}, {C.shape}")
    used = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    used &= np.all(np.isfinite(C), axis=(1, 2))
    au, bu, Cu = a[used], b[used], C[used]
    start = rigid_transform(au, bu, weights=1.0 / np.trace(Cu, axis1=1, axis2=2))
    R, t = start.R_a_b, start.t_a_b
    info = np.linalg.inv(Cu)
    n_iter, converged = 0, False
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        r, J, W = _rigid_linearise(R, t, au, bu, info)
        JtW = J.swapaxes(1, 2) @ W
        step = -np.linalg.solve((JtW @ J).sum(axis=0), (JtW @ r[..., None]).sum(axis=0)[:, 0])
        R = R_from_rotvec(step[:3]) @ R
        t = t + step[3:]
        if np.max(np.abs(step[:3])) < 1e-13 and np.max(np.abs(step[3:])) < 1e-10:
            converged = True
            break
    if not converged:
        raise SolveError(
            Reason.no_convergence,
            f"the covariance-weighted transform did not converge in {max_iter} iterations.",
        )
    r, J, W = _rigid_linearise(R, t, au, bu, info)
    cov = np.linalg.inv((J.swapaxes(1, 2) @ W @ J).sum(axis=0))
    chi2 = float(np.sum(r * (W @ r[..., None])[..., 0]))
    n = int(used.sum())
    residuals = np.full_like(a, np.nan)
    residuals[used] = r
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return RigidFitResult(
        T_a_b=T,
        covariance=cov,
        residuals_mm=residuals,
        rms_mm=float(np.sqrt(np.mean(np.sum(r**2, axis=1)))),
        sigma0=float(np.sqrt(chi2 / (3 * n - 6))),
        used=used,
        n_points=n,
        n_iter=n_iter,
    )
