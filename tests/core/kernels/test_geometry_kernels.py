"""The compiled per-point geometry (``service.core._kernels.geometry_kernels``) against references.

Each kernel is compared with the same quantity got another way: the Brown/Fraser correction
written as one numpy expression and differentiated by complex steps (exact to round-off, no
hand-written Jacobian), its inverse by ``scipy.optimize.root``, the projection by
``cv2.projectPoints``, the disk images' centres by fitting a conic to densely projected rim
points, the matching by ``scipy.spatial.cKDTree`` and the pose prediction by
``scipy.spatial.transform.Rotation``. Inputs are seeded and random, with the edge cases each
kernel meets in the product: no points, one point, points behind the camera, NaN, image borders.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.optimize import root
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.core._kernels.geometry_kernels import (
    correction_kernel,
    correction_point,
    eccentricity_kernel,
    flange_kernel,
    is_rigid_kernel,
    match_kernel,
    pose_at_kernel,
    predict_kernel,
    project_kernel,
    rotation_from_rotvec_kernel,
    rotvec_from_matrix_kernel,
    sensor_from_ideal_kernel,
    whitened_ideal_kernel,
)
from service.core.geometry.camera_model import BrownFraser

# The reference camera's coefficients (a real 12 mm lens) and a strong, made-up set in which
# every term (decentring, affinity) moves the corner points by tens of pixels.
COEFFICIENTS = {
    "lens": (-1.1e-3, 3.0e-6, -1.0e-8, 2.0e-5, -1.5e-5, 1.0e-4, -5.0e-5),
    "strong": (-3.0e-3, 2.0e-5, -1.0e-7, 3.0e-4, -2.0e-4, 2.0e-3, -1.0e-3),
}
SENSOR_MM = (4.36, 3.45)  # half the reference sensor (1300 x 1030 px of 6.7 um)
COMPLEX_STEP = 1e-30  # Im f(x + ih) / h is f'(x) to round-off for any h this small


def _correction(xb, yb, K1, K2, K3, P1, P2, B1, B2):
    """The Brown/Fraser correction (dx, dy), mm, of the paper's section 4.1, written plainly."""
    r2 = xb**2 + yb**2
    radial = K1 * r2 + K2 * r2**2 + K3 * r2**3
    dx = xb * radial + P1 * (r2 + 2 * xb**2) + 2 * P2 * xb * yb + B1 * xb + B2 * yb
    dy = yb * radial + 2 * P1 * xb * yb + P2 * (r2 + 2 * yb**2)
    return dx, dy


def _ideal_jacobian(xb, yb, k):
    """d(x + dx, y + dy)/d(x, y) (n, 2, 2) by complex steps: no derivative written by hand."""
    h = COMPLEX_STEP
    dxu, dyu = _correction(xb + 1j * h, yb + 0j, *k)
    dxv, dyv = _correction(xb + 0j, yb + 1j * h, *k)
    J = np.empty((len(xb), 2, 2))
    J[:, 0, 0], J[:, 0, 1] = 1 + dxu.imag / h, dxv.imag / h
    J[:, 1, 0], J[:, 1, 1] = dyu.imag / h, 1 + dyv.imag / h
    return J


def _sensor_points(rng, n):
    """Points (n, 2) mm over the whole sensor, corners included."""
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [0, 0]]) * SENSOR_MM
    return np.concatenate([corners, rng.uniform(-1, 1, (n, 2)) * SENSOR_MM])


# -- the Brown/Fraser correction and its inverse --------------------------------------------------


@pytest.mark.parametrize("kind", sorted(COEFFICIENTS))
def test_correction_and_its_jacobian_equal_the_formula_and_its_complex_step_derivative(rng, kind):
    k = COEFFICIENTS[kind]
    for n in (0, 1, 500):
        xy = _sensor_points(rng, n)[5:] if n < 5 else _sensor_points(rng, n)
        xb, yb = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
        dx, dy, J = correction_kernel(xb, yb, *k, True)
        dx_ref, dy_ref = _correction(xb, yb, *k)
        # the same polynomial, summed in another order: round-off of the ~0.2 mm correction
        np.testing.assert_allclose(dx, dx_ref, rtol=0, atol=1e-15)
        np.testing.assert_allclose(dy, dy_ref, rtol=0, atol=1e-15)
        # complex steps are exact to round-off; the entries are ~1, so 1e-14 absolute
        np.testing.assert_allclose(J, _ideal_jacobian(xb, yb, k), rtol=0, atol=1e-14)
        assert J.shape == (len(xb), 2, 2)
        assert correction_kernel(xb, yb, *k, False)[2].shape == (0, 2, 2)  # no Jacobian asked for


@pytest.mark.parametrize("kind", sorted(COEFFICIENTS))
def test_the_one_point_correction_is_the_reference_polynomial_and_its_jacobian(rng, kind):
    k = COEFFICIENTS[kind]
    xy = _sensor_points(rng, 40)
    dx_ref, dy_ref = _correction(xy[:, 0], xy[:, 1], *k)
    J_ref = _ideal_jacobian(xy[:, 0], xy[:, 1], k)
    for i, (x, y) in enumerate(xy):
        dx, dy, j00, j01, j10, j11 = correction_point(float(x), float(y), *k)
        assert abs(dx - dx_ref[i]) < 1e-15 and abs(dy - dy_ref[i]) < 1e-15
        np.testing.assert_allclose([[j00, j01], [j10, j11]], J_ref[i], rtol=0, atol=1e-14)


def test_correction_propagates_nan():
    xb, yb = np.array([np.nan, 1.0]), np.array([0.5, np.nan])
    dx, dy, J = correction_kernel(xb, yb, *COEFFICIENTS["lens"], True)
    assert np.all(np.isnan(dx)) and np.all(np.isnan(dy)) and np.all(np.isnan(J))


@pytest.mark.parametrize("kind", sorted(COEFFICIENTS))
def test_sensor_from_ideal_is_the_root_scipy_finds(rng, kind):
    k = COEFFICIENTS[kind]
    ideal = _sensor_points(rng, 150)
    got = sensor_from_ideal_kernel(ideal, *k, 20)
    ref = np.array(
        [
            root(lambda q, t=t: np.array(_correction(q[0], q[1], *k)) + q - t, t, method="hybr", tol=1e-15).x
            for t in ideal
        ]
    )
    # Newton stops below a 1e-12 mm step and hybr at a relative 1e-15: both at the root to ~1e-13 mm
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    # and the defining property, forward again: the ideal points to round-off
    dx, dy = _correction(got[:, 0], got[:, 1], *k)
    np.testing.assert_allclose(got + np.column_stack([dx, dy]), ideal, rtol=0, atol=1e-13)


def test_sensor_from_ideal_edge_cases():
    k = COEFFICIENTS["lens"]
    assert sensor_from_ideal_kernel(np.zeros((0, 2)), *k, 20).shape == (0, 2)
    target = np.array([[1.0, -2.0], [np.nan, 0.5]])
    np.testing.assert_array_equal(sensor_from_ideal_kernel(target, *k, 0), target)  # no step: the start
    got = sensor_from_ideal_kernel(target, *k, 20)
    assert np.all(np.isfinite(got[0])) and np.all(np.isnan(got[1]))
    np.testing.assert_array_equal(sensor_from_ideal_kernel(target[:1], *((0.0,) * 7), 20), target[:1])


@pytest.mark.parametrize("kind", sorted(COEFFICIENTS))
def test_whitened_ideal_is_the_ideal_point_and_the_inverse_of_its_pixel_jacobian(rng, kind):
    k = COEFFICIENTS[kind]
    width, height, pixel_u, pixel_v, x0, y0 = 1300, 1030, 0.0067, 0.0069, 0.031, -0.024
    cu, cv = (width - 1) / 2.0, (height - 1) / 2.0
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    uv = np.concatenate([corners, rng.uniform([-0.5, -0.5], [width - 0.5, height - 0.5], (400, 2))])
    xy, W = whitened_ideal_kernel(uv, cu, cv, pixel_u, pixel_v, x0, y0, *k)
    xb, yb = (uv[:, 0] - cu) * pixel_u - x0, (uv[:, 1] - cv) * pixel_v - y0
    dx, dy = _correction(xb, yb, *k)
    np.testing.assert_allclose(xy, np.column_stack([xb + dx, yb + dy]), rtol=0, atol=1e-14)  # mm
    J_pixel = _ideal_jacobian(xb, yb, k) * np.array([pixel_u, pixel_v])  # mm/px
    # W ~ 150 px/mm; the 2x2 inverse by cofactors and by LAPACK agree to ~1e-15 relative
    np.testing.assert_allclose(W, np.linalg.inv(J_pixel), rtol=1e-12, atol=0)
    empty = whitened_ideal_kernel(np.zeros((0, 2)), cu, cv, pixel_u, pixel_v, x0, y0, *k)
    assert empty[0].shape == (0, 2) and empty[1].shape == (0, 2, 2)


# -- rigid transforms and the pose prediction -----------------------------------------------------


def _is_rigid(T, tol):
    """The definition, with numpy: finite, R^T R = I and det R > 0, last row (0, 0, 0, 1)."""
    if not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.max(np.abs(R.T @ R - np.eye(3))) <= tol
        and np.linalg.det(R) > 0
        and np.max(np.abs(T[3] - [0, 0, 0, 1])) <= tol
    )


def test_is_rigid_agrees_with_the_definition(rng):
    tol = 1e-6
    results = []
    for k in range(400):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        T[:3, 3] = rng.uniform(-2000, 2000, 3)
        kind = k % 8
        if kind == 1:  # within the tolerance, or a hundred times beyond it
            T[:3, :3] += rng.normal(0, 0.01 * tol, (3, 3))
        elif kind == 2:
            T[:3, :3] += rng.normal(0, 100 * tol, (3, 3))
        elif kind == 3:  # a reflection
            T[:3, 0] *= -1
        elif kind == 4:  # a scale
            T[:3, :3] *= 1 + rng.choice([-1, 1]) * 10 * tol
        elif kind == 5:  # the last row
            T[3, rng.integers(4)] += rng.choice([0.01, 100]) * tol
        elif kind == 6:
            T[rng.integers(4), rng.integers(4)] = rng.choice([np.nan, np.inf, -np.inf])
        elif kind == 7:
            T[:3, :3] = 0.0
        expected = _is_rigid(T, tol)
        assert is_rigid_kernel(T, tol) == expected, (kind, T)
        results.append(expected)
    assert 0.2 < np.mean(results) < 0.5  # both answers were exercised


def _axis(rng):
    a = rng.normal(size=3)
    return a / np.linalg.norm(a)


def test_rotation_vector_kernels_are_scipys(rng):
    # (not imported outside _kernels, but predict_kernel is made of them)
    angles = np.concatenate(
        [[0.0, 1e-12, 1e-9, 1e-8, 1e-7, 1.0, np.pi - 1e-7, np.pi - 1e-3], rng.uniform(0, np.pi, 50)]
    )
    for theta in angles:
        w = theta * _axis(rng)
        R = rotation_from_rotvec_kernel(w)
        R_ref = Rotation.from_rotvec(w).as_matrix()
        # Rodrigues (its series below 1e-8 rad) and scipy's quaternion route: round-off of unit entries
        np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-15)
        got = rotvec_from_matrix_kernel(np.ascontiguousarray(R_ref))
        # near pi the rotation vector is +-pi n (both are the same rotation): compare the rotations,
        # to ~1e-15 / sin(theta) away from pi
        np.testing.assert_allclose(Rotation.from_rotvec(got).as_matrix(), R_ref, rtol=0, atol=1e-14)
        if theta < np.pi - 1e-4:
            np.testing.assert_allclose(got, Rotation.from_matrix(R_ref).as_rotvec(), rtol=0, atol=1e-13)


def test_predicted_pose_is_the_geodesic_extrapolation_scipy_computes(rng):
    for k in range(60):
        T0, T1 = np.eye(4), np.eye(4)
        T0[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        # the motion between frames: from none to a large turn (3 rad, near the geodesic's end)
        turn = [0.0, 1e-9, 1e-3, 0.3, 3.0][k % 5]
        T1[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(turn * _axis(rng)).as_matrix()
        T0[:3, 3], T1[:3, 3] = rng.uniform(-1000, 1000, (2, 3))
        for s in (0.0, 1.0, 0.37, -1.0, 2.5):
            T = predict_kernel(T0, T1, s)
            rel = Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).as_rotvec()
            R_ref = T1[:3, :3] @ Rotation.from_rotvec(s * rel).as_matrix()
            np.testing.assert_allclose(T[:3, :3], R_ref, rtol=0, atol=1e-13)  # unit entries, a few products
            np.testing.assert_allclose(T[:3, 3], T1[:3, 3] + s * (T1[:3, 3] - T0[:3, 3]), rtol=0, atol=1e-12)
            np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(predict_kernel(T0, T1, -1.0), T0, rtol=0, atol=1e-12)  # back to the start


# -- projection, eccentricity, matching -----------------------------------------------------------


def _pose(rng, view_angle_deg=40.0, distance_mm=1000.0):
    """T_field_camera looking at the field origin from ``distance_mm`` at a view angle."""
    az = rng.uniform(0, 2 * np.pi)
    tilt = np.radians(view_angle_deg)
    C = distance_mm * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    z = -C / np.linalg.norm(C)
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    R = R @ Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)]).as_matrix()
    return R, C


def _camera(kind):
    K1, K2, K3, P1, P2, B1, B2 = COEFFICIENTS[kind]
    return BrownFraser(1300, 1030, (0.0067, 0.0067), 12.0, 0.031, -0.024, K1, K2, K3, P1, P2, B1, B2)


def _project(camera, R, t, xyz, margin):
    return project_kernel(
        R,
        t,
        xyz,
        camera.c_mm,
        camera.K1,
        camera.K2,
        camera.K3,
        camera.P1,
        camera.P2,
        camera.B1,
        camera.B2,
        camera.x0_mm,
        camera.y0_mm,
        camera.pixel_size_mm[0],
        camera.pixel_size_mm[1],
        camera.width,
        camera.height,
        margin,
    )


def _field_points(rng, R, t, n, reach=1.25):
    """Field points (n, 3) mm whose pinhole images lie within ``reach`` times the sensor's half
    size (the lens model's domain, see the xfail below), 500-1500 mm deep."""
    xy = rng.uniform(-reach, reach, (n, 2)) * SENSOR_MM
    depth = rng.uniform(500, 1500, (n, 1))
    return np.column_stack([xy * depth / 12.0, depth]) @ R.T + t


@pytest.mark.parametrize("kind", sorted(COEFFICIENTS))
def test_projection_is_cv2_project_points_through_the_correction(rng, kind):
    camera = _camera(kind)
    for _ in range(5):
        R, t = _pose(rng, rng.uniform(0, 70))
        xyz = _field_points(rng, R, t, 300)
        xyz[:3] = [t + 1000 * R[:, 2], t - 500 * R[:, 2], t - 800 * R[:, 2] + 300 * R[:, 0]]  # on the axis, behind
        margin = rng.uniform(0, 20)
        uv, depth, inside = _project(camera, R, t, xyz, margin)
        rvec, tvec = cv2.Rodrigues(R.T)[0], -R.T @ t  # T_camera_field
        depth_ref = (xyz - t) @ R[:, 2]
        np.testing.assert_allclose(depth, depth_ref, rtol=1e-14, atol=1e-10)  # mm
        front = depth_ref > 0
        assert 0 < front.sum() < len(xyz)
        assert np.all(np.isnan(uv[~front])) and not np.any(inside[~front])
        K_mm = np.diag([camera.c_mm, camera.c_mm, 1.0])  # ideal coordinates, mm
        ideal = cv2.projectPoints(xyz[front], rvec, tvec, K_mm, None)[0].reshape(-1, 2)
        # the kernel's pixels, corrected (the forward direction): cv2's ideal points to the Newton
        # inverse's 1e-12 mm stop, plus round-off of the rotation through cv2.Rodrigues
        xb = (uv[front] - [(camera.width - 1) / 2, (camera.height - 1) / 2]) * camera.pixel_size_mm
        xb -= [camera.x0_mm, camera.y0_mm]
        dx, dy = _correction(xb[:, 0], xb[:, 1], *COEFFICIENTS[kind])
        np.testing.assert_allclose(xb + np.column_stack([dx, dy]), ideal, rtol=0, atol=1e-11)
        u, v = uv[front, 0], uv[front, 1]
        w, h = camera.width, camera.height
        inside_ref = (u >= -0.5 + margin) & (u <= w - 0.5 - margin) & (v >= -0.5 + margin) & (v <= h - 0.5 - margin)
        np.testing.assert_array_equal(inside[front], inside_ref)
        assert 0 < inside_ref.sum() < len(inside_ref)


def test_points_far_outside_the_field_of_view_are_never_reported_inside_the_image():
    camera = _camera("lens")  # the reference camera's own lens
    phi = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    for radius_mm in (9.0, 12.0, 20.0):
        xy = radius_mm * np.column_stack([np.cos(phi), np.sin(phi)])
        xyz = np.column_stack([xy * 1000.0 / camera.c_mm, np.full(len(phi), 1000.0)])
        _, _, inside = _project(camera, np.eye(3), np.zeros(3), xyz, 0.0)
        assert not inside.any(), f"{inside.sum()} points {radius_mm} mm off axis reported inside"


def test_projection_without_distortion_is_cv2s_pixels(rng):
    camera = BrownFraser(1300, 1030, (0.0067, 0.0071), 12.0, 0.031, -0.024)
    R, t = _pose(rng, 30.0)
    xyz = np.column_stack([rng.uniform(-300, 300, (200, 2)), np.zeros(200)])
    uv, _, _ = _project(camera, R, t, xyz, 0.0)
    px, py = camera.pixel_size_mm
    K_px = np.array(
        [
            [camera.c_mm / px, 0, (camera.width - 1) / 2 + camera.x0_mm / px],
            [0, camera.c_mm / py, (camera.height - 1) / 2 + camera.y0_mm / py],
            [0, 0, 1],
        ]
    )
    ref = cv2.projectPoints(xyz, cv2.Rodrigues(R.T)[0], -R.T @ t, K_px, None)[0].reshape(-1, 2)
    np.testing.assert_allclose(uv, ref, rtol=0, atol=1e-9)  # px: round-off of coordinates ~1000 px


def test_projection_edge_cases(rng):
    camera = _camera("lens")
    R, t = _pose(rng)
    uv, depth, inside = _project(camera, R, t, np.zeros((0, 3)), 0.0)
    assert uv.shape == (0, 2) and depth.shape == (0,) and inside.shape == (0,)
    xyz = np.array([[np.nan, 0.0, 0.0], t + [0.0, 0.0, 0.0]])  # NaN, and the projection centre (Z = 0)
    uv, depth, inside = _project(camera, R, t, xyz, 0.0)
    assert np.all(np.isnan(uv)) and not inside.any() and np.isnan(depth[0]) and depth[1] == 0.0
    # the principal point's ray lands on (x0, y0) off the sensor centre, inside by any sane margin
    on_axis = t + 800.0 * R[:, 2]
    uv, _, inside = _project(camera, R, t, on_axis[None], 0.0)
    np.testing.assert_allclose(uv[0], [649.5 + 0.031 / 0.0067, 514.5 - 0.024 / 0.0067], atol=1e-9)
    assert inside[0] and not _project(camera, R, t, on_axis[None], 520.0)[2][0]


def _conic_centre_ideal(R_cf, t_cf, c, centre, ex, ey, radius, n=720):
    """Centre (2,) mm of the image conic of a circle, from a least-squares conic through densely
    projected rim points: nothing of the homography's adjugate the kernel uses."""
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = centre + radius * (np.cos(phi)[:, None] * ex + np.sin(phi)[:, None] * ey)
    pc = rim @ R_cf.T + t_cf
    xy = c * pc[:, :2] / pc[:, 2:]
    m = xy.mean(axis=0)
    s = np.sqrt(np.mean(np.sum((xy - m) ** 2, axis=1)))
    x, y = ((xy - m) / s).T  # conditioned: centred and scaled to ~1
    A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, cc, d, e, _ = np.linalg.svd(A, full_matrices=False)[2][-1]
    centre_n = np.linalg.solve([[2 * a, b], [b, 2 * cc]], [-d, -e])
    return m + s * centre_n


def test_eccentricity_is_the_centre_of_the_projected_circle(rng):
    c = 12.0
    for per_disk in (False, True):
        for _ in range(4):
            R, C = _pose(rng, rng.uniform(0, 70), rng.uniform(500, 1500))
            R_cf, t_cf = np.ascontiguousarray(R.T), -R.T @ C
            n = 40
            p = np.column_stack([rng.uniform(-300, 300, (n, 2)), rng.uniform(-20, 20, n)])
            radius = rng.uniform(2.0, 10.0, n)
            if per_disk:  # each disk in its own plane, up to 50 deg off the field's
                normal = Rotation.from_rotvec(np.column_stack([rng.uniform(-0.9, 0.9, (n, 2)), np.zeros(n)])).apply(
                    [0.0, 0.0, 1.0]
                )
                ex = np.cross(normal, [1.0, 0.0, 0.0])
                ex /= np.linalg.norm(ex, axis=1, keepdims=True)
                ey = np.cross(normal, ex)
            else:
                ex, ey = np.array([[0.0, 1.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]])
            W = np.linalg.inv(np.eye(2) * 0.0067 + rng.normal(0, 2e-4, (n, 2, 2)))  # px/mm, a little skew
            got = eccentricity_kernel(np.ascontiguousarray(ex), np.ascontiguousarray(ey), p, R_cf, t_cf, c, radius, W)
            ref = np.empty((n, 2))
            for i in range(n):
                k = i if per_disk else 0
                pc = R_cf @ p[i] + t_cf
                off = _conic_centre_ideal(R_cf, t_cf, c, p[i], ex[k], ey[k], radius[i]) - c * pc[:2] / pc[2]
                ref[i] = W[i] @ off
            # offsets of 0.001-0.5 px. Checked against exact rational arithmetic (fractions) on these
            # scenes: the conic fit is good to 2e-11 px, the kernel's adjugate of H (entries ~c * 1500
            # mm multiplied and cancelled) to 1.4e-9 px, a millionth of the smallest offsets
            np.testing.assert_allclose(got, ref, rtol=0, atol=5e-9)
            assert np.max(np.abs(ref)) > 0.02  # the scenes do have a perspective offset


def test_eccentricity_edge_cases():
    ex, ey = np.array([[0.0, 1.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]])
    R, t = np.eye(3), np.array([0.0, 0.0, 1000.0])
    empty = eccentricity_kernel(ex, ey, np.zeros((0, 3)), R, t, 12.0, np.zeros(0), np.zeros((0, 2, 2)))
    assert empty.shape == (0, 2)
    # a disk face-on on the optical axis images as a circle about its centre's image: no offset
    one = eccentricity_kernel(ex, ey, np.zeros((1, 3)), R, t, 12.0, np.array([5.0]), np.eye(2)[None] / 0.0067)
    np.testing.assert_allclose(one, 0.0, atol=1e-12)


def _match_reference(uv_pred, blob_uv, free, tol):
    """One free blob strictly within ``tol`` (cKDTree, its radius made strict), and no blob for two."""
    cand = np.full(len(uv_pred), -1)
    idx_free = np.flatnonzero(free)
    if len(uv_pred) == 0 or len(idx_free) == 0 or not tol > 0:
        return cand
    tree = cKDTree(blob_uv[idx_free])
    for i, q in enumerate(uv_pred):
        if not np.all(np.isfinite(q)):
            continue
        near = [j for j in tree.query_ball_point(q, tol) if np.sum((blob_uv[idx_free[j]] - q) ** 2) < tol**2]
        if len(near) == 1:
            cand[i] = idx_free[near[0]]
    claimed = np.bincount(cand[cand >= 0], minlength=len(blob_uv))
    cand[(cand >= 0) & (claimed[np.maximum(cand, 0)] > 1)] = -1
    return cand


def test_matching_is_the_kd_tree_neighbour_search(rng):
    for k in range(30):
        m, n = [1, 5, 80, 400][k % 4], [1, 3, 60, 300][k // 8 % 4]
        blob_uv = rng.uniform(0, [1300, 1030], (m, 2))
        if k % 3 == 0:  # blobs at the image corners and on one row (a one-cell-high grid)
            blob_uv[: min(m, 2)] = [[0.0, 0.0], [1299.0, 1029.0]][: min(m, 2)]
            blob_uv[:, 1] = blob_uv[0, 1]
        near = blob_uv[rng.integers(0, m, n)] + rng.normal(0, 2.0, (n, 2))
        uv_pred = np.where(rng.random((n, 1)) < 0.7, near, rng.uniform(-100, 1400, (n, 2)))
        uv_pred[rng.random(n) < 0.05] = np.nan
        free = rng.random(m) < 0.85
        tol = rng.uniform(0.5, 40.0)
        got = match_kernel(uv_pred, blob_uv, free, tol)
        np.testing.assert_array_equal(got, _match_reference(uv_pred, blob_uv, free, tol))


def test_matching_edge_cases(rng):
    blob_uv = rng.uniform(0, 100, (10, 2))
    free = np.ones(10, dtype=bool)
    pred = blob_uv[:3] + 0.1
    assert match_kernel(np.zeros((0, 2)), blob_uv, free, 3.0).shape == (0,)
    np.testing.assert_array_equal(match_kernel(pred, np.zeros((0, 2)), np.zeros(0, bool), 3.0), -1)
    for tol in (0.0, -1.0, np.nan):
        np.testing.assert_array_equal(match_kernel(pred, blob_uv, free, tol), -1)
    np.testing.assert_array_equal(match_kernel(pred, blob_uv, np.zeros(10, bool), 3.0), -1)  # all taken
    two = np.array([[50.0, 50.0], [50.5, 50.0]])  # two blobs in reach: ambiguous, no match
    np.testing.assert_array_equal(match_kernel(np.array([[50.2, 50.0]]), two, np.ones(2, bool), 1.0), -1)
    both = np.array([[50.0, 50.0], [50.4, 50.0]])  # two predictions for one blob: neither gets it
    np.testing.assert_array_equal(match_kernel(both, two[:1], np.ones(1, bool), 1.0), [-1, -1])
    np.testing.assert_array_equal(match_kernel(both[:1], two[:1], np.ones(1, bool), 1.0), [0])


def _T(rng: np.random.Generator, scale_mm: float = 500.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-scale_mm, scale_mm, 3)
    return T


def _pose_at_reference(t, ts, Ts, max_gap):
    """The pairing's rules (``timesync.pose_at``) with scipy's Slerp for the rotation."""
    from scipy.spatial.transform import Slerp

    n = len(ts)
    if n == 0:
        return None
    k = int(np.searchsorted(ts, t, side="right"))
    if k == 0:
        return Ts[0] if ts[0] - t <= 1e-9 * max(1.0, abs(t)) else None
    if k == n:
        if n >= 2 and t - ts[-1] <= max_gap and ts[-1] - ts[-2] <= max_gap:
            a, b, s = Ts[-2], Ts[-1], (t - ts[-2]) / (ts[-1] - ts[-2])
        else:
            return Ts[-1] if t == ts[-1] else None
    else:
        if ts[k] - ts[k - 1] > max_gap:
            return None
        a, b, s = Ts[k - 1], Ts[k], (t - ts[k - 1]) / (ts[k] - ts[k - 1])
    step = Rotation.from_matrix(a[:3, :3]).inv() * Rotation.from_matrix(b[:3, :3])
    out = np.eye(4)
    if s <= 1.0:
        out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))(s).as_matrix()
    else:  # extrapolated along the same geodesic
        out[:3, :3] = (Rotation.from_matrix(a[:3, :3]) * Rotation.from_rotvec(s * step.as_rotvec())).as_matrix()
    out[:3, 3] = (1.0 - s) * a[:3, 3] + s * b[:3, 3]
    return out


def test_pose_at_kernel_follows_the_pairing_rules_and_slerp():
    rng = np.random.default_rng(11)
    ts = np.cumsum(rng.uniform(1.0, 3.0, 40))
    ts[20:] += 30.0  # a gap wider than max_gap
    # a slow motion: samples a few degrees apart, as a robot reports
    Ts = np.stack([_T(rng, 1.0) for _ in range(40)])
    base = _T(rng)
    for k in range(40):
        Ts[k] = (
            base @ Ts[k]
            if k == 0
            else Ts[k - 1]
            @ np.block(
                [
                    [Rotation.from_rotvec(rng.normal(0, 0.03, 3)).as_matrix(), rng.normal(0, 2, (3, 1))],
                    [np.zeros((1, 3)), 1],
                ]
            )
        )
    queries = np.concatenate([rng.uniform(ts[0] - 5, ts[-1] + 5, 300), ts, [ts[-1] + 1.0, ts[-1] + 10.0]])
    for t in queries:
        covered, T = pose_at_kernel(float(t), ts, Ts, 5.0)
        ref = _pose_at_reference(t, ts, Ts, 5.0)
        assert covered == (ref is not None), t
        if ref is not None:
            np.testing.assert_allclose(T, ref, rtol=0, atol=1e-9)
        else:
            np.testing.assert_array_equal(T, np.eye(4))
    assert pose_at_kernel(1.0, np.zeros(0), np.zeros((0, 4, 4)), 5.0)[0] is False


def test_flange_kernel_is_z_times_the_camera_times_x_inverse_and_its_deviation():
    rng = np.random.default_rng(12)
    for _ in range(50):
        Z, T_fc, X, T_rep = _T(rng), _T(rng), _T(rng, 100.0), _T(rng)
        T_m, dpos, dang, d = flange_kernel(Z, T_fc, X, T_rep, True)
        np.testing.assert_allclose(T_m, Z @ T_fc @ np.linalg.inv(X), rtol=0, atol=1e-9)
        np.testing.assert_allclose(d, T_m[:3, 3] - T_rep[:3, 3], rtol=0, atol=1e-12)
        assert dpos == pytest.approx(np.linalg.norm(d), abs=1e-12)
        ref = (Rotation.from_matrix(T_m[:3, :3]).inv() * Rotation.from_matrix(T_rep[:3, :3])).magnitude()
        assert dang == pytest.approx(ref, abs=1e-12)
        _, dpos0, dang0, d0 = flange_kernel(Z, T_fc, X, T_rep, False)  # no reported pose: no deviation
        assert dpos0 == dang0 == 0.0 and not d0.any()
    tiny = np.eye(4)
    tiny[:3, :3] = Rotation.from_rotvec([0.0, 1e-10, 0.0]).as_matrix()
    T_m = flange_kernel(Z, T_fc, X, T_rep, False)[0]
    assert flange_kernel(Z, T_fc, X, tiny @ T_m, True)[2] == pytest.approx(1e-10, rel=1e-4)
