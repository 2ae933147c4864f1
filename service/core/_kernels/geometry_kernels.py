"""Per-point loops of the resection and of target prediction, compiled (numba).

Written as loops because each call handles a few hundred points many times
per frame: the collinearity residuals and their Jacobian (the adjustment's
inner loop), the data-snooping statistics, the disk centres' perspective
offsets, the inverse of the Brown/Fraser correction, the projection of the
field and the matching of predictions to blobs, the pose prediction, and the
resection's input checks and whitening. As numpy expressions they cost tens of
array passes per call, more than their arithmetic. The formulas are those of
:mod:`service.core.pose.resection`, :mod:`service.core.pose.resection_closed_form`,
:mod:`service.core.targets.identify`, :mod:`service.core.pose.tracking` and
:mod:`service.core.geometry.camera_model`, in the same order of operations.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def residuals_kernel(R, t, p, xy, W, c):
    """Whitened residuals (n, 2) px, camera-frame points (n, 3) mm, ``sum(r**2)`` and the number of
    points in front (Z > 0), for ``p_c = R^T (p - t)`` and ideal ``xy`` (n, 2) mm."""
    n = p.shape[0]
    r = np.empty((n, 2))
    pc = np.empty((n, 3))
    ss, n_front = 0.0, 0
    for i in range(n):
        d0, d1, d2 = p[i, 0] - t[0], p[i, 1] - t[1], p[i, 2] - t[2]
        x = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
        y = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
        z = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
        pc[i, 0], pc[i, 1], pc[i, 2] = x, y, z
        iz = c / z
        e0, e1 = xy[i, 0] - x * iz, xy[i, 1] - y * iz
        r0 = W[i, 0, 0] * e0 + W[i, 0, 1] * e1
        r1 = W[i, 1, 0] * e0 + W[i, 1, 1] * e1
        r[i, 0], r[i, 1] = r0, r1
        ss += r0 * r0 + r1 * r1
        if z > 0:
            n_front += 1
    return r, pc, ss, n_front


@njit(cache=True, nogil=True, error_model="numpy")
def design_kernel(R, W, c, pc):
    """Jacobian (n, 2, 6) of the whitened computed coordinates wrt [dθ, dt], field axes (the
    formulas are in :mod:`service.core.pose.resection`)."""
    n = pc.shape[0]
    A = np.empty((n, 2, 6))
    b = np.empty((2, 6))
    for i in range(n):
        iz = 1.0 / pc[i, 2]
        xn, yn = pc[i, 0] * iz, pc[i, 1] * iz
        ciz = c * iz
        # camera axes: rows u, v; columns rotation (3), centre (3)
        cam0 = (c * xn * yn, -c * (1.0 + xn * xn), c * yn, -ciz, 0.0, ciz * xn)
        cam1 = (c * (1.0 + yn * yn), -c * xn * yn, -c * xn, 0.0, -ciz, ciz * yn)
        for blk in range(2):
            o = 3 * blk
            for k in range(3):  # field axes: R @ (camera-axes vector)
                b[0, o + k] = R[k, 0] * cam0[o] + R[k, 1] * cam0[o + 1] + R[k, 2] * cam0[o + 2]
                b[1, o + k] = R[k, 0] * cam1[o] + R[k, 1] * cam1[o + 1] + R[k, 2] * cam1[o + 2]
        for j in range(6):
            A[i, 0, j] = W[i, 0, 0] * b[0, j] + W[i, 0, 1] * b[1, j]
            A[i, 1, j] = W[i, 1, 0] * b[0, j] + W[i, 1, 1] * b[1, j]
    return A


@njit(cache=True, nogil=True, error_model="numpy")
def normal_kernel(A, r):
    """Normal matrix ``A^T A`` (6, 6) and right-hand side ``A^T r`` (6,) over all points."""
    N = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(A.shape[0]):
        for k in range(2):
            rk = r[i, k]
            for a in range(6):
                x = A[i, k, a]
                g[a] += x * rk
                for b in range(a, 6):
                    N[a, b] += x * A[i, k, b]
    for a in range(6):
        for b in range(a):
            N[a, b] = N[b, a]
    return N, g


@njit(cache=True, nogil=True, error_model="numpy")
def point_statistics_kernel(v, A, Qxx, sign):
    """Each point's ``v_i^T Q_i^-1 v_i`` and ``det Q_i`` (n,), ``Q_i = I + sign A_i Qxx A_i^T``."""
    n = v.shape[0]
    T2, det = np.empty(n), np.empty(n)
    aq = np.empty((2, 6))
    for i in range(n):
        for k in range(2):
            for b in range(6):
                x = 0.0
                for a in range(6):
                    x += A[i, k, a] * Qxx[a, b]
                aq[k, b] = x
        q00 = q01 = q11 = 0.0
        for b in range(6):
            q00 += aq[0, b] * A[i, 0, b]
            q01 += aq[0, b] * A[i, 1, b]
            q11 += aq[1, b] * A[i, 1, b]
        q00, q01, q11 = 1.0 + sign * q00, sign * q01, 1.0 + sign * q11
        d = q00 * q11 - q01 * q01
        det[i] = d
        T2[i] = (q11 * v[i, 0] ** 2 - 2 * q01 * v[i, 0] * v[i, 1] + q00 * v[i, 1] ** 2) / d
    return T2, det


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def correction_point(x, y, K1, K2, K3, P1, P2, B1, B2):
    """The Brown/Fraser correction (dx, dy) mm at one point (x, y) mm relative to the principal point,
    and the Jacobian (j00, j01, j10, j11) of (x + dx, y + dy) by (x, y): the one formula of every
    kernel that corrects (``BrownFraser._correction`` and its Jacobian, in the same order)."""
    r2 = x * x + y * y
    radial = r2 * (K1 + r2 * (K2 + r2 * K3))
    dx = x * radial + P1 * (r2 + 2 * x * x) + 2 * P2 * x * y + B1 * x + B2 * y
    dy = y * radial + 2 * P1 * x * y + P2 * (r2 + 2 * y * y)
    g = K1 + r2 * (2 * K2 + 3 * K3 * r2)
    j00 = 1 + radial + 2 * x * x * g + 6 * P1 * x + 2 * P2 * y + B1
    j01 = 2 * x * y * g + 2 * P1 * y + 2 * P2 * x + B2
    j10 = 2 * x * y * g + 2 * P1 * y + 2 * P2 * x
    j11 = 1 + radial + 2 * y * y * g + 2 * P1 * x + 6 * P2 * y
    return dx, dy, j00, j01, j10, j11


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sensor_from_ideal_point(tx, ty, K1, K2, K3, P1, P2, B1, B2, max_iter):
    """Newton inverse of the Brown/Fraser correction at one ideal point (mm, relative to the
    principal point): the measured point, until the step is below 1e-12 mm. NaN where there is
    none: Newton did not converge, or converged beyond the fold of the distortion polynomial
    (the mapping's Jacobian no longer positive: far outside the lens model's range, e.g. a point
    45 deg off the axis of a lens whose image ends at 25 deg), never a wrong point inside the image."""
    xb, yb = tx, ty
    det = 1.0
    converged = max_iter <= 0  # no step asked for: the start
    for _ in range(max_iter):
        dx, dy, j00, j01, j10, j11 = correction_point(xb, yb, K1, K2, K3, P1, P2, B1, B2)
        rx, ry = xb + dx - tx, yb + dy - ty
        det = j00 * j11 - j01 * j10
        sx, sy = (j11 * rx - j01 * ry) / det, (-j10 * rx + j00 * ry) / det
        xb -= sx
        yb -= sy
        if abs(sx) < 1e-12 and abs(sy) < 1e-12:
            converged = True
            break
    if not converged or not det > 0:
        return np.nan, np.nan
    return xb, yb


@njit(cache=True, nogil=True, error_model="numpy")
def sensor_from_ideal_kernel(target, K1, K2, K3, P1, P2, B1, B2, max_iter):
    """Newton inverse of the Brown/Fraser correction per point, relative to the principal point:
    (n, 2) mm, each point until its step is below 1e-12 mm (see ``BrownFraser.sensor_from_ideal``)."""
    n = target.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        out[i, 0], out[i, 1] = _sensor_from_ideal_point(
            target[i, 0], target[i, 1], K1, K2, K3, P1, P2, B1, B2, max_iter
        )
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def whitened_ideal_kernel(uv, cu, cv, pixel_u, pixel_v, x0, y0, K1, K2, K3, P1, P2, B1, B2):
    """Ideal coordinates (n, 2) mm of pixels ``uv`` (n, 2) and the inverses (n, 2, 2) px/mm of
    d(ideal)/d(pixel) there, in one pass: ``BrownFraser.ideal_from_pixel`` and the inverse of
    ``BrownFraser.ideal_from_pixel_jacobian`` (the resection's inputs), the same arithmetic."""
    n = uv.shape[0]
    xy = np.empty((n, 2))
    W = np.empty((n, 2, 2))
    for i in range(n):
        x, y = (uv[i, 0] - cu) * pixel_u - x0, (uv[i, 1] - cv) * pixel_v - y0
        dx, dy, c00, c01, c10, c11 = correction_point(x, y, K1, K2, K3, P1, P2, B1, B2)
        xy[i, 0], xy[i, 1] = x + dx, y + dy
        j00, j01, j10, j11 = c00 * pixel_u, c01 * pixel_v, c10 * pixel_u, c11 * pixel_v
        det = j00 * j11 - j01 * j10
        W[i, 0, 0], W[i, 0, 1], W[i, 1, 0], W[i, 1, 1] = j11 / det, -j01 / det, -j10 / det, j00 / det
    return xy, W


@njit(cache=True, nogil=True, error_model="numpy")
def scatter_kernel(p, xy):
    """Scatter matrices about the centroids: (3, 3) of field points ``p`` (n, 3) and (2, 2) of
    image points ``xy`` (n, 2) (``resection_closed_form.check_geometry``'s input)."""
    n = p.shape[0]
    mp, mx = np.zeros(3), np.zeros(2)
    for i in range(n):
        for k in range(3):
            mp[k] += p[i, k]
        mx[0] += xy[i, 0]
        mx[1] += xy[i, 1]
    mp /= n
    mx /= n
    S, Sx = np.zeros((3, 3)), np.zeros((2, 2))
    for i in range(n):
        d0, d1, d2 = p[i, 0] - mp[0], p[i, 1] - mp[1], p[i, 2] - mp[2]
        S[0, 0] += d0 * d0
        S[0, 1] += d0 * d1
        S[0, 2] += d0 * d2
        S[1, 1] += d1 * d1
        S[1, 2] += d1 * d2
        S[2, 2] += d2 * d2
        e0, e1 = xy[i, 0] - mx[0], xy[i, 1] - mx[1]
        Sx[0, 0] += e0 * e0
        Sx[0, 1] += e0 * e1
        Sx[1, 1] += e1 * e1
    S[1, 0], S[2, 0], S[2, 1], Sx[1, 0] = S[0, 1], S[0, 2], S[1, 2], Sx[0, 1]
    return S, Sx


@njit(cache=True, nogil=True, error_model="numpy")
def is_rigid_kernel(T, tol):
    """Whether ``T`` (4, 4) is finite, its rotation orthonormal and proper, and its last row
    (0, 0, 0, 1), each within ``tol``."""
    for i in range(4):
        for j in range(4):
            if not np.isfinite(T[i, j]):
                return False
    for i in range(3):
        for j in range(3):
            d = T[0, i] * T[0, j] + T[1, i] * T[1, j] + T[2, i] * T[2, j] - (1.0 if i == j else 0.0)
            if abs(d) > tol:
                return False
    det = (
        T[0, 0] * (T[1, 1] * T[2, 2] - T[1, 2] * T[2, 1])
        - T[0, 1] * (T[1, 0] * T[2, 2] - T[1, 2] * T[2, 0])
        + T[0, 2] * (T[1, 0] * T[2, 1] - T[1, 1] * T[2, 0])
    )
    return det > 0 and abs(T[3, 0]) <= tol and abs(T[3, 1]) <= tol and abs(T[3, 2]) <= tol and abs(T[3, 3] - 1) <= tol


@njit(cache=True, nogil=True, error_model="numpy")
def project_kernel(R, t, xyz, c, K1, K2, K3, P1, P2, B1, B2, x0, y0, pixel_u, pixel_v, width, height, margin):
    """Pixels (n, 2) px of field points ``xyz`` (n, 3) mm seen from ``T_field_camera`` = (R, t), as
    ``BrownFraser.pixel_from_camera`` computes them; their depth Z (n,) mm; and which are in front
    and inside the image by ``margin`` px (``BrownFraser.in_image``). Points behind give NaN."""
    n = xyz.shape[0]
    uv = np.full((n, 2), np.nan)
    depth = np.empty(n)
    inside = np.zeros(n, dtype=np.bool_)
    cu, cv = (width - 1) / 2.0, (height - 1) / 2.0
    for i in range(n):
        d0, d1, d2 = xyz[i, 0] - t[0], xyz[i, 1] - t[1], xyz[i, 2] - t[2]
        X = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
        Y = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
        Z = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
        depth[i] = Z
        if not Z > 0:
            continue
        xb, yb = _sensor_from_ideal_point(c * X / Z, c * Y / Z, K1, K2, K3, P1, P2, B1, B2, 20)
        u, v = (xb + x0) / pixel_u + cu, (yb + y0) / pixel_v + cv
        uv[i, 0], uv[i, 1] = u, v
        inside[i] = (
            u >= -0.5 + margin and u <= width - 0.5 - margin and v >= -0.5 + margin and v <= height - 0.5 - margin
        )
    return uv, depth, inside


@njit(cache=True, nogil=True, error_model="numpy")
def eccentricity_kernel(ex, ey, p_field, R, t, c, radius, W):
    """Offset (n, 2) px of each disk image's centre from the image of the disk's centre.

    In ideal coordinates it is the centre of the conic ``H^-T diag(1, 1, -r^2) H^-1`` with ``H``
    the homography from the disk's plane (axes ``ex``, ``ey`` (m, 3) field frame, one row for all
    disks or one per disk; centre ``p_field`` (n, 3) mm) to the image; ``W`` (n, 2, 2), the inverse
    of the ideal-from-pixel Jacobian at each disk, takes it to pixels. ``R``, ``t``: ``T_camera_field``.
    """
    n = p_field.shape[0]
    out = np.empty((n, 2))
    H = np.empty((3, 3))
    Hi = np.empty((3, 3))
    for i in range(n):
        a = min(i, ex.shape[0] - 1)
        for k in range(3):
            H[k, 0] = R[k, 0] * ex[a, 0] + R[k, 1] * ex[a, 1] + R[k, 2] * ex[a, 2]
            H[k, 1] = R[k, 0] * ey[a, 0] + R[k, 1] * ey[a, 1] + R[k, 2] * ey[a, 2]
            H[k, 2] = R[k, 0] * p_field[i, 0] + R[k, 1] * p_field[i, 1] + R[k, 2] * p_field[i, 2] + t[k]
        for j in range(3):
            H[0, j] *= c
            H[1, j] *= c
        # the adjugate: the conic's centre does not depend on the inverse's scale
        Hi[0, 0] = H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]
        Hi[0, 1] = H[0, 2] * H[2, 1] - H[0, 1] * H[2, 2]
        Hi[0, 2] = H[0, 1] * H[1, 2] - H[0, 2] * H[1, 1]
        Hi[1, 0] = H[1, 2] * H[2, 0] - H[1, 0] * H[2, 2]
        Hi[1, 1] = H[0, 0] * H[2, 2] - H[0, 2] * H[2, 0]
        Hi[1, 2] = H[0, 2] * H[1, 0] - H[0, 0] * H[1, 2]
        Hi[2, 0] = H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]
        Hi[2, 1] = H[0, 1] * H[2, 0] - H[0, 0] * H[2, 1]
        Hi[2, 2] = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
        r2 = radius[i] * radius[i]
        # C = Hi^T diag(1, 1, -r2) Hi; only its first two rows are needed
        c00 = Hi[0, 0] * Hi[0, 0] + Hi[1, 0] * Hi[1, 0] - r2 * Hi[2, 0] * Hi[2, 0]
        c01 = Hi[0, 0] * Hi[0, 1] + Hi[1, 0] * Hi[1, 1] - r2 * Hi[2, 0] * Hi[2, 1]
        c11 = Hi[0, 1] * Hi[0, 1] + Hi[1, 1] * Hi[1, 1] - r2 * Hi[2, 1] * Hi[2, 1]
        c02 = Hi[0, 0] * Hi[0, 2] + Hi[1, 0] * Hi[1, 2] - r2 * Hi[2, 0] * Hi[2, 2]
        c12 = Hi[0, 1] * Hi[0, 2] + Hi[1, 1] * Hi[1, 2] - r2 * Hi[2, 1] * Hi[2, 2]
        det = c00 * c11 - c01 * c01
        cx, cy = -(c11 * c02 - c01 * c12) / det, -(-c01 * c02 + c00 * c12) / det
        ox, oy = cx - H[0, 2] / H[2, 2], cy - H[1, 2] / H[2, 2]
        out[i, 0] = W[i, 0, 0] * ox + W[i, 0, 1] * oy  # to pixels
        out[i, 1] = W[i, 1, 0] * ox + W[i, 1, 1] * oy
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _solve6(N, g):
    """``N x = g`` by Gaussian elimination with partial pivoting (LAPACK's gesv, unblocked);
    NaN where N is singular. ``N`` and ``g`` are left as they are."""
    return solve_in_place(N.copy(), g.copy())


@njit(cache=True, nogil=True, error_model="numpy")
def solve_in_place(M, x):
    """:func:`_solve6` on ``M`` and the right-hand side ``x``, both overwritten (``x`` becomes the
    solution, returned): no allocation, for a solve per target in a loop."""
    n = x.size
    for k in range(n):
        piv, big = k, abs(M[k, k])
        for i in range(k + 1, n):
            if abs(M[i, k]) > big:
                piv, big = i, abs(M[i, k])
        if big == 0.0:
            x[:] = np.nan
            return x
        if piv != k:
            for j in range(n):
                M[k, j], M[piv, j] = M[piv, j], M[k, j]
            x[k], x[piv] = x[piv], x[k]
        for i in range(k + 1, n):
            f = M[i, k] / M[k, k]
            for j in range(k, n):
                M[i, j] -= f * M[k, j]
            x[i] -= f * x[k]
    for k in range(n - 1, -1, -1):
        s = x[k]
        for j in range(k + 1, n):
            s -= M[k, j] * x[j]
        x[k] = s / M[k, k]
    return x


@njit(cache=True, nogil=True, error_model="numpy")
def rotation_from_rotvec_kernel(w):
    """Rodrigues' formula (3, 3)."""
    theta = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    K2 = K @ K
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K2
    return np.eye(3) + (np.sin(theta) / theta) * K + ((1 - np.cos(theta)) / theta**2) * K2


@njit(cache=True, nogil=True, error_model="numpy")
def rotvec_from_matrix_kernel(R):
    """Rotation vector (3,) rad of a rotation matrix, through its unit quaternion (Shepperd's
    method, stable at any angle)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)  # x, y, z, w
    k, big = 0, tr
    for d in range(3):
        if R[d, d] > big:
            k, big = d + 1, R[d, d]
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + tr)
        f = 0.25 / w
        q[0], q[1], q[2], q[3] = (R[2, 1] - R[1, 2]) * f, (R[0, 2] - R[2, 0]) * f, (R[1, 0] - R[0, 1]) * f, w
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        q[i] = 0.5 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[m, m])
        f = 0.25 / q[i]
        q[j], q[m], q[3] = (R[j, i] + R[i, j]) * f, (R[m, i] + R[i, m]) * f, (R[m, j] - R[j, m]) * f
    if q[3] < 0:
        q *= -1.0
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    if n < 1e-12:
        return 2.0 * q[:3]
    return (2.0 * np.arctan2(n, q[3]) / n) * q[:3]


@njit(cache=True, nogil=True, error_model="numpy")
def predict_kernel(T0, T1, s):
    """``T1`` moved on by ``s`` times the motion from ``T0`` to ``T1`` (4, 4): linear in position,
    along the geodesic in rotation (``tracking.predict_pose``)."""
    R0, R1 = np.ascontiguousarray(T0[:3, :3]), np.ascontiguousarray(T1[:3, :3])
    R = R1 @ rotation_from_rotvec_kernel(s * rotvec_from_matrix_kernel(R0.T @ R1))
    T = np.eye(4)
    T[:3, :3] = R
    for k in range(3):
        T[k, 3] = T1[k, 3] + s * (T1[k, 3] - T0[k, 3])
    return T


@njit(cache=True, nogil=True, error_model="numpy")
def pose_at_kernel(t, ts, Ts, max_gap):
    """(covered, T (4, 4)): the pose at ``t`` between the samples ``Ts`` (n, 4, 4) at increasing
    ``ts`` (n,), as :func:`service.core.pose.timesync.pose_at` (which documents the rules); T is
    the identity when not covered."""
    n = ts.shape[0]
    if n == 0:
        return False, np.eye(4)
    k = np.searchsorted(ts, t, side="right")
    if k == 0:
        if ts[0] - t <= 1e-9 * max(1.0, abs(t)):
            return True, Ts[0].copy()
        return False, np.eye(4)
    if k == n:
        if n >= 2 and t - ts[n - 1] <= max_gap and ts[n - 1] - ts[n - 2] <= max_gap:
            s = (t - ts[n - 2]) / (ts[n - 1] - ts[n - 2])  # s > 1: a short extrapolation
            return True, predict_kernel(Ts[n - 2], Ts[n - 1], s - 1.0)
        if t == ts[n - 1]:
            return True, Ts[n - 1].copy()
        return False, np.eye(4)
    t0, t1 = ts[k - 1], ts[k]
    if t1 - t0 > max_gap:
        return False, np.eye(4)
    return True, predict_kernel(Ts[k - 1], Ts[k], (t - t0) / (t1 - t0) - 1.0)


@njit(cache=True, nogil=True, error_model="numpy")
def flange_kernel(Z, T_field_camera, X, T_reported, with_reported):
    """The measured flange ``Z @ T_field_camera @ X^-1`` (4, 4) and, ``with_reported``, its
    deviation from ``T_reported``: distance mm, angle rad, position difference (3,) mm
    (:mod:`service.pipeline.flange`, in one call instead of a dozen numpy ones a frame)."""
    X_inv = np.eye(4)
    for i in range(3):
        for j in range(3):
            X_inv[i, j] = X[j, i]
    for i in range(3):
        X_inv[i, 3] = -(X[0, i] * X[0, 3] + X[1, i] * X[1, 3] + X[2, i] * X[2, 3])
    T_m = Z @ T_field_camera @ X_inv
    d = np.zeros(3)
    if not with_reported:
        return T_m, 0.0, 0.0, d
    for i in range(3):
        d[i] = T_m[i, 3] - T_reported[i, 3]
    R_m, R_r = np.ascontiguousarray(T_m[:3, :3]), np.ascontiguousarray(T_reported[:3, :3])
    w = rotvec_from_matrix_kernel(R_m.T @ R_r)  # exact for tiny angles (no arccos of a trace)
    return T_m, np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2), np.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2), d


#: :func:`adjust_kernel`'s outcomes
CONVERGED, MAX_ITER, BEHIND, SINGULAR, NO_STEP = 0, 1, 2, 3, 4


@njit(cache=True, nogil=True, error_model="numpy")
def adjust_kernel(R, t, p, xy, W, c, scale_mm, max_iter):
    """Levenberg-Marquardt on the collinearity equations (see :mod:`service.core.pose.resection`).

    Returns R (3, 3), t (3,), iterations, residuals (n, 2), camera-frame points (n, 3), design
    (n, 2, 6), its normal matrix (6, 6) (the snooping's, which needs both), ``sum(r**2)`` at the
    start and the outcome (CONVERGED, MAX_ITER, BEHIND, SINGULAR, NO_STEP).
    """
    R, t = R.copy(), t.copy()
    r, pc, ss, n_front = residuals_kernel(R, t, p, xy, W, c)
    ss0, cost = ss, 0.5 * ss
    A3 = np.zeros((p.shape[0], 2, 6))
    N = np.zeros((6, 6))
    if not np.isfinite(cost):
        return R, t, 0, r, pc, A3, N, ss0, BEHIND
    tol_mm = 1e-10 * scale_mm
    lam = 0.0  # Marquardt's damping, relative to diag(N); 0 = Gauss-Newton
    for it in range(1, max_iter + 1):
        A3 = design_kernel(R, W, c, pc)
        N, g = normal_kernel(A3, r)
        delta = _solve6(N, g)
        if not np.all(np.isfinite(delta)):
            return R, t, it, r, pc, A3, N, ss0, SINGULAR
        step = np.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
        turn = np.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
        if step + scale_mm * turn < tol_mm:
            return rotation_from_rotvec_kernel(delta[:3]) @ R, t + delta[3:], it, r, pc, A3, N, ss0, CONVERGED
        while True:
            if lam > 0.0:
                Nl = N.copy()
                for k in range(6):
                    Nl[k, k] += lam * N[k, k]
                delta = _solve6(Nl, g)
            R_new = rotation_from_rotvec_kernel(delta[:3]) @ R
            t_new = t + delta[3:]
            r_new, pc_new, ss_new, n_front_new = residuals_kernel(R_new, t_new, p, xy, W, c)
            cost_new = 0.5 * ss_new
            predicted = delta @ g - 0.5 * delta @ (N @ delta)
            rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
            # a step that puts more points behind the camera jumps across Z = 0: refuse it
            if np.isfinite(cost_new) and n_front_new >= n_front and (rho > 0 or cost_new <= cost):
                break
            lam = max(4.0 * lam, 1e-6)
            if lam > 1e12:
                return R, t, it, r, pc, A3, N, ss0, NO_STEP
        if rho > 0.75:
            lam = 0.0 if lam < 1e-6 else lam / 4.0
        elif rho < 0.25:
            lam = max(2.0 * lam, 1e-6)
        if cost - cost_new <= 1e-12 * cost:
            return R, t, it, r, pc, A3, N, ss0, CONVERGED
        R, t, r, pc, cost, n_front = R_new, t_new, r_new, pc_new, cost_new, n_front_new
    A3 = design_kernel(R, W, c, pc)
    return R, t, max_iter, r, pc, A3, normal_kernel(A3, r)[0], ss0, MAX_ITER


@njit(cache=True, nogil=True, error_model="numpy")
def correction_kernel(xb, yb, K1, K2, K3, P1, P2, B1, B2, jacobian):
    """The Brown/Fraser correction (dx, dy) (n,) mm at (xb, yb) (n,) mm relative to the principal
    point, and with ``jacobian`` also d(x, y)/d(x_bar, y_bar) (n, 2, 2) (see ``BrownFraser``)."""
    n = xb.size
    dx, dy = np.empty(n), np.empty(n)
    J = np.empty((n if jacobian else 0, 2, 2))
    for i in range(n):
        dx[i], dy[i], j00, j01, j10, j11 = correction_point(xb[i], yb[i], K1, K2, K3, P1, P2, B1, B2)
        if jacobian:
            J[i, 0, 0], J[i, 0, 1], J[i, 1, 0], J[i, 1, 1] = j00, j01, j10, j11
    return dx, dy, J


@njit(cache=True, nogil=True, error_model="numpy")
def match_kernel(uv_pred, blob_uv, free, tol):
    """Per prediction (n, 2) px: the one free blob (``blob_uv`` (m, 2), ``free`` (m,)) closer than
    ``tol`` px, or -1 when there is none or more than one; then -1 also where two predictions
    got the same blob (``identify.match_predicted``). Through a grid of about one blob a cell, no
    smaller than ``tol`` (so a prediction's blobs lie in its cell's 3 x 3): a grid of tol-sized cells
    over a frame was 84 000 cells for 230 blobs, and clearing and summing them most of the call."""
    n, m = uv_pred.shape[0], blob_uv.shape[0]
    cand = np.full(n, -1, dtype=np.int64)
    if n == 0 or m == 0 or not tol > 0:
        return cand
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for j in range(m):
        x0, x1 = min(x0, blob_uv[j, 0]), max(x1, blob_uv[j, 0])
        y0, y1 = min(y0, blob_uv[j, 1]), max(y1, blob_uv[j, 1])
    size = max(tol, np.sqrt((x1 - x0 + 1.0) * (y1 - y0 + 1.0) / m))
    nx, ny = int((x1 - x0) / size) + 1, int((y1 - y0) / size) + 1
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    cell = np.full(m, -1, dtype=np.int64)
    for j in range(m):
        if free[j]:
            cell[j] = int((blob_uv[j, 1] - y0) / size) * nx + int((blob_uv[j, 0] - x0) / size)
            start[cell[j] + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    order, fill = np.empty(m, dtype=np.int64), start[:-1].copy()
    for j in range(m):
        if cell[j] >= 0:
            order[fill[cell[j]]] = j
            fill[cell[j]] += 1
    tol2 = tol * tol
    for i in range(n):
        u, v = uv_pred[i, 0], uv_pred[i, 1]
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        cx, cy = int(np.floor((u - x0) / size)), int(np.floor((v - y0) / size))
        count, best = 0, -1
        for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
            for gx in range(max(cx - 1, 0), min(cx + 2, nx)):
                k = gy * nx + gx
                for q in range(start[k], start[k + 1]):
                    j = order[q]
                    du, dv = blob_uv[j, 0] - u, blob_uv[j, 1] - v
                    if du * du + dv * dv < tol2:
                        count += 1
                        best = j
        if count == 1:
            cand[i] = best
    # a blob wanted by two predictions belongs to neither
    claims = np.zeros(m, dtype=np.int64)
    for i in range(n):
        if cand[i] >= 0:
            claims[cand[i]] += 1
    for i in range(n):
        if cand[i] >= 0 and claims[cand[i]] > 1:
            cand[i] = -1
    return cand


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel here for the types the product passes,
    so that no frame pays for it. Cheap after the first call in a process."""
    p = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [100.0, 100.0, 10.0]])
    xy = np.zeros((4, 2))
    W = np.repeat(np.eye(2)[None], 4, axis=0)
    R, t = np.eye(3), np.array([0.0, 0.0, -1000.0])
    r, pc, _, _ = residuals_kernel(R, t, p, xy, W, 12.0)
    A = design_kernel(R, W, 12.0, pc)
    N, _ = normal_kernel(A, r)
    point_statistics_kernel(r, A, np.eye(6), -1.0)
    adjust_kernel(R, t, p, xy, W, 12.0, 1000.0, 2)
    rotation_from_rotvec_kernel(np.zeros(3))
    rotvec_from_matrix_kernel(np.eye(3))  # also called alone (so3.rotvec_from_R of one matrix)
    predict_kernel(np.eye(4), np.eye(4), 1.0)
    pose_at_kernel(0.5, np.array([0.0, 1.0]), np.stack([np.eye(4), np.eye(4)]), 2.0)
    flange_kernel(np.eye(4), np.eye(4), np.eye(4), np.eye(4), True)
    whitened_ideal_kernel(xy, 1.0, 1.0, 0.0067, 0.0067, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    is_rigid_kernel(np.eye(4), 1e-6)
    scatter_kernel(p, xy)
    sensor_from_ideal_kernel(xy, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20)
    correction_kernel(xy[:, 0].copy(), xy[:, 1].copy(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, True)
    eccentricity_kernel(
        np.array([[1.0, 0.0, 0.0]]),
        np.array([[0.0, 1.0, 0.0]]),
        p,
        R,
        t,
        12.0,
        np.full(4, 3.0),
        np.repeat(np.eye(2)[None], 4, axis=0),
    )
    match_kernel(xy, xy + 1.0, np.ones(4, dtype=np.bool_), 4.0)
    project_kernel(R, t, p, 12.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0067, 0.0067, 1300, 1030, 0.0)
