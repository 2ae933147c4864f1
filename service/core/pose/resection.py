"""Space resection (the paper, section 4.3): the camera's pose from known field points.

Two stages, as in the paper. :func:`resect_closed_form` needs no prior pose: for
a planar field, the plane-to-plane transformation (a homography from >= 4 points,
Fischler & Bolles) gives the projection centre in front of the plane, and the
rotation follows from the known centre (Kraus) as the one that best aligns the
field rays from the centre with the image rays. A non-planar field's centre comes
from a DLT on ideal coordinates (OpenCV's P3P over all triples for 4-5 points).
When that start fails or its adjustment is not confirmed (one target off the plane of
the others leaves the DLT underdetermined), every other closed form that applies is
adjusted in turn: the homography of the coplanar majority, the DLT, P3P with a
consensus (:func:`~service.core.pose.resection_closed_form.fallback_starts`).
:func:`resect` then adjusts the collinearity equations over all points by
least squares (Levenberg-Marquardt on an analytic Jacobian), rejects gross errors
by iterative data snooping, and returns pose, covariance, sigma0 and residuals.

Observed pixels are turned into ideal coordinates once, as the paper does, and
each point's residual is whitened by the inverse of ``d(ideal)/d(pixel)``: residuals,
costs and sigma0 are in pixels of the distorted image (to first order, i.e. to
far below 1e-3 px at sub-pixel residuals). The adjustment is written by hand,
not handed to ``scipy.optimize``: it is the product's core method, it runs per
frame at >= 1 kHz with ~230 points, and a generic solver's overhead would exceed
its arithmetic. Its per-point loops and the Levenberg-Marquardt iteration are
compiled (:mod:`service.core._kernels.geometry_kernels`), and the whole adjustment with its data
snooping is one compiled call (:mod:`service.core._kernels.resection_kernel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core._kernels import kernel_array
from service.core._kernels.geometry_kernels import is_rigid_kernel, whitened_ideal_kernel
from service.core._kernels.resection_kernel import (
    DEGENERATE,
    INLIER_BEHIND,
    NO_CONVERGENCE,
    NO_DESCENT,
    NORMAL_SINGULAR,
    OK,
    START_BEHIND,
    TOO_FEW_AGREE,
    TOO_MANY_GROSS,
    resect_kernel,
)
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T
from service.core.pose.resection_closed_form import (
    CONFIRM_MAX_REJECTED,
    CONSENSUS_PX,
    check_geometry,
    check_observations,
    closed_form_ideal,
    fallback_starts,
    resect_closed_form,
)
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

__all__ = ["ResectionResult", "resect", "resect_closed_form"]

#: Per-point false-alarm probability of the default data-snooping test.
SNOOPING_ALPHA = 1e-5
#: Floor of the data-snooping sigma, px: far below any real measurement, it keeps
#: the scale-free studentized test from "detecting" round-off in perfect data.
SNOOPING_SIGMA_FLOOR_PX = 1e-4


@dataclass(frozen=True)
class ResectionResult:
    """The adjusted exterior orientation and its quality.

    Attributes
    ----------
    T_field_camera : (4, 4) float
        Pose of the camera in the field; its translation is the projection centre, mm.
    covariance : (6, 6) float
        Over ``[rotation (3) rad, position (3) mm]``; the rotation is a small one about
        the FIELD axes applied on the left (``R_true = exp([dθ]x) @ R_field_camera``).
        Scaled by ``sigma0_px**2``, or by ``sigma_px**2`` when ``resect`` was given it.
    sigma0_px : float
        A-posteriori sigma of unit weight, px: ``sqrt(sum(r**2) / (2 n - 6))`` over inliers.
    rms_px : float
        Per-coordinate RMS of the inliers' residuals, px: ``sqrt(mean(du**2 and dv**2))``.
    sigma_position_mm, sigma_rotation_deg : (3,) float
        Standard deviations of the centre along, and the rotation about, the field x, y, z axes.
    residuals_px : (N, 2) float
        Observed minus computed, px, for all input points (rejected ones too).
    inliers : (N,) bool
        Points used in the final adjustment.
    n_iter : int
        Adjustment iterations, summed over all data-snooping rounds.
    converged : bool
        Always True: an adjustment that does not converge raises ``no_convergence``.
    initial_cost, final_cost : float
        ``0.5 * sum(r**2)``, px^2, over all points at the start and over the inliers at the end.
    """

    T_field_camera: Array
    covariance: Array
    sigma0_px: float
    rms_px: float
    sigma_position_mm: Array
    sigma_rotation_deg: Array
    residuals_px: Array
    inliers: NDArray[np.bool_]
    n_iter: int
    converged: bool
    initial_cost: float
    final_cost: float

    @property
    def rejected(self) -> NDArray[np.intp]:
        """Indices of the input points rejected as gross errors."""
        return np.flatnonzero(~self.inliers)


# -- input checks -------------------------------------------------------------


def _check_pose(T_field_camera: ArrayLike) -> Array:
    """The start pose as a (4, 4) array; ``frames.check_T`` (a tenth of a resection's time)
    only judges a pose that fails this cheaper test."""
    T = np.array(T_field_camera, dtype=np.float64)
    if T.shape != (4, 4) or not is_rigid_kernel(T, 1e-6):  # compiled: numpy calls cost 0.03 ms per frame
        T = np.ascontiguousarray(check_T(T, "T_field_camera_init"))
    return T


# -- the adjustment (compiled) and its failures ------------------------------------
#
# The collinearity equations' analytic Jacobian: with p_c = R^T (p - t) and
# R <- exp([dθ]x) R, dp_c/dθ = R^T [p - t]x and dp_c/dt = -R^T. In camera axes,
# with xn = X/Z and yn = Y/Z, this gives the classical rows ``c [xn yn, -(1 + xn^2), yn]``
# and ``c [1 + yn^2, -xn yn, -xn]`` for the rotation and ``-(c/Z) [1, 0, -xn]``,
# ``-(c/Z) [0, 1, -yn]`` for the centre; both blocks are then turned to field axes by R
# (``geometry_kernels.design_kernel``). Levenberg-Marquardt's gain-ratio control of the
# damping copes with large residuals (gross errors not yet rejected make Gauss-Newton
# zig-zag), and a stationary cost counts as converged: the step tolerance may be out of
# reach in a flat valley. On convergence by the step tolerance the residuals and design
# were evaluated just before that step, below 1e-10 of the scene's size, so they stand
# for the final pose (to ~1e-10 px) (``geometry_kernels.adjust_kernel``).
#
# Data snooping (``resection_kernel``): with a priori ``sigma_px`` each point's statistic
# ``v_i^T Qvv_i^-1 v_i / sigma^2`` is chi^2(2) (Baarda's w-test, 2 dof). Otherwise sigma^2
# is the a-posteriori variance without the point, with ``m`` degrees of freedom
# independent of it (the statistic is then 2 F(2, m)), capped at ``max_sigma_px**2`` so
# that many gross errors cannot hide behind the sigma0 they inflate (chi^2(2) again).
# Both quantiles have closed forms.


def _error(
    status: int,
    n: int,
    min_keep: int,
    max_iter: int,
    max_sigma_px: float,
    inliers: NDArray[np.bool_],
    n_in: int,
    sigma0: float,
    behind: NDArray[np.bool_],
) -> SolveError:
    """The ``SolveError`` of a failed :func:`~service.core._kernels.resection_kernel.resect_kernel`."""
    if status == START_BEHIND:
        return SolveError(
            Reason.behind_camera,
            "The start pose puts a target in the camera's focal plane (Z = 0).",
        )
    if status == NORMAL_SINGULAR:
        return SolveError(Reason.degenerate_geometry, "The resection's normal equations are singular.")
    if status == NO_DESCENT:
        return SolveError(Reason.no_convergence, "The resection found no step that lowers its cost.")
    if status == DEGENERATE:
        return SolveError(Reason.degenerate_geometry, "The points do not determine the camera pose.")
    if status == TOO_MANY_GROSS:
        return SolveError(
            Reason.too_few_targets,
            f"Too many gross errors: rejecting another point would leave fewer than {min_keep} of {n}.",
            {"rejected": np.flatnonzero(~inliers).tolist(), "n_targets": n},
        )
    if status == NO_CONVERGENCE:
        return SolveError(Reason.no_convergence, f"The resection did not converge in {max_iter} iterations.")
    if status == TOO_FEW_AGREE:
        return SolveError(
            Reason.too_few_targets,
            f"Too few targets agree: after rejecting {n - n_in} of {n}, the rest still fit "
            f"with sigma0 = {sigma0:.2f} px, more than max_sigma_px = {max_sigma_px:g} px.",
            {"rejected": np.flatnonzero(~inliers).tolist(), "sigma0_px": sigma0, "n_targets": n},
        )
    if status == INLIER_BEHIND:
        return SolveError(
            Reason.behind_camera,
            f"{int(np.sum(behind))} of {n_in} targets lie behind the adjusted camera.",
            {"behind": np.flatnonzero(behind).tolist()},
        )
    raise AssertionError(f"unknown resection status {status}")


def _confirmed(out: tuple, n: int) -> bool:
    """Whether an adjustment without a given start stands: it succeeded and rejected few points."""
    return out[0] == OK and n - out[4] <= CONFIRM_MAX_REJECTED * n


def resect(
    camera: BrownFraser,
    p_field: ArrayLike,
    uv: ArrayLike,
    *,
    T_field_camera_init: ArrayLike | None = None,
    sigma_px: float | None = None,
    reject_outliers: bool = True,
    critical_value: float | None = None,
    max_sigma_px: float = 0.5,
    max_iter: int = 50,
) -> ResectionResult:
    """Least-squares space resection with gross-error rejection.

    Parameters
    ----------
    camera : BrownFraser
        Interior orientation.
    p_field : (N, 3) float, mm
        Target coordinates in the field frame, N >= 4.
    uv : (N, 2) float, px
        Their measured pixel coordinates.
    T_field_camera_init : (4, 4) float, optional
        Start pose (e.g. the previous frame's), followed or refused. By default the closed
        form; if its adjustment fails or rejects more than ``CONFIRM_MAX_REJECTED`` of the
        points, the other closed forms' starts are adjusted until one is confirmed (else
        the successful one with the most inliers, then the lowest sigma0, is kept).
    sigma_px : float, optional
        A-priori sigma of an image coordinate, px. Given, it scales the covariance
        and data snooping is Baarda's w-test; otherwise the covariance is scaled by
        ``sigma0_px**2`` and snooping studentizes each point by sigma0 computed
        without it. ``sigma0_px`` is always the a-posteriori value.
    reject_outliers : bool
        Iterative data snooping: reject the worst point while its statistic
        ``sqrt(v_i^T Qvv_ii^-1 v_i) / sigma`` exceeds the critical value and re-adjust;
        at the end take back rejected points that fit the clean solution.
    critical_value : float, optional
        Threshold on that statistic, in sigmas. By default its quantile at a
        per-point false-alarm probability of 1e-5 (about 4.8 for many points).
    max_sigma_px : float
        The largest image noise believed possible, px (5-10 times the paper's
        1/10-1/20 px). Without ``sigma_px``, snooping uses ``min(sigma0 without the
        point, max_sigma_px)`` so that many gross errors cannot mask themselves by
        inflating sigma0, and a final sigma0 above it fails (too few targets agree).
    max_iter : int
        Iterations per adjustment.

    Returns
    -------
    ResectionResult

    Raises
    ------
    SolveError
        ``too_few_targets`` (N < 4, rejection would leave fewer than ``max(4, ceil(N/2))``
        points, or too few agree), ``degenerate_geometry`` (collinear points, singular
        normal equations), ``behind_camera`` (an inlier behind the adjusted camera),
        ``no_convergence``, ``bad_input`` (non-finite values).
    """
    p, q = check_observations(p_field, uv)
    p, q = kernel_array(p), kernel_array(q)  # the one array type the kernels know
    n, c = len(p), float(camera.c_mm)
    # camera.ideal_from_pixel and the inverse of camera.ideal_from_pixel_jacobian in one compiled pass:
    # as two array pipelines they cost a sixth of an ROI frame's resection
    xy, W = whitened_ideal_kernel(q, *camera.whitening_args)
    spread = check_geometry(p, xy)
    nan = np.nan

    def adjust(T: Array) -> tuple:
        return resect_kernel(
            T,
            p,
            xy,
            W,
            c,
            int(max_iter),
            bool(reject_outliers),
            nan if sigma_px is None else float(sigma_px),
            float(max_sigma_px),
            nan if critical_value is None else float(critical_value),
            SNOOPING_ALPHA,
            SNOOPING_SIGMA_FLOOR_PX,
        )

    def error(out: tuple) -> SolveError:
        return _error(out[0], n, max(4, -(-n // 2)), max_iter, max_sigma_px, out[3], out[4], out[8], out[12])

    if T_field_camera_init is not None:  # the caller's start: followed or refused, never replaced
        out = adjust(_check_pose(T_field_camera_init))
        if out[0] != OK:
            raise error(out)
        return _result(out)
    # Without a start: the usual closed form, and only when its adjustment is not confirmed every
    # other one that applies, so that the common frame pays for one start and one adjustment.
    first_error: SolveError | None
    try:
        out = adjust(closed_form_ideal(p, xy, c, spread))
    except SolveError as e:
        first_error, start_failed, best = e, True, None
    else:
        if _confirmed(out, n):
            return _result(out)
        # a success not confirmed (too many rejected) stays the best so far, and has no error
        first_error, start_failed = (None if out[0] == OK else error(out)), out[0] == START_BEHIND
        best = out if out[0] == OK else None
    for T in fallback_starts(p, xy, c, CONSENSUS_PX * camera.mean_pixel_size_mm):
        cand = adjust(T)
        if _confirmed(cand, n):
            return _result(cand)
        if cand[0] == OK:
            # unconfirmed ones: the most inliers, then the smallest sigma0
            if best is None or (cand[4], -cand[8]) > (best[4], -best[8]):
                best = cand
        elif start_failed and cand[0] != START_BEHIND:
            # a start most points agreed with, adjusted: its verdict is the data's, not the start's
            first_error, start_failed = error(cand), False
    if best is None:
        assert first_error is not None  # (None only with a successful first adjustment: the best)
        raise first_error
    return _result(best)


def _result(out: tuple) -> ResectionResult:
    """The :class:`ResectionResult` of a successful :func:`~service.core._kernels.resection_kernel.resect_kernel`."""
    _, T, n_iter, inliers, _, r_all, cov, sig, sigma0, rms, omega, ss0, _ = out
    return ResectionResult(
        T_field_camera=T,
        covariance=cov,
        sigma0_px=sigma0,
        rms_px=rms,
        sigma_position_mm=sig[3:],
        sigma_rotation_deg=sig[:3],
        residuals_px=r_all,
        inliers=inliers,
        n_iter=n_iter,
        converged=True,
        initial_cost=0.5 * ss0 if ss0 == ss0 else np.inf,
        final_cost=0.5 * omega,
    )
