"""``posecell targets sheet``: a printable target sheet (SVG, true size in mm) and the field.json of
exactly that sheet (the layout is in :mod:`service.workflows.targets_sheet`)."""

from __future__ import annotations

import argparse

from service.cli.common import CliError, Subparsers, print_err


def add_parser(subparsers: Subparsers) -> None:
    tg = subparsers.add_parser("targets", help="target sheets").add_subparsers(dest="what", metavar="WHAT")
    tg.required = True
    sh = tg.add_parser(
        "sheet",
        help="printable target sheet (SVG, true size in mm) and its field.json",
        description="Writes a printable SVG sheet (white targets on black, exact size in mm, each measuring "
        "disk a <circle id=...>) and the field.json of exactly that sheet. The default suits the reference "
        "scene: a plate seen from about 1 m by a 12 mm lens on a 1300x1030 px, 6.7 um sensor.",
    )
    sh.add_argument("--svg", required=True, help="output SVG")
    sh.add_argument("--field", required=True, help="output field.json")
    # default None: not given, SheetOptions' default applies (see run), so the CLI and the library cannot
    # drift, and building the parser does not import the layout (numpy and the core)
    sh.add_argument("--width-mm", type=float)
    sh.add_argument("--height-mm", type=float)
    sh.add_argument("--coded", type=int, help="number of coded targets")
    sh.add_argument("--uncoded", type=int, help="number of uncoded targets")
    sh.add_argument("--coded-diameter-mm", type=float)
    sh.add_argument("--uncoded-diameter-mm", type=float)
    sh.add_argument("--margin-mm", type=float)
    sh.add_argument("--clearance-mm", type=float)
    sh.add_argument("--first-code", type=int)
    sh.add_argument("--title")
    sh.add_argument("--name", help="the field's name")
    sh.add_argument("--seed", type=int, default=None, help="jitter the uncoded grid with this seed")
    sh.add_argument("--ruler-mm", type=float, default=None, help="length of the drawn scale bar")
    sh.add_argument("--no-labels", action="store_true", help="do not print target ids")
    sh.set_defaults(func=run_sheet)


def run_sheet(args: argparse.Namespace) -> int:
    from pathlib import Path

    from service.store import formats
    from service.workflows.targets_sheet import SheetOptions, field_json_of_sheet, make_sheet

    given = {
        "width_mm": args.width_mm,
        "height_mm": args.height_mm,
        "n_coded": args.coded,
        "n_uncoded": args.uncoded,
        "coded_diameter_mm": args.coded_diameter_mm,
        "uncoded_diameter_mm": args.uncoded_diameter_mm,
        "margin_mm": args.margin_mm,
        "clearance_mm": args.clearance_mm,
        "first_code": args.first_code,
        "title": args.title,
        "name": args.name,
    }
    try:
        options = SheetOptions(
            **{k: v for k, v in given.items() if v is not None},
            # None is a value of these two (no jitter; the longest ruler that fits), as is the library's default
            seed=args.seed,
            ruler_mm=args.ruler_mm,
            labels=not args.no_labels,
        )
        svg, field = make_sheet(options)
    except ValueError as e:
        # SheetOptions and the layout say what cannot be drawn; that is the user's to change
        raise CliError(str(e)) from None
    svg_path = Path(args.svg)
    svg_path.parent.mkdir(parents=True, exist_ok=True)
    svg_path.write_text(svg, encoding="utf-8")
    formats.write_json_atomic(args.field, field_json_of_sheet(field, options))
    n_coded = int(field.is_coded.sum())
    print_err(
        f"posecell targets sheet: {options.width_mm:g} x {options.height_mm:g} mm, {n_coded} coded + "
        f"{len(field) - n_coded} uncoded targets -> {args.svg}, {args.field}"
    )
    return 0
