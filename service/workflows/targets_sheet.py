"""Printable target sheets: one layout gives the SVG to print and the field.json to measure.

``posecell targets sheet --svg OUT.svg --field OUT.json`` (DESIGN section 3)
calls :func:`make_sheet` and :func:`field_json_of_sheet` and writes what they
return. Nothing here touches files.

Field frame of a sheet (right-handed, mm)::

    origin  the centre of the sheet
    x       to the right along the printed sheet, as the title reads
    y       up the sheet, towards the title
    z       out of the printed face, towards the camera; every target at z = 0

    SVG user units are mm with y running down the page, so
    x_svg = x + width_mm / 2 and y_svg = height_mm / 2 - y.

A camera looking at the sheet head-on, with the title at the top of its image,
has camera x = field x and camera y = field -y. That is the pose ``reference_pose``
in ``service.sim.scene`` uses.

Drawing (white on black; a retro-reflective print or cut-out on a dark plate):

- A black rectangle covers the whole sheet.
- Each target's central measuring disk is a ``<circle>`` whose ``id`` is the
  target's id in the field (``C<code>`` coded, ``P<n>`` uncoded).
- A coded target's ring sectors (:mod:`service.core.targets.codes`) are white annular
  sector paths, one path per run of bright sectors. Sector k spans
  [30k, 30k + 30) deg counter-clockwise from +x as seen on the printed face.
- The title, labels and the ruler are grey and stay in the margins and
  between the targets, outside every ring.

Layout: the targets sit on one regular grid of slots spanning the sheet
inside the margins. The coded targets take an evenly spread sub-grid of it:
6 x 5 for 30 targets on the default sheet, about 170 mm apart, so any
camera view of a third of the sheet holds at least 4 whole coded targets.
The uncoded targets are spread evenly over the remaining slots. A ``seed``
jitters them off the grid (never closer than the clearance), so that
matching by projection cannot slip by one slot. The default sheet suits
the reference scene: the reference camera at about 1 m sees about
1089 x 862 mm of a head-on plate.

Scale: the field file lists ``scale_bars`` between distant coded targets
(nominal centre distances, to be replaced by measured ones if the print may
be scaled), and a drawn ruler of known length under ``rulers``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
from numpy.typing import NDArray

from service.core.targets.codes import N_BITS, RING_INNER, RING_OUTER, bright_runs, n_codes
from service.core.targets.field import Field
from service.store.formats import field_to_json

Array = NDArray[np.float64]

FRAME_DESCRIPTION = (
    "origin at the centre of the sheet; x to the right and y up the printed sheet (towards the "
    "title); z out of the printed face towards the camera; mm; x_svg = x + width_mm/2, "
    "y_svg = height_mm/2 - y"
)
LABEL_GREY = "#5a5a5a"


@dataclass(frozen=True)
class SheetOptions:
    """Layout of a printable target sheet; lengths in mm.

    ``clearance_mm`` is the least free space between the outer edges of any
    two targets: a coded target's edge is its ring, at ``RING_OUTER`` disk
    radii. ``margin_mm`` is the least space between a target's edge and the
    sheet's edge, and it also holds the title and the ruler. With ``seed`` None
    the uncoded targets sit exactly on the grid. Otherwise they are jittered by
    up to ``jitter_fraction`` of the grid pitch, deterministically for that
    seed. Coded targets carry ``first_code .. first_code + n_coded - 1``.
    """

    width_mm: float = 720.0  # the reference scene: the view of c = 12 mm, 1300x1030 px at ~1 m
    height_mm: float = 580.0
    n_coded: int = 30
    n_uncoded: int = 200
    coded_diameter_mm: float = 10.0
    uncoded_diameter_mm: float = 6.0
    margin_mm: float = 40.0
    clearance_mm: float = 5.0
    first_code: int = 1
    title: str = "posecell target sheet"
    name: str = "posecell-sheet"
    seed: int | None = None
    jitter_fraction: float = 0.2
    ruler_mm: float | None = None  # drawn ruler length; None: the largest 100 mm multiple that fits
    labels: bool = True  # print each coded target's id under it

    def __post_init__(self) -> None:
        for name in ("width_mm", "height_mm", "coded_diameter_mm", "uncoded_diameter_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive, got {v}")
        for name in ("margin_mm", "clearance_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be non-negative, got {v}")
        if self.n_coded < 0 or self.n_uncoded < 0 or self.n_coded + self.n_uncoded < 1:
            raise ValueError(f"need at least one target, got {self.n_coded} coded and {self.n_uncoded} uncoded")
        last = self.first_code + self.n_coded - 1
        if self.n_coded and not (1 <= self.first_code and last <= n_codes()):
            raise ValueError(f"codes {self.first_code}..{last} are outside the family 1..{n_codes()}")
        if not 0 <= self.jitter_fraction < 0.5:
            raise ValueError(f"jitter_fraction must lie in [0, 0.5), got {self.jitter_fraction}")


def _grid_shape(n: int, aspect: float) -> tuple[int, int]:
    """Columns and rows (nx, ny), nx * ny >= n, nx / ny close to ``aspect``."""
    nx = max(1, round(math.sqrt(n * aspect)))
    return nx, max(1, math.ceil(n / nx))


def _slot_grid(
    n: int, n_coded: int, span_x: float, span_y: float
) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """Slots (nx, ny), coded sub-grid (kx, ky) and block size (sx, sy) with nx = kx*sx, ny = ky*sy.

    The smallest grid of at least ``n`` slots whose pitch is nearly the same
    along x and y; coded targets take one slot per block.
    """
    aspect = max(span_x, 1e-9) / max(span_y, 1e-9)
    if n_coded == 0:
        nx, ny = _grid_shape(n, aspect)
        return (nx, ny), (0, 0), (1, 1)
    kx, ky = _grid_shape(n_coded, aspect)
    best: tuple[float, int, int, int] | None = None
    for sx in range(1, 40):
        for sy in range(1, 40):
            nx, ny = kx * sx, ky * sy
            if nx * ny < n:
                continue
            px = span_x / max(nx - 1, 1)
            py = span_y / max(ny - 1, 1)
            skew = max(px, py) / min(px, py)
            key = (nx * ny * max(skew, 1.25), nx * ny, sx, sy)  # few slots, square cells
            if best is None or key < best:
                best = key
    assert best is not None
    sx, sy = best[2], best[3]
    return (kx * sx, ky * sy), (kx, ky), (sx, sy)


def _outer_radius(o: SheetOptions, coded: bool) -> float:
    return RING_OUTER * o.coded_diameter_mm / 2 if coded else o.uncoded_diameter_mm / 2


def _min_distance_violations(xy: Array, outer: Array, clearance_mm: float) -> NDArray[np.intp]:
    """Pairs (K, 2) of targets closer than their outer radii plus the clearance."""
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    need = outer[:, None] + outer[None] + clearance_mm
    i, j = np.nonzero(np.triu(d < need - 1e-9, 1))
    return np.stack([i, j], axis=1)


def _layout(o: SheetOptions) -> tuple[Array, NDArray[np.bool_]]:
    """Target centres (N, 2) in SVG mm and the coded mask (N,).

    Coded targets come first; each group is in raster order from the top left.
    """
    r_c, r_u = _outer_radius(o, True), _outer_radius(o, False)
    r_max = r_c if o.n_coded else r_u
    x0, x1 = o.margin_mm + r_max, o.width_mm - o.margin_mm - r_max
    y0, y1 = o.margin_mm + r_max, o.height_mm - o.margin_mm - r_max
    if x1 < x0 or y1 < y0:
        raise ValueError(
            f"a {o.width_mm} x {o.height_mm} mm sheet with {o.margin_mm} mm margins has no room for targets"
        )
    n = o.n_coded + o.n_uncoded
    span_x, span_y = x1 - x0, y1 - y0
    coded_slot_shape = _slot_grid(n, o.n_coded, span_x, span_y)
    (nx, ny), (kx, ky), (sx, sy) = coded_slot_shape
    xs = np.linspace(x0, x1, nx) if nx > 1 else np.array([(x0 + x1) / 2])
    ys = np.linspace(y0, y1, ny) if ny > 1 else np.array([(y0 + y1) / 2])

    coded_slot = np.zeros((ny, nx), dtype=bool)
    if o.n_coded:
        # One coded target in the middle slot of each sx x sy block: a regular sub-grid.
        rr, cc = np.meshgrid(sy // 2 + sy * np.arange(ky), sx // 2 + sx * np.arange(kx), indexing="ij")
        coded_slot[rr.ravel()[: o.n_coded], cc.ravel()[: o.n_coded]] = True
    coded_xy = np.array([(xs[c], ys[r]) for r in range(ny) for c in range(nx) if coded_slot[r, c]])
    free = [(r, c) for r in range(ny) for c in range(nx) if not coded_slot[r, c]]
    keep = np.round(np.linspace(0, len(free) - 1, o.n_uncoded)).astype(int) if o.n_uncoded else []
    uncoded_xy = np.array([(xs[free[k][1]], ys[free[k][0]]) for k in keep])
    xy = np.concatenate([a.reshape(-1, 2) for a in (coded_xy, uncoded_xy)])
    is_coded = np.r_[np.ones(o.n_coded, bool), np.zeros(o.n_uncoded, bool)]
    outer = np.where(is_coded, r_c, r_u)

    bad = _min_distance_violations(xy, outer, o.clearance_mm)
    if len(bad):
        pitch = min(np.diff(xs).min(initial=np.inf), np.diff(ys).min(initial=np.inf))
        raise ValueError(
            f"{o.n_coded} coded and {o.n_uncoded} uncoded targets do not fit a {o.width_mm} x "
            f"{o.height_mm} mm sheet: the grid pitch {pitch:.1f} mm leaves less than "
            f"{o.clearance_mm} mm between rings; use a larger sheet or fewer targets"
        )
    if o.seed is not None and o.n_uncoded and o.jitter_fraction > 0:
        pitch = (np.diff(xs).min(initial=x1 - x0), np.diff(ys).min(initial=y1 - y0))
        xy = _jitter(xy, is_coded, outer, o, pitch)
    return xy, is_coded


def _jitter(xy: Array, is_coded: NDArray[np.bool_], outer: Array, o: SheetOptions, pitch: tuple[float, float]) -> Array:
    """Move each uncoded target by up to ``jitter_fraction`` of the pitch, keeping the clearance."""
    rng = np.random.default_rng(o.seed)
    out = xy.copy()
    r_u = _outer_radius(o, False)
    lo = np.array([o.margin_mm + r_u, o.margin_mm + r_u])
    hi = np.array([o.width_mm - o.margin_mm - r_u, o.height_mm - o.margin_mm - r_u])
    for i in np.flatnonzero(~is_coded):
        for _ in range(8):  # a few tries; a target that finds no room stays where it is
            step = rng.uniform(-1, 1, 2) * o.jitter_fraction * np.asarray(pitch)
            cand = np.clip(xy[i] + step, lo, hi)
            d = np.linalg.norm(out - cand, axis=1)
            d[i] = np.inf
            if np.all(d >= outer + r_u + o.clearance_mm):
                out[i] = cand
                break
    return out


def _f(v: float) -> str:
    """A number for SVG: 4 decimals (0.1 um), no trailing zeros."""
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def ring_path(cx: float, cy: float, radius_mm: float, code: int) -> str:
    """SVG path data of the bright sectors of ``code`` about an SVG point (mm), a subpath per run.

    Angles run counter-clockwise on the printed face. SVG's y runs down, so
    the point at angle theta is ``(cx + r cos theta, cy - r sin theta)``. The
    outer arc goes counter-clockwise (sweep-flag 0) and the inner arc comes
    back (sweep-flag 1).
    """
    r_in, r_out = RING_INNER * radius_mm, RING_OUTER * radius_mm
    step = 2 * math.pi / N_BITS

    def pt(r: float, t: float) -> str:
        return f"{_f(cx + r * math.cos(t))} {_f(cy - r * math.sin(t))}"

    parts = []
    for first, n in bright_runs(code):
        t0, t1 = first * step, (first + n) * step
        large = 1 if n * step > math.pi + 1e-9 else 0
        parts.append(
            f"M {pt(r_out, t0)} A {_f(r_out)} {_f(r_out)} 0 {large} 0 {pt(r_out, t1)} "
            f"L {pt(r_in, t1)} A {_f(r_in)} {_f(r_in)} 0 {large} 1 {pt(r_in, t0)} Z"
        )
    return " ".join(parts)


def _ruler_length(o: SheetOptions) -> float:
    if o.ruler_mm is not None:
        return float(o.ruler_mm)
    return float(max(100.0, 100.0 * math.floor(0.6 * o.width_mm / 100.0)))


def _ruler_ends(o: SheetOptions) -> tuple[tuple[float, float], tuple[float, float]]:
    """Ends of the drawn ruler, SVG mm: centred, in the bottom margin."""
    length = _ruler_length(o)
    y = o.height_mm - 0.55 * o.margin_mm
    return ((o.width_mm - length) / 2, y), ((o.width_mm + length) / 2, y)


def _field_from_layout(o: SheetOptions, xy_svg: Array, is_coded: NDArray[np.bool_]) -> Field:
    x = xy_svg[:, 0] - o.width_mm / 2
    y = o.height_mm / 2 - xy_svg[:, 1]
    xyz = np.c_[x, y, np.zeros(len(xy_svg))]
    codes = np.where(is_coded, 0, -1)
    codes[is_coded] = o.first_code + np.arange(int(is_coded.sum()))
    ids = [f"C{c}" for c in codes[is_coded]] + [f"P{k + 1}" for k in range(int((~is_coded).sum()))]
    diameters = np.where(is_coded, o.coded_diameter_mm, o.uncoded_diameter_mm)
    return Field(name=o.name, ids=tuple(ids), xyz=xyz, codes=codes.astype(np.int64), diameters_mm=diameters)


def make_sheet(options: SheetOptions | None = None) -> tuple[str, Field]:
    """The SVG text of a printable target sheet and the field of its targets.

    Parameters
    ----------
    options : SheetOptions, optional
        The layout; the default sheet when not given.

    Returns
    -------
    svg_text : str
        A standalone SVG document, sized in mm (``width="...mm"`` with a
        matching mm ``viewBox``).
    field : Field
        The targets in the sheet's field frame (see the module docstring), mm.
        Coded targets come first (``C<code>``), then the uncoded ones
        (``P1..``), each group in reading order from the top left of the sheet.

    Raises
    ------
    ValueError
        When the targets do not fit the sheet with the requested clearance.
    """
    o = options if options is not None else SheetOptions()
    xy, is_coded = _layout(o)
    field = _field_from_layout(o, xy, is_coded)
    W, H = o.width_mm, o.height_mm
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" '
        f'width="{_f(W)}mm" height="{_f(H)}mm" viewBox="0 0 {_f(W)} {_f(H)}">',
        f"<title>{escape(o.title)}</title>",
        f"<desc>{escape(o.name)}: {len(field)} targets ({int(is_coded.sum())} coded). Field frame: "
        f"{escape(FRAME_DESCRIPTION)}. Print at 100 % scale.</desc>",
        f'<rect id="background" x="0" y="0" width="{_f(W)}" height="{_f(H)}" fill="#000000"/>',
        '<g id="targets" fill="#ffffff" stroke="none">',
    ]
    for i, tid in enumerate(field.ids):
        cx, cy = xy[i]
        r = field.diameters_mm[i] / 2
        out.append(f'<circle id="{tid}" cx="{_f(cx)}" cy="{_f(cy)}" r="{_f(r)}"/>')
        if is_coded[i]:
            out.append(f'<path id="{tid}-ring" d="{ring_path(cx, cy, r, int(field.codes[i]))}"/>')
    out.append("</g>")
    out.extend(_annotations(o, field, xy, is_coded))
    out.append("</svg>")
    return "\n".join(out) + "\n", field


def _annotations(o: SheetOptions, field: Field, xy: Array, is_coded: NDArray[np.bool_]) -> list[str]:
    """Title, coded-target labels and the ruler, in grey, clear of every ring."""
    W, H, m = o.width_mm, o.height_mm, o.margin_mm
    font = max(2.0, min(10.0, 0.3 * m))
    out = [f'<g id="annotations" fill="{LABEL_GREY}" stroke="none" font-family="sans-serif">']
    if m >= 8.0:
        n_c = int(is_coded.sum())
        codes = f"codes {o.first_code}..{o.first_code + n_c - 1}, " if n_c else ""
        text = (
            f"{o.title}  |  {_f(W)} x {_f(H)} mm  |  {n_c} coded ({codes}ring "
            f"{RING_INNER:g}-{RING_OUTER:g} R) + {len(field) - n_c} uncoded  |  origin: sheet "
            "centre, x right, y up, z out  |  print at 100 %"
        )
        out.append(f'<text x="{_f(m)}" y="{_f(0.6 * m)}" font-size="{_f(font)}">{escape(text)}</text>')
        (ax, ay), (bx, by) = _ruler_ends(o)
        length = _ruler_length(o)
        tick = 0.15 * m
        out.append(f'<rect id="ruler" x="{_f(ax)}" y="{_f(ay - 0.2)}" width="{_f(length)}" height="0.4"/>')
        # Ticks every 10 mm (centred on their positions), longer every 50 and 100 mm.
        n_ticks = max(1, round(length / 10.0))
        for k in range(n_ticks + 1):
            h = tick if k % 10 == 0 else (0.6 * tick if k % 5 == 0 else 0.35 * tick)
            x = ax + k * length / n_ticks
            out.append(f'<rect x="{_f(x - 0.2)}" y="{_f(ay - h)}" width="0.4" height="{_f(h)}"/>')
        out.append(
            f'<text x="{_f(bx + 3)}" y="{_f(ay)}" font-size="{_f(0.6 * font)}">'
            f"{_f(length)} mm from the first to the last tick</text>"
        )
    if o.labels:
        size = 0.8 * o.coded_diameter_mm / 2
        for i in np.flatnonzero(is_coded):
            cx, cy = xy[i]
            y = cy + RING_OUTER * o.coded_diameter_mm / 2 + 0.5 * o.clearance_mm + 0.35 * size
            out.append(
                f'<text x="{_f(cx)}" y="{_f(y)}" font-size="{_f(size)}" text-anchor="middle">{field.ids[i]}</text>'
            )
    out.append("</g>")
    return out


def scale_bars(field: Field) -> list[dict[str, Any]]:
    """Nominal scale bars between far-apart coded targets (or uncoded ones if there are no coded).

    One across the sheet, one up it and one along the diagonal, each as
    ``{"from": id, "to": id, "length_mm": centre distance}``.
    """
    rows = np.flatnonzero(field.is_coded)
    if len(rows) < 2:
        rows = np.arange(len(field))
    if len(rows) < 2:
        return []
    xy = field.xyz[rows, :2]
    pairs = []
    for direction in ((1.0, 0.0), (0.0, 1.0), (1.0, 1.0)):
        proj = xy @ np.asarray(direction)
        # Ends of the longest extent along the direction; ties go to the one nearest the middle.
        perp = xy @ np.array([-direction[1], direction[0]])
        lo = np.lexsort((np.abs(perp - np.median(perp)), proj))[0]
        hi = np.lexsort((np.abs(perp - np.median(perp)), -proj))[0]
        if lo != hi and (lo, hi) not in pairs:
            pairs.append((lo, hi))
    return [
        {
            "from": field.ids[rows[a]],
            "to": field.ids[rows[b]],
            "length_mm": round(float(np.linalg.norm(field.xyz[rows[a]] - field.xyz[rows[b]])), 6),
        }
        for a, b in pairs
    ]


def field_json_of_sheet(field: Field, options: SheetOptions | None = None) -> dict[str, Any]:
    """The ``field.json`` content of a sheet: DESIGN section 3's targets plus the sheet's metadata.

    Readers ignore the extra keys: ``frame`` (in words), ``sheet`` (size in
    mm), ``scale_bars``, ``rulers`` (the drawn ruler's ends in the field frame
    and its length) and ``coded_ring`` (the ring geometry in disk radii).
    """
    options = options if options is not None else SheetOptions()
    (ax, ay), (bx, by) = _ruler_ends(options)
    W, H = options.width_mm, options.height_mm
    data = field_to_json(field)
    return {
        "name": data["name"],
        "frame": FRAME_DESCRIPTION,
        "sheet": {"width_mm": W, "height_mm": H, "title": options.title},
        "coded_ring": {
            "inner_radius_over_disk_radius": RING_INNER,
            "outer_radius_over_disk_radius": RING_OUTER,
            "sectors": N_BITS,
        },
        "scale_bars": scale_bars(field),
        "rulers": [
            {
                "xyz_from": [round(ax - W / 2, 6), round(H / 2 - ay, 6), 0.0],
                "xyz_to": [round(bx - W / 2, 6), round(H / 2 - by, 6), 0.0],
                "length_mm": _ruler_length(options),
            }
        ]
        if options.margin_mm >= 8.0
        else [],
        "targets": data["targets"],
    }
