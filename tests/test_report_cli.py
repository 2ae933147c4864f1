"""``posecell report iso9283|table1`` on CSV files whose answers are known in closed form."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from service.cli import main as cli

HEADER = [
    "pose",
    "cycle",
    "x_cmd_mm",
    "y_cmd_mm",
    "z_cmd_mm",
    "a_cmd_deg",
    "b_cmd_deg",
    "c_cmd_deg",
    "x_mm",
    "y_mm",
    "z_mm",
    "a_deg",
    "b_deg",
    "c_deg",
]


def _write(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def test_iso9283_report_gives_the_barycentre_offset_and_spread(tmp_path, capsys):
    rng = np.random.default_rng(3)
    offset = {"P1": (0.3, -0.4, 0.0), "P2": (0.0, 0.0, 1.2)}  # AP_p 0.5 and 1.2 mm
    rows = []
    for name, b in offset.items():
        cmd = [800.0, 100.0, 600.0, 10.0, 5.0, 170.0]
        u = rng.normal(size=(30, 3))
        u -= u.mean(axis=0)  # the attained positions' barycentre is exactly cmd + b
        for k in range(30):
            p = np.add(cmd[:3], b) + 0.01 * u[k]
            rows.append([name, k + 1, *cmd, *p, cmd[3] + 0.002, cmd[4], cmd[5]])
    csv_path = _write(tmp_path / "poses.csv", HEADER, rows)
    assert cli.main(["report", "iso9283", "--poses", str(csv_path), "-o", str(tmp_path / "out")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["poses"]["P1"]["AP_p_mm"] == pytest.approx(0.5, abs=1e-9)
    assert report["poses"]["P2"]["AP_z_mm"] == pytest.approx(1.2, abs=1e-9)
    assert report["poses"]["P1"]["AP_a_deg"] == pytest.approx(0.002, abs=1e-6)
    assert 0.0 < report["poses"]["P1"]["RP_l_mm"] < 0.1 and report["poses"]["P1"]["n"] == 30
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == report
    assert "| P2 |" in (tmp_path / "out" / "report.md").read_text()
    # the plotted positions are in the JSON: offsets from the command, µm, one per cycle
    assert np.array(report["attained"]["P2"]["offset_um"]).mean(axis=0) == pytest.approx([0, 0, 1200], abs=1e-3)
    for name in ("iso9283.svg", "iso9283.png", "report.html"):
        assert (tmp_path / "out" / name).stat().st_size > 1000


def test_table1_report_gives_each_positions_deviation_between_its_two_visits(tmp_path, capsys):
    forward = [[1000.0 + 100 * k, 0.0, 500.0, 0.0, 0.0, 180.0] for k in range(3)]
    visits = forward + [list(p) for p in reversed(forward)]
    visits[3][1] += 0.25  # position 3's second visit is 0.25 mm further along y
    header = [*HEADER[8:], "sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_a_deg", "sigma_b_deg", "sigma_c_deg"]
    rows = [[*v, 0.03, 0.04, 0.0, 0.001, 0.001, 0.001] for v in visits]
    csv_path = _write(tmp_path / "visits.csv", header, rows)
    assert cli.main(["report", "table1", "--poses", str(csv_path), "-o", str(tmp_path / "out")]) == 0
    report = json.loads(capsys.readouterr().out)
    by_position = {str(r["position"]): r for r in report["rows"]}
    assert by_position["3"]["dp_mm"] == pytest.approx(0.25, abs=1e-9)
    assert by_position["1"]["dp_mm"] == pytest.approx(0.0, abs=1e-9)
    assert report["n_positions"] == 3
    sigma = [v for k, v in by_position["3"].items() if k.startswith("sigma_")]
    assert pytest.approx(sorted(sigma)[-1], abs=1e-9) == 0.04 * np.sqrt(2)  # the two visits' σ combined


def test_a_missing_column_is_named(tmp_path, capsys):
    csv_path = _write(tmp_path / "bad.csv", HEADER[:-1], [[0] * 13])
    assert cli.main(["report", "iso9283", "--poses", str(csv_path), "-o", str(tmp_path / "out")]) == 2
    assert "c_deg" in capsys.readouterr().err


def test_circle_report_gives_the_iso_230_4_figures_of_an_elliptic_path(tmp_path, capsys):
    # an ellipse of semi-axes R + e, R - e about (1200, 0, 800) in the xy plane, both directions:
    # G = 2e, F_max = e, F_min = -e (ISO 230-4's figures, closed form)
    R, e = 300.0, 0.05
    rows = []
    for direction, sign in (("ccw", 1.0), ("cw", -1.0)):
        for k in range(360):
            th = sign * np.radians(k)
            rows.append([len(rows) * 0.01, direction, 1200 + (R + e) * np.cos(th), (R - e) * np.sin(th), 800.0])
    csv_path = _write(tmp_path / "circle.csv", ["t_s", "direction", "x_mm", "y_mm", "z_mm"], rows)
    args = ["report", "circle", "--poses", str(csv_path), "--radius-mm", str(R), "--centre-mm", "1200,0,800"]
    assert cli.main([*args, "-o", str(tmp_path / "out")]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert report["G_bidirectional_mm"] == pytest.approx(2 * e, rel=1e-3)
    assert report["F_max_mm"] == pytest.approx(e, rel=1e-3) and report["F_min_mm"] == pytest.approx(-e, rel=1e-3)
    assert report["H_mm"] == pytest.approx(0.0, abs=1e-6)  # both directions trace the same ellipse
    assert "G_bidirectional_mm" in (tmp_path / "out" / "report.md").read_text()
    # the files are listed as written; the page embeds the polar plot and shows G
    written = {Path(line.rsplit("wrote ", 1)[1]).name for line in err.splitlines() if "wrote" in line}
    assert written == {"report.json", "report.md", "circle.svg", "circle.png", "report.html"}
    page = (tmp_path / "out" / "report.html").read_text()
    assert (tmp_path / "out" / "circle.svg").read_text().split("<svg", 1)[1] in page
    assert f">{report['G_bidirectional_mm']:.4f}<" in page
    # the profile the plot is drawn from: an ellipse's deviation is e cos 2θ, its envelopes ±e
    cw = report["profile"]["cw"]
    th = np.radians(cw["theta_deg"])
    assert np.array(cw["radial_deviation_mm"]) == pytest.approx(e * np.cos(2 * th), abs=1e-4)
    assert cw["envelope_outer_mm"] - cw["envelope_inner_mm"] == pytest.approx(report["G_cw_mm"], abs=2e-6)
    assert "robot_path" not in report  # no x_cmd_mm columns
    assert cli.main([*args[:-2], "--centre-mm", "1,2", "-o", str(tmp_path / "o2")]) == 2
