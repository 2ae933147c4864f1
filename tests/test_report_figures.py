"""The report figures and the HTML page: drawn from the report's JSON, deterministic, escaped, and
consistent with the figures they show (the circle's profile against closed forms)."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from service.core.accuracy.circle import circle_profile, circle_result
from service.workflows.report_figures import PNG_DPI, figures, magnification, profile_of
from service.workflows.report_html import fmt, render_html
from service.workflows.reports import CIRCLE_FIGURES, circle_report, iso9283_report, table1_report

R_MM, E_MM = 300.0, 0.05  # the ellipse: semi-axes R + e along x, R - e along y
SHIFT_MM = 0.01  # the cw lap is shifted this far along x: its LSC centre is not the common one


def _ellipse(shift_cw_mm: float = 0.0, n: int = 360) -> tuple[np.ndarray, list[str]]:
    p, d = [], []
    for direction, sign in (("ccw", 1.0), ("cw", -1.0)):
        th = sign * np.radians(np.arange(n) * 360.0 / n)
        dx = shift_cw_mm if direction == "cw" else 0.0
        p += np.column_stack(
            [1200 + dx + (R_MM + E_MM) * np.cos(th), (R_MM - E_MM) * np.sin(th), 800 + 0 * th]
        ).tolist()
        d += [direction] * n
    return np.array(p), d


def _write(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture(scope="module")
def circle(tmp_path_factory) -> dict:
    """The circle report of the shifted ellipse with a robot-reported path (a true circle + 2 µm 3-lobe)."""
    p, d = _ellipse(SHIFT_MM)
    th = np.arctan2(p[:, 1], p[:, 0] - 1200)
    robot = np.column_stack([1200 + R_MM * np.cos(th), (R_MM + 0.002 * np.cos(3 * th)) * np.sin(th), p[:, 2]])
    rows = [[0.01 * i, d[i], *p[i], *robot[i]] for i in range(len(p))]
    header = ["t_s", "direction", "x_mm", "y_mm", "z_mm", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm"]
    path = _write(tmp_path_factory.mktemp("circle") / "circle.csv", header, rows)
    return circle_report(path, R_MM, [1200.0, 0.0, 800.0])


@pytest.fixture(scope="module")
def circle_files(circle) -> dict[str, bytes]:
    return figures("circle", circle)


def test_the_profile_of_an_ellipse_is_its_second_harmonic():
    p, d = _ellipse()
    prof = circle_profile(circle_result(p, d, R_MM))
    for k in ("cw", "ccw"):
        th = np.radians(prof[k]["theta_deg"])
        dev = np.array(prof[k]["radial_deviation_mm"])
        # r(θ) of the ellipse = R + e cos 2θ to first order in e / R (the rest is < e² / R ≈ 8 nm)
        np.testing.assert_allclose(dev, E_MM * np.cos(2 * th), atol=2 * E_MM**2 / R_MM)
        assert prof[k]["envelope_inner_mm"] == pytest.approx(-E_MM, abs=1e-6)
        assert prof[k]["envelope_outer_mm"] == pytest.approx(E_MM, abs=1e-6)
        assert prof[k]["centre_offset_mm"] == pytest.approx([0.0, 0.0], abs=1e-6)
    assert len(prof["cw"]["theta_deg"]) == len(prof["ccw"]["theta_deg"]) == 360
    assert json.loads(json.dumps(prof)) == prof  # JSON as it stands


def test_each_envelope_spans_the_g_of_its_direction_about_its_own_centre():
    p, d = _ellipse(SHIFT_MM)
    result = circle_result(p, d, R_MM)
    prof = circle_profile(result)
    assert prof["cw"]["centre_offset_mm"] == pytest.approx([SHIFT_MM / 2, 0.0], abs=1e-6)  # by symmetry
    assert prof["ccw"]["centre_offset_mm"] == pytest.approx([-SHIFT_MM / 2, 0.0], abs=1e-6)
    for k, G in (("cw", result.G_cw_mm), ("ccw", result.G_ccw_mm), ("bidirectional", result.G_bidirectional_mm)):
        assert prof[k]["envelope_outer_mm"] - prof[k]["envelope_inner_mm"] == pytest.approx(G, abs=2e-6)
    # the points' radii about their direction's centre, rebuilt from the profile alone: max - min = G
    th = np.radians(prof["cw"]["theta_deg"])
    q = (R_MM + np.array(prof["cw"]["radial_deviation_mm"]))[:, None] * np.column_stack([np.cos(th), np.sin(th)])
    r_own = np.linalg.norm(q - prof["cw"]["centre_offset_mm"], axis=1)
    assert np.ptp(r_own) == pytest.approx(result.G_cw_mm, abs=2e-6)
    assert prof["bidirectional"]["envelope_inner_mm"] == pytest.approx(result.F_min_mm, abs=1e-6)
    assert prof["bidirectional"]["envelope_outer_mm"] == pytest.approx(result.F_max_mm, abs=1e-6)


def test_the_magnification_makes_the_band_visible_and_is_a_round_number():
    N = magnification(300.0, 0.05)
    assert N == 1000.0  # 0.3 * 300 / 0.05 = 1800 -> 1000
    for band_mm in (1e-4, 3.3e-3, 0.05, 0.7):
        N = magnification(300.0, band_mm)
        assert 0.3 * 300.0 / 2.5 <= N * band_mm <= 0.3 * 300.0  # a 1-2-5 step is at most x2.5
    assert magnification(300.0, 200.0) == 1.0  # a gross error is drawn true to scale


def test_the_circle_svg_has_both_paths_of_both_panels_and_the_results_block(circle, circle_files):
    svg = ET.fromstring(circle_files["circle.svg"])
    ids = {g.get("id") for g in svg.iter("{http://www.w3.org/2000/svg}g")}
    paths = sorted(i for i in ids if i and "-path-" in i)
    assert paths == ["camera-path-ccw", "camera-path-cw", "robot-path-ccw", "robot-path-cw"]
    envelopes = [i for i in ids if i and i.startswith("camera-envelope-")]
    assert len(envelopes) == 4  # inner and outer of cw and ccw
    assert "camera-lsc-centre" in ids and "camera-nominal" in ids
    text = " ".join("".join(t.itertext()) for t in svg.iter("{http://www.w3.org/2000/svg}text"))
    for key in ("G_cw_mm", "G_ccw_mm", "G_bidirectional_mm", "H_mm", "F_max_mm", "F_min_mm"):
        assert fmt(circle[key]) in text
    assert "deviations ×1000" in text  # the band is about 0.055 mm on R = 300 mm
    assert "robot-reported path" in text


def test_the_circle_png_is_a_png_of_the_figure_size(circle_files):
    data = circle_files["circle.png"]
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(io.BytesIO(data), format="png")
    assert image.shape[0] == round(5.6 * PNG_DPI) and image.shape[1] == round((2 * 5.2 + 3.0) * PNG_DPI)
    assert image[..., :3].min() < 0.5 < image[..., :3].max()  # something is drawn on the white


def test_the_same_report_gives_the_same_files(circle, circle_files):
    assert figures("circle", circle) == circle_files  # SVG and PNG, byte for byte
    svgs = {"circle.svg": circle_files["circle.svg"]}
    assert render_html("circle", circle, svgs=svgs) == render_html("circle", dict(circle), svgs=svgs)


def test_the_page_shows_every_headline_figure_and_embeds_the_svg(circle, circle_files):
    page = render_html("circle", circle)
    for key in CIRCLE_FIGURES:
        assert f">{fmt(circle[key])}<" in page
    assert page.count("<svg") == 1 and "<?xml" not in page and "<!DOCTYPE svg" not in page
    assert "camera-path-cw" in page
    assert "http://" not in page.replace('xmlns="http://www.w3.org/2000/svg"', "").split("<svg")[0]
    assert "<script" not in page
    # the pre-rendered SVG is the one it draws itself
    assert render_html("circle", circle, svgs={"circle.svg": circle_files["circle.svg"]}) == page


def test_a_report_without_the_plot_data_still_renders_and_escapes_its_notes():
    p, d = _ellipse()
    old = circle_result(p, d, R_MM).to_dict()  # a report.json from before the profile
    old["notes"] = ['<img src=x onerror="alert(1)">']
    assert figures("circle", old) == {}
    page = render_html("circle", old)
    assert "<svg" not in page and fmt(old["G_bidirectional_mm"]) in page
    assert "<img" not in page and "&lt;img src=x onerror=&quot;alert(1)&quot;&gt;" in page


def test_a_report_with_the_per_point_arrays_is_plotted_from_them():
    p, d = _ellipse(SHIFT_MM)
    result = circle_result(p, d, R_MM)
    with_points = result.to_dict(points=True)  # what the service's stored tests keep
    rebuilt = profile_of(with_points)
    expected = circle_profile(result)
    for k in ("cw", "ccw", "bidirectional"):
        for key, value in expected[k].items():
            assert rebuilt[k][key] == pytest.approx(value, abs=2e-6), (k, key)
    assert set(figures("circle", with_points, formats=("svg",))) == {"circle.svg"}


@pytest.fixture(scope="module")
def iso9283(tmp_path_factory) -> dict:
    rng = np.random.default_rng(5)
    rows = []
    for name, b in {"P1": (0.03, -0.04, 0.0), "<script>alert(1)</script>": (0.0, 0.0, 0.02)}.items():
        cmd = [800.0, 100.0, 600.0, 10.0, 5.0, 170.0]
        for k in range(10):
            rows.append([name, k + 1, *cmd, *(np.add(cmd[:3], b) + 0.01 * rng.normal(size=3)), *cmd[3:]])
    header = ["pose", "cycle", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm", "a_cmd_deg", "b_cmd_deg", "c_cmd_deg"]
    header += ["x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg"]
    return iso9283_report(_write(tmp_path_factory.mktemp("iso") / "poses.csv", header, rows))


@pytest.fixture(scope="module")
def iso9283_files(iso9283) -> dict[str, bytes]:
    return figures("iso9283", iso9283)


def test_the_iso9283_figure_has_three_projections_per_pose_and_escapes_the_names(iso9283, iso9283_files):
    files = iso9283_files
    assert set(files) == {"iso9283.svg", "iso9283.png"}
    svg = ET.fromstring(files["iso9283.svg"])  # a pose named <script> still gives well-formed XML
    ids = [g.get("id") or "" for g in svg.iter("{http://www.w3.org/2000/svg}g")]
    assert len([i for i in ids if i.endswith("-attained")]) == 6
    assert len([i for i in ids if i.endswith("-rp-sphere")]) == 6
    offsets = np.array(iso9283["attained"]["P1"]["offset_um"])
    assert offsets.shape == (10, 3)
    assert np.linalg.norm(offsets.mean(axis=0)) / 1e3 == pytest.approx(iso9283["poses"]["P1"]["AP_p_mm"], abs=1e-5)


def test_the_iso9283_page_escapes_a_hostile_pose_name(iso9283, iso9283_files):
    page = render_html("iso9283", iso9283, svgs=iso9283_files)
    assert page.count("<svg") == 1
    assert "<script" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    for figs in iso9283["poses"].values():
        assert f">{fmt(figs['AP_p_mm'])}<" in page and f">{fmt(figs['RP_l_mm'])}<" in page


def test_the_table1_figure_has_six_bar_series_with_error_bars(tmp_path):
    forward = [[1000.0 + 100 * k, 0.0, 500.0, 0.0, 0.0, 180.0] for k in range(3)]
    visits = forward + [list(p) for p in reversed(forward)]
    visits[3][1] += 0.025
    header = ["position", "x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg"]
    header += ["sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_a_deg", "sigma_b_deg", "sigma_c_deg"]
    labels = ["A", "B", "<b>C</b>", "<b>C</b>", "B", "A"]
    rows = [[lab, *v, 0.003, 0.004, 0.005, 0.001, 0.001, 0.001] for lab, v in zip(labels, visits)]
    report = table1_report(_write(tmp_path / "visits.csv", header, rows))
    files = figures("table1", report, formats=("svg",))
    svg = ET.fromstring(files["table1.svg"])
    ids = [g.get("id") or "" for g in svg.iter("{http://www.w3.org/2000/svg}g")]
    bars = [i for i in ids if i.startswith("bar-")]
    assert len(bars) == len(set(bars)) == 6 * 3  # six components, three positions
    assert len({i.rsplit("-", 1)[0] for i in bars}) == 6
    assert len([i for i in ids if i.startswith("sigma-")]) == 6  # an error-bar series per component
    page = render_html("table1", report, svgs=files)
    assert "<b>C</b>" not in page and "&lt;b&gt;C&lt;/b&gt;" in page
    assert ">0.0250<" in page  # dy of C
    with pytest.raises(ValueError, match="formats"):
        figures("table1", report, formats=("pdf",))


def test_a_robot_path_that_fits_no_circle_is_a_note_not_a_failure(tmp_path):
    p, d = _ellipse()
    rows = [[0.01 * i, d[i], *p[i], 1200.0, 0.0, 800.0] for i in range(len(p))]  # the robot reports one point
    header = ["t_s", "direction", "x_mm", "y_mm", "z_mm", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm"]
    report = circle_report(_write(tmp_path / "circle.csv", header, rows), R_MM)
    assert "robot_path" not in report and report["robot_deviation_max_mm"] == pytest.approx(R_MM + E_MM, abs=1e-6)
    assert any("robot's reported path" in n for n in report["notes"])


def test_the_drawn_path_breaks_where_points_are_missing_along_the_arc():
    from service.workflows.report_figures import _broken_at_gaps

    theta = np.radians(np.r_[np.arange(0.0, 90.0, 1.0), np.arange(130.0, 360.0, 1.0)])
    t, d = _broken_at_gaps(theta, np.zeros_like(theta))
    assert np.isnan(t).sum() == 1 and np.isnan(t[90]) and np.isnan(d[90])
    # a full lap wrapping past 360 deg is no gap
    t, _ = _broken_at_gaps(np.radians(np.arange(300.0, 420.0, 1.0)), np.zeros(120))
    assert not np.isnan(t).any()
