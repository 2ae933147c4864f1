"""``posecell report circle|iso9283|table1``: the robot's accuracy from recorded poses (DESIGN section 5).

One JSON object on stdout (the figures), and ``report.json``, ``report.md``, the plots (SVG and PNG) and
``report.html`` in ``-o DIR``; the
CSV formats and the analyses are in :mod:`service.workflows.reports` and :mod:`service.core.accuracy`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.common import CliError, Subparsers, print_err, print_json, solving


def add_parser(subparsers: Subparsers) -> None:
    rp = subparsers.add_parser(
        "report", help="the robot's accuracy: ISO 230-4 circle, ISO 9283 poses, the paper's Table 1"
    )
    kinds = rp.add_subparsers(dest="what", metavar="WHAT")
    kinds.required = True
    circle = kinds.add_parser(
        "circle",
        help="ISO 230-4 circular test: G (cw, ccw, bidirectional), H, F, mean radial deviation",
        description="CSV columns in time order: t_s, direction (cw or ccw), x_mm, y_mm, z_mm; optional a_deg, "
        "b_deg, c_deg (KUKA A, B, C: the orientation deviation along the path) and x_cmd_mm, y_cmd_mm, "
        "z_cmd_mm (the robot's reported path).",
    )
    circle.add_argument("--radius-mm", required=True, type=float, help="the nominal radius, mm")
    circle.add_argument("--centre-mm", help="the nominal centre X,Y,Z mm (for the centre offset)")
    iso = kinds.add_parser(
        "iso9283",
        help="ISO 9283 pose accuracy and repeatability (AP, RP, vAP) per pose",
        description="CSV columns: pose, cycle, x_cmd_mm, y_cmd_mm, z_cmd_mm, a_cmd_deg, b_cmd_deg, c_cmd_deg, "
        "x_mm, y_mm, z_mm, a_deg, b_deg, c_deg (KUKA A, B, C), optional direction (of approach).",
    )
    t1 = kinds.add_parser(
        "table1",
        help="the paper's Table 1: positions visited forward then in reverse order, deviations with σ",
        description="CSV columns in visit order: [position,] x_mm, y_mm, z_mm, a_deg, b_deg, c_deg (KUKA A, B, C) "
        "[, sigma_x_mm, sigma_y_mm, sigma_z_mm, sigma_a_deg, sigma_b_deg, sigma_c_deg]; without position the "
        "rows are positions 1..K then K..1.",
    )
    for p, kind in ((circle, "circle"), (iso, "iso9283"), (t1, "table1")):
        p.add_argument("--poses", required=True, type=Path, help="the recorded poses (CSV)")
        p.add_argument(
            "-o",
            "--out",
            required=True,
            type=Path,
            help="folder for report.json, report.md, the figures (SVG, PNG) and report.html",
        )
        p.set_defaults(func=run, kind=kind)


def run(args: argparse.Namespace) -> int:
    from service.workflows.reports import circle_report, iso9283_report, table1_report, write_report

    with solving(f"report {args.kind}"):
        if args.kind == "circle":
            report = circle_report(args.poses, args.radius_mm, _centre(args.centre_mm))
        elif args.kind == "iso9283":
            report = iso9283_report(args.poses)
        else:
            report = table1_report(args.poses)
    for path in write_report(args.out, args.kind, report):
        print_err(f"posecell report {args.kind}: wrote {path}")
    print_json(report)
    return 0


def _centre(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise CliError(f"--centre-mm takes X,Y,Z in mm, e.g. 1200,0,800, not {text!r}")
    return values
