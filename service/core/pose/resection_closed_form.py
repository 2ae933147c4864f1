"""Closed-form space resection (the paper, section 4.3, first stage): a pose with no prior.

For a planar field, the plane-to-plane transformation (a homography from >= 4
points, Fischler & Bolles) gives the projection centre in front of the plane,
and the rotation follows from the known centre (Kraus) as the one that best
aligns the field rays from the centre with the image rays. A non-planar field's
centre comes from a DLT on ideal coordinates (OpenCV's P3P over all triples for
4-5 points, a case the paper does not treat). Written by hand because it is the
paper's method; :mod:`service.core.pose.resection` refines its result. When that start
fails or is not confirmed, :func:`fallback_starts` offers every other closed form that
applies (the homography of the coplanar majority, the DLT, P3P with a consensus).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core._kernels import kernel_array
from service.core._kernels.resection_kernel import centre_planar_kernel, rotation_from_centre_kernel, spread_kernel
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import make_T
from service.core.geometry.so3 import R_from_rotvec
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

#: Below this ratio of the smallest to the largest spread of the field points the
#: planar (homography) closed form is used; it is only a start, so a field with
#: some relief is still refined exactly by the adjustment.
PLANAR_RATIO = 0.1
#: Below this ratio the field counts as flat (1 mm over 1 m) and only the planar
#: closed form is tried; between it and PLANAR_RATIO both closed forms are.
FLAT_RATIO = 1e-3
#: Below this ratio of the second to the first spread, points count as collinear.
COLLINEAR_RATIO = 1e-3
#: Fallback starts (:func:`fallback_starts`): a field point within this fraction of the field's
#: RMS radius of a plane counts as on it. The homography ignores that much relief and stays a
#: start the adjustment converges from; a raised block's targets are well outside.
PLANE_TOLERANCE = 0.03
#: Triples of field points tried for the plane of the coplanar majority.
PLANE_SAMPLES = 100
#: Triples of points tried for a P3P start (all of them when there are fewer), judged this many at a time.
P3P_SAMPLES = 60
P3P_CHUNK = 15
#: A point agrees with a start when it images within this many pixels of its measurement: wide,
#: since a start from three points or from the plane alone is off by a few pixels.
CONSENSUS_PX = 8.0
#: Without a start pose, a start is confirmed when its adjustment (``resection.resect``) succeeds
#: with at most this fraction of the points rejected, or, unadjusted (:func:`resect_closed_form`),
#: when all but this fraction agree with it; otherwise every other closed form is tried too.
CONFIRM_MAX_REJECTED = 0.2


def check_observations(p_field: ArrayLike, uv: ArrayLike) -> tuple[Array, Array]:
    p = np.asarray(p_field, dtype=np.float64)
    q = np.asarray(uv, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"p_field must have shape (N, 3), got {p.shape}")
    if q.ndim != 2 or q.shape[1] != 2:
        raise ValueError(f"uv must have shape (N, 2), got {q.shape}")
    if len(p) != len(q):
        raise ValueError(f"p_field has {len(p)} points but uv has {len(q)}")
    # the ufunc's own reduce: np.all's wrappers cost ~10 us of an ROI frame
    if not (np.logical_and.reduce(np.isfinite(p), axis=None) and np.logical_and.reduce(np.isfinite(q), axis=None)):
        raise SolveError(Reason.bad_input, "Field or image coordinates contain NaN or infinity.")
    if len(p) < 4:
        msg = f"Resection needs at least 4 targets, got {len(p)}."
        raise SolveError(Reason.too_few_targets, msg, {"n_targets": len(p)})
    return p, q


def check_geometry(p: Array, xy: Array) -> Array:
    """Raise on collinear field or image points; return the field points' spread (3,)."""
    # compiled: as array expressions the scatter matrices and their spreads were a sixth of
    # the resection of an ROI frame
    s, s_img = spread_kernel(kernel_array(p), kernel_array(xy))
    if s[0] <= 0 or s[1] < COLLINEAR_RATIO * s[0]:
        msg = "The field points are collinear (or coincide): the rotation about them is unknown."
        raise SolveError(Reason.degenerate_geometry, msg)
    if s_img[0] <= 0 or s_img[1] < COLLINEAR_RATIO * s_img[0]:
        msg = "The image points are collinear: the camera looks at the field edge-on."
        raise SolveError(Reason.degenerate_geometry, msg)
    return s


def _c_array(a: Array) -> Array:
    """``a`` as a writable C array of float64: the one array type the kernels know."""
    return kernel_array(a)


def _normalizer(points: Array) -> Array:
    """Hartley's similarity (d+1, d+1): centroid to the origin, RMS distance sqrt(d)."""
    d = points.shape[1]
    m = points.mean(axis=0)
    rms = np.sqrt(np.mean(np.sum((points - m) ** 2, axis=1)))
    s = np.sqrt(d) / rms
    N = np.eye(d + 1)
    N[:d, :d] *= s
    N[:d, d] = -s * m
    return N


def _null_vector(A: Array, what: str) -> Array:
    """Right null vector of a DLT system; raise if it is not unique (degenerate points)."""
    # Eigen-decomposition of the small A^T A: far cheaper than an SVD of the tall A,
    # and Hartley normalisation keeps its conditioning harmless for a start.
    ev, V = np.linalg.eigh(A.T @ A)
    if ev[1] < 1e-18 * ev[-1]:
        raise SolveError(
            Reason.degenerate_geometry,
            f"The points do not determine a unique {what} (too many of them are collinear).",
        )
    return V[:, 0]


def _rotation_from_centre(p: Array, xy: Array, c: float, C_field: Array) -> Array:
    """Kraus: R_field_camera aligning the image rays with the field rays from a known centre.

    The orthogonal Procrustes solution over all points, so every point counts,
    not only the four the paper's closed form needs.
    """
    # compiled, as is the planar centre: in numpy they were two thirds of the full frame's resection
    # from the coded targets
    return rotation_from_centre_kernel(_c_array(p), _c_array(xy), float(c), _c_array(C_field))


def _centre_planar(p: Array, n_img: Array) -> Array:
    """Projection centre (3,) mm from the plane-to-plane transformation, in front of the plane."""
    C, unique = centre_planar_kernel(_c_array(p), _c_array(n_img))
    if not unique:
        raise SolveError(
            Reason.degenerate_geometry,
            "The points do not determine a unique plane-to-plane transformation (too many of them are collinear).",
        )
    return C


def _centre_dlt(p: Array, n_img: Array) -> Array:
    """Projection centre (3,) mm by a DLT on ideal coordinates (non-planar field, >= 6 points)."""
    Np, Ni = _normalizer(p), _normalizer(n_img)
    X = np.column_stack([p @ Np[:3, :3].T + Np[:3, 3], np.ones(len(p))])
    x = n_img @ Ni[:2, :2].T + Ni[:2, 2]
    n = len(p)
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = X
    A[0::2, 8:12] = -x[:, :1] * X
    A[1::2, 4:8] = X
    A[1::2, 8:12] = -x[:, 1:] * X
    P = np.linalg.solve(Ni, _null_vector(A, "projection matrix").reshape(3, 4) @ Np)
    M = P[:, :3]
    det = np.linalg.det(M)
    if abs(det) < 1e-12 * np.linalg.norm(M) ** 3:
        raise SolveError(Reason.degenerate_geometry, "The DLT projection matrix is singular.")
    # P ~ lam [R | t] with R proper, so sign(det M) = sign(lam) fixes the depth sign.
    depth = np.sign(det) * (np.column_stack([p, np.ones(n)]) @ P[2])
    if np.mean(depth > 0) < 0.5:
        raise SolveError(
            Reason.behind_camera,
            "The image points are only consistent with the field lying behind the camera.",
            {"n_behind": int(np.sum(depth <= 0))},
        )
    return -np.linalg.solve(M, P[:, 3])


def _centre_p3p(p: Array, n_img: Array) -> Array:
    return _pose_p3p(p, n_img)[:3, 3]


def _image_error(T_field_camera: Array, p: Array, n_img: Array) -> float:
    """Sum of squared errors in normalized image coordinates; inf if a point is behind."""
    pc = (p - T_field_camera[:3, 3]) @ T_field_camera[:3, :3]
    if np.any(pc[:, 2] <= 0):
        return np.inf
    return float(np.sum((pc[:, :2] / pc[:, 2:3] - n_img) ** 2))


def _pose_p3p(p: Array, n_img: Array) -> Array:
    """T_field_camera of 4-5 non-planar points, too few for a DLT.

    OpenCV's P3P on every triple (at most 10), keeping the solution with all
    points in front and the smallest error over all points. This case is not
    the paper's, so OpenCV's solver serves rather than one written here.
    """
    best, best_err = None, np.inf
    for sel in itertools.combinations(range(len(p)), 3):
        X, x = np.ascontiguousarray(p[list(sel)]), np.ascontiguousarray(n_img[list(sel)])
        _, rvecs, tvecs = cv2.solveP3P(X, x, np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
            R_field_camera = R_from_rotvec(np.ravel(rvec)).T
            T = make_T(R_field_camera, -R_field_camera @ tvec.ravel())
            err = _image_error(T, p, n_img)
            if err < best_err:
                best, best_err = T, err
    if best is None:
        raise SolveError(Reason.behind_camera, "No pose puts all targets in front of the camera.")
    return best


def closed_form_ideal(p: Array, xy: Array, c: float, spread: Array) -> Array:
    n_img = xy / c
    planar = spread[2] < PLANAR_RATIO * spread[0]
    if planar and spread[2] < FLAT_RATIO * spread[0]:
        C = _centre_planar(p, n_img)
        return make_T(_rotation_from_centre(p, xy, c, C), C)
    # A field with some relief: the homography (a start that ignores the relief)
    # and the 3-D closed form (ill-conditioned when the relief is small) each fail
    # somewhere, so take the one that fits the image better.
    solvers: list[Callable[[Array, Array], Array]] = [_centre_planar] if planar else []
    solvers.append(_centre_dlt if len(p) >= 6 else _centre_p3p)
    best, best_err, error = None, np.inf, None
    for solve in solvers:
        try:
            C = solve(p, n_img)
        except SolveError as e:
            error = e
            continue
        T = make_T(_rotation_from_centre(p, xy, c, C), C)
        err = _image_error(T, p, n_img)
        if best is None or err < best_err:
            best, best_err = T, err
    if best is None:
        assert error is not None
        raise error
    return best


# -- fallback starts: every closed form that applies --------------------------------
#
# The usual start above decides planar / non-planar from the spread of all points. One
# target off the plane of the others (a raised block) makes the field non-planar, yet the
# DLT is then underdetermined (a plane's points fix only 8 of its 11 parameters, each other
# point 2): its start is garbage and the frame would fail though every observation is right.
# When the usual start fails or its adjustment is not confirmed, :func:`fallback_starts`
# offers the homography of the coplanar majority, the DLT when enough points stand off that
# plane, and P3P over sampled triples with a consensus (robust to wrong codes as well);
# :func:`service.core.pose.resection.resect` adjusts them in turn and keeps the first its checks
# confirm (else the best). A start counts only if most points agree with it: with no real
# start the frame keeps the usual start's failure instead of a made-up one.


def _triples(n: int, n_samples: int) -> NDArray[np.intp]:
    """Index triples (K, 3): all of them if there are at most ``n_samples``, else a seeded sample
    (the same on every call: the core stays deterministic)."""
    if math.comb(n, 3) <= n_samples:
        return np.array(list(itertools.combinations(range(n), 3)), dtype=np.intp).reshape(-1, 3)
    rng = np.random.default_rng(0)
    return np.argsort(rng.random((n_samples, n)), axis=1)[:, :3]


def coplanar_majority(p: Array) -> NDArray[np.bool_] | None:
    """The largest set of field points ``p`` (N, 3) mm near one plane, if it holds at least
    ``max(4, ceil(N / 2))`` of them; else None.

    RANSAC over triples: the plane through each triple, the points within
    ``PLANE_TOLERANCE`` of the field's RMS radius of it; then the plane fitted to the
    best set, and the points near that.
    """
    n = len(p)
    d = p - p.mean(axis=0)
    tol_mm = PLANE_TOLERANCE * np.sqrt(np.mean(np.sum(d**2, axis=1)))
    tri = _triples(n, PLANE_SAMPLES)
    a = d[tri[:, 0]]
    normal = np.cross(d[tri[:, 1]] - a, d[tri[:, 2]] - a)
    length = np.linalg.norm(normal, axis=1)
    good = length > 1e-9 * max(float(length.max(initial=0.0)), 1e-300)
    if not np.any(good):
        return None
    normal = normal[good] / length[good, None]
    near = np.abs((d[None] - a[good, None]) @ normal[..., None])[..., 0] < tol_mm  # (K, N)
    best = near[np.argmax(near.sum(axis=1))]
    m = d[best].mean(axis=0)
    normal = np.linalg.eigh((d[best] - m).T @ (d[best] - m))[1][:, 0]
    on = np.abs((d - m) @ normal) < tol_mm
    return on if on.sum() >= max(4, -(-n // 2)) else None


def _consensus(T_field_camera: Array, p: Array, n_img: Array, tol: float) -> int:
    """How many points lie in front of the camera and image within ``tol`` (normalized) of ``n_img``."""
    pc = (p - T_field_camera[:3, 3]) @ T_field_camera[:3, :3]
    z = pc[:, 2]
    front = z > 0
    e = pc[front, :2] / z[front, None] - n_img[front]
    return int(np.sum(np.sum(e**2, axis=1) < tol**2))


_EYE3 = np.eye(3)  # the camera matrix of normalized image coordinates


def _pose_p3p_consensus(p: Array, n_img: Array, tol: float) -> Array | None:
    """T_field_camera from the P3P solution over sampled triples that most points agree with."""
    n = len(p)
    triples = _triples(n, P3P_SAMPLES)
    best, best_count = None, 0
    # in chunks, each chunk's solutions judged in one pass: per solution, numpy calls cost more
    # than the arithmetic; and a chunk may already hold a start good enough to stop at
    for chunk in np.array_split(triples, -(-len(triples) // P3P_CHUNK)):
        rvecs: list[Any] = []  # OpenCV's MatLike
        tvecs: list[Any] = []
        for sel in chunk:
            try:
                _, r, t = cv2.solveP3P(
                    np.ascontiguousarray(p[sel]), np.ascontiguousarray(n_img[sel]), _EYE3, None, flags=cv2.SOLVEPNP_P3P
                )
            except cv2.error:  # a degenerate triple (coincident image points): the next one
                continue
            rvecs.extend(r)
            tvecs.extend(t)
        if not rvecs:
            continue
        R_camera_field = R_from_rotvec(np.reshape(rvecs, (-1, 3)))  # (K, 3, 3)
        t_camera_field = np.reshape(tvecs, (-1, 3))
        pc = np.einsum("kij,nj->kni", R_camera_field, p) + t_camera_field[:, None]  # (K, N, 3)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            e2 = np.sum((pc[..., :2] / z[..., None] - n_img) ** 2, axis=2)
        counts = np.sum((z > 0) & (e2 < tol**2), axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            R_field_camera = R_camera_field[k].T
            best, best_count = make_T(R_field_camera, -R_field_camera @ t_camera_field[k]), int(counts[k])
        if best_count >= 0.9 * n:  # a start this good is all the adjustment needs
            break
    return best


def fallback_starts(p: Array, xy: Array, c: float, tol_mm: float) -> Iterator[Array]:
    """Start poses T_field_camera (4, 4) from every closed form that applies, cheapest first.

    Parameters
    ----------
    p : (N, 3) float, mm
        Field points (checked: N >= 4, not collinear).
    xy : (N, 2) float, mm
        Their ideal image coordinates.
    c : float, mm
        Principal distance.
    tol_mm : float, mm
        Image distance (ideal coordinates) within which a point agrees with a start.

    Yields
    ------
    (4, 4) float
        The homography of the coplanar majority (:func:`coplanar_majority`), the DLT when at
        least 6 points and 2 of them off that plane, P3P over sampled triples: each only if
        at least ``max(4, ceil(N / 2))`` points agree with it. A generator, so that the caller
        stops at the first its adjustment confirms and the costlier P3P mostly never runs.
    """
    n_img, tol, majority = xy / c, tol_mm / c, max(4, -(-len(p) // 2))
    on_plane = coplanar_majority(p)
    if on_plane is not None:
        try:
            C = _centre_planar(p[on_plane], n_img[on_plane])
        except SolveError:
            pass
        else:
            T = make_T(_rotation_from_centre(p[on_plane], xy[on_plane], c, C), C)
            if _consensus(T, p, n_img, tol) >= majority:
                yield T
    if len(p) >= 6 and (on_plane is None or np.sum(~on_plane) >= 2):
        try:
            C = _centre_dlt(p, n_img)
        except SolveError:
            pass
        else:
            T = make_T(_rotation_from_centre(p, xy, c, C), C)
            if _consensus(T, p, n_img, tol) >= majority:
                yield T
    T_p3p = _pose_p3p_consensus(p, n_img, tol)
    if T_p3p is not None and _consensus(T_p3p, p, n_img, tol) >= majority:
        yield T_p3p


def resect_closed_form(camera: BrownFraser, p_field: ArrayLike, uv: ArrayLike) -> Array:
    """Camera pose from image points without a prior pose (the paper's closed form).

    Parameters
    ----------
    camera : BrownFraser
        Interior orientation.
    p_field : (N, 3) float, mm
        Target coordinates in the field frame, N >= 4.
    uv : (N, 2) float, px
        Their measured pixel coordinates.

    Returns
    -------
    T_field_camera : (4, 4) float
        Pose of the camera in the field (translation = projection centre, mm).

    Raises
    ------
    SolveError
        ``too_few_targets`` for N < 4, ``degenerate_geometry`` for collinear field
        or image points, ``behind_camera`` if the points can only lie behind the
        camera, ``bad_input`` for non-finite coordinates; each only when no start of
        :func:`fallback_starts` has most points agree with it either.
    """
    p, q = check_observations(p_field, uv)
    xy = camera.ideal_from_pixel(q)
    spread = check_geometry(p, xy)
    c, tol_mm = camera.c_mm, CONSENSUS_PX * camera.mean_pixel_size_mm
    best: Array | None
    error: SolveError | None
    try:
        best, error = closed_form_ideal(p, xy, c, spread), None
    except SolveError as e:
        best, error = None, e
    # without an adjustment to confirm it, a start stands when nearly all points agree with it,
    # else the one most points agree with
    count = -1 if best is None else _consensus(best, p, xy / c, tol_mm / c)
    if best is not None and len(p) - count <= CONFIRM_MAX_REJECTED * len(p):
        return best
    for T in fallback_starts(p, xy, c, tol_mm):
        k = _consensus(T, p, xy / c, tol_mm / c)
        if k > count:
            best, count = T, k
    if best is None:
        assert error is not None
        raise error
    return best


# -- adjustment -----------------------------------------------------------------
