"""Hand-eye and robot-world calibration (the paper, section 5).

Unknowns (DESIGN section 1): ``X = T_flange_camera`` (the paper's H_CG) and
``Z = T_base_field``. Every sample ``j`` pairs the controller's flange pose
``P_j = T_base_flange_j`` with the measured camera pose ``C_j = T_field_camera_j``;
both sides of

    P_j @ X = Z @ C_j                       (= T_base_camera_j)

are the camera's pose in the base. For two samples i, j this gives the paper's
``A X = X B`` (H_Gj H_CG = H_CG H_Cj) with ``A = inv(P_i) @ P_j`` and
``B = inv(C_i) @ C_j``; A and B rotate by the same angle.

The solve runs in three steps:

1. :func:`tsai_lenz`, Tsai and Lenz's closed form for X over all sample pairs
   (written by hand: it is the paper's method);
2. :func:`robot_world_closed_form`, Z as the mean of ``P_j X inv(C_j)``;
3. :func:`calibrate_handeye`, a joint weighted least-squares refinement of X and Z
   over all samples (``scipy.optimize.least_squares``), with a covariance.

Noise model of the refinement: each robot pose is off by a small rigid motion
in the flange frame (``P_j = P_true @ exp(xi)``, isotropic, sigma_robot_* per
axis: rotation about the flange origin, displacement of the flange origin) and
each camera pose likewise in the camera frame (rotation about the projection
centre). The residual of sample j is ``inv(Z C_j) @ P_j @ X`` (rotation vector
rad, translation mm), whose 6x6 covariance follows from these by first-order
propagation, including the robot rotation's lever arm ``|t_X|``. Samples are
independent, so the weighted refinement is the maximum-likelihood estimate.
The defaults describe the robot's repeatability (0.1 mm, 0.01 deg) and a good
resection (0.05 mm, 0.005 deg); a robot's *absolute* error is rather ~1 mm
(the paper, section 3), and where it shows up in the residuals the
a-posteriori variance factor scales the covariance (see :func:`calibrate_handeye`).

Perturbation frames of the covariance: X rotates about the flange axes and its
position is ``t_X`` in the flange frame; Z rotates about the base axes and its
position is the field origin in the base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from service.core.geometry.frames import make_T, orientation_report
from service.core.geometry.so3 import R_from_rotvec, R_mean, left_jacobian, left_jacobian_inv, rotvec_from_R, skew
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

# Limits on the robot motions: below MIN_* the answer would be noise (SolveError),
# below ADVISED_* it is weak (a warning). Tsai and Lenz need two motions (three
# samples) about non-parallel axes; ``axis_spread`` is defined in motion_quality.
MIN_SAMPLES = 3
ADVISED_SAMPLES = 8
MIN_ROTATION_DEG = 1.0
ADVISED_ROTATION_DEG = 10.0
MIN_AXIS_SPREAD = 0.02  # all axes parallel to within about 1 deg
ADVISED_AXIS_SPREAD = 0.15
SIGMA0_WARN = 3.0  # residuals this many times the declared sigmas: warn
MAX_SIGMA_X_POSITION_MM = 1.0  # warn when X is less precise than this
MAX_SIGMA_X_ROTATION_DEG = 0.1


@dataclass(frozen=True)
class HandEyeResult:
    """X = T_flange_camera and Z = T_base_field with their precision and residuals.

    Attributes
    ----------
    T_flange_camera, T_base_field : (4, 4) float, mm
    sigma_flange_camera_position_mm, sigma_flange_camera_rotation_deg : (3,) float
        Standard deviations of X: position along the flange axes, small rotations
        about the flange axes.
    sigma_base_field_position_mm, sigma_base_field_rotation_deg : (3,) float
        Standard deviations of Z: field origin along the base axes, small rotations
        about the base axes.
    covariance : (12, 12) float
        Order [X rot (rad), X pos (mm), Z rot (rad), Z pos (mm)], scaled by
        ``max(1, sigma0**2)``.
    residual_position_mm : (M,) float
        Per sample, distance between the camera centres of ``P_j X`` and ``Z C_j``.
    residual_rotation_deg : (M,) float
        Per sample, angle between the orientations of ``P_j X`` and ``Z C_j``.
    rms_position_mm, rms_rotation_deg : float
        Root mean square of the residuals above.
    warnings : tuple of str
        Sentences for a person: poor motions, few samples, optimistic sigmas.
    converged : bool
    n_iter : int
        Jacobian evaluations (= iterations) of the refinement.
    sigma0 : float
        A-posteriori standard deviation of unit weight (about 1 when the declared
        robot and camera sigmas are right).
    motion : dict
        :func:`motion_quality` of the robot poses.
    """

    T_flange_camera: Array
    T_base_field: Array
    sigma_flange_camera_position_mm: Array
    sigma_flange_camera_rotation_deg: Array
    sigma_base_field_position_mm: Array
    sigma_base_field_rotation_deg: Array
    covariance: Array
    residual_position_mm: Array
    residual_rotation_deg: Array
    rms_position_mm: float
    rms_rotation_deg: float
    warnings: tuple[str, ...]
    converged: bool
    n_iter: int
    sigma0: float = float("nan")
    motion: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (lists and plain numbers) for ``posecell calibrate handeye``."""
        return {
            "T_flange_camera": self.T_flange_camera.tolist(),
            "T_base_field": self.T_base_field.tolist(),
            "flange_camera": orientation_report(self.T_flange_camera),
            "base_field": orientation_report(self.T_base_field),
            "sigma_flange_camera_position_mm": self.sigma_flange_camera_position_mm.tolist(),
            "sigma_flange_camera_rotation_deg": self.sigma_flange_camera_rotation_deg.tolist(),
            "sigma_base_field_position_mm": self.sigma_base_field_position_mm.tolist(),
            "sigma_base_field_rotation_deg": self.sigma_base_field_rotation_deg.tolist(),
            "covariance": self.covariance.tolist(),
            "residual_position_mm": self.residual_position_mm.tolist(),
            "residual_rotation_deg": self.residual_rotation_deg.tolist(),
            "rms_position_mm": float(self.rms_position_mm),
            "rms_rotation_deg": float(self.rms_rotation_deg),
            "sigma0": float(self.sigma0),
            "n_samples": len(self.residual_position_mm),
            "motion": {k: float(v) for k, v in self.motion.items()},
            "warnings": list(self.warnings),
            "converged": bool(self.converged),
            "n_iter": int(self.n_iter),
        }


# -- small vectorised helpers --------------------------------------------------


def _poses(T: ArrayLike, name: str) -> Array:
    """``T`` as a float (M, 4, 4) stack of rigid transforms, or an error saying what is wrong."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (M, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise SolveError(Reason.bad_input, f"{name} contains non-finite values.")
    R = T[:, :3, :3]
    RtR = np.einsum("mki,mkj->mij", R, R)
    bad = (
        ~np.all(np.isclose(T[:, 3], [0.0, 0.0, 0.0, 1.0], atol=1e-6), axis=1)
        | ~np.all(np.isclose(RtR, np.eye(3), atol=1e-6), axis=(1, 2))
        | (np.linalg.det(R) <= 0)
    )
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise SolveError(
            Reason.bad_input,
            f"{name}[{k}] is not a rigid transform (rotation block not orthonormal or last row not 0 0 0 1).",
            {"index": k},
        )
    return T


def _relative(T: Array, i: NDArray[np.intp], j: NDArray[np.intp]) -> tuple[Array, Array]:
    """Rotation (P, 3, 3) and translation (P, 3) of ``inv(T_i) @ T_j`` for each pair."""
    Ri = T[i, :3, :3]
    R = np.einsum("pki,pkj->pij", Ri, T[j, :3, :3])
    t = np.einsum("pki,pk->pi", Ri, T[j, :3, 3] - T[i, :3, 3])
    return R, t


def _modified_rodrigues(rotvec: Array) -> Array:
    """Tsai's ``2 sin(theta/2) n`` from rotation vectors ``theta n`` (P, 3)."""
    theta = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    return rotvec * np.sinc(theta / (2.0 * np.pi))  # sinc(x) = sin(pi x)/(pi x)


# -- motion quality --------------------------------------------------------------


def motion_quality(T_base_flange: ArrayLike) -> dict[str, float]:
    """How well a set of robot poses determines X and Z.

    Looks at the relative motions ``inv(P_i) @ P_j`` of all pairs of samples.

    Parameters
    ----------
    T_base_flange : (M, 4, 4) float, mm

    Returns
    -------
    dict
        ``n_samples``; ``max_rotation_deg`` and ``median_rotation_deg``, the largest
        and the median rotation between two samples; ``axis_spread`` = s2/s1 and
        ``axis_spread_3d`` = s3/s1, singular value ratios of the stacked
        ``2 sin(theta/2) n`` of the motions (``axis_spread`` is 0 when all rotation
        axes are parallel, about 0.5 or more for well spread axes; Tsai and Lenz
        need it > 0); ``max_translation_mm``, the largest distance between two
        flange positions.

    >>> from service.core.geometry.frames import T_from_rotvec
    >>> q = motion_quality([T_from_rotvec([0, 0, a], [0, 0, 0]) for a in (0.0, 0.2, 0.5)])
    >>> round(q["max_rotation_deg"], 3), round(q["axis_spread"], 6)
    (28.648, 0.0)
    """
    P = np.asarray(T_base_flange, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ValueError(f"T_base_flange must have shape (M, 4, 4), got {P.shape}")
    M = len(P)
    q = {"n_samples": float(M), "max_rotation_deg": 0.0, "median_rotation_deg": 0.0}
    q |= {"axis_spread": 0.0, "axis_spread_3d": 0.0, "max_translation_mm": 0.0}
    if M < 2:
        return q
    i, j = np.triu_indices(M, k=1)
    R, _ = _relative(P, i, j)
    rotvec = rotvec_from_R(R)
    angle_deg = np.degrees(np.linalg.norm(rotvec, axis=1))
    s = np.linalg.svd(_modified_rodrigues(rotvec), compute_uv=False)
    s = np.pad(s, (0, 3 - len(s)))
    if s[0] > 0:
        q["axis_spread"] = float(s[1] / s[0])
        q["axis_spread_3d"] = float(s[2] / s[0])
    q["max_rotation_deg"] = float(angle_deg.max())
    q["median_rotation_deg"] = float(np.median(angle_deg))
    q["max_translation_mm"] = float(np.linalg.norm(P[j, :3, 3] - P[i, :3, 3], axis=1).max())
    return q


def _require_motion(q: dict[str, float]) -> list[str]:
    """Raise ``SolveError(poor_motion)`` for motions that cannot determine X; else the warnings."""
    n = int(q["n_samples"])
    if n < MIN_SAMPLES:
        raise SolveError(
            Reason.poor_motion,
            f"Hand-eye calibration needs at least {MIN_SAMPLES} samples (two robot motions), got {n}.",
            dict(q),
        )
    if q["max_rotation_deg"] < MIN_ROTATION_DEG:
        raise SolveError(
            Reason.poor_motion,
            f"The robot poses differ by at most {q['max_rotation_deg']:.2f} deg in orientation, "
            f"so the camera's orientation on the flange cannot be determined; rotate the flange "
            f"by {ADVISED_ROTATION_DEG:.0f} deg or more between samples.",
            dict(q),
        )
    if q["axis_spread"] < MIN_AXIS_SPREAD:
        raise SolveError(
            Reason.poor_motion,
            f"All robot rotations are about parallel axes (axis spread {q['axis_spread']:.4f}), "
            "so X is not determined along that axis; rotate the flange about at least two "
            "different axes.",
            dict(q),
        )
    warnings = []
    if n < ADVISED_SAMPLES:
        warnings.append(
            f"Only {n} samples; use {ADVISED_SAMPLES} or more so that the result and its sigmas can be trusted."
        )
    if q["max_rotation_deg"] < ADVISED_ROTATION_DEG:
        warnings.append(
            f"The robot orientations differ by at most {q['max_rotation_deg']:.1f} deg; "
            f"rotations of {ADVISED_ROTATION_DEG:.0f} deg or more determine X much better."
        )
    if q["axis_spread"] < ADVISED_AXIS_SPREAD:
        warnings.append(
            f"The robot's rotation axes are nearly parallel (axis spread {q['axis_spread']:.3f} "
            f"< {ADVISED_AXIS_SPREAD}); rotate the flange about well spread axes."
        )
    return warnings


def _check_pair(T_base_flange: ArrayLike, T_field_camera: ArrayLike) -> tuple[Array, Array]:
    P = _poses(T_base_flange, "T_base_flange")
    C = _poses(T_field_camera, "T_field_camera")
    if len(P) != len(C):
        raise ValueError(f"got {len(P)} robot poses but {len(C)} camera poses; they must pair up")
    return P, C


# -- closed forms ----------------------------------------------------------------


def tsai_lenz(T_base_flange: ArrayLike, T_field_camera: ArrayLike) -> Array:
    """Tsai and Lenz's closed-form hand-eye solution X = T_flange_camera.

    Solves ``A X = X B`` over all pairs of samples, rotation first (from the
    modified Rodrigues vectors ``2 sin(theta/2) n`` of A and B), then translation
    from ``(R_A - I) t_X = R_X t_B - t_A``, each by linear least squares.

    Tsai's rotation parameter ``tan(theta_X / 2) n_X`` is singular for a camera
    turned by 180 deg on the flange (a common mounting); the rotation equation is
    therefore solved in a frame pre-rotated by a coarse estimate (the best
    alignment of the motions' rotation vectors), where X's rotation is small.

    Parameters
    ----------
    T_base_flange : (M, 4, 4) float, mm
        Robot poses from the controller.
    T_field_camera : (M, 4, 4) float, mm
        Camera poses measured at the same instants.

    Returns
    -------
    T_flange_camera : (4, 4) float, mm

    Raises
    ------
    SolveError
        ``poor_motion`` for fewer than 3 samples, nearly pure translations or
        rotations all about parallel axes; ``bad_input`` for non-rigid matrices.
    """
    P, C = _check_pair(T_base_flange, T_field_camera)
    _require_motion(motion_quality(P))
    i, j = np.triu_indices(len(P), k=1)
    R_A, t_A = _relative(P, i, j)
    R_B, t_B = _relative(C, i, j)
    rv_A = rotvec_from_R(R_A)
    rv_B = rotvec_from_R(R_B)
    # A's axis is R_X times B's axis and the angles are equal, so the rotation vectors align.
    R0 = Rotation.align_vectors(rv_A, rv_B)[0].as_matrix()

    Pg = _modified_rodrigues(rv_A)
    Pc = _modified_rodrigues(rv_B) @ R0.T  # B's axes in the pre-rotated camera frame
    p_prime = np.linalg.lstsq(skew(Pg + Pc).reshape(-1, 3), (Pc - Pg).reshape(-1), rcond=None)[0]
    Pcg = 2.0 * p_prime / np.sqrt(1.0 + p_prime @ p_prime)
    n2 = Pcg @ Pcg
    R_small = (1.0 - n2 / 2.0) * np.eye(3) + 0.5 * (np.outer(Pcg, Pcg) + np.sqrt(max(4.0 - n2, 0.0)) * skew(Pcg))
    R_X = R_from_rotvec(rotvec_from_R(R_small @ R0))  # re-orthonormalise

    lhs = (R_A - np.eye(3)).reshape(-1, 3)
    rhs = (t_B @ R_X.T - t_A).reshape(-1)
    t_X = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return make_T(R_X, t_X)


def base_field_from_flange_camera(
    T_base_flange: ArrayLike, T_field_camera: ArrayLike, T_flange_camera: ArrayLike
) -> Array:
    """Z = T_base_field for a given X: the mean of ``P_j @ X @ inv(C_j)`` over the samples.

    Rotations are averaged by ``Rotation.mean`` (chordal L2 mean), translations
    arithmetically.

    Parameters
    ----------
    T_base_flange, T_field_camera : (M, 4, 4) float, mm
    T_flange_camera : (4, 4) float, mm

    Returns
    -------
    T_base_field : (4, 4) float, mm
    """
    P, C = _check_pair(T_base_flange, T_field_camera)
    X = np.asarray(T_flange_camera, dtype=np.float64)
    R_Z_j = P[:, :3, :3] @ X[:3, :3] @ np.transpose(C[:, :3, :3], (0, 2, 1))
    t_Z_j = np.einsum("mij,j->mi", P[:, :3, :3], X[:3, 3]) + P[:, :3, 3] - np.einsum("mij,mj->mi", R_Z_j, C[:, :3, 3])
    return make_T(R_mean(R_Z_j), t_Z_j.mean(axis=0))


def robot_world_closed_form(T_base_flange: ArrayLike, T_field_camera: ArrayLike) -> tuple[Array, Array]:
    """X by :func:`tsai_lenz`, then Z = T_base_field by :func:`base_field_from_flange_camera`.

    Parameters
    ----------
    T_base_flange, T_field_camera : (M, 4, 4) float, mm

    Returns
    -------
    T_flange_camera, T_base_field : (4, 4) float, mm
    """
    P, C = _check_pair(T_base_flange, T_field_camera)
    X = tsai_lenz(P, C)
    return X, base_field_from_flange_camera(P, C, X)


# -- joint refinement --------------------------------------------------------------


def _residual_covariance(X: Array, sigma_robot: tuple[float, float], sigma_camera: tuple[float, float]) -> Array:
    """6x6 covariance of one sample's residual ``inv(Z C) P X`` (rotvec rad, translation mm).

    ``sigma_*`` are (position mm, rotation rad). The robot's flange perturbation
    reaches the camera frame through ``Ad(inv X)``, whose translation row carries
    the lever arm ``-R_X^T skew(t_X)`` of the robot's rotation error.
    """
    R, t = X[:3, :3], X[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R.T
    Ad[3:, :3] = -R.T @ skew(t)
    Ad[3:, 3:] = R.T
    S_robot = np.diag([sigma_robot[1] ** 2] * 3 + [sigma_robot[0] ** 2] * 3)
    S_camera = np.diag([sigma_camera[1] ** 2] * 3 + [sigma_camera[0] ** 2] * 3)
    return Ad @ S_robot @ Ad.T + S_camera


def _update(X0: Array, Z0: Array, x: Array) -> tuple[Array, Array]:
    """Apply increments x (12,) = [X rot, X pos, Z rot, Z pos]; rotations act on the left."""
    X = make_T(R_from_rotvec(x[0:3]) @ X0[:3, :3], X0[:3, 3] + x[3:6])
    Z = make_T(R_from_rotvec(x[6:9]) @ Z0[:3, :3], Z0[:3, 3] + x[9:12])
    return X, Z


def _sample_residuals(P: Array, C: Array, X: Array, Z: Array, jacobian: bool = False) -> Any:
    """(M, 6) rotation vector (rad) and translation (mm) of ``E_j = inv(Z C_j) @ P_j @ X``.

    With ``jacobian``, also (M, 6, 12) derivatives with respect to left
    perturbations [X rot, X pos, Z rot, Z pos] of ``X = [exp(a) R_X, t_X + b]``
    and ``Z = [exp(c) R_Z, t_Z + d]``: with ``W = R_Z R_C`` and ``phi = log R_E``,
    ``d phi = Jl^-1(phi) W^T (R_P da - dc)`` and
    ``d t_E = W^T (R_P db + skew(q) dc - dd)``, ``q = R_P t_X + t_P - t_Z``.
    """
    W = Z[:3, :3] @ C[:, :3, :3]
    t_ZC = np.einsum("ij,mj->mi", Z[:3, :3], C[:, :3, 3]) + Z[:3, 3]
    R_PX = P[:, :3, :3] @ X[:3, :3]
    t_PX = np.einsum("mij,j->mi", P[:, :3, :3], X[:3, 3]) + P[:, :3, 3]
    WT = np.transpose(W, (0, 2, 1))
    phi = rotvec_from_R(WT @ R_PX)
    t_E = np.einsum("mij,mj->mi", WT, t_PX - t_ZC)
    r = np.concatenate([phi, t_E], axis=1)
    if not jacobian:
        return r
    WT_RP = WT @ P[:, :3, :3]
    Jl_inv = left_jacobian_inv(phi)
    J = np.zeros((len(P), 6, 12))
    J[:, :3, 0:3] = Jl_inv @ WT_RP
    J[:, :3, 6:9] = -Jl_inv @ WT
    J[:, 3:, 3:6] = WT_RP
    J[:, 3:, 6:9] = WT @ skew(t_PX - Z[:3, 3])
    J[:, 3:, 9:12] = -WT
    return r, J


def calibrate_handeye(
    T_base_flange: ArrayLike,
    T_field_camera: ArrayLike,
    *,
    sigma_robot_position_mm: float = 0.1,
    sigma_robot_rotation_deg: float = 0.01,
    sigma_camera_position_mm: float = 0.05,
    sigma_camera_rotation_deg: float = 0.005,
) -> HandEyeResult:
    """Hand-eye and robot-world calibration: X = T_flange_camera and Z = T_base_field.

    Tsai-Lenz for X, the mean for Z, then a joint least-squares refinement of
    both over all samples, each residual whitened by the covariance that the
    declared sigmas give it (module docstring). The covariance is the inverse
    normal matrix times ``max(1, sigma0**2)``: the declared sigmas are a floor,
    and residuals larger than they allow (the robot's absolute error, a bad
    sample) widen the reported sigmas rather than being ignored; smaller
    residuals do not shrink them, since with few samples sigma0 is itself
    uncertain.

    Parameters
    ----------
    T_base_flange : (M, 4, 4) float, mm
        Flange poses reported by the robot controller.
    T_field_camera : (M, 4, 4) float, mm
        Camera poses measured (resection) at the same instants.
    sigma_robot_position_mm, sigma_robot_rotation_deg : float
        Per-axis noise of the robot poses (displacement of the flange origin,
        rotation about it).
    sigma_camera_position_mm, sigma_camera_rotation_deg : float
        Per-axis noise of the camera poses (projection centre, rotation about it).

    Returns
    -------
    HandEyeResult

    Raises
    ------
    SolveError
        ``poor_motion`` for fewer than 3 samples, nearly pure translations,
        rotations about parallel axes or a singular normal matrix;
        ``bad_input`` for non-rigid or non-finite matrices.
    """
    P, C = _check_pair(T_base_flange, T_field_camera)
    sigmas = np.array([sigma_robot_position_mm, sigma_robot_rotation_deg])
    sigmas = np.r_[sigmas, sigma_camera_position_mm, sigma_camera_rotation_deg]
    if not np.all(np.isfinite(sigmas) & (sigmas >= 0)):
        raise ValueError(f"sigmas must be finite and non-negative, got {sigmas.tolist()}")
    if sigmas[0] + sigmas[2] <= 0 or sigmas[1] + sigmas[3] <= 0:
        raise ValueError("robot and camera sigmas must not both be zero, for position or rotation")
    quality = motion_quality(P)
    warnings = _require_motion(quality)
    M = len(P)

    X0, Z0 = robot_world_closed_form(P, C)
    cov_r = _residual_covariance(
        X0,
        (sigma_robot_position_mm, np.radians(sigma_robot_rotation_deg)),
        (sigma_camera_position_mm, np.radians(sigma_camera_rotation_deg)),
    )
    whiten = np.linalg.inv(np.linalg.cholesky(cov_r))

    def residuals(x: Array) -> Array:
        X, Z = _update(X0, Z0, x)
        return (_sample_residuals(P, C, X, Z) @ whiten.T).reshape(-1)

    def jacobian(x: Array) -> Array:
        X, Z = _update(X0, Z0, x)
        _, J = _sample_residuals(P, C, X, Z, jacobian=True)
        # x composes as exp(x_rot) @ R0, so a step in x is a left perturbation through Jl(x_rot).
        J[:, :, 0:3] = J[:, :, 0:3] @ left_jacobian(x[0:3])
        J[:, :, 6:9] = J[:, :, 6:9] @ left_jacobian(x[6:9])
        return (whiten @ J).reshape(-1, 12)

    sol = least_squares(
        residuals, np.zeros(12), jac=jacobian, method="lm",
        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200,
    )  # fmt: skip
    X, Z = _update(X0, Z0, sol.x)

    r, J = _sample_residuals(P, C, X, Z, jacobian=True)
    J = (whiten @ J).reshape(-1, 12)
    N = J.T @ J
    scale = np.sqrt(np.diag(N))
    if np.any(scale == 0) or np.linalg.cond(N / np.outer(scale, scale)) > 1e12:
        raise SolveError(
            Reason.poor_motion,
            "The robot motions leave X and Z undetermined (singular normal matrix); "
            "rotate the flange about several well spread axes.",
            dict(quality),
        )
    v = r @ whiten.T
    dof = 6 * M - 12
    sigma0 = float(np.sqrt(np.sum(v**2) / dof))
    covariance = max(1.0, sigma0**2) * np.linalg.inv(N)
    sd = np.sqrt(np.diag(covariance))

    res_rot_deg = np.degrees(np.linalg.norm(r[:, :3], axis=1))
    res_pos_mm = np.linalg.norm(r[:, 3:], axis=1)  # same length in camera or base axes

    converged = bool(sol.status > 0)
    if not converged:
        warnings.append(f"The refinement stopped before converging ({sol.message}).")
    if sigma0 > SIGMA0_WARN:
        warnings.append(
            f"The residuals are {sigma0:.1f} times what the declared robot and camera sigmas "
            "allow; "
            "the robot's absolute error (often ~1 mm) or a bad sample dominates, and the sigmas "
            "were scaled up to match."
        )
    sd_X_rot_deg = np.degrees(sd[0:3].max())
    if sd[3:6].max() > MAX_SIGMA_X_POSITION_MM or sd_X_rot_deg > MAX_SIGMA_X_ROTATION_DEG:
        warnings.append(
            f"X is poorly determined (sigma up to {sd[3:6].max():.2f} mm, "
            f"{sd_X_rot_deg:.3f} deg); add samples with larger, well spread rotations."
        )

    return HandEyeResult(
        T_flange_camera=X,
        T_base_field=Z,
        sigma_flange_camera_position_mm=sd[3:6],
        sigma_flange_camera_rotation_deg=np.degrees(sd[0:3]),
        sigma_base_field_position_mm=sd[9:12],
        sigma_base_field_rotation_deg=np.degrees(sd[6:9]),
        covariance=covariance,
        residual_position_mm=res_pos_mm,
        residual_rotation_deg=res_rot_deg,
        rms_position_mm=float(np.sqrt(np.mean(res_pos_mm**2))),
        rms_rotation_deg=float(np.sqrt(np.mean(res_rot_deg**2))),
        warnings=tuple(warnings),
        converged=converged,
        n_iter=int(sol.njev or 0),
        sigma0=sigma0,
        motion=quality,
    )
