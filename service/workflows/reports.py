"""The robot's accuracy reports from recorded poses (``posecell report …``): CSV in; JSON, a table,
figures and a page out.

The analyses are the core's (:mod:`service.core.accuracy`); here only the files: reading the
CSV of DESIGN section 5 by its header (columns in any order, extra columns ignored, a missing
one named), and writing ``report.json``, ``report.md``, the figures
(:mod:`service.workflows.report_figures`) and ``report.html`` (:mod:`service.workflows.report_html`)
into the output folder. The JSON carries what the figures are drawn from (the circle's
``profile``, the poses' ``attained`` offsets), so the page can be rendered again from it alone.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.core.accuracy.circle import circle_profile, circle_result
from service.core.accuracy.iso9283 import attained_offsets, iso9283_dict, series_from_table
from service.core.accuracy.table1 import table1
from service.core.geometry.frames import R_from_kuka_abc_deg, make_T
from service.core.results import SolveError
from service.store.formats import FormatError
from service.workflows.report_figures import figures
from service.workflows.report_html import render_html

ISO9283_COLUMNS = ("pose", "cycle", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm", "a_cmd_deg", "b_cmd_deg", "c_cmd_deg")
ATTAINED = ("x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg")
TABLE1_SIGMA = ("sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_a_deg", "sigma_b_deg", "sigma_c_deg")


def read_table(path: Path, required: Sequence[str]) -> dict[str, list[str]]:
    """The CSV's columns by name; a FormatError naming the file and what is missing."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise FormatError(f"cannot read {path}: {e.strerror or e}") from None
    if not rows:
        raise FormatError(f"{path} has no rows (a header line and one row per pose are needed)")
    missing = [c for c in required if c not in rows[0]]
    if missing:
        raise FormatError(f"{path} lacks the column(s) {', '.join(missing)}; it has {', '.join(rows[0])}")
    return {k: [r[k] for r in rows] for k in rows[0]}


def _numbers(table: dict[str, list[str]], columns: Sequence[str], path: Path) -> np.ndarray:
    try:
        return np.array([[float(v) for v in table[c]] for c in columns]).T
    except ValueError as e:
        raise FormatError(f"{path}: a value of {', '.join(columns)} is not a number ({e})") from None


def iso9283_report(path: Path) -> dict[str, Any]:
    """ISO 9283 pose characteristics of the rows ``pose, cycle, x_cmd_mm … c_cmd_deg, x_mm … c_deg``."""
    t = read_table(path, (*ISO9283_COLUMNS, *ATTAINED))
    try:
        cycles = [int(c) for c in t["cycle"]]
    except ValueError:
        raise FormatError(f"{path}: the column cycle must hold whole numbers") from None
    series = series_from_table(
        t["pose"],
        cycles,
        _numbers(t, ISO9283_COLUMNS[2:], path),
        _numbers(t, ATTAINED, path),
        t.get("direction"),
    )
    return iso9283_dict(series) | {"attained": attained_offsets(series)}


CIRCLE_COLUMNS = ("direction", "x_mm", "y_mm", "z_mm")
CIRCLE_FIGURES = (
    "G_cw_mm",
    "G_ccw_mm",
    "G_bidirectional_mm",
    "H_mm",
    "F_max_mm",
    "F_min_mm",
    "mean_radial_deviation_mm",
)


def circle_report(path: Path, radius_mm: float, centre_mm: Sequence[float] | None = None) -> dict[str, Any]:
    """The ISO 230-4 circular test of the rows ``t_s, direction, x_mm, y_mm, z_mm`` (direction ``cw`` or
    ``ccw``; optional ``a_deg, b_deg, c_deg`` for the orientation deviation along the path and
    ``x_cmd_mm, y_cmd_mm, z_cmd_mm`` for the robot's own belief), in time order."""
    t = read_table(path, CIRCLE_COLUMNS)
    p = _numbers(t, CIRCLE_COLUMNS[1:], path)
    R = None
    if all(c in t for c in ATTAINED[3:]):
        R = np.stack([R_from_kuka_abc_deg(abc) for abc in _numbers(t, ATTAINED[3:], path)])
    cmd = ("x_cmd_mm", "y_cmd_mm", "z_cmd_mm")
    p_robot = _numbers(t, cmd, path) if all(c in t for c in cmd) else None
    directions = [d.strip().lower() for d in t["direction"]]
    result = circle_result(p, directions, radius_mm, centre_mm=centre_mm, R=R, p_robot_mm=p_robot)
    report = result.to_dict() | {"profile": circle_profile(result)}
    if p_robot is not None:
        # the robot's own belief of its path, analysed as the camera's is (about its own LSC): the
        # seed paper's Figure 7 sets the two side by side; a robot path that fits no circle is a note
        try:
            robot = circle_result(p_robot, directions, radius_mm, centre_mm=centre_mm, minimum_zone=False)
        except SolveError as e:
            report["notes"].append(f"the robot's reported path (x_cmd_mm …) gives no circle: {e}")
        else:
            robot_figures = {k: v for k, v in robot.to_dict().items() if k in (*CIRCLE_FIGURES, "notes")}
            report["robot_path"] = robot_figures | {"profile": circle_profile(robot)}
    return report


def table1_report(path: Path) -> dict[str, Any]:
    """The paper's Table 1 from the rows ``[position,] x_mm … c_deg [, sigma_x_mm … sigma_c_deg]`` in
    visit order (KUKA A, B, C deg; positions visited forward, then in reverse order)."""
    t = read_table(path, ATTAINED)
    xyzabc = _numbers(t, ATTAINED, path)
    T = np.stack([make_T(R_from_kuka_abc_deg(p[3:]), p[:3]) for p in xyzabc])
    sigma = _numbers(t, TABLE1_SIGMA, path) if all(c in t for c in TABLE1_SIGMA) else np.zeros((len(T), 6))
    return table1(T, sigma[:, :3], sigma[:, 3:], labels=t.get("position")).to_dict()


def _markdown(title: str, rows: list[dict[str, Any]], columns: Sequence[str]) -> str:
    def cell(v: Any) -> str:
        return f"{v:.4f}" if isinstance(v, float) else str(v)

    lines = [f"# {title}", "", "| " + " | ".join(columns) + " |", "|" + "---:|" * len(columns)]
    lines += ["| " + " | ".join(cell(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write_report(out_dir: Path, kind: str, report: dict[str, Any]) -> list[Path]:
    """``report.json``, ``report.md`` (a table), the figures (``circle.svg``, ``circle.png`` …) and
    ``report.html`` (the page, figures inline) in ``out_dir``; the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, md_path = out_dir / "report.json", out_dir / "report.md"
    json_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    if kind == "circle":
        rows = [{"figure": k, "mm": report.get(k)} for k in CIRCLE_FIGURES]
        md = _markdown("ISO 230-4 circular test", rows, ["figure", "mm"])
        md += "\n" + "\n".join(f"- {note}" for note in report.get("notes", [])) + "\n"
    elif kind == "iso9283":
        poses = [{"pose": name, **figures} for name, figures in report["poses"].items()]
        columns = ["pose", *[k for k in (poses[0] if poses else {}) if k != "pose"]]
        md = _markdown("ISO 9283 pose characteristics", poses, columns)
    else:
        rows = report["rows"]
        md = _markdown("Forward and reverse visits (the paper's Table 1)", rows, list(rows[0]) if rows else [])
    md_path.write_text(md, encoding="utf-8")
    written = [json_path, md_path]
    drawn = figures(kind, report)
    for name, data in drawn.items():
        (out_dir / name).write_bytes(data)
        written.append(out_dir / name)
    html_path = out_dir / "report.html"
    html_path.write_text(render_html(kind, report, svgs=drawn), encoding="utf-8")
    return [*written, html_path]
