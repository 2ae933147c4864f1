"""ISO 9283 pose characteristics on hand-built cycle sets whose answers are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.accuracy import iso9283 as I
from service.core.geometry.frames import R_from_kuka_abc_deg, kuka_abc_deg_from_R
from service.core.results import Reason, SolveError

CMD = np.array([1000.0, -200.0, 800.0])
ABC_CMD = np.array([30.0, 20.0, 10.0])


def standardised(rng, n):
    """n values with mean exactly 0 and (n - 1) standard deviation exactly 1."""
    z = rng.normal(size=n)
    return (z - z.mean()) / z.std(ddof=1)


def triples(rng, radii):
    """Offsets (3 per radius) at 120 deg in a random plane: each triple sums to 0, each is r from 0."""
    out = []
    for r in radii:
        u, v = np.linalg.qr(rng.normal(size=(3, 2)))[0].T
        out += [r * (math.cos(t) * u + math.sin(t) * v) for t in (0.0, 2 * math.pi / 3, 4 * math.pi / 3)]
    return np.array(out)


def angles(rng, n, means, stds, abc_cmd=ABC_CMD):
    """(n, 3) attained A, B, C deg whose differences from the command have these exact means and stds."""
    return abc_cmd + np.array([m + s * standardised(rng, n) for m, s in zip(means, stds)]).T


def test_pose_accuracy_is_the_barycentre_offset_and_repeatability_mean_plus_3_sigma(rng):
    b = CMD + [0.3, -0.4, 1.2]  # |b - cmd| = 1.3
    xyz = b + triples(rng, [0.1] * 5 + [0.3] * 5)  # 30 cycles: 15 at 0.1 mm, 15 at 0.3 mm from b
    s = I.pose_series("P1", CMD, ABC_CMD, xyz, np.tile(ABC_CMD, (30, 1)))
    c = I.pose_characteristics(s)
    assert c.n == 30
    assert c.AP_p_mm == pytest.approx(1.3, abs=1e-9)
    assert (c.AP_x_mm, c.AP_y_mm, c.AP_z_mm) == pytest.approx((0.3, -0.4, 1.2), abs=1e-9)
    # l = 0.1 or 0.3, 15 each: mean 0.2, S_l^2 = 30 * 0.1^2 / 29
    assert c.RP_l_mm == pytest.approx(0.2 + 3 * math.sqrt(0.3 / 29), abs=1e-9)
    assert (c.AP_a_deg, c.AP_b_deg, c.AP_c_deg, c.RP_a_deg) == pytest.approx((0, 0, 0, 0), abs=1e-9)


def test_orientation_accuracy_and_repeatability_follow_the_angle_mean_and_std(rng):
    abc = angles(rng, 30, means=(0.05, -0.02, 0.1), stds=(0.01, 0.005, 0.02))
    c = I.pose_characteristics(I.pose_series("P2", CMD, ABC_CMD, np.tile(CMD, (30, 1)), abc))
    assert (c.AP_a_deg, c.AP_b_deg, c.AP_c_deg) == pytest.approx((0.05, -0.02, 0.1), abs=1e-9)
    assert (c.RP_a_deg, c.RP_b_deg, c.RP_c_deg) == pytest.approx((0.03, 0.015, 0.06), abs=1e-9)
    assert c.AP_p_mm == pytest.approx(0.0, abs=1e-12) and c.RP_l_mm == pytest.approx(0.0, abs=1e-12)
    assert c.gimbal_margin_deg == pytest.approx(70.0, abs=1e-9)


def test_angle_deviations_wrap_around_at_plus_minus_180(rng):
    abc_cmd = np.array([179.95, 5.0, -179.9])
    abc = angles(rng, 30, means=(0.1, 0.0, -0.15), stds=(0.02, 0.001, 0.01), abc_cmd=abc_cmd)
    canonical = kuka_abc_deg_from_R(R_from_kuka_abc_deg(abc))
    assert (canonical[:, 0] < 0).all() and (canonical[:, 2] > 0).all()  # the attained ones did wrap
    for cmd in (abc_cmd, abc_cmd + [-360.0, 0.0, 360.0]):  # the command's own spelling does not matter
        c = I.pose_characteristics(I.pose_series("P3", CMD, cmd, np.tile(CMD, (30, 1)), canonical))
        assert (c.AP_a_deg, c.AP_b_deg, c.AP_c_deg) == pytest.approx((0.1, 0.0, -0.15), abs=1e-9)
        assert (c.RP_a_deg, c.RP_c_deg) == pytest.approx((0.06, 0.03), abs=1e-9)


def test_matrices_and_kuka_angles_give_the_same_figures(rng):
    xyz = CMD + triples(rng, [0.05, 0.1, 0.2, 0.15])
    abc = angles(rng, 12, means=(0.01, 0.02, 0.03), stds=(0.01, 0.01, 0.01))
    a = I.pose_characteristics(I.pose_series("P1", CMD, ABC_CMD, xyz, abc)).to_dict()
    b = I.pose_characteristics(
        I.pose_series("P1", CMD, R_from_kuka_abc_deg(ABC_CMD), xyz, R_from_kuka_abc_deg(abc))
    ).to_dict()
    assert a.keys() == b.keys()
    assert all(a[k] == pytest.approx(b[k], abs=1e-9) for k in a)


def test_euler_differences_swing_near_the_gimbal_singularity():
    # the weakness the module names: 0.01 deg of rotation at B = 89.9 deg moves A and C by degrees
    R_cmd = R_from_kuka_abc_deg([0.0, 89.9, 0.0])
    R = np.array([R_cmd @ Rotation.from_rotvec([0.0, 0.0, s * 1e-2], degrees=True).as_matrix() for s in (1, -1)])
    c = I.pose_characteristics(I.pose_series("P1", CMD, R_cmd, np.tile(CMD, (2, 1)), R))
    assert c.gimbal_margin_deg == pytest.approx(0.1, abs=1e-9)
    assert c.RP_a_deg > 100 * 1e-2 and c.RP_c_deg > 100 * 1e-2


def test_two_approach_directions_give_the_distance_of_their_barycentres(rng):
    b1, b2 = CMD + [0.1, 0.0, 0.0], CMD + [-0.2, 0.4, 0.0]  # 0.5 mm apart
    xyz1, xyz2 = b1 + triples(rng, [0.1] * 5), b2 + triples(rng, [0.2] * 5)
    abc1 = angles(rng, 15, means=(0.03, 0.0, 0.05), stds=(0.01, 0.01, 0.01))
    abc2 = angles(rng, 15, means=(-0.01, 0.02, 0.05), stds=(0.01, 0.01, 0.01))
    xyz, abc = np.empty((30, 3)), np.empty((30, 3))
    xyz[0::2], xyz[1::2], abc[0::2], abc[1::2] = xyz1, xyz2, abc1, abc2  # interleaved: grouped by label
    c = I.pose_characteristics(I.pose_series("P1", CMD, ABC_CMD, xyz, abc, approach=["+x", "-y"] * 15))
    assert c.vAP_p_mm == pytest.approx(0.5, abs=1e-9)
    assert (c.vAP_a_deg, c.vAP_b_deg, c.vAP_c_deg) == pytest.approx((0.04, 0.02, 0.0), abs=1e-9)
    assert (c.AP_x_mm, c.AP_y_mm, c.AP_z_mm) == pytest.approx((-0.05, 0.2, 0.0), abs=1e-9)  # all 30 cycles
    assert {"vAP_p_mm", "vAP_a_deg", "vAP_b_deg", "vAP_c_deg"} <= c.to_dict().keys()


def test_three_approach_directions_take_the_largest_pair(rng):
    offsets = ([0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0])  # pairs: 0.2236, 0.1, 0.2
    xyz = np.vstack([CMD + o + triples(rng, [0.1] * 2) for o in offsets])
    abc = np.vstack([angles(rng, 6, (m, 0.0, 0.0), (0.01, 0.01, 0.01)) for m in (0.0, 0.01, 0.03)])
    c = I.pose_characteristics(I.pose_series("P1", CMD, ABC_CMD, xyz, abc, approach=[*"a" * 6, *"b" * 6, *"c" * 6]))
    assert c.vAP_p_mm == pytest.approx(math.sqrt(0.05), abs=1e-9)
    assert c.vAP_a_deg == pytest.approx(0.03, abs=1e-9)


def test_a_single_approach_direction_has_no_vap(rng):
    s = I.pose_series("P1", CMD, ABC_CMD, CMD + triples(rng, [0.1] * 2), np.tile(ABC_CMD, (6, 1)), ["+z"] * 6)
    d = I.pose_characteristics(s).to_dict()
    assert set(d) == {*I._POSE_KEYS, "n"} and "vAP_p_mm" not in d


def test_distance_accuracy_and_repeatability_between_two_poses(rng):
    u = np.array([2.0, 3.0, 6.0]) / 7.0  # unit; the commanded distance 700 mm along it
    cmd_a, cmd_b = CMD, CMD + 700.0 * u
    e = 0.12 + 0.03 * standardised(rng, 30)  # attained distance minus commanded: mean 0.12, std 0.03
    xyz_a = cmd_a + rng.normal(0, 0.05, (30, 3))
    xyz_b = xyz_a + (700.0 + e)[:, None] * u
    abc = np.tile(ABC_CMD, (30, 1))
    series = [I.pose_series("P2", cmd_a, ABC_CMD, xyz_a, abc), I.pose_series("P4", cmd_b, ABC_CMD, xyz_b, abc)]
    d = I.iso9283_result(series, distances=[("P2", "P4")]).to_dict()["distances"]["P2-P4"]
    assert d["n"] == 30 and d["D_cmd_mm"] == pytest.approx(700.0, abs=1e-9)
    assert d["AD_p_mm"] == pytest.approx(0.12, abs=1e-9)
    assert (d["AD_x_mm"], d["AD_y_mm"], d["AD_z_mm"]) == pytest.approx(tuple(0.12 * u), abs=1e-9)
    assert d["RD_l_mm"] == pytest.approx(0.09, abs=1e-9)
    assert (d["RD_x_mm"], d["RD_y_mm"], d["RD_z_mm"]) == pytest.approx(tuple(0.09 * u), abs=1e-9)


def test_result_dict_has_every_pose_with_the_iso_names(rng):
    series = {
        f"P{k}": I.pose_series(
            f"P{k}",
            CMD + k,
            ABC_CMD,
            CMD + k + 0.1 * k + triples(rng, [0.1] * 10),
            angles(rng, 30, (0, 0, 0), (0.01,) * 3),
        )
        for k in range(1, 6)
    }
    d = I.iso9283_dict(series)
    assert list(d) == ["poses"] and list(d["poses"]) == ["P1", "P2", "P3", "P4", "P5"]
    p3 = d["poses"]["P3"]
    assert list(p3) == [*I._POSE_KEYS, "n"] and p3["n"] == 30
    assert p3["AP_p_mm"] == pytest.approx(0.3 * math.sqrt(3), abs=1e-9)


def test_series_from_table_groups_rows_by_pose_and_sorts_the_cycles(rng):
    xyz = CMD + triples(rng, [0.1, 0.2, 0.3, 0.1])  # 12 cycles
    abc = angles(rng, 12, (0.02, 0.0, -0.01), (0.01, 0.01, 0.01))
    ref = I.pose_characteristics(I.pose_series("P1", CMD, ABC_CMD, xyz, abc))
    cmd_rows = np.tile(np.r_[CMD, ABC_CMD], (24, 1))
    cmd_rows[12:, :3] += 100.0  # P2 commanded elsewhere
    att_rows = np.vstack([np.c_[xyz, abc], np.c_[xyz + 100.0, abc]])
    pose, cycle = ["P1"] * 12 + ["P2"] * 12, [*range(1, 13)] * 2
    order = rng.permutation(24)
    got = I.series_from_table([pose[i] for i in order], [cycle[i] for i in order], cmd_rows[order], att_rows[order])
    assert set(got) == {"P1", "P2"} and got["P1"].cycles == tuple(range(1, 13))
    for name in ("P1", "P2"):
        c = I.pose_characteristics(got[name])
        assert (c.AP_p_mm, c.RP_l_mm, c.AP_a_deg, c.RP_c_deg) == pytest.approx(
            (ref.AP_p_mm, ref.RP_l_mm, ref.AP_a_deg, ref.RP_c_deg), abs=1e-9
        )
    bad = cmd_rows.copy()
    bad[3, 0] += 0.5
    with pytest.raises(SolveError, match="different poses"):
        I.series_from_table(pose, cycle, bad, att_rows)
    with pytest.raises(SolveError, match="distinct cycle"):
        I.series_from_table(pose, [1] * 24, cmd_rows, att_rows)


def test_cube_puts_p1_at_the_centre_and_p2_to_p5_a_tenth_of_the_diagonal_from_the_corners():
    cube = I.iso9283_cube([1000.0, 0.0, 800.0], 400.0)
    C, P = cube.corners, cube.poses
    assert np.allclose(
        [C["C1"], C["C2"], C["C7"], C["C8"]], [[800, -200, 600], [1200, -200, 600], [1200, 200, 1000], [800, 200, 1000]]
    )
    expected = [[1000, 0, 800], [840, -160, 640], [1160, -160, 640], [1160, 160, 960], [840, 160, 960]]
    assert np.allclose(cube.commanded_positions(), expected, atol=1e-12)
    assert cube.diagonal_mm == pytest.approx(400 * math.sqrt(3))
    for p, corner in (("P2", "C1"), ("P3", "C2"), ("P4", "C7"), ("P5", "C8")):
        assert np.linalg.norm(P[p] - C[corner]) == pytest.approx(40 * math.sqrt(3), abs=1e-9)


def test_a_turned_cube_keeps_the_poses_in_its_diagonal_plane():
    R = Rotation.from_euler("ZYX", [90.0, 0.0, 0.0], degrees=True).as_matrix()
    cube = I.iso9283_cube([1000.0, 0.0, 800.0], 400.0, R, corner_fraction=0.12)
    C, P = cube.corners, cube.poses
    assert np.allclose(C["C1"], [1200, -200, 600]) and np.allclose(C["C7"], [800, 200, 1000])
    assert np.allclose(P["P2"], [1200 - 48, -200 + 48, 600 + 48])
    normal = np.cross(C["C2"] - C["C1"], C["C8"] - C["C1"])
    assert abs(np.dot(C["C7"] - C["C1"], normal)) < 1e-6  # the four corners are one plane
    for p in P.values():
        assert abs(np.dot(p - C["C1"], normal) / np.linalg.norm(normal)) < 1e-9
    assert np.linalg.norm(C["C1"] - C["C2"]) == pytest.approx(400) and np.linalg.norm(
        C["C2"] - C["C7"]
    ) == pytest.approx(400 * math.sqrt(2))
    for p, corner in (("P2", "C1"), ("P3", "C2"), ("P4", "C7"), ("P5", "C8")):
        assert np.linalg.norm(P[p] - C[corner]) == pytest.approx(0.12 * 400 * math.sqrt(3), abs=1e-9)


def _raises(match, fn, *args, **kw):
    with pytest.raises(SolveError, match=match) as e:
        fn(*args, **kw)
    assert e.value.reason is Reason.bad_input


def test_bad_input_is_a_clear_solve_error(rng):
    xyz, abc = CMD + triples(rng, [0.1] * 10), np.tile(ABC_CMD, (30, 1))
    _raises("at least 2 cycles", I.pose_series, "P1", CMD, ABC_CMD, xyz[:1], abc[:1])
    _raises(r"30 cycles.*\(30, 3\)", I.pose_series, "P1", CMD, ABC_CMD, xyz, abc[:29])
    _raises(r"shape \(3,\)", I.pose_series, "P1", CMD[:2], ABC_CMD, xyz, abc)
    _raises(r"shape \(n, 3\)", I.pose_series, "P1", CMD, ABC_CMD, xyz[:, :2], abc)
    bad = xyz.copy()
    bad[4, 1] = np.nan
    _raises("NaN or infinity", I.pose_series, "P1", CMD, ABC_CMD, bad, abc)
    _raises("NaN or infinity", I.pose_series, "P1", CMD, [np.inf, 0, 0], xyz, abc)
    _raises("not a proper rotation", I.pose_series, "P1", CMD, 2 * np.eye(3), xyz, abc)
    _raises("approach labels", I.pose_series, "P1", CMD, ABC_CMD, xyz, abc, approach=["a"] * 29)
    s = I.pose_series("P1", CMD, ABC_CMD, xyz, abc)
    _raises("same pose name", I.iso9283_result, [s, s])
    _raises("not measured", I.iso9283_result, [s], distances=[("P1", "P9")])
    short = I.pose_series("P2", CMD, ABC_CMD, xyz[:12], abc[:12])
    _raises("different cycles", I.distance_characteristics, s, short)
    _raises("positive length", I.iso9283_cube, CMD, 0.0)
    _raises("10 % ± 2 %", I.iso9283_cube, CMD, 400.0, corner_fraction=0.2)
