"""The compiled resection (adjustment, data snooping, closed form) against plain NumPy references.

Each reference below is the method written the straightforward way, with numpy and
scipy: Levenberg-Marquardt on the whitened collinearity equations, iterative data
snooping with re-admission, the planar closed form. Scenes are seeded plates and
volumes with noise and gross errors; the compiled path must give the same inliers
and the same pose, covariance and residuals to ~1e-9 (mm, px), and the same
failures for degenerate input. The kernels are also called directly against OpenCV and
SciPy: ``resect_kernel`` against ``cv2.solvePnPRefineLM`` (no distortion, so both minimise
the same reprojection error), ``rotation_from_centre_kernel`` against
``Rotation.align_vectors`` (Kabsch), ``spread_kernel`` against the singular values of the
centred points, ``centre_planar_kernel`` against the closed form above.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core._kernels.geometry_kernels import whitened_ideal_kernel
from service.core._kernels.resection_kernel import (
    OK,
    centre_planar_kernel,
    resect_kernel,
    rotation_from_centre_kernel,
    spread_kernel,
)
from service.core.geometry.camera_model import BrownFraser
from service.core.pose.resection import SNOOPING_ALPHA, SNOOPING_SIGMA_FLOOR_PX, resect
from service.core.pose.resection_closed_form import _centre_planar, _rotation_from_centre, resect_closed_form
from service.core.results import SolveError
from tests.core.test_resection import plate_scene, volume_scene

SIGMA_PX = 0.05


# -- the references ---------------------------------------------------------------


class _Failed(Exception):
    pass


def _residuals(cam: BrownFraser, R, t, p, xy, W):
    pc = (p - t) @ R
    e = xy - cam.c_mm * pc[:, :2] / pc[:, 2:]
    return np.einsum("nij,nj->ni", W, e), pc


def _design(cam: BrownFraser, R, W, pc):
    c = cam.c_mm
    xn, yn, iz = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2], c / pc[:, 2]
    zero = np.zeros_like(xn)
    rot = c * np.stack([np.stack([xn * yn, -(1 + xn**2), yn], -1), np.stack([1 + yn**2, -xn * yn, -xn], -1)], 1)
    cen = -iz[:, None, None] * np.stack([np.stack([1 + zero, zero, -xn], -1), np.stack([zero, 1 + zero, -yn], -1)], 1)
    J = np.concatenate([rot @ R.T, cen @ R.T], axis=2)  # (n, 2, 6), field axes
    return W @ J


def _lm(cam, R, t, p, xy, W, scale_mm, max_iter):
    r, pc = _residuals(cam, R, t, p, xy, W)
    cost, n_front = 0.5 * np.sum(r**2), np.sum(pc[:, 2] > 0)
    if not np.isfinite(cost):
        raise _Failed("behind")
    lam = 0.0
    for _ in range(max_iter):
        A = _design(cam, R, W, pc).reshape(-1, 6)
        N, g = A.T @ A, A.T @ r.ravel()
        delta = np.linalg.solve(N, g)
        if np.linalg.norm(delta[3:]) + scale_mm * np.linalg.norm(delta[:3]) < 1e-10 * scale_mm:
            return Rotation.from_rotvec(delta[:3]).as_matrix() @ R, t + delta[3:], r, pc, A, True
        while True:
            if lam > 0:
                delta = np.linalg.solve(N + lam * np.diag(np.diag(N)), g)
            R_new, t_new = Rotation.from_rotvec(delta[:3]).as_matrix() @ R, t + delta[3:]
            r_new, pc_new = _residuals(cam, R_new, t_new, p, xy, W)
            cost_new, front_new = 0.5 * np.sum(r_new**2), np.sum(pc_new[:, 2] > 0)
            predicted = delta @ g - 0.5 * delta @ N @ delta
            rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
            if np.isfinite(cost_new) and front_new >= n_front and (rho > 0 or cost_new <= cost):
                break
            lam = max(4 * lam, 1e-6)
            if lam > 1e12:
                raise _Failed("no step")
        lam = (0.0 if lam < 1e-6 else lam / 4) if rho > 0.75 else max(2 * lam, 1e-6) if rho < 0.25 else lam
        if cost - cost_new <= 1e-12 * cost:
            return R, t, r, pc, A, True
        R, t, r, pc, cost, n_front = R_new, t_new, r_new, pc_new, cost_new, front_new
    return R, t, r, pc, _design(cam, R, W, pc).reshape(-1, 6), False


def _statistics(v, A, Qxx, sign):
    """``v_i^T Q_i^-1 v_i`` and ``det Q_i`` with ``Q_i = I + sign A_i Qxx A_i^T`` (n,)."""
    A = A.reshape(-1, 2, 6)
    Q = np.eye(2) + sign * A @ Qxx @ A.transpose(0, 2, 1)
    return np.einsum("ni,nij,nj->n", v, np.linalg.inv(Q), v), np.linalg.det(Q)


def _scores(T2, s2_post, m, sigma_px, max_sigma_px):
    chi2 = -2 * np.log(SNOOPING_ALPHA)
    if sigma_px is not None:
        return T2 / (sigma_px**2 * chi2)
    capped = s2_post > max_sigma_px**2
    s2 = np.where(capped, max_sigma_px**2, np.maximum(s2_post, SNOOPING_SIGMA_FLOOR_PX**2))
    f_crit = m * (SNOOPING_ALPHA ** (-2 / m) - 1) if m >= 1 else np.inf
    return T2 / (s2 * np.where(capped, chi2, f_crit))


def reference_resect(cam, p, uv, T0, sigma_px=None, max_sigma_px=0.5, max_iter=50):
    """(T_field_camera, covariance, sigma0_px, residuals_px (n, 2), inliers (n,)) or ``_Failed``."""
    xy, W = cam.ideal_from_pixel(uv), np.linalg.inv(cam.ideal_from_pixel_jacobian(uv))
    n = len(p)
    R, t = T0[:3, :3], T0[:3, 3]
    scale_mm = np.sqrt(np.mean(np.sum((p - t) ** 2, axis=1)))
    inliers, readmitted = np.ones(n, bool), False
    while True:
        idx = np.flatnonzero(inliers)
        R, t, v, pc, A, converged = _lm(cam, R, t, p[idx], xy[idx], W[idx], scale_mm, max_iter)
        Qxx = np.linalg.inv(A.T @ A)
        f, omega = 2 * len(idx) - 6, np.sum(v**2)
        T2, det = _statistics(v, A, Qxx, -1.0)
        score = np.where(
            det > 1e-6, _scores(T2, np.maximum(omega - T2, 0) / max(f - 2, 1), f - 2, sigma_px, max_sigma_px), 0.0
        )
        if score.max() > 1:
            if len(idx) - 1 < max(4, -(-n // 2)):
                raise _Failed("too many gross errors")
            inliers[idx[np.argmax(score)]] = False
            continue
        assert converged
        out = np.flatnonzero(~inliers)
        if readmitted or len(out) == 0:
            break
        readmitted = True
        r_out, pc_out = _residuals(cam, R, t, p[out], xy[out], W[out])
        T2, _ = _statistics(r_out, _design(cam, R, W[out], pc_out), Qxx, 1.0)
        back = out[_scores(T2, np.full(len(out), omega / f), f, sigma_px, max_sigma_px) <= 1]
        if len(back) == 0:
            break
        inliers[back] = True
    sigma0 = np.sqrt(omega / f)
    if sigma_px is None and sigma0 > max_sigma_px:
        raise _Failed("too few agree")
    if np.any(pc[:, 2] <= 0):
        raise _Failed("behind")
    r_all = np.empty((n, 2))
    r_all[idx] = v
    r_all[~inliers] = _residuals(cam, R, t, p[~inliers], xy[~inliers], W[~inliers])[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, (sigma_px or sigma0) ** 2 * Qxx, sigma0, r_all, inliers


def reference_planar_closed_form(p, xy, c):
    """The plane-to-plane transformation's centre and Kraus' rotation, in numpy."""
    m = p.mean(axis=0)
    e = np.linalg.svd(p - m)[2]  # rows: in-plane axes by decreasing spread, then the normal
    e[2] *= np.sign(np.linalg.det(e))  # right-handed, or the centre comes out mirrored in the plane
    ab0, x0 = (p - m) @ e[:2].T, xy / c

    def hartley(q):  # similarity taking q's centroid to 0 and its RMS distance to sqrt(2)
        s = np.sqrt(2) / np.sqrt(np.mean(np.sum((q - q.mean(axis=0)) ** 2, axis=1)))
        return np.array([[s, 0, -s * q[:, 0].mean()], [0, s, -s * q[:, 1].mean()], [0, 0, 1]])

    Na, Ni = hartley(ab0), hartley(x0)
    ab, x = ab0 @ Na[:2, :2].T + Na[:2, 2], x0 @ Ni[:2, :2].T + Ni[:2, 2]
    A = np.zeros((2 * len(p), 9))
    A[0::2, 0:2], A[0::2, 2], A[1::2, 3:5], A[1::2, 5] = ab, 1, ab, 1
    A[0::2, 6:8], A[0::2, 8] = -x[:, :1] * ab, -x[:, 0]
    A[1::2, 6:8], A[1::2, 8] = -x[:, 1:] * ab, -x[:, 1]
    H = np.linalg.inv(Ni) @ np.linalg.svd(A)[2][-1].reshape(3, 3) @ Na
    H *= np.sign(H[2, 2]) / np.sqrt(np.linalg.norm(H[:, 0]) * np.linalg.norm(H[:, 1]))
    U, _, Vt = np.linalg.svd(np.column_stack([H[:, 0], H[:, 1], np.cross(H[:, 0], H[:, 1])]))
    R_camera_plane = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    C = m + (-R_camera_plane.T @ H[:, 2]) @ e
    d = (p - C) / np.linalg.norm(p - C, axis=1, keepdims=True)
    b = np.column_stack([xy, np.full(len(p), c)])
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(d.T @ b)
    return C, U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt


# -- scenes -------------------------------------------------------------------------


def noisy_scene(cam, rng, kind, n, n_gross, gross_px=(1.0, 30.0)):
    T, p, uv = (
        plate_scene(cam, rng, n=n, view_angle_deg=rng.uniform(60, 90))
        if kind == "plate"
        else volume_scene(cam, rng, n=n)
    )
    uv = uv + rng.normal(0, SIGMA_PX, uv.shape)
    wrong = rng.choice(n, n_gross, replace=False)
    angle = rng.uniform(0, 2 * np.pi, n_gross)
    uv[wrong] += rng.uniform(*gross_px, (n_gross, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
    # the start: a few mm and tenths of a degree off, as a tracked frame's prediction
    T0 = T.copy()
    T0[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.005, 3)).as_matrix() @ T[:3, :3]
    T0[:3, 3] += rng.normal(0, 3.0, 3)
    return p, uv, T0


# -- tests ----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["plate", "volume"])
@pytest.mark.parametrize("sigma_px", [None, SIGMA_PX])
def test_compiled_resection_matches_the_numpy_reference_with_gross_errors(reference_camera, rng, kind, sigma_px):
    n_rejected = 0
    for k in range(12):
        n = [12, 30, 60, 230][k % 4]
        p, uv, T0 = noisy_scene(reference_camera, rng, kind, n, n_gross=[0, 1, 3, n // 8][k // 3])
        T_ref, cov_ref, sigma0_ref, r_ref, inl_ref = reference_resect(reference_camera, p, uv, T0, sigma_px)
        res = resect(reference_camera, p, uv, T_field_camera_init=T0, sigma_px=sigma_px)
        np.testing.assert_array_equal(res.inliers, inl_ref)
        np.testing.assert_allclose(res.T_field_camera[:3, 3], T_ref[:3, 3], rtol=0, atol=1e-9)  # mm
        np.testing.assert_allclose(res.T_field_camera[:3, :3], T_ref[:3, :3], rtol=0, atol=1e-12)  # rad
        np.testing.assert_allclose(res.residuals_px, r_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.covariance, cov_ref, rtol=1e-8, atol=0)
        assert res.sigma0_px == pytest.approx(sigma0_ref, rel=1e-9)
        assert res.rms_px == pytest.approx(np.sqrt(np.mean(r_ref[inl_ref] ** 2)), rel=1e-9)
        np.testing.assert_allclose(res.sigma_position_mm, np.sqrt(np.diag(cov_ref))[3:], rtol=1e-8)
        n_rejected += int(np.sum(~res.inliers))
    assert n_rejected >= 12  # the scenes did exercise the snooping


@pytest.mark.parametrize("sigma_px", [None, SIGMA_PX])
def test_too_many_gross_errors_fail_in_both(reference_camera, rng, sigma_px):
    p, uv, T0 = noisy_scene(reference_camera, rng, "plate", 20, n_gross=11, gross_px=(5.0, 40.0))
    with pytest.raises(_Failed, match="too many gross errors"):
        reference_resect(reference_camera, p, uv, T0, sigma_px)
    with pytest.raises(SolveError, match="Too many gross errors: rejecting another point would leave fewer than 10"):
        resect(reference_camera, p, uv, T_field_camera_init=T0, sigma_px=sigma_px)


@pytest.mark.parametrize("n", [4, 8, 30, 230])
def test_compiled_planar_closed_form_matches_the_numpy_reference(reference_camera, rng, n):
    for _ in range(5):
        _, p, uv = plate_scene(reference_camera, rng, n=n, view_angle_deg=rng.uniform(55, 90))
        uv = uv + rng.normal(0, SIGMA_PX, uv.shape)
        xy = reference_camera.ideal_from_pixel(uv)
        C_ref, R_ref = reference_planar_closed_form(p, xy, reference_camera.c_mm)
        C = _centre_planar(p, xy / reference_camera.c_mm)
        # both solve the DLT through A^T A, which squares its condition: round-off ~1e-12 of the distance
        tol_mm = 1e-11 * np.linalg.norm(C_ref)
        np.testing.assert_allclose(C, C_ref, rtol=0, atol=tol_mm)
        R = _rotation_from_centre(p, xy, reference_camera.c_mm, C_ref)
        np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-12)
        T = resect_closed_form(reference_camera, p, uv)
        np.testing.assert_allclose(T[:3, 3], C_ref, rtol=0, atol=tol_mm)


# -- the kernels called directly, against OpenCV and SciPy ------------------------------------------


def test_compiled_adjustment_is_opencvs_refined_pnp_without_distortion(rng):
    # no distortion and square pixels: W is 1 / pixel size for every point, so the whitened
    # least squares and OpenCV's reprojection error in ideal coordinates have the same minimum
    camera = BrownFraser(1300, 1030, (0.0067, 0.0067), 12.0, 0.031, -0.024)
    K_mm = np.diag([camera.c_mm, camera.c_mm, 1.0])
    for kind in ("plate", "volume"):
        for n in (4, 6, 30, 230):
            T, p, uv = (
                plate_scene(camera, rng, n=n, view_angle_deg=70.0)
                if kind == "plate"
                else volume_scene(camera, rng, n=n)
            )
            uv = uv + rng.normal(0, SIGMA_PX, uv.shape)
            xy, W = whitened_ideal_kernel(uv, 649.5, 514.5, 0.0067, 0.0067, 0.031, -0.024, *(0.0,) * 7)
            T0 = T.copy()
            T0[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ T[:3, :3]
            T0[:3, 3] += rng.normal(0, 5.0, 3)
            out = resect_kernel(T0, p, xy, W, camera.c_mm, 50, False, np.nan, 0.5, np.nan, SNOOPING_ALPHA, 1e-4)
            status, T_k, sigma_k, sigma0 = out[0], out[1], out[7], out[8]
            assert status == OK
            T_cf = np.linalg.inv(T0)  # OpenCV's rvec, tvec are T_camera_field
            rvec, tvec = cv2.Rodrigues(T_cf[:3, :3])[0], T_cf[:3, 3].copy()
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-15)
            rvec, tvec = cv2.solvePnPRefineLM(p, xy, K_mm, None, rvec, tvec, criteria=criteria)
            R = cv2.Rodrigues(rvec)[0]
            C = -R.T @ tvec.ravel()
            # both at the least-squares minimum: to 1e-5 of the pose's own standard deviation (4 and 6
            # points leave a flat valley where either stops ~1e-7 mm short), to 1e-9 mm with more
            np.testing.assert_allclose(T_k[:3, 3], C, rtol=0, atol=1e-5 * sigma_k[3:].max() + 1e-9)
            np.testing.assert_allclose(T_k[:3, :3], R.T, rtol=0, atol=1e-5 * np.radians(sigma_k[:3].max()) + 1e-12)
            # sigma0 from OpenCV's own projection: sqrt(sum r^2 / (2n - 6)), px
            r_px = (cv2.projectPoints(p, rvec, tvec, K_mm, None)[0].reshape(-1, 2) - xy) / 0.0067
            assert sigma0 == pytest.approx(np.sqrt(np.sum(r_px**2) / (2 * n - 6)), rel=1e-9)
            np.testing.assert_array_equal(out[3], True)  # no snooping asked for: every point in


def test_spread_is_the_singular_values_of_the_centred_points(rng):
    for n in (1, 2, 4, 30, 230):
        rot = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        p = rng.normal(0, [300.0, 100.0, 10.0], (n, 3)) @ rot
        xy = rng.normal(0, [3.0, 0.5], (n, 2))
        if n == 30:  # collinear field points, and image points on one line
            p = np.outer(rng.normal(0, 100, n), [0.6, 0.8, 0.0]) + [10.0, 20.0, 30.0]
            xy = np.outer(rng.normal(0, 1, n), [1.0, 2.0])
        s, s_img = spread_kernel(p, xy)
        ref = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        ref_img = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
        ref, ref_img = np.pad(ref, (0, 3 - len(ref))), np.pad(ref_img, (0, 2 - len(ref_img)))
        # eigenvalues of the scatter matrix, rooted: a vanishing spread only to sqrt(1e-16) of the
        # largest (the square root of round-off), the others to 1e-9 relative
        np.testing.assert_allclose(s, ref, rtol=1e-9, atol=1e-7 * ref[0])
        np.testing.assert_allclose(s_img, ref_img, rtol=1e-9, atol=1e-7 * ref_img[0])


def test_rotation_from_centre_is_the_kabsch_rotation_of_the_rays(reference_camera, rng):
    for k in range(20):
        n = [3, 4, 30, 230][k % 4]
        _, p, uv = plate_scene(reference_camera, rng, n=n, view_angle_deg=rng.uniform(40, 90))
        xy = reference_camera.ideal_from_pixel(uv + rng.normal(0, 1.0, uv.shape))
        C = rng.normal(0, 50.0, 3) + [0.0, 0.0, 1000.0]  # a centre a little off: rays that disagree
        d = (p - C) / np.linalg.norm(p - C, axis=1, keepdims=True)
        b = np.column_stack([xy, np.full(n, reference_camera.c_mm)])
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        R_ref = Rotation.align_vectors(d, b)[0].as_matrix()  # minimises sum |d - R b|^2
        R = rotation_from_centre_kernel(p, xy, reference_camera.c_mm, C)
        np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-12)  # two SVDs of one 3 x 3 matrix


def test_planar_centre_kernel_is_the_numpy_closed_form_and_rejects_collinear_points(reference_camera, rng):
    for n in (4, 30):
        _, p, uv = plate_scene(reference_camera, rng, n=n, view_angle_deg=rng.uniform(55, 90))
        xy = reference_camera.ideal_from_pixel(uv + rng.normal(0, SIGMA_PX, uv.shape))
        C_ref, _ = reference_planar_closed_form(p, xy, reference_camera.c_mm)
        C, unique = centre_planar_kernel(p, xy / reference_camera.c_mm)
        assert unique
        np.testing.assert_allclose(C, C_ref, rtol=0, atol=1e-11 * np.linalg.norm(C_ref))
    # all on one line of the plate: the DLT has a second null vector
    t = rng.uniform(-200, 200, (12, 1))
    p = np.column_stack([t, 0.5 * t, np.zeros_like(t)]) + [10.0, -20.0, 0.0]
    n_img = np.column_stack([0.001 * t[:, 0], 0.0002 * t[:, 0]]) + [0.01, -0.02]
    C, unique = centre_planar_kernel(p, n_img)
    assert not unique and np.all(C == 0)
