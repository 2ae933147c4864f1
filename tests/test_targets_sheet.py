"""The printable target sheet: what is printed (SVG) and what is measured (field) must agree.

The SVG is read back with ``xml.etree`` and its arcs are traced with an
implementation of the SVG specification's endpoint-to-centre conversion
written here. That way the drawing is checked against the code convention of
``service.core.targets.codes``, and not against the sheet module's own geometry.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from service.core.targets import codes as C
from service.core.targets.decode import read_codes
from service.sim.render import render_frame
from service.sim.scene import reference_camera, reference_pose
from service.store.formats import field_from_json
from service.workflows.targets_sheet import SheetOptions, field_json_of_sheet, make_sheet

SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture(scope="module")
def sheet():
    options = SheetOptions()
    svg, field = make_sheet(options)
    return options, ET.fromstring(svg.encode()), field


def _mm(value: str) -> float:
    assert value.endswith("mm"), value
    return float(value[:-2])


def _svg_from_field(options, xyz):
    """The documented transform: x_svg = x + W/2, y_svg = H/2 - y."""
    return np.c_[xyz[:, 0] + options.width_mm / 2, options.height_mm / 2 - xyz[:, 1]]


# -- an SVG path reader (M, L, A, Z, absolute) written from the SVG 1.1 spec, appendix F.6.5 --


def _arc_points(p1, p2, r, large, sweep, n=64):
    x1p, y1p = (p1[0] - p2[0]) / 2, (p1[1] - p2[1]) / 2
    rad = max(0.0, (r * r - x1p * x1p - y1p * y1p) / (x1p * x1p + y1p * y1p))
    sign = 1.0 if large != sweep else -1.0
    cxp, cyp = sign * math.sqrt(rad) * y1p, -sign * math.sqrt(rad) * x1p
    cx, cy = cxp + (p1[0] + p2[0]) / 2, cyp + (p1[1] + p2[1]) / 2
    t1 = math.atan2((y1p - cyp) / r, (x1p - cxp) / r)
    t2 = math.atan2((-y1p - cyp) / r, (-x1p - cxp) / r)
    dt = (t2 - t1) % (2 * math.pi)  # in [0, 2 pi): the positive (clockwise on the page) way round
    if not sweep and dt > 0:
        dt -= 2 * math.pi
    t = t1 + dt * np.linspace(0, 1, n)
    return np.c_[cx + r * np.cos(t), cy + r * np.sin(t)]


def _path_polygons(d: str) -> list[np.ndarray]:
    tokens = re.findall(r"[MLAZ]|-?[\d.]+(?:e-?\d+)?", d)
    polys, pts, pos, i = [], [], None, 0
    while i < len(tokens):
        cmd = tokens[i]
        i += 1
        if cmd == "M":
            pos = (float(tokens[i]), float(tokens[i + 1]))
            pts = [pos]
            i += 2
        elif cmd == "L":
            pos = (float(tokens[i]), float(tokens[i + 1]))
            pts.append(pos)
            i += 2
        elif cmd == "A":
            rx, ry, _rot, large, sweep, x, y = (float(t) for t in tokens[i : i + 7])
            assert rx == ry
            arc = _arc_points(pos, (x, y), rx, int(large), int(sweep))
            pts.extend(map(tuple, arc[1:]))
            pos = (x, y)
            i += 7
        elif cmd == "Z":
            polys.append(np.array(pts, dtype=np.float32))
        else:  # pragma: no cover - the sheet writes only M, L, A, Z
            raise AssertionError(f"unexpected path command {cmd}")
    return polys


def _inside(polys, point) -> bool:
    xy = (float(point[0]), float(point[1]))
    return any(cv2.pointPolygonTest(p.reshape(-1, 1, 2), xy, False) > 0 for p in polys)


# -- the tests ---------------------------------------------------------------


def test_sheet_states_its_physical_size_in_mm_with_a_matching_viewbox(sheet):
    options, root, _ = sheet
    assert root.tag == SVG + "svg"
    assert _mm(root.get("width")) == options.width_mm == 720.0
    assert _mm(root.get("height")) == options.height_mm == 580.0
    view_box = [float(v) for v in root.get("viewBox").split()]
    assert view_box == [0.0, 0.0, options.width_mm, options.height_mm]


def test_targets_are_white_on_a_black_background_covering_the_sheet(sheet):
    options, root, field = sheet
    background = root.find(SVG + "rect")
    assert background.get("fill") == "#000000"
    assert [float(background.get(k)) for k in ("x", "y", "width", "height")] == [
        0.0,
        0.0,
        options.width_mm,
        options.height_mm,
    ]
    group = root.find(f"{SVG}g[@id='targets']")
    assert group.get("fill") == "#ffffff"
    # The white group is drawn after the background, and every target sits inside it.
    children = list(root)
    assert children.index(background) < children.index(group)
    assert len(group.findall(SVG + "circle")) == len(field) == 230


def test_every_circle_matches_its_field_target_after_the_documented_transform(sheet):
    options, root, field = sheet
    circles = {c.get("id"): c for c in root.iter(SVG + "circle")}
    assert set(circles) == set(field.ids)
    assert np.all(field.xyz[:, 2] == 0.0)
    svg_xy = _svg_from_field(options, field.xyz)
    for i, tid in enumerate(field.ids):
        c = circles[tid]
        assert float(c.get("cx")) == pytest.approx(svg_xy[i, 0], abs=1e-4)
        assert float(c.get("cy")) == pytest.approx(svg_xy[i, 1], abs=1e-4)
        assert 2 * float(c.get("r")) == pytest.approx(field.diameters_mm[i], abs=1e-4)
    coded = field.is_coded
    assert coded.sum() == 30
    assert np.all(field.diameters_mm[coded] == 10.0) and np.all(field.diameters_mm[~coded] == 6.0)
    assert all(t == f"C{c}" for t, c in zip(np.array(field.ids)[coded], field.codes[coded]))
    assert [t for t in field.ids if t.startswith("P")] == [f"P{k}" for k in range(1, 201)]


def test_field_y_runs_up_the_printed_sheet_so_that_z_points_out_of_it(sheet):
    options, root, field = sheet
    circles = {c.get("id"): c for c in root.iter(SVG + "circle")}
    top = max(range(len(field)), key=lambda i: field.xyz[i, 1])
    right = max(range(len(field)), key=lambda i: field.xyz[i, 0])
    cy = [float(c.get("cy")) for c in circles.values()]
    cx = [float(c.get("cx")) for c in circles.values()]
    assert float(circles[field.ids[top]].get("cy")) == min(cy)  # field +y is up the page
    assert float(circles[field.ids[right]].get("cx")) == max(cx)
    # The title is printed at the top, towards field +y.
    title = root.find(f"{SVG}g[@id='annotations']/{SVG}text")
    assert float(title.get("y")) < options.margin_mm


def test_ring_sectors_follow_the_code_counter_clockwise_on_the_printed_face(sheet):
    options, root, field = sheet
    paths = {p.get("id"): p.get("d") for p in root.iter(SVG + "path")}
    svg_xy = _svg_from_field(options, field.xyz)
    step = 2 * math.pi / C.N_BITS
    for i in np.flatnonzero(field.is_coded):
        polys = _path_polygons(paths[f"{field.ids[i]}-ring"])
        bits = C.bits_of(int(field.codes[i]))
        R = field.diameters_mm[i] / 2
        cx, cy = svg_xy[i]

        def page(r, theta):  # noqa: B023 - evaluated inside this iteration
            return cx + r * math.cos(theta), cy - r * math.sin(theta)

        for k in range(C.N_BITS):
            for frac in (0.1, 0.5, 0.9):  # near both sector edges and in the middle
                theta = (k + frac) * step
                assert _inside(polys, page(2.6 * R, theta)) == bits[k], (field.ids[i], k, frac)
            assert not _inside(polys, page((C.RING_INNER - 0.05) * R, (k + 0.5) * step))
            assert not _inside(polys, page((C.RING_OUTER + 0.05) * R, (k + 0.5) * step))
            assert _inside(polys, page((C.RING_INNER + 0.05) * R, (k + 0.5) * step)) == bits[k]
            assert _inside(polys, page((C.RING_OUTER - 0.05) * R, (k + 0.5) * step)) == bits[k]


def test_targets_keep_their_clearance_and_the_margin(sheet):
    options, _, field = sheet
    outer = np.where(field.is_coded, C.RING_OUTER * field.diameters_mm / 2, field.diameters_mm / 2)
    xy = field.xyz[:, :2]
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2) - outer[:, None] - outer[None]
    np.fill_diagonal(d, np.inf)
    assert d.min() >= options.clearance_mm - 1e-9
    assert d.min() < 10 * options.clearance_mm  # the sheet is used, not left empty
    half = np.array([options.width_mm, options.height_mm]) / 2 - options.margin_mm
    assert np.all(np.abs(xy) + outer[:, None] <= half + 1e-9)


def test_any_view_of_a_third_of_the_sheet_holds_at_least_four_whole_coded_targets(sheet):
    options, _, field = sheet
    aspect = 1300 / 1030  # the reference camera's
    area = options.width_mm * options.height_mm / 3
    w, h = math.sqrt(area * aspect), math.sqrt(area / aspect)
    coded = field.xyz[field.is_coded, :2]
    ring = C.RING_OUTER * 10.0 / 2
    counts = []
    for x0 in np.linspace(-options.width_mm / 2, options.width_mm / 2 - w, 25):
        for y0 in np.linspace(-options.height_mm / 2, options.height_mm / 2 - h, 25):
            inside = (
                (coded[:, 0] - ring >= x0)
                & (coded[:, 0] + ring <= x0 + w)
                & (coded[:, 1] - ring >= y0)
                & (coded[:, 1] + ring <= y0 + h)
            )
            counts.append(int(inside.sum()))
    assert 4 <= min(counts) <= 12  # at least four everywhere; spread, not bunched


def test_field_file_carries_scale_bars_and_the_drawn_ruler(sheet):
    options, root, field = sheet
    data = field_json_of_sheet(field, options)
    assert data["sheet"] == {"width_mm": 720.0, "height_mm": 580.0, "title": options.title}
    ids = {t["id"]: np.array(t["xyz"]) for t in data["targets"]}
    assert len(data["scale_bars"]) >= 2
    for bar in data["scale_bars"]:
        length = np.linalg.norm(ids[bar["from"]] - ids[bar["to"]])
        assert bar["length_mm"] == pytest.approx(length, abs=1e-5)
        assert length > 0.5 * options.height_mm  # long bars, across the sheet
    (ruler,) = data["rulers"]
    a, b = np.array(ruler["xyz_from"]), np.array(ruler["xyz_to"])
    assert np.linalg.norm(b - a) == pytest.approx(ruler["length_mm"])
    drawn = root.find(f".//{SVG}rect[@id='ruler']")
    ends_svg = _svg_from_field(options, np.stack([a, b]))
    assert float(drawn.get("x")) == pytest.approx(ends_svg[0, 0])
    assert float(drawn.get("width")) == pytest.approx(ruler["length_mm"])
    assert float(drawn.get("y")) + float(drawn.get("height")) / 2 == pytest.approx(ends_svg[0, 1])
    assert ends_svg[0, 1] > options.height_mm - options.margin_mm  # in the bottom margin


def test_field_file_reads_back_as_the_same_field(sheet):
    options, _, field = sheet
    again = field_from_json(field_json_of_sheet(field, options))
    assert again.ids == field.ids
    assert np.allclose(again.xyz, field.xyz, atol=1e-6)
    assert np.array_equal(again.codes, field.codes)
    assert np.array_equal(again.diameters_mm, field.diameters_mm)


def test_layout_is_deterministic_and_a_seed_jitters_only_the_uncoded_targets():
    svg1, f1 = make_sheet(SheetOptions())
    svg2, f2 = make_sheet(SheetOptions())
    assert svg1 == svg2
    _, j1 = make_sheet(SheetOptions(seed=7))
    _, j2 = make_sheet(SheetOptions(seed=7))
    assert np.array_equal(j1.xyz, j2.xyz)
    moved = np.linalg.norm(j1.xyz - f1.xyz, axis=1)
    assert np.all(moved[f1.is_coded] == 0)
    assert np.median(moved[~f1.is_coded]) > 1.0  # most uncoded targets left the grid
    outer = np.where(j1.is_coded, C.RING_OUTER * 5.0, 3.0)
    d = np.linalg.norm(j1.xyz[:, None, :2] - j1.xyz[None, :, :2], axis=2)
    d -= outer[:, None] + outer[None]
    np.fill_diagonal(d, np.inf)
    assert d.min() >= SheetOptions().clearance_mm - 1e-9


def test_options_choose_codes_counts_and_sizes():
    svg, field = make_sheet(
        SheetOptions(
            width_mm=600, height_mm=450, n_coded=12, n_uncoded=40, first_code=100, coded_diameter_mm=8.0, margin_mm=25.0
        )
    )
    assert sorted(field.codes[field.is_coded].tolist()) == list(range(100, 112))
    assert len(field) == 52 and np.all(field.diameters_mm[field.is_coded] == 8.0)
    assert 'width="600mm"' in svg and 'height="450mm"' in svg


def test_too_many_targets_for_the_sheet_are_refused_in_one_sentence():
    with pytest.raises(ValueError, match="do not fit"):
        make_sheet(SheetOptions(width_mm=300, height_mm=200, n_coded=30, n_uncoded=200))
    with pytest.raises(ValueError, match="outside the family"):
        SheetOptions(n_coded=30, first_code=140)


def test_rendered_sheet_reads_back_its_own_codes():
    # End to end: the camera sees the whole default sheet from 1.5 m, head-on.
    options = SheetOptions()
    _, field = make_sheet(options)
    camera = reference_camera()
    T = reference_pose(distance_mm=1500.0)
    frame = render_frame(camera, field, T, rng=np.random.default_rng(5))
    rows = field.indices_of(list(frame.ids))
    coded = np.flatnonzero(field.is_coded[rows] & frame.fully_visible)
    assert len(coded) == 30
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ellipses = []
    for i in rows[coded]:
        rim = field.xyz[i] + 5.0 * np.c_[np.cos(t), np.sin(t), 0 * t]
        uv = camera.pixel_from_camera((np.linalg.inv(T) @ np.c_[rim, np.ones(64)].T).T[:, :3])
        (cu, cv), (w, h), ang = cv2.fitEllipse(uv.astype(np.float32))
        ellipses.append((cu, cv, w / 2, h / 2, np.radians(ang)))
    readings = read_codes(frame.image, np.array(ellipses))
    assert [r.code if r else 0 for r in readings] == field.codes[rows[coded]].tolist()
