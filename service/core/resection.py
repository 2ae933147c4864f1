"""Space resection (the paper, section 4.3): the camera's pose from known field points.

Two stages, as in the paper. :func:`resect_closed_form` needs no prior pose: for
a planar field, the plane-to-plane transformation (a homography from >= 4 points,
Fischler & Bolles) gives the projection centre in front of the plane, and the
rotation follows from the known centre (Kraus) as the one that best aligns the
field rays from the centre with the image rays. A non-planar field's centre comes
from a DLT on ideal coordinates (OpenCV's P3P over all triples for 4-5 points).
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
compiled (:mod:`service.core.geometry_kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.camera_model import BrownFraser
from service.core.frames import check_T, make_T
from service.core.geometry_kernels import (
    BEHIND,
    CONVERGED,
    NO_STEP,
    SINGULAR,
    adjust_kernel,
    design_kernel,
    is_rigid_kernel,
    normal_kernel,
    point_statistics_kernel,
    residuals_kernel,
    whitened_ideal_kernel,
)
from service.core.resection_closed_form import (
    check_geometry,
    check_observations,
    closed_form_ideal,
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
        T = check_T(T, "T_field_camera_init")
    return T


# -- closed form ----------------------------------------------------------------


def _residuals(R: Array, t: Array, p: Array, xy: Array, W: Array, c: float) -> tuple[Array, Array]:
    """Whitened residuals (n, 2) px and camera-frame points (n, 3) mm."""
    r, pc, _, _ = residuals_kernel(np.ascontiguousarray(R), np.ascontiguousarray(t), p, xy, W, float(c))
    return r, pc


def _design(R: Array, t: Array, p: Array, W: Array, c: float, pc: Array) -> Array:
    """Analytic Jacobian (n, 2, 6) of the whitened computed coordinates wrt [dθ, dt].

    With p_c = R^T (p - t) and R <- exp([dθ]x) R: dp_c/dθ = R^T [p - t]x and
    dp_c/dt = -R^T. In camera axes, with xn = X/Z and yn = Y/Z, this gives the
    classical rows ``c [xn yn, -(1 + xn^2), yn]`` and ``c [1 + yn^2, -xn yn, -xn]``
    for the rotation and ``-(c/Z) [1, 0, -xn]``, ``-(c/Z) [0, 1, -yn]`` for the
    centre; both blocks are then turned to field axes by R.
    """
    return design_kernel(np.ascontiguousarray(R), W, float(c), pc)


def _adjust(
    T: Array, p: Array, xy: Array, W: Array, c: float, scale_mm: float, max_iter: int
) -> tuple[Array, int, Array, Array, Array, bool]:
    """Levenberg-Marquardt on the collinearity equations.

    Returns the pose, the iterations, the residuals (n, 2), camera-frame points
    (n, 3) and design matrix (n, 2, 6), and whether it converged. On convergence
    by the step tolerance they were evaluated just before that step, which is
    below 1e-10 of the scene's size, so they stand for the final pose (to
    ~1e-10 px) without another evaluation.
    """
    R, t, it, r, pc, A3, outcome = adjust_kernel(
        np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), p, xy, W, c, scale_mm, max_iter)
    if outcome == BEHIND:
        raise SolveError(
            Reason.behind_camera,
            "The start pose puts a target in the camera's focal plane (Z = 0).",
        )
    if outcome == SINGULAR:
        raise SolveError(Reason.degenerate_geometry, "The resection's normal equations are singular.")
    if outcome == NO_STEP:
        raise SolveError(Reason.no_convergence, "The resection found no step that lowers its cost.")
    # Gain-ratio control of the damping: large residuals (gross errors not yet rejected) make
    # Gauss-Newton zig-zag, damping restores descent. A stationary cost counts as converged:
    # the step tolerance may be out of reach in a flat valley.
    return make_T(R, t), it, r, pc, A3, outcome == CONVERGED


def _point_statistics(v: Array, A: Array, Qxx: Array, sign: float) -> tuple[Array, Array]:
    """Each point's ``v_i^T Q_i^-1 v_i`` and ``det Q_i`` (n,), ``Q_i = I + sign A_i Qxx A_i^T``.

    ``sign = -1`` gives the cofactor of an adjusted point's residual, ``+1`` that
    of a point left out of the adjustment (its prediction error).
    """
    return point_statistics_kernel(v, A, Qxx, float(sign))


def _scores(
    T2: Array,
    s2_post: Array,
    m: int,
    sigma_px: float | None,
    max_sigma_px: float,
    critical_value: float | None,
) -> Array:
    """Squared test statistics ``T2 / sigma^2`` over their critical values (n,); > 1: gross error.

    With a priori ``sigma_px`` the statistic is chi^2(2) (Baarda's w-test, 2 dof).
    Otherwise sigma^2 is ``s2_post``, an a-posteriori variance with ``m`` degrees
    of freedom independent of the point (the statistic is then 2 F(2, m)), capped
    at ``max_sigma_px**2`` so that many gross errors cannot hide behind the
    sigma0 they inflate (chi^2(2) again). Both quantiles have closed forms.
    """
    chi2_crit = -2.0 * np.log(SNOOPING_ALPHA)  # P(chi^2(2) > x) = exp(-x/2)
    if sigma_px is not None:
        crit = critical_value**2 if critical_value is not None else chi2_crit
        return T2 / (sigma_px**2 * crit)
    capped = s2_post > max_sigma_px**2
    s2 = np.where(capped, max_sigma_px**2, np.maximum(s2_post, SNOOPING_SIGMA_FLOOR_PX**2))
    if critical_value is not None:
        return T2 / (s2 * critical_value**2)
    # P(F(2, m) > x) = (1 + 2x/m)^(-m/2); the statistic is 2F.
    f_crit = m * (SNOOPING_ALPHA ** (-2.0 / m) - 1.0) if m >= 1 else np.inf
    return T2 / (s2 * np.where(capped, chi2_crit, f_crit))


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
        Start pose (e.g. the previous frame's); by default :func:`resect_closed_form`.
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
    p, q = (np.require(a, np.float64, ['C', 'W']) for a in (p, q))  # the one array type the kernels know
    n, c = len(p), float(camera.c_mm)
    # camera.ideal_from_pixel and the inverse of camera.ideal_from_pixel_jacobian in one compiled pass:
    # as two array pipelines they cost a sixth of an ROI frame's resection
    xy, W = whitened_ideal_kernel(
        q, (camera.width - 1) / 2.0, (camera.height - 1) / 2.0, *map(float, camera.pixel_size_mm), float(camera.x0_mm),
        float(camera.y0_mm), *map(float, (camera.K1, camera.K2, camera.K3, camera.P1, camera.P2, camera.B1, camera.B2)))
    spread = check_geometry(p, xy)
    if T_field_camera_init is None:
        T = closed_form_ideal(p, xy, c, spread)
    else:
        T = _check_pose(T_field_camera_init)
    # W (px/mm) whitens ideal residuals
    d_mm = p - T[:3, 3]
    scale_mm = max(float(np.sqrt(np.einsum("ij,ij->", d_mm, d_mm) / n)), 1e-9)
    ss0 = residuals_kernel(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), p, xy, W, c)[2]
    initial_cost = 0.5 * ss0 if ss0 == ss0 else np.inf
    test = (sigma_px, max_sigma_px, critical_value)

    inliers = np.ones(n, dtype=bool)
    min_keep = max(4, -(-n // 2))
    n_iter, readmitted = 0, False
    while True:
        idx = np.flatnonzero(inliers)
        if len(idx) == n:  # no copies while every point is in (the usual case)
            T, it, v, pc, A, converged = _adjust(T, p, xy, W, c, scale_mm, max_iter)
        else:
            T, it, v, pc, A, converged = _adjust(T, p[idx], xy[idx], W[idx], c, scale_mm, max_iter)
        n_iter += it
        N = normal_kernel(A, v)[0]
        d = np.sqrt(np.diag(N))
        ev = np.linalg.eigvalsh(N / np.outer(d, d)) if np.all(d > 0) else np.zeros(6)
        if not ev[0] > 1e-12 * ev[-1]:
            raise SolveError(
                Reason.degenerate_geometry, "The points do not determine the camera pose."
            )
        Qxx = np.linalg.inv(N)
        f = 2 * len(idx) - 6
        omega = float(np.sum(v * v))
        score = np.zeros(len(idx))
        if reject_outliers:
            T2, det = _point_statistics(v, A, Qxx, -1.0)
            score = _scores(T2, np.maximum(omega - T2, 0.0) / max(f - 2, 1), f - 2, *test)
            score[det <= 1e-6] = 0.0  # a point the pose must pass through cannot be tested
        worst = int(np.argmax(score))
        if score[worst] > 1.0:
            # Even an unsettled adjustment (slow with large residuals) shows this.
            if len(idx) - 1 < min_keep:
                raise SolveError(
                    Reason.too_few_targets,
                    f"Too many gross errors: rejecting another point would leave fewer "
                    f"than {min_keep} of {n}.",
                    {"rejected": np.flatnonzero(~inliers).tolist(), "n_targets": n},
                )
            inliers[idx[worst]] = False
            continue
        if not converged:
            raise SolveError(
                Reason.no_convergence, f"The resection did not converge in {max_iter} iterations."
            )
        out = np.flatnonzero(~inliers)
        if readmitted or len(out) == 0:
            break
        # Swamping: next to a gross error still in the adjustment a good point can
        # look wrong. Test the rejected points once more, as new observations
        # against the clean solution, and take back those that fit.
        readmitted = True
        r_out, pc_out = _residuals(T[:3, :3], T[:3, 3], p[out], xy[out], W[out], c)
        T2, _ = _point_statistics(
            r_out, _design(T[:3, :3], T[:3, 3], p[out], W[out], c, pc_out), Qxx, 1.0
        )
        back = out[_scores(T2, np.full(len(out), omega / f), f, *test) <= 1.0]
        if len(back) == 0:
            break
        inliers[back] = True

    sigma0 = float(np.sqrt(omega / f))  # f >= 2 since n >= 4
    if reject_outliers and sigma_px is None and sigma0 > max_sigma_px:
        raise SolveError(
            Reason.too_few_targets,
            f"Too few targets agree: after rejecting {n - len(idx)} of {n}, the rest still fit "
            f"with sigma0 = {sigma0:.2f} px, more than max_sigma_px = {max_sigma_px:g} px.",
            {"rejected": np.flatnonzero(~inliers).tolist(), "sigma0_px": sigma0, "n_targets": n},
        )
    behind = pc[:, 2] <= 0
    if np.any(behind):
        raise SolveError(
            Reason.behind_camera,
            f"{int(np.sum(behind))} of {len(idx)} targets lie behind the adjusted camera.",
            {"behind": idx[behind].tolist()},
        )
    r_all = np.empty((n, 2))
    r_all[idx] = v
    if len(idx) < n:
        out = np.flatnonzero(~inliers)
        r_all[out] = _residuals(T[:3, :3], T[:3, 3], p[out], xy[out], W[out], c)[0]
    cov = (sigma_px if sigma_px is not None else sigma0) ** 2 * Qxx
    sig = np.sqrt(np.diag(cov))
    return ResectionResult(
        T_field_camera=T,
        covariance=cov,
        sigma0_px=sigma0,
        rms_px=float(np.sqrt(omega / (2 * len(idx)))),
        sigma_position_mm=sig[3:],
        sigma_rotation_deg=np.degrees(sig[:3]),
        residuals_px=r_all,
        inliers=inliers,
        n_iter=n_iter,
        converged=True,
        initial_cost=initial_cost,
        final_cost=0.5 * omega,
    )
