"""Figures of the robot's accuracy reports: file name -> PNG or SVG bytes, from the report's JSON alone.

- ``circle``: ISO 230-4's polar plot in the style of the seed paper's Figure 7. Each point is
  drawn at its angle about the common LSC centre and at the radius ``R + N · (r - R)``: the
  nominal circle at its true size, the deviations magnified N times (stated on the plot), the cw
  and ccw paths in two colours, the G envelope circles of each direction (about that direction's
  LSC centre, so under magnification they are limaçons about the common centre), the LSC centre
  mark and the results block. With the robot's reported path in the report, a second panel at
  the same magnification shows it beside the camera's.
- ``iso9283``: per pose, the attained positions as offsets from the command (µm) projected on
  the xy, xz and yz planes, the barycentre (its offset is AP) and the RP_l sphere about it (a
  sphere projects to a circle of its own radius).
- ``table1``: per position the bars of dx, dy, dz (µm) and dω, dφ, dκ (mdeg) with ±σ error bars.

Why matplotlib (headless, Agg) and not an SVG writer of our own: the same figure gives the PNG
the issue asks for, text and tick layout come for free, and the deterministic SVG is two
settings. :class:`matplotlib.figure.Figure` is used directly, never ``pyplot``: pyplot keeps a
global list of figures, which a service rendering reports in its threads must not share; a bare
Figure is garbage once its bytes are written. The settings live in one ``rc_context`` so the
process's own rcParams are left alone. ``svg.fonttype = "none"`` writes text as ``<text>`` (the
page can be searched, the numbers read by a test) rather than as glyph outlines;
``svg.hashsalt`` and ``metadata={"Date": None}`` make the same report give the same bytes.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")  # headless: the cell PC and CI have no display (a bare Figure needs no backend)

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from service.core.accuracy.circle import radial_profile

_RC = {
    "svg.hashsalt": "posecell-report",  # ids from content, not random: two renders, one file
    "svg.fonttype": "none",
    "font.family": "DejaVu Sans",
    "font.size": 9.0,
    "axes.titlesize": 10.0,
}
PNG_DPI = 100
GAP_DEG = 3.0  # consecutive points farther apart than this are not joined by the drawn path
COLOURS = {"cw": "#1f5fbf", "ccw": "#d0312d"}
DIRECTIONS = ("cw", "ccw")
BAND_FRACTION = 0.3  # the magnified deviations fill this fraction of the nominal radius
MAX_PLOTTED_POINTS = 3600  # per path: a denser path is thinned for the plot (the JSON keeps every point)


def _fmt(value: Any) -> str:
    return "—" if value is None else f"{value:.4f}" if isinstance(value, float) else str(value)


def nice_floor(x: float) -> float:
    """The largest of 1, 2, 5 × 10^k not above x (x > 0).

    >>> nice_floor(1500.0), nice_floor(0.7), nice_floor(49.0)
    (1000.0, 0.5, 20.0)
    """
    k = math.floor(math.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**k <= x * (1.0 + 1e-12):
            return m * 10.0**k
    return 10.0**k


def magnification(radius_mm: float, max_abs_deviation_mm: float) -> float:
    """N of the polar plot: the largest 1-2-5 number that keeps ``N · max|r - R|`` within
    ``BAND_FRACTION`` of R, at least 1 (a path off by more than that is drawn true to scale),
    and 10⁶ for a path with no deviation at all."""
    if max_abs_deviation_mm <= 0.0:
        return 1e6
    return max(1.0, min(1e6, nice_floor(BAND_FRACTION * radius_mm / max_abs_deviation_mm)))


def _envelope_deviation_mm(theta: np.ndarray, radius_mm: float, offset_mm: Sequence[float]) -> np.ndarray:
    """The radius minus R, at angles theta (k,) about the common centre, of a circle of
    ``radius_mm`` about ``offset_mm`` (2,), the point of the circle in direction theta."""
    dx, dy = offset_mm
    along = dx * np.cos(theta) + dy * np.sin(theta)
    across = dx * np.sin(theta) - dy * np.cos(theta)
    return np.asarray(along + np.sqrt(np.maximum(radius_mm**2 - across**2, 0.0)))


FORMATS = ("svg", "png")


def _save(fig: Figure, stem: str, formats: Sequence[str]) -> dict[str, bytes]:
    out = {}
    for fmt in formats:
        buf = io.BytesIO()
        metadata = {"Date": None} if fmt == "svg" else {"Software": None}
        fig.savefig(buf, format=fmt, dpi=PNG_DPI, metadata=metadata)
        out[f"{stem}.{fmt}"] = buf.getvalue()
    return out


def _deviation_band_mm(profile: dict[str, Any]) -> float:
    values = [0.0]
    for k in DIRECTIONS:
        d = profile.get(k)
        if d:
            values += [abs(v) for v in d["radial_deviation_mm"]]
            values += [abs(d["envelope_inner_mm"]), abs(d["envelope_outer_mm"])]
    return max(values)


def _deviation_range_mm(profiles: Sequence[dict[str, Any]]) -> tuple[float, float]:
    """The smallest and largest deviation (mm, 0 included) of all paths' points."""
    devs = [v for p in profiles for k in DIRECTIONS if p.get(k) for v in p[k]["radial_deviation_mm"]]
    return min(0.0, *devs), max(0.0, *devs)


def _broken_at_gaps(theta: np.ndarray, dev_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The path with a NaN (a break in the drawn line) wherever consecutive points are more than
    ``GAP_DEG`` apart in angle: frames missing along an arc, or where a lap starts again, must not
    be drawn as a chord across the circle."""
    if theta.size < 2:
        return theta, dev_mm
    jump = np.abs(np.angle(np.exp(1j * np.diff(theta))))
    cuts = np.flatnonzero(jump > math.radians(GAP_DEG)) + 1
    return np.insert(theta, cuts, np.nan), np.insert(dev_mm, cuts, np.nan)


def _polar_panel(ax: Any, profile: dict[str, Any], N: float, rings_mm: Sequence[float], title: str, gid: str) -> None:
    """One path's magnified polar plot on ``ax`` (mm in the plane; the radius R + N (r - R)); the
    SVG groups are named ``{gid}-path-cw``, ``{gid}-envelope-cw-inner`` … (unique in the page)."""
    R = float(profile["radius_mm"])
    grid = np.radians(np.arange(0.0, 360.5, 0.5))

    def xy(theta: np.ndarray, dev_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rho = R + N * dev_mm
        return rho * np.cos(theta), rho * np.sin(theta)

    for i, t_mm in enumerate(rings_mm):  # reading rings at round deviations, labelled in µm
        ax.plot(*xy(grid, np.full_like(grid, t_mm)), color="#cccccc", lw=0.5, gid=f"{gid}-ring-{i}")
        label = f"{t_mm * 1e3:+.4g} µm"
        box = {"fc": "white", "ec": "none", "alpha": 0.8, "pad": 0.5}  # on its ring, under the paths (zorder)
        ax.text(0.0, R + N * t_mm, label, fontsize=7, color="#888888", ha="center", va="center", bbox=box, zorder=1)
    ax.plot(*xy(grid, np.zeros_like(grid)), color="#555555", lw=0.8, ls="--", gid=f"{gid}-nominal", label="nominal")
    for k in DIRECTIONS:
        d = profile.get(k)
        if not d:
            continue
        theta = np.radians(np.asarray(d["theta_deg"]))
        dev = np.asarray(d["radial_deviation_mm"])
        step = max(1, math.ceil(len(theta) / MAX_PLOTTED_POINTS))
        t_k, d_k = _broken_at_gaps(theta[::step], dev[::step])
        ax.plot(*xy(t_k, d_k), color=COLOURS[k], lw=1.2, gid=f"{gid}-path-{k}", label=k)
        for edge in ("inner", "outer"):
            env = _envelope_deviation_mm(grid, R + d[f"envelope_{edge}_mm"], d["centre_offset_mm"]) - R
            ax.plot(*xy(grid, env), color=COLOURS[k], lw=0.6, ls=":", gid=f"{gid}-envelope-{k}-{edge}")
    ax.plot([0.0], [0.0], marker="+", ms=10, color="black", ls="none", gid=f"{gid}-lsc-centre", label="LSC centre")
    ax.set_aspect("equal")
    limit = 1.12 * (R + N * max(max(rings_mm, default=0.0), _deviation_range_mm([profile])[1]))
    ax.set_xlim(-limit, limit)
    ax.set_ylim(-limit, limit)
    ax.set_axis_off()
    ax.set_title(title)
    ax.text(0.0, -0.04, f"deviations ×{N:g}", transform=ax.transAxes, fontsize=9, fontweight="bold")


_RESULT_ROWS = (
    ("G_cw", "G_cw_mm"),
    ("G_ccw", "G_ccw_mm"),
    ("G_bi", "G_bidirectional_mm"),
    ("H", "H_mm"),
    ("F_max", "F_max_mm"),
    ("F_min", "F_min_mm"),
    ("mean r - R", "mean_radial_deviation_mm"),
)


def _circle_results_lines(report: dict[str, Any], N: float) -> list[str]:
    """The results block: the figures (mm), the conditions, the scale; one line each."""
    c = report.get("conditions", {})

    def row(label: str, value: Any, unit: str = "mm") -> str:
        return f"{label:<12} {_fmt(value):>9} {unit}"

    lines = [row(label, report.get(key)) for label, key in _RESULT_ROWS]
    lines += ["", row("R nominal", c.get("radius_mm")), row("R of LSC", c.get("radius_lsc_mm"))]
    lines.append(f"{'points':<12} {c.get('n_cw', '—')} cw, {c.get('n_ccw', '—')} ccw")
    if report.get("centre_offset_in_plane_mm") is not None:
        lines.append(row("centre off.", report["centre_offset_in_plane_mm"]))
    lines.append(row("out of plane", report.get("out_of_plane_span_mm")))
    lines.append(f"{'scale':<12} deviations ×{N:g}")
    robot = report.get("robot_path")
    if robot:
        lines += ["", "robot-reported path:"]
        lines += [row(label, robot.get(key)) for label, key in _RESULT_ROWS[:6]]
    return lines


def profile_of(report: dict[str, Any]) -> dict[str, Any] | None:
    """The circle report's ``profile``; or, for a report that kept the per-point arrays instead
    (``CircleResult.to_dict(points=True)``), the same rebuilt from them and the conditions; None
    when it has neither."""
    if report.get("profile"):
        return dict(report["profile"])
    points, c = report.get("points"), report.get("conditions", {})
    needed = ("radius_mm", "centre_mm", "plane_normal", "theta_zero_axis", "radius_lsc_mm")
    if not points or "theta_deg" not in points or not all(c.get(k) is not None for k in needed):
        return None
    return radial_profile(
        np.radians(points["theta_deg"]),
        points["radial_deviation_mm"],
        [d == "cw" for d in points["direction"]],
        c["radius_mm"],
        centre_mm=c["centre_mm"],
        centre_cw_mm=c.get("centre_cw_mm"),
        centre_ccw_mm=c.get("centre_ccw_mm"),
        plane_normal=c["plane_normal"],
        theta_zero_axis=c["theta_zero_axis"],
        radius_lsc_mm=c["radius_lsc_mm"],
    )


def circle_figures(report: dict[str, Any], formats: Sequence[str] = FORMATS) -> dict[str, bytes]:
    """``circle.svg`` and ``circle.png``; none when the report has no profile (:func:`profile_of`)."""
    profile = profile_of(report)
    if not profile:
        return {}
    robot = report.get("robot_path") or {}
    panels = [(profile, "camera-measured path (base frame)")]  # the true path
    robot_profile = profile_of(robot) if robot else None
    if robot_profile:
        panels.append((robot_profile, "robot-reported path"))
    band = max(_deviation_band_mm(p) for p, _ in panels)
    R = float(profile["radius_mm"])
    N = magnification(R, band)
    # one set of rings for every panel (same scale, same rings), within the deviations drawn
    lo, hi = _deviation_range_mm([p for p, _ in panels])
    ticks = MaxNLocator(nbins=4, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
    rings = [float(t) for t in ticks if lo - 1e-12 <= t <= hi + 1e-12 and abs(t) > 1e-12 and R + N * t > 0.0]
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(5.2 * len(panels) + 3.0, 5.6))
        gs = fig.add_gridspec(1, len(panels) + 1, width_ratios=[1.0] * len(panels) + [0.6], wspace=0.05)
        for i, (p, title) in enumerate(panels):
            _polar_panel(fig.add_subplot(gs[0, i]), p, N, rings, title, ("camera", "robot")[i])
        fig.axes[0].legend(loc="upper left", fontsize=7, frameon=False, bbox_to_anchor=(-0.02, 1.02))
        text_ax = fig.add_subplot(gs[0, -1])
        text_ax.set_axis_off()
        for j, line in enumerate(_circle_results_lines(report, N)):  # one <text> a line: each found on its own
            text_ax.text(0.0, 0.98 - 0.04 * j, line, family="DejaVu Sans Mono", fontsize=8.5, va="top")
        fig.suptitle("ISO 230-4 circular test")
        return _save(fig, "circle", formats)


def _projection_panel(
    ax: Any, offset_um: np.ndarray, rp_um: float | None, axes: tuple[int, int], names: str, gid: str
) -> None:
    """Offsets (n, 3) µm projected on the plane of ``axes``; SVG groups ``{gid}-attained`` …"""
    i, j = axes
    bary = offset_um.mean(axis=0)
    ax.scatter(offset_um[:, i], offset_um[:, j], s=8, color="#1f5fbf", alpha=0.7, gid=f"{gid}-attained", lw=0)
    ax.plot([0.0], [0.0], marker="x", ms=8, color="black", ls="none", gid=f"{gid}-command")
    ax.plot([bary[i]], [bary[j]], marker="o", ms=5, mfc="none", color="#d0312d", ls="none", gid=f"{gid}-barycentre")
    if rp_um is not None and rp_um > 0.0:
        t = np.linspace(0.0, 2.0 * np.pi, 181)
        ax.plot(
            bary[i] + rp_um * np.cos(t), bary[j] + rp_um * np.sin(t), color="#d0312d", lw=0.8, gid=f"{gid}-rp-sphere"
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{names[0]} (µm)")
    ax.set_ylabel(f"{names[1]} (µm)")
    ax.tick_params(labelsize=7)


def iso9283_figures(report: dict[str, Any], formats: Sequence[str] = FORMATS) -> dict[str, bytes]:
    """``iso9283.svg`` and ``.png``: a row of three projections per pose; none without ``attained``."""
    attained = report.get("attained") or {}
    poses = [name for name in report.get("poses", {}) if name in attained]
    if not poses:
        return {}
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(9.0, 2.8 * len(poses) + 0.6))
        # fixed margins, not layout="constrained": that solver costs about half the drawing time
        axs = fig.subplots(len(poses), 3, squeeze=False, gridspec_kw={"wspace": 0.35, "hspace": 0.45})
        fig.subplots_adjust(
            left=0.07, right=0.98, bottom=0.6 / fig.get_figheight(), top=1.0 - 0.55 / fig.get_figheight()
        )
        for k, (row, name) in enumerate(zip(axs, poses, strict=True)):
            offset = np.asarray(attained[name]["offset_um"], dtype=np.float64).reshape(-1, 3)
            rp_mm = report["poses"][name].get("RP_l_mm")
            rp = None if rp_mm is None else 1e3 * float(rp_mm)
            for ax, axes, names in zip(row, ((0, 1), (0, 2), (1, 2)), ("xy", "xz", "yz"), strict=True):
                _projection_panel(ax, offset, rp, axes, names, f"pose{k}-{names}")  # the index: names are free text
            ap = report["poses"][name].get("AP_p_mm")
            row[0].set_title(f"{name}: AP_p {_fmt(ap)} mm, RP_l {_fmt(rp_mm)} mm", loc="left")
        fig.suptitle("ISO 9283: attained positions about the command (×), barycentre (o), RP_l sphere")
        return _save(fig, "iso9283", formats)


TABLE1_BARS = (
    (("dx_mm", "sigma_x_mm"), ("dy_mm", "sigma_y_mm"), ("dz_mm", "sigma_z_mm")),
    (("domega_deg", "sigma_omega_deg"), ("dphi_deg", "sigma_phi_deg"), ("dkappa_deg", "sigma_kappa_deg")),
)
_TABLE1_PANELS = (("position deviation (µm)", 1e3, ("x", "y", "z")), ("orientation deviation (mdeg)", 1e3, "ωφκ"))


def table1_figures(report: dict[str, Any], formats: Sequence[str] = FORMATS) -> dict[str, bytes]:
    """``table1.svg`` and ``.png``: per position the six deviations as bars with ±σ; none without rows."""
    rows = report.get("rows") or []
    if not rows:
        return {}
    x = np.arange(len(rows), dtype=np.float64)
    width = 0.26
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(max(6.0, 1.0 * len(rows) + 3.0), 5.6), layout="constrained")
        axs = fig.subplots(2, 1, sharex=True)
        for ax, bars, (label, scale, names) in zip(axs, TABLE1_BARS, _TABLE1_PANELS, strict=True):
            for k, ((value, sigma), name) in enumerate(zip(bars, names, strict=True)):
                v = scale * np.array([float(r.get(value) or 0.0) for r in rows])
                s = scale * np.array([float(r.get(sigma) or 0.0) for r in rows])
                bars_k = ax.bar(x + (k - 1) * width, v, width, yerr=s, capsize=2, label=name)
                for i, rect in enumerate(bars_k):  # SVG ids unique in the page: one per bar
                    rect.set_gid(f"bar-{value}-{i}")
                if bars_k.errorbar is not None:
                    for line in bars_k.errorbar.lines[2]:
                        line.set_gid(f"sigma-{value}")
            ax.axhline(0.0, color="black", lw=0.6)
            ax.set_ylabel(label)
            ax.legend(fontsize=7, ncols=3, frameon=False)
        axs[1].set_xticks(x, [str(r.get("position", i + 1)) for i, r in enumerate(rows)])
        axs[1].set_xlabel("position (later visit minus earlier, ±σ)")
        fig.suptitle("Deviation between the two visits of each position")
        return _save(fig, "table1", formats)


_BY_KIND: dict[str, Callable[[dict[str, Any], Sequence[str]], dict[str, bytes]]] = {
    "circle": circle_figures,
    "iso9283": iso9283_figures,
    "table1": table1_figures,
    "verify": lambda report, formats: {},  # a verification's per-pose table is its picture
}


def figures(kind: str, report: dict[str, Any], formats: Sequence[str] = FORMATS) -> dict[str, bytes]:
    """File name -> contents (``circle.svg``, ``circle.png`` …) of the figures of a report of ``kind``
    in each of ``formats`` (``"svg"``, ``"png"``); empty when the report lacks what they are drawn
    from (e.g. a report.json from before the plots)."""
    if kind not in _BY_KIND:
        raise ValueError(f"no figures of kind {kind!r}; kinds: {', '.join(_BY_KIND)}")
    unknown = set(formats) - set(FORMATS)
    if unknown:
        raise ValueError(f"figure formats are {', '.join(FORMATS)}, not {', '.join(sorted(unknown))}")
    return _BY_KIND[kind](report, formats)
