"""Forward intersection with a calibrated multi-camera rig (the paper, section 4.4).

A rig is 2..K calibrated cameras whose relative orientation to a *master*
camera (camera 0) is known; the master camera's frame is the paper's "model
system". Per frame the rig

1. matches the uncoded targets of the master image with those of every other
   image along epipolar lines (:func:`epipolar_matches`, :func:`match_rig_images`);
2. intersects the rays of each target in the master frame by least squares on
   the collinearity equations, with the covariance of every point
   (:func:`intersect_rays`);
3. finds the master camera's pose in the field from the intersected points and
   their field coordinates: the closed-form transform, then a Gauss-Newton
   refinement weighted by each point's full 3x3 covariance (both in
   :mod:`service.core.geometry.similarity`; :func:`pose_from_intersection`).

Design notes
------------
- Residuals are whitened to pixels: the ideal-coordinate residual of each ray
  is multiplied by the inverse of ``d ideal / d uv`` at the measured pixel, so
  ``sigma_px`` is the isotropic image noise of the target measurement and the
  lens distortion is propagated to first order.
- Per-point degeneracy is a value, not an exception, because one bad target
  must not spoil a frame: a point seen by fewer than 2 cameras, with rays
  meeting at less than ``min_ray_angle_deg``, lying behind a camera, or not
  converging gets NaN coordinates, covariance and residuals and
  ``valid = False``. Whole-frame degeneracy (fewer than 3 usable points, or
  collinear ones, for the pose) raises :class:`SolveError`.
- Covariance: with an a-priori ``sigma_px`` the points' covariance is
  ``sigma_px**2 (A^T A)^-1``; without it ``sigma_px`` is replaced by the
  a-posteriori ``sigma0_px`` of the whole frame (one value: a 2-ray point has a
  redundancy of 1, far too little for its own estimate).
- Pose covariance: with the rig fixed and the field coordinates taken as
  error-free, the image noise of different targets is independent, so the
  intersected points are independent and the pose fitted to them with their
  full covariance as weights is, to first order, the same estimate (and the
  same covariance) as a joint adjustment of the pose on all image rays. The
  covariance is not rescaled by the fit's ``sigma0``; that number is reported
  so a caller can see field or rig errors (it should be about 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T, inv_T
from service.core.geometry.similarity import rigid_transform_with_covariance
from service.core.geometry.so3 import skew
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Rig:
    """Calibrated cameras with their relative orientation to the master camera.

    Attributes
    ----------
    cameras : tuple of BrownFraser, length K >= 2
        Camera 0 is the master.
    T_master_camera : (K, 4, 4) float, mm
        Pose of each camera in the master camera's frame; ``[0]`` is identity.
    """

    cameras: tuple[BrownFraser, ...]
    T_master_camera: Array

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        T = np.array(self.T_master_camera, dtype=np.float64)
        if len(cams) < 2:
            raise ValueError(f"a rig needs at least 2 cameras, got {len(cams)}")
        if T.shape != (len(cams), 4, 4):
            raise ValueError(f"T_master_camera must have shape ({len(cams)}, 4, 4), got {T.shape}")
        for k in range(len(cams)):
            check_T(T[k], name=f"T_master_camera[{k}]")
        if not np.allclose(T[0], np.eye(4), atol=1e-9):
            raise ValueError("T_master_camera[0] must be the identity: camera 0 is the master")
        T.setflags(write=False)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "T_master_camera", T)

    @classmethod
    def from_T_field_camera(cls, cameras: Sequence[BrownFraser], T_field_camera: ArrayLike) -> Rig:
        """A rig from each camera's pose in a common frame, e.g. resections in a calibration field.

        ``T_field_camera`` is (K, 4, 4); camera 0 becomes the master.
        """
        T = np.asarray(T_field_camera, dtype=np.float64)
        T_master_field = inv_T(T[0])
        rel = np.array([T_master_field @ T[k] for k in range(len(T))])
        rel[0] = np.eye(4)
        return cls(tuple(cameras), rel)

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    def centres_master(self) -> Array:
        """Projection centres (K, 3) mm of all cameras in the master frame."""
        return self.T_master_camera[:, :3, 3].copy()


@dataclass(frozen=True)
class IntersectionResult:
    """Points intersected from the rays of a rig, in the master camera's frame.

    Attributes
    ----------
    p_master : (N, 3) float, mm
        NaN where ``valid`` is False.
    covariance : (N, 3, 3) float, mm^2
        From ``sigma_px`` when given, else from ``sigma0_px``; NaN where invalid.
    residuals_px : (N, K, 2) float, px
        Measured minus reprojected pixel coordinates; NaN where unseen or invalid.
    n_rays : (N,) int
        Cameras that saw the point.
    valid : (N,) bool
        Intersected (>= 2 rays, rays not near-parallel, in front of every
        camera that saw it, converged).
    ray_angle_deg : (N,) float, deg
        Largest angle (0..90) between the lines of two of the point's rays
        (0 with fewer than 2).
    sigma0_px : float, px
        A-posteriori standard deviation of unit weight (per image coordinate)
        over all valid points; NaN without redundancy.
    rms_px : float, px
        Root mean square of all residual coordinates of valid points.
    sigma_px : float or None, px
        The a-priori image noise the covariance was computed from, if given.
    redundancy : int
        ``sum(2 * n_rays - 3)`` over valid points.
    n_iter : int
        Gauss-Newton iterations run.
    """

    p_master: Array
    covariance: Array
    residuals_px: Array
    n_rays: NDArray[np.int64]
    valid: NDArray[np.bool_]
    ray_angle_deg: Array
    sigma0_px: float
    rms_px: float
    sigma_px: float | None
    redundancy: int
    n_iter: int

    @property
    def sigma_mm(self) -> Array:
        """Standard deviations (N, 3) mm of each point's master-frame coordinates."""
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))


def _stack_observations(rig: Rig, uv_per_camera: Sequence[ArrayLike]) -> tuple[Array, NDArray[np.bool_]]:
    if len(uv_per_camera) != rig.n_cameras:
        raise ValueError(f"need one (N, 2) array per camera ({rig.n_cameras}), got {len(uv_per_camera)}")
    uv = np.stack([np.asarray(a, dtype=np.float64) for a in uv_per_camera])
    if uv.ndim != 3 or uv.shape[2] != 2:
        raise ValueError(f"every uv array must be (N, 2) with the same N, got {uv.shape[1:]}")
    seen = np.all(np.isfinite(uv), axis=2)
    return uv, seen


def _ray_angles_deg(rig: Rig, uv: Array, seen: NDArray[np.bool_]) -> tuple[Array, Array]:
    """Unit rays (K, N, 3) in the master frame and the largest pairwise angle (N,) deg."""
    K, N = seen.shape
    rays = np.full((K, N, 3), np.nan)
    for k, cam in enumerate(rig.cameras):
        if np.any(seen[k]):
            R_master_camera = rig.T_master_camera[k, :3, :3]
            rays[k, seen[k]] = cam.rays_from_pixel(uv[k, seen[k]]) @ R_master_camera.T
    best = np.zeros(N)
    for i in range(K):
        for j in range(i + 1, K):
            both = seen[i] & seen[j]
            # lines, not half-rays: opposite directions are as degenerate as equal ones
            cosang = np.clip(np.abs(np.sum(rays[i, both] * rays[j, both], axis=1)), 0.0, 1.0)
            best[both] = np.maximum(best[both], np.degrees(np.arccos(cosang)))
    return rays, best


def intersect_rays(
    rig: Rig,
    uv_per_camera: Sequence[ArrayLike],
    sigma_px: float | None = None,
    min_ray_angle_deg: float = 1.0,
    max_iter: int = 10,
) -> IntersectionResult:
    """Least-squares intersection of each target's rays, with covariance.

    The start is the midpoint (the point nearest to all rays in the master
    frame), refined by Gauss-Newton on the collinearity equations with the
    analytic 3x3 normal matrix, vectorised over all points. Hand-written
    because the N problems are independent 3-unknown ones; one
    ``least_squares`` call per target would be two orders of magnitude slower.

    Parameters
    ----------
    rig : Rig
    uv_per_camera : sequence of K arrays (N, 2) float, px
        Row i of every array is the same target; NaN where a camera did not see it.
    sigma_px : float, optional
        A-priori standard deviation of each image coordinate; when given the
        covariance is computed from it instead of from ``sigma0_px``.
    min_ray_angle_deg : float
        Points whose rays meet at a smaller angle are rejected as degenerate.
    max_iter : int
        Gauss-Newton iterations at most; points still moving by more than
        1e-9 mm after that are marked invalid.

    Returns
    -------
    IntersectionResult
    """
    if sigma_px is not None and not sigma_px > 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    uv, seen = _stack_observations(rig, uv_per_camera)
    K, N = seen.shape
    n_rays = seen.sum(axis=0).astype(np.int64)
    rays, ray_angle = _ray_angles_deg(rig, uv, seen)
    valid = (n_rays >= 2) & (ray_angle >= min_ray_angle_deg)

    # Midpoint start: sum_k (I - d d^T)(p - o_k) = 0 over the point's rays.
    centres = rig.centres_master()
    d = np.where(seen[..., None], rays, 0.0)
    P = seen[..., None, None] * np.eye(3) - d[..., :, None] * d[..., None, :]  # (K, N, 3, 3)
    M = P.sum(axis=0)
    b = np.einsum("knij,kj->ni", P, centres)
    M[~valid] = np.eye(3)
    b[~valid] = 0.0
    p = np.linalg.solve(M, b[..., None])[..., 0]

    # Constant per observation: measured ideal coordinates and d uv / d ideal at the measured pixel.
    x_obs = np.zeros((K, N, 2))
    W = np.zeros((K, N, 2, 2))
    for k, cam in enumerate(rig.cameras):
        if np.any(seen[k]):
            x_obs[k, seen[k]] = cam.ideal_from_pixel(uv[k, seen[k]])
            W[k, seen[k]] = np.linalg.inv(cam.ideal_from_pixel_jacobian(uv[k, seen[k]]))
    c = np.array([cam.c_mm for cam in rig.cameras])
    T_camera_master = np.array([inv_T(T) for T in rig.T_master_camera])
    R_cm, t_cm = T_camera_master[:, :3, :3], T_camera_master[:, :3, 3]

    def linearise(p: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Whitened residuals (K, N, 2) px, Jacobians (K, N, 2, 3) px/mm, in-front mask (N,)."""
        pc = p @ R_cm.transpose(0, 2, 1) + t_cm[:, None, :]
        Z = pc[..., 2]
        in_front = np.all((Z > 0) | ~seen, axis=0)
        Zs = np.where(seen & (Z > 0), Z, 1.0)
        proj = c[:, None, None] * pc[..., :2] / Zs[..., None]
        D = np.zeros((K, N, 2, 3))
        D[..., 0, 0] = D[..., 1, 1] = c[:, None] / Zs
        D[..., :, 2] = -proj / Zs[..., None]
        A = W @ D @ R_cm[:, None]
        r = (W @ (x_obs - proj)[..., None])[..., 0]
        mask = seen[..., None]
        return np.where(mask, r, 0.0), np.where(mask[..., None], A, 0.0), in_front

    n_iter = 0
    moving = valid.copy()
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        r, A, in_front = linearise(p)
        valid &= in_front
        moving &= valid
        if not np.any(moving):
            break
        Am = A[:, moving]
        Nmat = (Am.swapaxes(-1, -2) @ Am).sum(axis=0)
        g = (Am.swapaxes(-1, -2) @ r[:, moving][..., None]).sum(axis=0)[..., 0]
        step = np.linalg.solve(Nmat, g[..., None])[..., 0]
        p[moving] += step
        idx = np.flatnonzero(moving)
        moving[idx[np.max(np.abs(step), axis=1) < 1e-9]] = False
    valid &= ~moving
    r, A, in_front = linearise(p)
    valid &= in_front

    # Reported residuals are true reprojections (the whitened ones agree to first order).
    residuals = np.full((N, K, 2), np.nan)
    for k, cam in enumerate(rig.cameras):
        sel = seen[k] & valid
        if np.any(sel):
            p_cam = p[sel] @ R_cm[k].T + t_cm[k]
            residuals[sel, k] = uv[k, sel] - cam.pixel_from_camera(p_cam)
    redundancy = int(np.sum(2 * n_rays[valid] - 3))
    used = residuals[valid][np.isfinite(residuals[valid])]
    sum_sq = float(np.sum(used**2))
    sigma0 = float(np.sqrt(sum_sq / redundancy)) if redundancy > 0 else float("nan")
    rms = float(np.sqrt(np.mean(used**2))) if used.size else float("nan")

    cov = np.full((N, 3, 3), np.nan)
    if np.any(valid):
        Av = A[:, valid]
        Nmat = (Av.swapaxes(-1, -2) @ Av).sum(axis=0)
        s = sigma_px if sigma_px is not None else sigma0
        cov[valid] = s**2 * np.linalg.inv(Nmat)
    p[~valid] = np.nan
    return IntersectionResult(
        p_master=p,
        covariance=cov,
        residuals_px=residuals,
        n_rays=n_rays,
        valid=valid,
        ray_angle_deg=ray_angle,
        sigma0_px=sigma0,
        rms_px=rms,
        sigma_px=sigma_px,
        redundancy=redundancy,
        n_iter=n_iter,
    )


# -- epipolar matching -----------------------------------------------------------


def epipolar_matches(
    rig: Rig,
    uv_master: ArrayLike,
    uv_other: ArrayLike,
    camera_index: int,
    tol_px: float,
    depth_range_mm: tuple[float, float] | None = None,
) -> NDArray[np.int64]:
    """Pair targets of the master image with targets of another rig image.

    A target j of camera ``camera_index`` is a candidate for master target i
    when it lies within ``tol_px`` of i's epipolar line (the distance is
    measured in pixels of the other image, through the lens distortion) and
    the two rays meet in front of both cameras (and, if given, at a master
    depth inside ``depth_range_mm``). A pair is kept only when each is the
    other's *only* candidate; ambiguous targets are left unmatched, never
    guessed.

    Parameters
    ----------
    rig : Rig
    uv_master : (N, 2) float, px
        Targets measured in the master image.
    uv_other : (M, 2) float, px
        Targets measured in the image of camera ``camera_index``.
    camera_index : int
        1 .. K-1.
    tol_px : float, px
        Half-width of the band around the epipolar line; a few times the
        image noise plus the rig calibration's uncertainty.
    depth_range_mm : (float, float), optional
        Accepted range of the depth (master-frame Z) of the intersected pair.

    Returns
    -------
    (P, 2) int
        Index pairs ``[i_master, j_other]``, sorted by ``i_master``.
    """
    if not 1 <= camera_index < rig.n_cameras:
        raise ValueError(f"camera_index must be in 1..{rig.n_cameras - 1}, got {camera_index}")
    if not tol_px > 0:
        raise ValueError(f"tol_px must be positive, got {tol_px}")
    uv0 = np.asarray(uv_master, dtype=np.float64).reshape(-1, 2)
    uv1 = np.asarray(uv_other, dtype=np.float64).reshape(-1, 2)
    empty = np.zeros((0, 2), dtype=np.int64)
    ok0 = np.flatnonzero(np.all(np.isfinite(uv0), axis=1))
    ok1 = np.flatnonzero(np.all(np.isfinite(uv1), axis=1))
    if ok0.size == 0 or ok1.size == 0:
        return empty
    cam0, cam1 = rig.cameras[0], rig.cameras[camera_index]
    T_other_master = inv_T(rig.T_master_camera[camera_index])
    R, t = T_other_master[:3, :3], T_other_master[:3, 3]
    E = skew(t) @ R  # m_other^T E m_master = 0 for normalised coordinates

    m0 = np.ones((ok0.size, 3))
    m0[:, :2] = cam0.ideal_from_pixel(uv0[ok0]) / cam0.c_mm
    x1 = cam1.ideal_from_pixel(uv1[ok1])
    J1 = cam1.ideal_from_pixel_jacobian(uv1[ok1])  # (M, 2, 2) mm/px
    lines = m0 @ E.T  # (N, 3): l . (x/c, y/c, 1) = 0 in the other image
    norm = np.linalg.norm(lines[:, :2], axis=1)
    if np.any(norm == 0):
        raise SolveError(Reason.degenerate_geometry, "the rig has no baseline between these cameras.")
    n = lines[:, :2] / norm[:, None]
    dist_mm = (x1 @ lines[:, :2].T + cam1.c_mm * lines[:, 2]).T / norm[:, None]  # (N, M)
    # mm -> px perpendicular to the line: |J^T n| is how far the ideal point moves per pixel.
    scale = np.linalg.norm(np.einsum("mji,nj->nmi", J1, n), axis=2)
    candidate = np.abs(dist_mm) / scale <= tol_px
    i, j = np.nonzero(candidate)
    if i.size:
        # Depths along both rays of the two-ray closest approach, in the master frame.
        d0 = m0[i] / np.linalg.norm(m0[i], axis=1, keepdims=True)
        m1 = np.concatenate([x1[j] / cam1.c_mm, np.ones((j.size, 1))], axis=1)
        d1 = m1 @ R  # R^T m1 as rows: other-camera rays in the master frame
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        o1 = rig.T_master_camera[camera_index, :3, 3]
        a12 = np.sum(d0 * d1, axis=1)
        b0, b1 = d0 @ o1, d1 @ o1
        den = 1.0 - a12**2
        with np.errstate(divide="ignore", invalid="ignore"):
            s0 = (b0 - a12 * b1) / den
            s1 = (a12 * b0 - b1) / den
        keep = (den > 1e-12) & (s0 > 0) & (s1 > 0)
        if depth_range_mm is not None:
            z0 = s0 * d0[:, 2]
            keep &= (z0 >= depth_range_mm[0]) & (z0 <= depth_range_mm[1])
        candidate[i[~keep], j[~keep]] = False
    only_one_other = candidate.sum(axis=1, keepdims=True) == 1
    only_one_master = candidate.sum(axis=0, keepdims=True) == 1
    unique = candidate & only_one_other & only_one_master
    i, j = np.nonzero(unique)
    if i.size == 0:
        return empty
    return np.stack([ok0[i], ok1[j]], axis=1).astype(np.int64)


def match_rig_images(
    rig: Rig,
    uv_per_image: Sequence[ArrayLike],
    tol_px: float,
    depth_range_mm: tuple[float, float] | None = None,
) -> list[Array]:
    """Observations for :func:`intersect_rays` from unordered target lists of every rig image.

    Row i of every returned array is master target i: ``uv_per_image[0]``
    itself for the master, the epipolar match (or NaN) for every other camera.

    Parameters
    ----------
    uv_per_image : sequence of K arrays (M_k, 2) float, px
        Uncoded targets measured in each image, in any order.
    tol_px, depth_range_mm
        As in :func:`epipolar_matches`.

    Returns
    -------
    list of K arrays (N, 2) float, px, N = len(uv_per_image[0])
    """
    if len(uv_per_image) != rig.n_cameras:
        raise ValueError(f"need one target list per camera ({rig.n_cameras}), got {len(uv_per_image)}")
    uv0 = np.asarray(uv_per_image[0], dtype=np.float64).reshape(-1, 2)
    out = [uv0.copy()]
    for k in range(1, rig.n_cameras):
        uvk = np.asarray(uv_per_image[k], dtype=np.float64).reshape(-1, 2)
        pairs = epipolar_matches(rig, uv0, uvk, k, tol_px, depth_range_mm)
        obs = np.full_like(uv0, np.nan)
        obs[pairs[:, 0]] = uvk[pairs[:, 1]]
        out.append(obs)
    return out


# -- pose of the rig in the field ------------------------------------------------


@dataclass(frozen=True)
class RigPoseResult:
    """Pose of the master camera in the field from intersected points.

    Attributes
    ----------
    T_field_master : (4, 4) float, mm
    covariance : (6, 6) float
        Over ``[wx, wy, wz]`` (rad, a small rotation about the field axes
        applied on the left, ``R_field_master <- exp([w]x) R_field_master``)
        and ``[dx, dy, dz]`` (mm, the master's projection centre in the
        field); the same order and perturbation as ``ResectionResult``.
    sigma_position_mm : (3,) float, mm
        Along the field x, y, z axes.
    sigma_rotation_deg : (3,) float, deg
        About the field x, y, z axes.
    residuals_mm : (N, 3) float, mm
        ``p_field - T_field_master @ p_master``; NaN for unused points.
    rms_mm : float, mm
        Root mean square length of the residual vectors of the used points.
    sigma0 : float
        sqrt(chi^2 / (3 n - 6)) of the covariance-weighted fit; about 1 when
        the field, the rig and ``sigma_px`` agree with the data.
    used : (N,) bool
        Points that entered the fit (intersected and with field coordinates).
    n_points : int
    n_iter : int
    T_field_camera : (K, 4, 4) float, mm
        Every rig camera's pose in the field.
    intersection : IntersectionResult
    """

    T_field_master: Array
    covariance: Array
    sigma_position_mm: Array
    sigma_rotation_deg: Array
    residuals_mm: Array
    rms_mm: float
    sigma0: float
    used: NDArray[np.bool_]
    n_points: int
    n_iter: int
    T_field_camera: Array
    intersection: IntersectionResult


def pose_from_intersection(
    rig: Rig,
    p_field: ArrayLike,
    uv_per_camera: Sequence[ArrayLike],
    sigma_px: float | None = None,
    min_ray_angle_deg: float = 1.0,
) -> RigPoseResult:
    """The rig's pose in the field: intersect every target, then fit the field coordinates.

    Parameters
    ----------
    rig : Rig
    p_field : (N, 3) float, mm
        Field coordinates of the N targets (NaN for a target not in the field).
    uv_per_camera : sequence of K arrays (N, 2) float, px
        As in :func:`intersect_rays`; row i is target i.
    sigma_px : float, optional
        A-priori image noise; without it the frame's ``sigma0_px`` is used.
    min_ray_angle_deg : float
        As in :func:`intersect_rays`.

    Returns
    -------
    RigPoseResult
        With ``T_field_camera`` for all K cameras and the ``intersection``.

    Raises
    ------
    SolveError
        ``too_few_targets`` when fewer than 3 targets with field coordinates
        were intersected; otherwise as
        :func:`service.core.geometry.similarity.rigid_transform_with_covariance`.
    """
    f = np.asarray(p_field, dtype=np.float64)
    inter = intersect_rays(rig, uv_per_camera, sigma_px=sigma_px, min_ray_angle_deg=min_ray_angle_deg)
    if f.shape != inter.p_master.shape:
        raise ValueError(f"p_field must have shape {inter.p_master.shape}, got {f.shape}")
    n_ok = int(np.count_nonzero(inter.valid & np.all(np.isfinite(f), axis=1)))
    if n_ok < 3:
        raise SolveError(
            Reason.too_few_targets,
            f"only {n_ok} targets with field coordinates were intersected by at least 2 cameras; "
            "the rig's pose needs 3.",
            {"n_intersected": int(inter.valid.sum()), "n_points": n_ok},
        )
    fit = rigid_transform_with_covariance(f, inter.p_master, inter.covariance)
    sig = np.sqrt(np.diag(fit.covariance))
    return RigPoseResult(
        T_field_master=fit.T_a_b,
        covariance=fit.covariance,
        sigma_position_mm=sig[3:],
        sigma_rotation_deg=np.degrees(sig[:3]),
        residuals_mm=fit.residuals_mm,
        rms_mm=fit.rms_mm,
        sigma0=fit.sigma0,
        used=fit.used,
        n_points=fit.n_points,
        n_iter=fit.n_iter,
        T_field_camera=fit.T_a_b @ rig.T_master_camera,
        intersection=inter,
    )
