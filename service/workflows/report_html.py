"""One self-contained HTML page of a robot accuracy report (``report.html``, ``GET /tests/{id}/report``).

The page is rendered from the report's JSON alone (the dict ``posecell report`` writes as
``report.json``), so the service can serve a stored test's page without the CSV: a title, the
conditions, every number of the JSON in tables with units, the figures inline as SVG, the notes.
No external assets and no script, so the page opens offline on the cell PC and can be mailed
as one file. Every piece of text from the report (pose names, labels, notes) is escaped: a pose
name is whatever the CSV said.
"""

from __future__ import annotations

import html
import re
from collections.abc import Iterable, Sequence
from typing import Any

from service.workflows.report_figures import figures, profile_of

TITLES = {
    "circle": "ISO 230-4 circular test",
    "iso9283": "ISO 9283 pose characteristics",
    "table1": "Forward and reverse visits (the paper's Table 1)",
    "verify": "Robot model verification (the shift's check)",
}
#: What a figure means (ISO 230-4, ISO 9283:1998, the seed paper): the tables' "meaning" column
MEANINGS = {
    "G_cw_mm": "circular deviation, cw: radial span about the cw points' LSC centre",
    "G_ccw_mm": "circular deviation, ccw: radial span about the ccw points' LSC centre",
    "G_bidirectional_mm": "bidirectional circular deviation: radial span of all points about their common LSC centre",
    "H_mm": "circular hysteresis: max |r_cw(θ) − r_ccw(θ)| where both directions cover θ",
    "F_max_mm": "largest radial deviation r − R (about the common centre)",
    "F_min_mm": "smallest radial deviation r − R (negative: inside the nominal circle)",
    "mean_radial_deviation_mm": "mean of the cw and ccw LSC radii, minus R",
    "G_mzc_cw_mm": "circular deviation, cw, about the minimum-zone centre",
    "G_mzc_ccw_mm": "circular deviation, ccw, about the minimum-zone centre",
    "G_mzc_bidirectional_mm": "bidirectional circular deviation about the minimum-zone centre",
    "out_of_plane_span_mm": "span of the points' signed distances from their least-squares plane",
    "out_of_plane_rms_mm": "RMS distance from the least-squares plane",
    "orientation_deviation_max_deg": "largest angle of a measured orientation from their mean",
    "orientation_deviation_rms_deg": "RMS angle of the orientations from their mean",
    "robot_deviation_max_mm": "largest distance of a measured point from the robot's own position",
    "robot_deviation_rms_mm": "RMS distance of the measured points from the robot's own positions",
    "centre_offset_mm": "common LSC centre minus the nominal centre",
    "centre_offset_in_plane_mm": "its length in the plane",
    "centre_offset_normal_mm": "its component along the plane normal",
    "radius_mm": "nominal radius R",
    "radius_lsc_mm": "radius of the common LSC",
    "max_gap_deg": "largest angular gap between a direction's points still counted as covered (for H)",
    "grid_step_deg": "angle grid of the hysteresis",
    "AP_p_mm": "position accuracy: distance of the barycentre from the command",
    "AP_x_mm": "position accuracy along x (barycentre − command)",
    "AP_y_mm": "position accuracy along y",
    "AP_z_mm": "position accuracy along z",
    "AP_a_deg": "orientation accuracy, KUKA A (mean wrapped difference)",
    "AP_b_deg": "orientation accuracy, KUKA B",
    "AP_c_deg": "orientation accuracy, KUKA C",
    "RP_l_mm": "position repeatability: mean + 3 S of the distances from the barycentre",
    "RP_a_deg": "orientation repeatability, KUKA A: ±3 S",
    "RP_b_deg": "orientation repeatability, KUKA B: ±3 S",
    "RP_c_deg": "orientation repeatability, KUKA C: ±3 S",
    "vAP_p_mm": "multi-directional position accuracy variation",
    "n": "cycles",
    "xyz_cmd_mm": "the commanded position",
    "dp_mm": "distance between the two visits",
}
_UNITS = (("_mm", "mm"), ("_deg", "deg"), ("_um", "µm"), ("_rad", "rad"), ("_s", "s"), ("_px", "px"))
_CSS = """
body { font-family: sans-serif; margin: 2em; color: #222; max-width: 72em; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #bbb; padding: 0.2em 0.6em; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #eee; }
figure { margin: 1em 0; }
figure svg { max-width: 100%; height: auto; }
dl.legend { font-size: 0.85em; display: grid; grid-template-columns: max-content auto; gap: 0 1em; }
dl.legend dd { margin: 0; }
"""


def fmt(value: Any) -> str:
    """A report value as the page and the figures print it: mm and deg to 4 decimals (0.1 µm),
    None as an em dash, vectors in parentheses (not escaped).

    >>> fmt(0.05), fmt(None), fmt(3), fmt([1.0, -0.00002, 2.5]), fmt(True)
    ('0.0500', '—', '3', '(1.0000, -0.0000, 2.5000)', 'yes')
    """
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.4f}" if abs(value) < 1e6 else f"{value:.4g}"
    if isinstance(value, list | tuple):
        return "(" + ", ".join(fmt(v) for v in value) + ")"
    return str(value)


def split_unit(key: str) -> tuple[str, str]:
    """A JSON key's name and unit by the house suffixes (STYLE: names carry units).

    >>> split_unit("G_cw_mm"), split_unit("n_cw"), split_unit("RP_a_deg")
    (('G_cw', 'mm'), ('n_cw', ''), ('RP_a', 'deg'))
    """
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return key[: -len(suffix)], unit
    return key, ""


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _cell(value: Any) -> str:
    numeric = isinstance(value, int | float) and not isinstance(value, bool)
    return f'<td class="num">{_e(fmt(value))}</td>' if numeric else f"<td>{_e(fmt(value))}</td>"


def _is_value(v: Any) -> bool:
    """A scalar or a flat list of scalars: something a table cell shows."""
    scalar = (type(None), bool, int, float, str)
    return isinstance(v, scalar) or (isinstance(v, list) and all(isinstance(x, scalar) for x in v))


def key_value_table(values: dict[str, Any], caption: str | None = None) -> str:
    """Rows name | value | unit | meaning of every scalar (or flat vector) in ``values``."""
    rows = [
        f"<tr><th>{_e(split_unit(k)[0])}</th>{_cell(v)}<td>{_e(split_unit(k)[1])}</td>"
        f"<td>{_e(MEANINGS.get(k, ''))}</td></tr>"
        for k, v in values.items()
        if _is_value(v)
    ]
    cap = f"<caption>{_e(caption)}</caption>" if caption else ""
    head = "<tr><th>quantity</th><th>value</th><th>unit</th><th>meaning</th></tr>"
    return f"<table>{cap}{head}{''.join(rows)}</table>"


def rows_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """One row per dict, one column per key; the unit goes into the column head."""

    def head(k: str) -> str:
        name, unit = split_unit(k)
        return f"<th>{_e(name)}" + (f" ({_e(unit)})" if unit else "") + "</th>"

    body = ["<tr>" + "".join(_cell(r.get(c)) for c in columns) + "</tr>" for r in rows]
    table = "<table><tr>" + "".join(head(c) for c in columns) + "</tr>" + "".join(body) + "</table>"
    legend = "".join(f"<dt>{_e(split_unit(c)[0])}</dt><dd>{_e(MEANINGS[c])}</dd>" for c in columns if c in MEANINGS)
    return table + (f'<dl class="legend">{legend}</dl>' if legend else "")


def _columns(rows: Iterable[dict[str, Any]], first: Sequence[str] = ()) -> list[str]:
    """The keys of all rows in order of first appearance (``first`` leading), values only."""
    keys = dict.fromkeys(first)
    for r in rows:
        keys.update(dict.fromkeys(k for k, v in r.items() if _is_value(v)))
    return list(keys)


def _notes(notes: Iterable[Any]) -> str:
    items = "".join(f"<li>{_e(n)}</li>" for n in notes)
    return f"<h2>Notes</h2><ul>{items}</ul>" if items else ""


def _envelopes(profile: dict[str, Any]) -> str:
    """The G envelope circles of the polar plot: centre (about the common one) and radii - R."""
    rows = [{"path": k, **v} for k, v in profile.items() if k in ("cw", "ccw", "bidirectional")]
    columns = ["path", "centre_offset_mm", "envelope_inner_mm", "envelope_outer_mm"]
    return rows_table(rows, columns) if rows else ""


def _circle_body(report: dict[str, Any]) -> list[str]:
    skip = ("conditions", "notes", "profile", "robot_path", "points")
    parts = ["<h2>Conditions</h2>", key_value_table(report.get("conditions", {}))]
    parts += ["<h2>Results</h2>", key_value_table({k: v for k, v in report.items() if k not in skip})]
    profile = profile_of(report)
    if profile:
        parts += ["<h2>G envelope circles (in the plane, about the common LSC centre)</h2>", _envelopes(profile)]
    robot = report.get("robot_path")
    if isinstance(robot, dict):
        parts.append("<h2>The robot's reported path (about its own LSC centre)</h2>")
        parts.append(key_value_table({k: v for k, v in robot.items() if k not in skip}))
        robot_profile = profile_of(robot)
        if robot_profile:
            parts.append(_envelopes(robot_profile))
    return parts


def _iso9283_body(report: dict[str, Any]) -> list[str]:
    attained = report.get("attained", {})
    poses = [
        {"pose": name, **figs, "xyz_cmd_mm": attained.get(name, {}).get("xyz_cmd_mm")}
        for name, figs in report.get("poses", {}).items()
    ]
    parts = ["<h2>Pose accuracy and repeatability</h2>", rows_table(poses, _columns(poses, ["pose"]))]
    distances = [{"poses": name, **figs} for name, figs in report.get("distances", {}).items()]
    if distances:
        parts += ["<h2>Distance accuracy and repeatability</h2>", rows_table(distances, _columns(distances))]
    return parts


def _table1_body(report: dict[str, Any]) -> list[str]:
    rows = report.get("rows", [])
    conditions = {k: v for k, v in report.items() if k not in ("rows", "summary", "notes")}
    parts = ["<h2>Conditions</h2>", key_value_table(conditions)]
    parts += ["<h2>Deviation between the two visits of each position</h2>", rows_table(rows, _columns(rows))]
    summary = report.get("summary", {})
    if summary:
        keys = list(dict.fromkeys(k for part in summary.values() for k in part))
        stats = [{"statistic": name, **values} for name, values in summary.items()]
        parts += ["<h2>Summary over the positions</h2>", rows_table(stats, ["statistic", *keys])]
    return parts


def _verify_body(report: dict[str, Any]) -> list[str]:
    head = {k: v for k, v in report.items() if k in ("verdict", "model_version", "threshold_mm", "threshold_deg")}
    parts = ["<h2>Verdict</h2>", key_value_table(head)]
    parts += ["<h2>Drift from the stored model</h2>", key_value_table(report.get("drift", {}))]
    parts += ["<h2>Error of the nominal model, for comparison</h2>", key_value_table(report.get("nominal", {}))]
    poses = report.get("poses", [])
    if poses:
        parts += ["<h2>Per pose</h2>", rows_table(poses, _columns(poses, ["stored_pose"]))]
    return parts


_BODIES = {"circle": _circle_body, "iso9283": _iso9283_body, "table1": _table1_body, "verify": _verify_body}
CAPTIONS = {
    "circle.svg": "Radial deviation against angle about the common LSC centre, magnified (the scale is on the "
    "plot; the nominal circle true to size, dashed): cw and ccw paths, dotted the G envelope circles of each "
    "direction about its own LSC centre, + the LSC centre.",
    "iso9283.svg": "Per pose the attained positions as offsets from the command (×), projected on xy, xz and yz, "
    "their barycentre (o: its offset is AP_p) and the RP_l sphere about it.",
    "table1.svg": "Per position the later visit minus the earlier, with ±σ error bars.",
}


def _inline_svg(svg: bytes) -> str:
    """The SVG element of a file, without its XML declaration and DOCTYPE (not allowed mid-page)."""
    text = svg.decode("utf-8")
    return re.sub(r"^\s*<\?xml[^>]*\?>\s*(<!DOCTYPE[^>]*>\s*)?", "", text)


def render_html(kind: str, report: dict[str, Any], *, svgs: dict[str, bytes] | None = None) -> str:
    """The report page of ``kind`` (``circle``, ``iso9283``, ``table1``) from its JSON dict.

    ``svgs``: the figures already rendered (name -> SVG bytes, as :func:`figures` gives them), so
    a caller that writes the files too draws them once; by default they are drawn here.
    """
    if kind not in TITLES:
        raise ValueError(f"no report of kind {kind!r}; kinds: {', '.join(TITLES)}")
    title = TITLES[kind]
    parts = [f"<h1>{_e(title)}</h1>", *_BODIES[kind](report)]
    if svgs is None:
        svgs = figures(kind, report, formats=("svg",))
    svgs = {name: data for name, data in svgs.items() if name.endswith(".svg")}
    if svgs:
        parts.append("<h2>Figures</h2>")
        parts += [
            f'<figure id="{_e(name)}">{_inline_svg(data)}'
            f"<figcaption>{_e(CAPTIONS.get(name, name))} ({_e(name)})</figcaption></figure>"
            for name, data in svgs.items()
        ]
    notes = list(report.get("notes", []))
    robot = report.get("robot_path")
    if isinstance(robot, dict):
        notes += [f"the robot's reported path: {n}" for n in robot.get("notes", [])]
    parts.append(_notes(notes))
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{_e(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(p for p in parts if p)
        + "\n</body>\n</html>\n"
    )
