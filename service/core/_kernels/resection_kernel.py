"""The resection's adjustment with data snooping and its planar closed form, compiled (numba).

:func:`resect_kernel` runs the whole loop of :func:`service.core.pose.resection.resect`
after its input checks and start pose: Levenberg-Marquardt on the collinearity
equations (:func:`~service.core._kernels.geometry_kernels.adjust_kernel`), the normal
matrix's conditioning test and inverse, each point's studentized statistic, the
rejection of the worst point and the re-admission of rejected points that fit
the clean solution, and the covariance. In Python these were some forty numpy
and LAPACK calls per resection, each with microseconds of overhead: together
more than the arithmetic of an ROI frame's ~230 points. Failures come back as a
status code; :mod:`service.core.pose.resection` turns them into ``SolveError``.

The planar closed form of :mod:`service.core.pose.resection_closed_form` (the centre from
the plane-to-plane transformation, Kraus' rotation) and its input's spread are
here too: as numpy and LAPACK calls they took two thirds of a resection from ~30
coded targets, the full frame's first one.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from service.core._kernels.geometry_kernels import (
    BEHIND,
    CONVERGED,
    NO_STEP,
    SINGULAR,
    adjust_kernel,
    design_kernel,
    point_statistics_kernel,
    residuals_kernel,
    scatter_kernel,
    whitened_ideal_kernel,
)

#: :func:`resect_kernel`'s outcomes: a solution, or which ``SolveError`` to raise
(
    OK,
    START_BEHIND,
    NORMAL_SINGULAR,
    NO_DESCENT,
    DEGENERATE,
    TOO_MANY_GROSS,
    NO_CONVERGENCE,
    TOO_FEW_AGREE,
    INLIER_BEHIND,
) = range(9)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _critical(m, alpha):
    """Critical values of chi^2(2) and of 2 F(2, m) at the false-alarm probability ``alpha``."""
    # P(chi^2(2) > x) = exp(-x/2); P(F(2, m) > x) = (1 + 2x/m)^(-m/2) and the statistic is 2F
    return -2.0 * np.log(alpha), m * (alpha ** (-2.0 / m) - 1.0) if m >= 1 else np.inf


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _score(T2, s2_post, sigma_px, max_sigma_px, critical_value, chi2_crit, f_crit, floor_px):
    """One point's ``T2 / sigma^2`` over its critical value (``resection.resect``'s data snooping;
    NaN ``sigma_px`` or ``critical_value``: not given)."""
    if sigma_px == sigma_px:
        crit = critical_value**2 if critical_value == critical_value else chi2_crit
        return T2 / (sigma_px**2 * crit)
    capped = s2_post > max_sigma_px**2
    s2 = max_sigma_px**2 if capped else max(s2_post, floor_px**2)
    if critical_value == critical_value:
        return T2 / (s2 * critical_value**2)
    return T2 / (s2 * (chi2_crit if capped else f_crit))


@njit(cache=True, nogil=True, error_model="numpy")
def resect_kernel(T, p, xy, W, c, max_iter, reject, sigma_px, max_sigma_px, critical_value, alpha, floor_px):
    """Adjust the start pose ``T`` (4, 4) (``T_field_camera``) over field points ``p`` (n, 3) mm,
    ideal coordinates ``xy`` (n, 2) mm and whitening ``W`` (n, 2, 2) px/mm, with data snooping
    as ``resection.resect`` describes (NaN ``sigma_px``, ``critical_value``: not given).

    Returns the status (OK or the failure), the pose (4, 4), iterations, inliers (n,) and their
    number, residuals of all points (n, 2) px, covariance (6, 6), its standard deviations (6,)
    (rotation deg, position mm), sigma0 px, RMS px, ``sum(v**2)`` over the inliers px^2, the
    initial ``sum(r**2)`` px^2 over all points, and the inliers behind the adjusted camera (n,)
    (for INLIER_BEHIND).
    """
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
    n = p.shape[0]
    ss = 0.0
    for i in range(n):
        d0, d1, d2 = p[i, 0] - t[0], p[i, 1] - t[1], p[i, 2] - t[2]
        ss += d0 * d0 + d1 * d1 + d2 * d2
    scale_mm = max(np.sqrt(ss / n), 1e-9)
    ss0 = np.nan  # sum(r**2) at the start, from the first adjustment's first evaluation
    inliers = np.ones(n, dtype=np.bool_)
    behind = np.zeros(n, dtype=np.bool_)
    min_keep = max(4, -(-n // 2))
    n_iter, readmitted, status, first = 0, False, OK, True
    Qxx = np.zeros((6, 6))
    omega, f = 0.0, 1
    idx = np.arange(n)
    v, pc = np.zeros((n, 2)), np.zeros((n, 3))
    S = np.empty((6, 6))
    while True:
        idx = np.flatnonzero(inliers)
        k = idx.size
        if k == n:  # no copies while every point is in (the usual case)
            # N: the normal matrix of the design A and residuals v it returns, for the snooping
            R, t, it, v, pc, A, N, ss_start, outcome = adjust_kernel(R, t, p, xy, W, c, scale_mm, max_iter)
        else:
            R, t, it, v, pc, A, N, ss_start, outcome = adjust_kernel(
                R, t, p[idx], xy[idx], W[idx], c, scale_mm, max_iter
            )
        if first:
            ss0, first = ss_start, False
        if outcome == BEHIND:
            status = START_BEHIND
            break
        if outcome == SINGULAR:
            status = NORMAL_SINGULAR
            break
        if outcome == NO_STEP:
            status = NO_DESCENT
            break
        n_iter += it
        well = True
        for a in range(6):
            if not np.sqrt(N[a, a]) > 0:
                well = False
        if well:
            for a in range(6):
                for b in range(6):
                    S[a, b] = N[a, b] / (np.sqrt(N[a, a]) * np.sqrt(N[b, b]))
            ev = np.linalg.eigvalsh(S)
            well = ev[0] > 1e-12 * ev[5]
        if not well:
            status = DEGENERATE
            break
        Qxx = np.linalg.inv(N)
        f = 2 * k - 6
        omega = 0.0
        for i in range(k):
            omega += v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1]
        score = np.zeros(k)
        if reject:
            T2, det = point_statistics_kernel(v, A, Qxx, -1.0)
            chi2_crit, f_crit = _critical(f - 2, alpha)
            for i in range(k):
                if det[i] > 1e-6:  # a point the pose must pass through cannot be tested
                    score[i] = _score(
                        T2[i],
                        max(omega - T2[i], 0.0) / max(f - 2, 1),
                        sigma_px,
                        max_sigma_px,
                        critical_value,
                        chi2_crit,
                        f_crit,
                        floor_px,
                    )
        worst = np.argmax(score)
        if score[worst] > 1.0:
            # even an unsettled adjustment (slow with large residuals) shows this
            if k - 1 < min_keep:
                status = TOO_MANY_GROSS
                break
            inliers[idx[worst]] = False
            continue
        if outcome != CONVERGED:
            status = NO_CONVERGENCE
            break
        out = np.flatnonzero(~inliers)
        if readmitted or out.size == 0:
            break
        # swamping: next to a gross error still in the adjustment a good point can look wrong, so
        # the rejected points are tested once more, as new observations against the clean solution
        readmitted = True
        W_out = W[out]
        r_out, pc_out, _, _ = residuals_kernel(R, t, p[out], xy[out], W_out, c)
        T2o = point_statistics_kernel(r_out, design_kernel(R, W_out, c, pc_out), Qxx, 1.0)[0]
        n_back = 0
        chi2_crit, f_crit = _critical(f, alpha)
        for j in range(out.size):
            if _score(T2o[j], omega / f, sigma_px, max_sigma_px, critical_value, chi2_crit, f_crit, floor_px) <= 1.0:
                inliers[out[j]] = True
                n_back += 1
        if n_back == 0:
            break

    sigma0 = np.sqrt(omega / f)
    n_in = idx.size
    r_all = np.empty((n, 2))
    cov = np.empty((6, 6))
    sig = np.empty(6)
    T_out = np.eye(4)
    if status == OK and reject and sigma_px != sigma_px and sigma0 > max_sigma_px:
        status = TOO_FEW_AGREE
    if status == OK:
        for i in range(n_in):
            if pc[i, 2] <= 0:
                behind[idx[i]] = True
                status = INLIER_BEHIND
    if status == OK:
        for i in range(n_in):
            r_all[idx[i]] = v[i]
        out = np.flatnonzero(~inliers)
        if out.size > 0:
            r_all[out] = residuals_kernel(R, t, p[out], xy[out], W[out], c)[0]
        s = sigma_px if sigma_px == sigma_px else sigma0
        cov[:] = s**2 * Qxx
        for a in range(6):
            sig[a] = np.sqrt(cov[a, a])
        for a in range(3):
            sig[a] *= 180.0 / np.pi  # as np.degrees
            T_out[a, 3] = t[a]
            for b in range(3):
                T_out[a, b] = R[a, b]
    return (
        status,
        T_out,
        n_iter,
        inliers,
        n_in,
        r_all,
        cov,
        sig,
        sigma0,
        np.sqrt(omega / (2 * n_in)),
        omega,
        ss0,
        behind,
    )


# -- the closed form's planar case and the input's spread (resection_closed_form) ----------------


@njit(cache=True, nogil=True, error_model="numpy")
def spread_kernel(p, xy):
    """Spread (3,) of field points ``p`` (n, 3) mm along their principal axes, decreasing, and
    of image points ``xy`` (n, 2) mm (2,) (``resection_closed_form.check_geometry``)."""
    S, Sx = scatter_kernel(p, xy)
    ev = np.linalg.eigvalsh(S)
    s = np.empty(3)
    for k in range(3):
        s[k] = np.sqrt(max(ev[2 - k], 0.0))
    sxx, syy, sxy = Sx[0, 0], Sx[1, 1], Sx[0, 1]
    # closed-form eigenvalues of the 2x2 scatter matrix
    half_tr, root = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    s_img = np.empty(2)
    s_img[0], s_img[1] = np.sqrt(max(half_tr + root, 0.0)), np.sqrt(max(half_tr - root, 0.0))
    return s, s_img


@njit(cache=True, nogil=True, error_model="numpy")
def _normalizer(points):
    """Hartley's similarity (d+1, d+1): centroid to the origin, RMS distance sqrt(d)."""
    n, d = points.shape
    m = np.zeros(d)
    for i in range(n):
        for k in range(d):
            m[k] += points[i, k]
    m /= n
    ss = 0.0
    for i in range(n):
        for k in range(d):
            ss += (points[i, k] - m[k]) ** 2
    s = np.sqrt(d) / np.sqrt(ss / n)
    N = np.eye(d + 1)
    for k in range(d):
        N[k, k] = s
        N[k, d] = -s * m[k]
    return N


@njit(cache=True, nogil=True, error_model="numpy")
def centre_planar_kernel(p, n_img):
    """Projection centre (3,) mm of a planar field ``p`` (n, 3) mm seen at normalized image points
    ``n_img`` (n, 2) from the plane-to-plane transformation, and whether that was unique
    (``resection_closed_form._centre_planar``)."""
    n = p.shape[0]
    m = np.zeros(3)
    for i in range(n):
        for k in range(3):
            m[k] += p[i, k]
    m /= n
    d = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            d[i, k] = p[i, k] - m[k]
    _, V = np.linalg.eigh(d.T @ d)
    e = np.empty((3, 3))  # rows: in-plane axes by decreasing spread, then the normal
    for r in range(3):
        for k in range(3):
            e[r, k] = V[k, 2 - r]
    if np.linalg.det(e) < 0:
        e[2] *= -1.0
    ab = np.empty((n, 2))  # in-plane coordinates, mm
    for i in range(n):
        for r in range(2):
            ab[i, r] = d[i, 0] * e[r, 0] + d[i, 1] * e[r, 1] + d[i, 2] * e[r, 2]
    Na, Ni = _normalizer(ab), _normalizer(n_img)
    M = np.zeros((9, 9))  # A^T A of the DLT's rows, accumulated point by point
    row = np.empty(9)
    for i in range(n):
        a0, a1 = Na[0, 0] * ab[i, 0] + Na[0, 2], Na[1, 1] * ab[i, 1] + Na[1, 2]
        x0, x1 = Ni[0, 0] * n_img[i, 0] + Ni[0, 2], Ni[1, 1] * n_img[i, 1] + Ni[1, 2]
        for half in range(2):
            row[:] = 0.0
            o = 3 * half
            x = x0 if half == 0 else x1
            row[o], row[o + 1], row[o + 2] = a0, a1, 1.0
            row[6], row[7], row[8] = -x * a0, -x * a1, -x
            for j in range(9):
                for k in range(j, 9):
                    M[j, k] += row[j] * row[k]
    for j in range(9):
        for k in range(j):
            M[j, k] = M[k, j]
    ev, V9 = np.linalg.eigh(M)
    C = np.zeros(3)
    if ev[1] < 1e-18 * ev[8]:
        return C, False
    h = np.ascontiguousarray(V9[:, 0]).reshape(3, 3)
    H = np.linalg.solve(Ni, h @ Na)
    # H ~ [r1 r2 t] of T_camera_plane; of the two mirror solutions the one with the points in
    # front of the camera has positive depth at the centroid (a = 0)
    lam = np.sign(H[2, 2]) / np.sqrt(np.linalg.norm(H[:, 0]) * np.linalg.norm(H[:, 1]))
    B = np.empty((3, 3))
    for k in range(3):
        B[k, 0], B[k, 1] = lam * H[k, 0], lam * H[k, 1]
    B[0, 2] = B[1, 0] * B[2, 1] - B[2, 0] * B[1, 1]
    B[1, 2] = B[2, 0] * B[0, 1] - B[0, 0] * B[2, 1]
    B[2, 2] = B[0, 0] * B[1, 1] - B[1, 0] * B[0, 1]
    U, _, Wt = np.linalg.svd(B)
    D = np.eye(3)
    D[2, 2] = np.linalg.det(U @ Wt)
    R_camera_plane = U @ D @ Wt
    for r in range(3):
        C_plane = -(
            R_camera_plane[0, r] * lam * H[0, 2]
            + R_camera_plane[1, r] * lam * H[1, 2]
            + R_camera_plane[2, r] * lam * H[2, 2]
        )
        for k in range(3):
            C[k] += C_plane * e[r, k]
    for k in range(3):
        C[k] += m[k]
    return C, True


@njit(cache=True, nogil=True, error_model="numpy")
def rotation_from_centre_kernel(p, xy, c, C):
    """Kraus: R_field_camera (3, 3) aligning the image rays of ``xy`` (n, 2) mm with the field rays
    from the centre ``C`` (3,) mm to ``p`` (n, 3) mm, over all points (orthogonal Procrustes)."""
    M = np.zeros((3, 3))
    for i in range(p.shape[0]):
        d0, d1, d2 = p[i, 0] - C[0], p[i, 1] - C[1], p[i, 2] - C[2]
        nd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        b0, b1, b2 = xy[i, 0], xy[i, 1], c
        nb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        d0, d1, d2, b0, b1, b2 = d0 / nd, d1 / nd, d2 / nd, b0 / nb, b1 / nb, b2 / nb
        M[0, 0] += d0 * b0
        M[0, 1] += d0 * b1
        M[0, 2] += d0 * b2
        M[1, 0] += d1 * b0
        M[1, 1] += d1 * b1
        M[1, 2] += d1 * b2
        M[2, 0] += d2 * b0
        M[2, 1] += d2 * b1
        M[2, 2] += d2 * b2
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for the types ``resect`` passes."""
    p = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [100.0, 100.0, 10.0], [50.0, 20.0, 0.0]])
    uv = np.array([[650.0, 515.0], [710.0, 515.0], [650.0, 575.0], [712.0, 577.0], [680.0, 527.0]])
    xy, W = whitened_ideal_kernel(uv, 649.5, 514.5, 0.0067, 0.0067, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for reject in (True, False):
        T = np.eye(4)
        T[2, 3] = -1000.0
        resect_kernel(T, p, xy, W, 12.0, 5, reject, np.nan, 0.5, np.nan, 1e-5, 1e-4)
    spread_kernel(p, xy)
    C, _ = centre_planar_kernel(p, xy / 12.0)
    rotation_from_centre_kernel(p, xy, 12.0, C)
