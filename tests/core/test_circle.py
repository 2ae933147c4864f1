"""ISO 230-4 circular test on hand-built paths whose figures are known in closed form.

Every path lies in a tilted plane about a centre far from the origin, so that the plane fit and
the 2-D coordinates are exercised; the expected figures are derived in each test's comment, never
read back from the function.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.core.accuracy.circle import GRID_STEP_DEG, MIN_POINTS, CircleResult, circle_result
from service.core.geometry.so3 import R_from_rotvec
from service.core.results import Reason, SolveError

R_NOM = 300.0
C = np.array([400.0, -250.0, 900.0])
N_HAT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
# E1: the input x axis projected into the plane, which is the result's theta_zero_axis
E1 = np.array([1.0, 0.0, 0.0]) - N_HAT[0] * N_HAT
E1 /= np.linalg.norm(E1)
E2 = np.cross(N_HAT, E1)
TOL = 1e-9  # mm: "zero" for a noise-free path


def points(theta, r, centre=C, z=0.0):
    """Points (n, 3) at plane angles theta (n,) rad, radii r mm about centre, z mm along N_HAT."""
    theta = np.asarray(theta, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), theta.shape)
    z = np.broadcast_to(np.asarray(z, dtype=np.float64), theta.shape)
    u = np.cos(theta)[:, None] * E1 + np.sin(theta)[:, None] * E2
    return centre + r[:, None] * u + z[:, None] * N_HAT


def two_way(r_ccw, r_cw=None, n=720, centre_cw=C, z=None, theta=None, theta_cw=None):
    """One ccw lap (theta rising) then one cw lap (theta falling) of n points each, and their labels."""
    t = np.arange(n) * 2 * np.pi / n if theta is None else theta
    tc = -t if theta_cw is None else theta_cw
    r_cw = r_ccw if r_cw is None else r_cw
    zf = (lambda a: 0.0) if z is None else z
    p = np.vstack([points(t, r_ccw(t), z=zf(t)), points(tc, r_cw(tc), centre_cw, z=zf(tc))])
    return p, ["ccw"] * len(t) + ["cw"] * len(tc)


def circle(r):
    return lambda t: np.full_like(t, r)


def test_perfect_circle_in_a_tilted_plane_gives_zero_figures():
    p, d = two_way(circle(R_NOM))
    res = circle_result(p, d, R_NOM)
    for k in ("G_cw_mm", "G_ccw_mm", "G_bidirectional_mm", "H_mm", "F_max_mm", "F_min_mm"):
        assert abs(getattr(res, k)) < TOL, k
    assert abs(res.mean_radial_deviation_mm) < TOL
    assert res.G_mzc_cw_mm < TOL and res.G_mzc_ccw_mm < TOL and res.G_mzc_bidirectional_mm < TOL
    assert res.out_of_plane_span_mm < TOL and res.out_of_plane_rms_mm < TOL
    np.testing.assert_allclose(res.centre_mm, C, atol=TOL)
    np.testing.assert_allclose(res.centre_mzc_mm, C, atol=TOL)
    assert abs(res.radius_lsc_mm - R_NOM) < TOL
    # ccw runs counter-clockwise about N_HAT, so the oriented normal is +N_HAT (not -N_HAT)
    np.testing.assert_allclose(res.plane_normal, N_HAT, atol=1e-12)
    np.testing.assert_allclose(res.theta_zero_axis, E1, atol=1e-12)
    t = np.arange(720) * 2 * np.pi / 720
    np.testing.assert_allclose(res.theta_rad, np.mod(np.concatenate([t, -t]), 2 * np.pi), atol=1e-12)
    assert (res.n_cw, res.n_ccw) == (720, 720) and res.notes == ()
    assert res.orientation_deviation_max_deg is None and res.centre_offset_mm is None


def test_normal_follows_the_labels():
    # the same points with the labels swapped: now "ccw" runs the other way, so the normal flips
    p, d = two_way(circle(R_NOM))
    swapped = ["cw" if x == "ccw" else "ccw" for x in d]
    res = circle_result(p, swapped, R_NOM)
    np.testing.assert_allclose(res.plane_normal, -N_HAT, atol=1e-12)
    # theta is then measured the other way round: the ccw lap (now labelled cw) falls from 0
    assert abs(res.theta_rad[1] - (2 * np.pi - 2 * np.pi / 720)) < 1e-12


@pytest.mark.parametrize("dr", [0.2, -0.15])
def test_circle_of_radius_R_plus_d_deviates_by_d_everywhere(dr):
    p, d = two_way(circle(R_NOM + dr))
    res = circle_result(p, d, R_NOM)
    assert abs(res.mean_radial_deviation_mm - dr) < TOL
    assert abs(res.F_max_mm - dr) < TOL and abs(res.F_min_mm - dr) < TOL  # signed: F_min = d also for d > 0
    assert res.G_cw_mm < TOL and res.G_bidirectional_mm < TOL and res.H_mm < TOL
    np.testing.assert_allclose(res.radial_deviation_mm, dr, atol=TOL)


def test_ellipse_spans_twice_its_axis_difference():
    # x = (R + e) cos t, y = (R - e) sin t, t on a grid of 720 (a multiple of 4): the point set is
    # symmetric about both axes, so the LSC centre is the ellipse's centre; about it r runs from
    # R - e (t = 90 deg) to R + e (t = 0), so G = 2e, F_max = +e, F_min = -e exactly. The mean radius:
    # r = R sqrt(1 + 2x cos 2t + x^2), x = e/R, whose mean is R (1 + x^2/4 + O(x^4)).
    e = 0.5
    n = 720
    t = np.arange(n) * 2 * np.pi / n
    ell = C + (R_NOM + e) * np.cos(t)[:, None] * E1 + (R_NOM - e) * np.sin(t)[:, None] * E2
    p = np.vstack([ell, ell[::-1]])
    res = circle_result(p, ["ccw"] * n + ["cw"] * n, R_NOM)
    for g in (res.G_cw_mm, res.G_ccw_mm, res.G_bidirectional_mm, res.G_mzc_bidirectional_mm):
        assert abs(g - 2 * e) < TOL
    assert abs(res.F_max_mm - e) < TOL and abs(res.F_min_mm + e) < TOL
    np.testing.assert_allclose(res.centre_mm, C, atol=TOL)
    assert abs(res.mean_radial_deviation_mm - e**2 / (4 * R_NOM)) < 1e-8
    assert res.H_mm < TOL  # the same ellipse both ways


def test_centre_shift_between_directions_gives_hysteresis_s():
    # ccw: radius R about C; cw: radius R about C + d, |d| = s at angle phi. The point reflection
    # through C + d/2 swaps the two sampled circles (p -> 2m - p maps C + R u(a) onto
    # (C + d) + R u(a + pi), and the grid of angles is closed under + pi), so the common LSC centre
    # is m = C + d/2. About m a circle of radius R centred at o (relative to m) has, along u(theta),
    #     rho(theta) = o.u + sqrt(R^2 - |o|^2 + (o.u)^2).
    # For o = +d/2 (cw) and o = -d/2 (ccw) the square roots are equal, so
    #     r_cw(theta) - r_ccw(theta) = d.u(theta) = s cos(theta - phi)    exactly,
    # and H = s (not 2s: each profile moves by s/2, in opposite senses). The grid (0.5 deg) may
    # miss theta = phi by 0.25 deg: H >= s cos(0.25 deg) = s (1 - 9.5e-6), minus the linear
    # interpolation's error ~ (0.5 deg)^2 / 8 * s/2, another 5e-6 s. Each circle is exact about
    # its own centre (G = 0); all points span rho from R - s/2 to R + s/2 about m: G_bi = s.
    s, phi = 0.05, np.radians(37.0)
    dvec = s * (np.cos(phi) * E1 + np.sin(phi) * E2)
    p, d = two_way(circle(R_NOM), centre_cw=C + dvec)
    res = circle_result(p, d, R_NOM)
    assert s * (1 - 2e-5) < res.H_mm <= s + TOL
    assert abs(res.G_bidirectional_mm - s) < 1e-6  # the extreme points are sampled to within 0.5 deg
    assert abs(res.F_max_mm - s / 2) < 1e-6 and abs(res.F_min_mm + s / 2) < 1e-6
    assert res.G_cw_mm < TOL and res.G_ccw_mm < TOL
    assert abs(res.mean_radial_deviation_mm) < TOL
    np.testing.assert_allclose(res.centre_mm, C + dvec / 2, atol=TOL)
    np.testing.assert_allclose(res.centre_cw_mm, C + dvec, atol=TOL)
    np.testing.assert_allclose(res.centre_ccw_mm, C, atol=TOL)


def test_three_lobes_span_2a_and_a_phase_shift_shows_as_hysteresis():
    # r = R + a cos 3t: 3-fold symmetric, so the LSC centre is C and its radius the mean r = R;
    # max r - min r = 2a (t = 0 and 60 deg are on the 0.5 deg grid); the zone touches 3 outer and 3
    # inner points alternately, so the minimum zone is the same. With cw lobes turned by psi,
    # |a cos 3t - a cos(3t + psi)| = 2a |sin(3t + psi/2) sin(psi/2)| peaks at 2a sin(psi/2) = a for
    # psi = 60 deg (grid and interpolation lose < 2e-4 a: 9 a (0.5 deg)^2 / 8 and 1 - cos 0.75 deg).
    a, psi = 0.08, np.radians(60.0)
    p, d = two_way(lambda t: R_NOM + a * np.cos(3 * t), lambda t: R_NOM + a * np.cos(3 * t + psi))
    res = circle_result(p, d, R_NOM)
    for g in (res.G_cw_mm, res.G_ccw_mm, res.G_bidirectional_mm, res.G_mzc_ccw_mm, res.G_mzc_bidirectional_mm):
        assert abs(g - 2 * a) < 1e-9
    assert abs(res.F_max_mm - a) < TOL and abs(res.F_min_mm + a) < TOL
    assert abs(res.mean_radial_deviation_mm) < TOL
    np.testing.assert_allclose(res.centre_mm, C, atol=TOL)
    assert a * (1 - 2e-4) < res.H_mm <= a + TOL


def test_out_of_plane_sine_is_measured_and_leaves_the_plane_figures_alone():
    # z = b sin 2t is orthogonal (over the grid) to 1, cos t, sin t: the least-squares plane is the
    # circle's own plane, so the projection leaves x, y unchanged and every in-plane figure is exact
    # (unaffected to all orders, not only the second). Span of z: 2b (t = 45, 135 deg sampled);
    # RMS: b / sqrt(2).
    b = 0.3
    p, d = two_way(circle(R_NOM), z=lambda t: b * np.sin(2 * t))
    res = circle_result(p, d, R_NOM)
    assert abs(res.out_of_plane_span_mm - 2 * b) < TOL
    assert abs(res.out_of_plane_rms_mm - b / np.sqrt(2)) < TOL
    t = np.arange(720) * 2 * np.pi / 720
    np.testing.assert_allclose(res.out_of_plane_mm, b * np.sin(2 * np.concatenate([t, -t])), atol=TOL)
    np.testing.assert_allclose(res.plane_normal, N_HAT, atol=1e-12)
    for k in ("G_cw_mm", "G_ccw_mm", "G_bidirectional_mm", "H_mm", "F_max_mm", "F_min_mm"):
        assert abs(getattr(res, k)) < TOL, k


def test_orientation_wobble_gives_its_amplitude_and_rms():
    # R_i = R0 exp(alpha sin(t_i + 10 deg) [k]x), so that no R_i is R0 itself: the mean of
    # exp(alpha sin t' [k]x) over the even grid is I + mean(sin(alpha sin t')) [k]x
    # + mean(1 - cos(alpha sin t')) [k]x^2, whose sin term vanishes (odd about t' = 0) and whose
    # nearest rotation is I; so the chordal mean is R0 and the angle of each R_i from it is
    # alpha |sin t'_i|: max alpha (t' = 90 deg is on the grid), RMS alpha / sqrt(2).
    alpha = np.radians(0.4)
    R0 = R_from_rotvec([0.3, -1.1, 2.0])
    k = np.array([0.2, 0.9, -0.4]) / np.linalg.norm([0.2, 0.9, -0.4])
    p, d = two_way(circle(R_NOM))
    t = np.concatenate([np.arange(720), -np.arange(720)]) * 2 * np.pi / 720 + np.radians(10.0)
    Rs = R0 @ R_from_rotvec(alpha * np.sin(t)[:, None] * k)
    res = circle_result(p, d, R_NOM, R=Rs)
    assert abs(res.orientation_deviation_max_deg - 0.4) < 1e-9
    assert abs(res.orientation_deviation_rms_deg - 0.4 / np.sqrt(2)) < 1e-9
    np.testing.assert_allclose(res.orientation_deviation_deg, 0.4 * np.abs(np.sin(t)), atol=1e-9)
    # a coning wobble (constant tilt alpha about an axis turning in R0's x-y plane): every angle alpha
    axes = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    res = circle_result(p, d, R_NOM, R=R0 @ R_from_rotvec(alpha * axes))
    assert abs(res.orientation_deviation_max_deg - 0.4) < 1e-9
    assert abs(res.orientation_deviation_rms_deg - 0.4) < 1e-9


def test_a_tool_turning_along_the_path_is_measured_against_the_robots_orientation():
    # the command turns the tool by up to 8 deg along the circle (a camera kept aimed at a plate);
    # the arm follows it with a constant 0.3 deg offset (hand-eye, base) and the same 0.4 deg
    # wobble as above: only the wobble is the deviation along the path
    alpha, R0 = np.radians(0.4), R_from_rotvec([0.3, -1.1, 2.0])
    k = np.array([0.2, 0.9, -0.4]) / np.linalg.norm([0.2, 0.9, -0.4])
    p, d = two_way(circle(R_NOM))
    t = np.concatenate([np.arange(720), -np.arange(720)]) * 2 * np.pi / 720 + np.radians(10.0)
    R_cmd = R0 @ R_from_rotvec(np.radians(8.0) * np.stack([np.cos(t), np.sin(t), 0 * t], axis=1))
    offset = R_from_rotvec(np.radians(0.3) * np.array([0.0, 0.6, 0.8]))
    Rs = R_cmd @ offset @ R_from_rotvec(alpha * np.sin(t)[:, None] * k)
    against_the_robot = circle_result(p, d, R_NOM, R=Rs, R_robot=R_cmd)
    assert abs(against_the_robot.orientation_deviation_max_deg - 0.4) < 1e-9
    np.testing.assert_allclose(against_the_robot.orientation_deviation_deg, 0.4 * np.abs(np.sin(t)), atol=1e-9)
    alone = circle_result(p, d, R_NOM, R=Rs)  # without the command, the turning counts: ~8 deg
    assert alone.orientation_deviation_max_deg > 7.0


def test_centre_offset_from_the_nominal_centre_in_plane_and_along_the_normal():
    shift_in, shift_n = 0.7 * (0.6 * E1 - 0.8 * E2), -0.25 * N_HAT  # 0.7 mm in the plane, -0.25 along n
    p, d = two_way(circle(R_NOM))
    res = circle_result(p, d, R_NOM, centre_mm=C - shift_in - shift_n)
    np.testing.assert_allclose(res.centre_offset_mm, shift_in + shift_n, atol=TOL)
    assert abs(res.centre_offset_in_plane_mm - 0.7) < TOL
    assert abs(res.centre_offset_normal_mm + 0.25) < TOL
    assert abs(res.F_max_mm) < TOL  # F is about the measured (LSC) centre, not the nominal one


def test_robot_deviation_is_the_distance_to_the_reported_positions():
    # reported = measured + a |sin t| along a fixed direction: max a, RMS a / sqrt(2)
    a = 1.3
    p, d = two_way(circle(R_NOM))
    t = np.concatenate([np.arange(720), -np.arange(720)]) * 2 * np.pi / 720
    v = np.array([0.48, 0.6, 0.64])
    res = circle_result(p, d, R_NOM, p_robot_mm=p + a * np.sin(t)[:, None] * v)
    assert abs(res.robot_deviation_max_mm - a) < 1e-9
    assert abs(res.robot_deviation_rms_mm - a / np.sqrt(2)) < 1e-9


def test_uneven_spacing_changes_nothing_on_a_circle_and_keeps_h_of_a_shift():
    # a perfect circle is fitted exactly whatever the spacing, and r(theta) = R + d is constant, so
    # linear interpolation is exact: G = H = 0, F = mean = d. The shifted pair (test above) has
    # r_cw - r_ccw = s cos(theta - phi) + O(s eps / R), eps = |common centre - midpoint| <= s/2
    # now that the point reflection no longer holds: |H - s| < 1e-3 s with R = 300, s = 0.05.
    u = np.arange(240) * 2 * np.pi / 240
    t_ccw, t_cw = u + 0.3 * np.sin(u), -(u + 0.25 * np.sin(2 * u + 1.0))
    dr = 0.12
    p, d = two_way(circle(R_NOM + dr), theta=t_ccw, theta_cw=t_cw)
    res = circle_result(p, d, R_NOM)
    assert res.G_cw_mm < TOL and res.G_ccw_mm < TOL and res.G_bidirectional_mm < TOL and res.H_mm < TOL
    assert abs(res.F_max_mm - dr) < TOL and abs(res.F_min_mm - dr) < TOL
    assert abs(res.mean_radial_deviation_mm - dr) < TOL
    np.testing.assert_allclose(res.centre_mm, C, atol=TOL)
    s = 0.05
    p, d = two_way(circle(R_NOM), centre_cw=C + s * E2, theta=t_ccw, theta_cw=t_cw)
    assert abs(circle_result(p, d, R_NOM).H_mm - s) < 1e-3 * s


def test_hysteresis_only_where_both_directions_cover_the_angle():
    # one curve r = R + a cos 2t about C: ccw a full lap, cw only the arc 60..120 deg, at angles
    # between the ccw ones. About any centre both directions sample the same profile, so where both
    # exist they differ only by the linear interpolation's error, 4a (0.5 deg)^2 / 8 = 4e-5 a.
    # Across the cw gap (120 deg round to 60 deg) its profile would be the chord between its ends,
    # r = R - a/2, against the ccw R + a at t = 0: 1.5 a, less the ~10 % that the common centre
    # moves towards the arc (1.35 a). Counting that 300 deg gap as covered (max_gap_deg 330) shows it.
    a = 0.1
    t_arc = np.radians(np.arange(120.25, 59.9, -0.5))  # cw: falling angles
    p, d = two_way(lambda t: R_NOM + a * np.cos(2 * t), theta_cw=t_arc)
    assert circle_result(p, d, R_NOM).H_mm < 2e-4 * a
    assert 1.2 * a < circle_result(p, d, R_NOM, max_gap_deg=330.0).H_mm < 1.8 * a


def test_hysteresis_of_a_shift_over_part_of_the_circle():
    # ccw: a full lap about C; cw: only the arc 60..120 deg, about C + s E1. The difference is
    # s cos(theta) + O(s^2 / R) wherever both exist: at most s cos 60 = s/2 at the arc's ends (the
    # grid may stop 0.5 deg short: s cos 60.5 = 0.4924 s); a full cw lap would give s.
    s = 0.05
    t_arc = np.radians(np.arange(120.0, 59.9, -0.5))  # cw: falling angles
    p, d = two_way(circle(R_NOM), lambda t: np.full_like(t, R_NOM), centre_cw=C + s * E1, theta_cw=t_arc)
    res = circle_result(p, d, R_NOM)
    assert 0.49 * s < res.H_mm < 0.5 * s + 1e-6
    assert res.G_cw_mm < TOL and res.G_ccw_mm < TOL


def test_directions_with_no_common_angle_have_no_hysteresis():
    t1, t2 = np.radians(np.arange(0.0, 90.1, 1.0)), np.radians(np.arange(270.0, 179.9, -1.0))
    p, d = two_way(circle(R_NOM), theta=t1, theta_cw=t2)
    res = circle_result(p, d, R_NOM)
    assert res.H_mm is None and any("share no angle" in n for n in res.notes)
    assert res.G_cw_mm < TOL and res.G_bidirectional_mm < TOL  # the arcs still fit


def test_single_bump_minimum_zone_halves_the_bump_shift():
    # n points on a circle, one pushed out by h at t = 0, spacing D = 2 pi / n. Linearised
    # (r_i(c + delta) = r_i - u_i.delta), a shift delta along the bump gives the span
    # max(h - delta, delta) + delta cos D, smallest at delta = h/2: the minimum zone is
    # h (1 + cos D) / 2 about C + (h/2) u_0. The LSC moves by only 2h/n (normal equations), so its
    # span is h - (2h/n)(1 - cos D). With h = 0.01, n = 24 (D = 15 deg): 0.98296 h vs 0.99716 h;
    # the linearisation errs by ~ delta^2 / R = 2.5e-7 mm. One direction only (ccw).
    h, n = 0.01, 24
    t = np.arange(n) * 2 * np.pi / n
    r = np.full(n, R_NOM)
    r[0] += h
    res = circle_result(points(t, r), ["ccw"] * n, R_NOM)
    D = 2 * np.pi / n
    assert abs(res.G_mzc_ccw_mm - h * (1 + np.cos(D)) / 2) < 2e-6
    assert abs(res.G_ccw_mm - (h - 2 * h / n * (1 - np.cos(D)))) < 2e-6
    np.testing.assert_allclose(res.centre_mzc_mm, C + h / 2 * E1, atol=1e-5)
    assert res.G_mzc_bidirectional_mm is None and res.G_cw_mm is None


def test_noisy_circle_figures_within_noise_bands(rng):
    # isotropic 3-D noise sigma on a circle of radius R + dr, 720 points a direction: the radial
    # and normal components are N(0, sigma^2) each (to O(sigma^2 / R)). The expected range of 720
    # normal samples is ~6.3 sigma (1440: ~6.6), their maximum ~3.2 sigma; H is the maximum of
    # |difference of two profiles| (variance ~2 sigma^2 at the grid points, which lie on the points):
    # ~3.3 * 1.4 = 4.6 sigma; the LSC radius is off by sigma / sqrt(720).
    sigma, dr = 0.002, 0.01
    p, d = two_way(circle(R_NOM + dr))
    res = circle_result(p + rng.normal(0.0, sigma, p.shape), d, R_NOM)
    assert 4.5 * sigma < res.G_cw_mm < 8.5 * sigma
    assert 4.5 * sigma < res.G_ccw_mm < 8.5 * sigma
    assert 5.0 * sigma < res.G_bidirectional_mm < 9.0 * sigma
    assert 2.5 * sigma < res.H_mm < 7.0 * sigma
    assert 2.0 * sigma < res.F_max_mm - dr < 4.5 * sigma
    assert 2.0 * sigma < dr - res.F_min_mm < 4.5 * sigma
    assert abs(res.mean_radial_deviation_mm - dr) < 0.15 * sigma
    assert 0.9 * sigma < res.out_of_plane_rms_mm < 1.1 * sigma
    assert 5.0 * sigma < res.out_of_plane_span_mm < 9.0 * sigma
    assert np.linalg.norm(res.centre_mm - C) < 0.3 * sigma
    # the minimum zone is no wider than the LSC's, and noise leaves it little to gain
    assert 0.8 * res.G_bidirectional_mm < res.G_mzc_bidirectional_mm <= res.G_bidirectional_mm + 1e-12


def test_noisy_ellipse_keeps_its_span_within_the_noise(rng):
    # G = 2e plus the noise at the extremes: within [2e - 2 sigma, 2e + 7 sigma] for 720 points
    sigma, e = 0.001, 0.05
    n = 720
    t = np.arange(n) * 2 * np.pi / n
    ell = C + (R_NOM + e) * np.cos(t)[:, None] * E1 + (R_NOM - e) * np.sin(t)[:, None] * E2
    p = np.vstack([ell, ell[::-1]]) + rng.normal(0.0, sigma, (2 * n, 3))
    res = circle_result(p, ["ccw"] * n + ["cw"] * n, R_NOM)
    assert 2 * e - 2 * sigma < res.G_bidirectional_mm < 2 * e + 7 * sigma
    assert e - sigma < res.F_max_mm < e + 4.5 * sigma
    assert -e - 4.5 * sigma < res.F_min_mm < -e + sigma
    assert np.linalg.norm(res.centre_mm - C) < 0.5 * sigma


def test_one_direction_missing_gives_none_and_says_why():
    dr = 0.1
    n = 90
    t = np.arange(n) * 2 * np.pi / n
    p = points(t, R_NOM + dr)
    res = circle_result(p, np.zeros(n, dtype=bool), R_NOM)  # bools: True = cw, so all ccw
    assert res.G_cw_mm is None and res.G_bidirectional_mm is None and res.H_mm is None
    assert res.G_ccw_mm < TOL and abs(res.F_max_mm - dr) < TOL and abs(res.mean_radial_deviation_mm - dr) < TOL
    assert any("no cw points" in x for x in res.notes)
    with pytest.raises(SolveError) as e:
        circle_result(p, ["ccw"] * n, R_NOM, require_both=True)
    assert e.value.reason == Reason.bad_input and "both directions" in e.value.message


def test_bool_labels_and_string_labels_agree():
    p, d = two_way(lambda t: R_NOM + 0.05 * np.cos(2 * t), n=120)
    a = circle_result(p, d, R_NOM)
    b = circle_result(p, np.array([x == "cw" for x in d]), R_NOM)
    c = circle_result(p, [x.upper() for x in d], R_NOM)
    assert a.to_dict() == b.to_dict() == c.to_dict()


def test_to_dict_carries_the_design_keys_and_the_conditions():
    p, d = two_way(lambda t: R_NOM + 0.05 * np.cos(3 * t), n=120)
    res = circle_result(p, d, R_NOM, centre_mm=C)
    out = json.loads(json.dumps(res.to_dict(points=True)))
    for k in ("G_cw_mm", "G_ccw_mm", "G_bidirectional_mm", "H_mm", "F_max_mm", "F_min_mm", "mean_radial_deviation_mm"):
        assert out[k] == pytest.approx(getattr(res, k), abs=1e-6)
    assert out["G_cw_mm"] == pytest.approx(0.1, abs=1e-6)
    cond = out["conditions"]
    assert cond["radius_mm"] == R_NOM and cond["n_cw"] == 120 and cond["n_ccw"] == 120
    assert cond["plane_normal"] == pytest.approx(N_HAT.tolist(), abs=1e-9)
    assert cond["centre_mm"] == pytest.approx(C.tolist(), abs=1e-6)
    assert cond["grid_step_deg"] == GRID_STEP_DEG <= 1.0
    pts = out["points"]
    assert len(pts["theta_deg"]) == len(pts["radial_deviation_mm"]) == len(pts["direction"]) == 240
    assert pts["direction"][:2] == ["ccw", "ccw"] and pts["orientation_deviation_deg"] is None
    assert max(pts["radial_deviation_mm"]) == pytest.approx(0.05, abs=1e-6)
    assert "points" not in res.to_dict()
    assert isinstance(res, CircleResult)


def test_too_few_points_in_a_direction_is_refused():
    p, d = two_way(circle(R_NOM), n=60)
    keep = np.r_[np.arange(60), 60 + np.arange(MIN_POINTS - 1)]  # 7 cw points
    with pytest.raises(SolveError) as e:
        circle_result(p[keep], np.asarray(d)[keep], R_NOM)
    assert e.value.reason == Reason.bad_input and "7 cw points" in e.value.message
    keep = np.r_[np.arange(60), 60 + np.arange(MIN_POINTS)]  # 8 are enough
    assert circle_result(p[keep], np.asarray(d)[keep], R_NOM).G_cw_mm < TOL


@pytest.mark.parametrize(
    "path",
    [
        np.linspace([0.0, 0.0, 0.0], [100.0, 50.0, 20.0], 40),  # a line
        np.tile([10.0, 20.0, 30.0], (40, 1)),  # one point
    ],
    ids=["collinear", "coincident"],
)
def test_degenerate_path_is_refused(path):
    with pytest.raises(SolveError) as e:
        circle_result(path, ["ccw"] * 20 + ["cw"] * 20, R_NOM)
    assert e.value.reason == Reason.degenerate_geometry


def test_a_direction_on_a_line_is_refused():
    # the cw points on a chord, the ccw points on the circle: the plane exists, the cw circle does not
    t = np.arange(60) * 2 * np.pi / 60
    chord = np.linspace(C + R_NOM * E1, C + R_NOM * E2, 20)
    p = np.vstack([points(t, R_NOM), chord])
    with pytest.raises(SolveError) as e:
        circle_result(p, ["ccw"] * 60 + ["cw"] * 20, R_NOM)
    assert e.value.reason == Reason.degenerate_geometry and "cw points" in e.value.message


def test_labels_turning_the_same_way_are_refused():
    t = np.arange(60) * 2 * np.pi / 60
    p = np.vstack([points(t, R_NOM), points(t, R_NOM)])  # both laps ccw
    with pytest.raises(SolveError) as e:
        circle_result(p, ["ccw"] * 60 + ["cw"] * 60, R_NOM)
    assert e.value.reason == Reason.bad_input and "same way" in e.value.message


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"p_mm": np.zeros((20, 2))}, "shape"),
        ({"direction": ["cw"] * 19}, "one label per point"),
        ({"direction": ["cw"] * 10 + ["up"] * 10}, "'cw' or 'ccw'"),
        ({"radius_mm": 0.0}, "radius_mm"),
        ({"R": np.zeros((19, 3, 3))}, "R must have shape"),
        ({"centre_mm": [1.0, 2.0]}, "centre_mm"),
        ({"p_mm": np.full((20, 3), np.nan)}, "NaN or infinity"),
    ],
)
def test_malformed_input_is_bad_input_with_a_sentence(kwargs, match):
    t = np.arange(10) * 2 * np.pi / 10
    args = {"p_mm": points(np.r_[t, -t], R_NOM), "direction": ["ccw"] * 10 + ["cw"] * 10, "radius_mm": R_NOM}
    args.update(kwargs)
    with pytest.raises(SolveError, match=match) as e:
        circle_result(**args)
    assert e.value.reason is Reason.bad_input
