"""Hand-eye refinement on the image observations themselves, with the robot's errors as unknowns.

The pose-level refinement (``handeye.calibrate_handeye``) whitens each sample by
an approximate covariance of the resected camera pose. Here the measurements
are the target images: for sample i the camera sees the field through

    T_field_camera_i = inv(Z) @ T_base_flange_i @ exp(d_i) @ X

where ``d_i`` (6,) is the robot's pose error at that sample (rotation rad about
the flange axes, translation mm along them), observed with the prior
``d_i ~ N(0, sigma_robot)``. Unknowns: X, Z and every ``d_i``; residuals: the
image residuals / σ_px and ``d_i`` / σ_robot. This is the paper's adjustment
of the collinearity equations with the robot pose as an observed quantity,
solved by ``scipy.optimize.least_squares`` (Levenberg–Marquardt).

The robot's systematic (kinematic) errors are not white, so σ0 above 1 is the
normal case; the covariance is scaled by ``max(1, σ0²)`` as in the pose-level
solver.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T, inv_T
from service.core.geometry.so3 import T_from_rotvec
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ImageSample:
    """One hand-eye sample: the robot's reported pose and the targets seen in the frame.

    T_base_flange : (4, 4) mm; p_field : (N, 3) mm target coordinates; uv : (N, 2) px measured
    """

    T_base_flange: Array
    p_field: Array
    uv: Array


@dataclass(frozen=True)
class ImageHandEyeResult:
    T_flange_camera: Array
    T_base_field: Array
    sigma_flange_camera_position_mm: Array  # (3,) along the camera axes (X = X0 @ exp(dx))
    sigma_flange_camera_rotation_deg: Array  # (3,)
    sigma_base_field_position_mm: Array  # (3,)
    sigma_base_field_rotation_deg: Array  # (3,)
    robot_error_position_mm: Array  # (M,) |translation of d_i|: what the robot got wrong at each sample
    robot_error_rotation_deg: Array  # (M,)
    rms_px: Array  # (M,) image RMS per sample after the adjustment
    sigma0: float
    converged: bool


def refine_handeye_on_images(
    camera: BrownFraser,
    samples: Sequence[ImageSample],
    T_flange_camera_init: ArrayLike,
    T_base_field_init: ArrayLike,
    *,
    sigma_px: float = 0.05,
    sigma_robot_position_mm: float = 0.5,
    sigma_robot_rotation_deg: float = 0.02,
) -> ImageHandEyeResult:
    """Refine X = T_flange_camera and Z = T_base_field on image observations (module docstring)."""
    X0 = check_T(T_flange_camera_init, "T_flange_camera_init")
    Z0 = check_T(T_base_field_init, "T_base_field_init")
    M = len(samples)
    if M < 3:
        raise SolveError(Reason.poor_motion, f"{M} samples; the image refinement needs at least 3")
    P = [check_T(s.T_base_flange, f"sample {k} T_base_flange") for k, s in enumerate(samples)]
    pts = [np.asarray(s.p_field, dtype=np.float64).reshape(-1, 3) for s in samples]
    uvs = [np.asarray(s.uv, dtype=np.float64).reshape(-1, 2) for s in samples]
    n_obs = [len(p) for p in pts]
    if min(n_obs) < 4:
        raise SolveError(Reason.too_few_targets, "every sample needs at least 4 measured targets")
    prior = np.r_[np.full(3, np.radians(sigma_robot_rotation_deg)), np.full(3, sigma_robot_position_mm)]
    n_par = 12 + 6 * M

    def poses(x: Array) -> tuple[Array, Array, list[Array]]:
        v = x.reshape(M + 2, 6)  # X's, Z's and each d_i's [rotation vector rad, translation mm]
        T_v = T_from_rotvec(v[:, :3], v[:, 3:])
        X = X0 @ T_v[0]
        Z = T_v[1] @ Z0
        Z_inv = inv_T(Z)
        T_cf = [inv_T(Z_inv @ P[i] @ T_v[2 + i] @ X) for i in range(M)]
        return X, Z, T_cf

    def residuals(x: Array) -> Array:
        _, _, T_cf = poses(x)
        out = []
        for i in range(M):
            p_cam = pts[i] @ T_cf[i][:3, :3].T + T_cf[i][:3, 3]
            if np.any(p_cam[:, 2] <= 0):
                raise SolveError(Reason.behind_camera, f"sample {i}: targets behind the camera during the adjustment")
            out.append(((camera.pixel_from_camera(p_cam) - uvs[i]) / sigma_px).ravel())
        d = x[12:].reshape(M, 6) / prior
        return np.concatenate([*out, d.ravel()])

    n_res = 2 * sum(n_obs) + 6 * M
    # 12 + 6 M unknowns (~70): a dense Levenberg-Marquardt step is cheaper than bookkeeping sparsity
    sol = least_squares(
        residuals, np.zeros(n_par), method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=50 * n_par
    )
    X, Z, T_cf = poses(sol.x)
    J = np.asarray(sol.jac)
    dof = max(1, n_res - n_par)
    sigma0 = float(np.sqrt(2 * sol.cost / dof))
    try:
        cov = np.linalg.inv(J.T @ J) * max(1.0, sigma0**2)
    except np.linalg.LinAlgError:
        raise SolveError(
            Reason.degenerate_geometry, "the samples do not determine X and Z (singular normal matrix)"
        ) from None
    s = np.sqrt(np.diag(cov))
    d = sol.x[12:].reshape(M, 6)
    r = sol.fun[: 2 * sum(n_obs)] * sigma_px
    rms, k = [], 0
    for n in n_obs:
        rms.append(float(np.sqrt(np.mean(r[k : k + 2 * n] ** 2) * 2)))
        k += 2 * n
    return ImageHandEyeResult(
        T_flange_camera=X,
        T_base_field=Z,
        sigma_flange_camera_position_mm=s[3:6],
        sigma_flange_camera_rotation_deg=np.degrees(s[0:3]),
        sigma_base_field_position_mm=s[9:12],
        sigma_base_field_rotation_deg=np.degrees(s[6:9]),
        robot_error_position_mm=np.linalg.norm(d[:, 3:], axis=1),
        robot_error_rotation_deg=np.degrees(np.linalg.norm(d[:, :3], axis=1)),
        rms_px=np.array(rms),
        sigma0=sigma0,
        converged=bool(sol.success),
    )
