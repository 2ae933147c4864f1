"""The paper's Table 1 (forward then reverse visits) on poses built with known deviations and σ."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.accuracy import table1 as T1
from service.core.geometry.frames import R_from_opk, make_T
from service.core.results import Reason, SolveError

# the paper's Table 1 (KUKA KR 125/2): per position dx, dy, dz mm and dω, dφ, dκ deg
PAPER_D_MM = np.array(
    [
        [1.174, -0.284, -1.642],
        [-0.243, 1.989, 0.471],
        [-0.035, -0.189, -0.330],
        [0.172, -0.774, 0.152],
        [-0.096, 0.618, 0.313],
        [0.386, 0.854, 1.459],
    ]
)
PAPER_D_DEG = np.array(
    [
        [-0.008, -0.006, 0.003],
        [0.126, -0.052, -0.165],
        [0.002, 0.000, 0.000],
        [-0.010, 0.004, 0.0019],
        [0.008, -0.003, -0.011],
        [-0.011, -0.028, 0.000],
    ]
)
# σ of the first and the second visit, chosen so that sqrt(σ1² + σ2²) is round: 3-4-5, 5-12-13, 8-15-17
S1_MM, S2_MM, S_MM = np.array([0.03, 0.05, 0.08]), np.array([0.04, 0.12, 0.15]), np.array([0.05, 0.13, 0.17])
S1_DEG, S2_DEG, S_DEG = S1_MM / 50, S2_MM / 50, S_MM / 50


def random_pose(rng):
    return make_T(Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(), rng.normal(0, 600, 3))


def forward_reverse(rng, d_mm, d_deg):
    """Visits 1 … K then K … 1; the second visit of position k is the first moved by d_mm (base
    axes) and turned by R_from_opk(d_deg) about the base axes; position k's σ is k times S1/S2."""
    K = len(d_mm)
    first = [random_pose(rng) for _ in range(K)]
    second = [make_T(R_from_opk(np.radians(d_deg[k])) @ first[k][:3, :3], first[k][:3, 3] + d_mm[k]) for k in range(K)]
    order = [*range(K), *range(K - 1, -1, -1)]
    T = np.array([first[k] for k in range(K)] + [second[k] for k in order[K:]])
    s_p = np.array([(k + 1) * S1_MM for k in range(K)] + [(k + 1) * S2_MM for k in order[K:]])
    s_r = np.array([(k + 1) * S1_DEG for k in range(K)] + [(k + 1) * S2_DEG for k in order[K:]])
    return T, s_p, s_r


def test_rows_recover_the_papers_deviations_and_the_propagated_sigma(rng):
    T, s_p, s_r = forward_reverse(rng, PAPER_D_MM, PAPER_D_DEG)
    res = T1.table1(T, s_p, s_r)
    assert [r.position for r in res.rows] == ["1", "2", "3", "4", "5", "6"]
    assert [r.visits for r in res.rows] == [(0, 11), (1, 10), (2, 9), (3, 8), (4, 7), (5, 6)]
    for k, r in enumerate(res.rows):
        assert r.d_mm == pytest.approx(tuple(PAPER_D_MM[k]), abs=1e-9)
        assert r.d_deg == pytest.approx(tuple(PAPER_D_DEG[k]), abs=1e-9)
        assert r.sigma_mm == pytest.approx(tuple((k + 1) * S_MM), abs=1e-12)
        assert r.sigma_deg == pytest.approx(tuple((k + 1) * S_DEG), abs=1e-12)
    assert res.rows[0].dp_mm == pytest.approx(math.sqrt(1.174**2 + 0.284**2 + 1.642**2), abs=1e-9)


def test_summary_gives_the_largest_deviation_and_the_rms(rng):
    T, s_p, s_r = forward_reverse(rng, PAPER_D_MM, PAPER_D_DEG)
    s = T1.table1(T, s_p, s_r).to_dict()["summary"]
    expected_max = (1.174, 1.989, 1.642, 0.126, 0.052, 0.165)  # read off the paper's columns
    assert [s["max_abs"][k] for k in T1.COMPONENTS] == pytest.approx(expected_max, abs=1e-9)
    # two positions with round numbers: dx = 3, -4 -> rms sqrt(12.5); dκ = 0.1, 0.2 -> sqrt(0.025)
    T, s_p, s_r = forward_reverse(rng, np.array([[3.0, 0, 0], [-4.0, 0, 0]]), np.array([[0, 0, 0.1], [0, 0, 0.2]]))
    s = T1.table1(T, s_p, s_r).to_dict()["summary"]
    assert s["rms"]["dx_mm"] == pytest.approx(math.sqrt(12.5), abs=1e-9)
    assert s["rms"]["dkappa_deg"] == pytest.approx(math.sqrt(0.025), abs=1e-9)
    assert s["rms"]["dy_mm"] == pytest.approx(0.0, abs=1e-9) and s["max_abs"]["dp_mm"] == pytest.approx(4.0)


def test_difference_mode_differences_each_poses_own_angles_with_wrap_around():
    o1 = np.radians([[10.0, 40.0, 179.9], [-20.0, 5.0, 0.0]])
    do = np.array([[0.05, -0.02, 0.3], [0.01, 0.02, -0.03]])  # deg; the first crosses κ = 180
    T = np.array(
        [make_T(R_from_opk(o), [0, 0, 0]) for o in o1]
        + [make_T(R_from_opk(o1[k] + np.radians(do[k])), [0, 0, 0]) for k in (1, 0)]
    )
    s = np.full((4, 3), 0.01)
    diff = T1.table1(T, s, s, angles="difference")
    assert diff.rows[0].d_deg == pytest.approx(tuple(do[0]), abs=1e-9)
    assert diff.rows[1].d_deg == pytest.approx(tuple(do[1]), abs=1e-9)
    rel = T1.table1(T, s, s)  # at φ = 40 deg the base-axes rotation is another triple
    assert abs(rel.rows[0].d_deg[0] - do[0, 0]) > 0.05 and rel.to_dict()["angles"] == "relative"


def test_labels_pair_the_visits_in_any_order(rng):
    labels = ["A", "B", "B", "C", "A", "C"]
    poses = {lab: random_pose(rng) for lab in "ABC"}
    moved = {"A": [0.1, 0, 0], "B": [0, -0.2, 0], "C": [0, 0, 0.3]}
    seen: set[str] = set()
    T = []
    for lab in labels:
        T.append(make_T(poses[lab][:3, :3], poses[lab][:3, 3] + (moved[lab] if lab in seen else 0)))
        seen.add(lab)
    res = T1.table1(np.array(T), np.full((6, 3), 0.02), np.full((6, 3), 0.001), labels=labels)
    assert [(r.position, r.visits) for r in res.rows] == [("A", (0, 4)), ("B", (1, 2)), ("C", (3, 5))]
    assert [r.d_mm for r in res.rows] == [pytest.approx(tuple(moved[lab]), abs=1e-9) for lab in "ABC"]
    assert res.rows[0].sigma_mm == pytest.approx((0.02 * math.sqrt(2),) * 3)


def test_to_dict_has_the_papers_columns_with_their_sigma(rng):
    T, s_p, s_r = forward_reverse(rng, PAPER_D_MM[:2], PAPER_D_DEG[:2])
    d = T1.table1(T, s_p, s_r).to_dict()
    assert d["n_positions"] == 2 and set(d) == {"rows", "summary", "n_positions", "angles"}
    row = d["rows"][1]
    assert list(row) == ["position", "visits", *T1.COMPONENTS, *T1.SIGMAS, "dp_mm"]
    assert row["position"] == "2" and row["dy_mm"] == pytest.approx(1.989, abs=1e-9)
    assert row["sigma_z_mm"] == pytest.approx(2 * 0.17, abs=1e-12)
    assert row["sigma_kappa_deg"] == pytest.approx(2 * 0.17 / 50, abs=1e-12)


def _raises(match, *args, **kw):
    with pytest.raises(SolveError, match=match) as e:
        T1.table1(*args, **kw)
    assert e.value.reason is Reason.bad_input


def test_bad_input_is_a_clear_solve_error(rng):
    T, s_p, s_r = forward_reverse(rng, PAPER_D_MM[:3], PAPER_D_DEG[:3])
    _raises("even number", T[:5], s_p[:5], s_r[:5])
    _raises("exactly twice", T, s_p, s_r, labels=["1", "1", "1", "2", "2", "3"])
    _raises("6 position labels", T, s_p, s_r, labels=["1", "2", "3"])
    _raises(r"shape \(6, 3\)", T, s_p[:5], s_r)
    _raises("negative", T, -s_p, s_r)
    bad = s_r.copy()
    bad[2, 1] = np.nan
    _raises("NaN or infinity", T, s_p, bad)
    bent = T.copy()
    bent[3, 0, 0] = 1.5
    _raises("visit 4.*not a proper rotation", bent, s_p, s_r)
    _raises(r"m >= 2", T[:1], s_p[:1], s_r[:1])
    _raises("angles must be", T, s_p, s_r, angles="euler")
