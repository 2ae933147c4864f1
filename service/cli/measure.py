"""``posecell measure``: detect, decode and identify the targets in each image and resect the camera.

One JSON line per image (DESIGN section 4). An image that cannot be read or measured gives ok=false
with its reason and the run goes on; the exit code is 1 only when no image could be measured.
"""

from __future__ import annotations

import argparse

from service.cli.common import EXIT_FAILED, CliError, Subparsers, print_err, print_json


def add_parser(subparsers: Subparsers) -> None:
    m = subparsers.add_parser(
        "measure",
        help="measure targets and the camera pose in images",
        description="Detects, decodes and identifies the targets in each image and resects the camera; "
        "prints one JSON line per image (DESIGN section 4). An image that cannot be measured gives "
        "ok=false with a reason, and the run goes on.",
    )
    m.add_argument("--camera", required=True, help="camera.json")
    m.add_argument("--field", required=True, help="field.json or field.csv")
    m.add_argument("--sigma-px", type=float, default=None, help="a-priori image precision, px")
    m.add_argument(
        "--no-eccentricity", action="store_true", help="do not correct the perspective bias of circle centres"
    )
    m.add_argument(
        "--code-family",
        choices=["posecell12", "aicon14"],
        default="posecell12",
        help="ring code of the coded targets: posecell's own 12-bit targets (default) or "
        "AICON-style 14-bit targets as MicMac MMVII reads them (field: an AICON point list .txt)",
    )
    m.add_argument(
        "--min-contrast-dn",
        type=float,
        default=None,
        help="smallest target contrast above the local background, 8-bit DN (default 20, and "
        "never less than 8 times the noise the detector measures in the image)",
    )
    m.add_argument("--min-area-px", type=int, default=None, help="smallest blob area, px (default 6)")
    m.add_argument(
        "--max-area-px",
        type=int,
        default=None,
        help="largest blob area, px (default 5000); lower it for images where bright patches "
        "bigger than any target (stickers, labels) are many",
    )
    m.add_argument(
        "--max-sigma0-px",
        type=float,
        default=None,
        help="largest accepted sigma0 of the final adjustment, px (default 0.5)",
    )
    m.add_argument(
        "--codes-enough",
        type=int,
        default=None,
        help="rings read until this many coded targets are named; the others are named from their "
        "pose like the uncoded targets (default 12; 0: read every ring)",
    )
    m.add_argument(
        "--bit-depth",
        type=int,
        choices=range(8, 17),
        default=None,
        metavar="8-16",
        help="significant bits of the images, which sets their saturation level: 12 for a 12-bit camera's "
        "frames saved as 16-bit images with values up to 4095 (default: 8 or 16, the file's)",
    )
    m.add_argument(
        "--centre",
        choices=["centroid", "edge"],
        default=None,
        help="a target's centre: the centre of the disk's ellipse fitted to its half-level edge (default: "
        "about twice as consistent on real panels), or the intensity centroid (~1 us a target less; "
        "the default before 2026-12-06)",
    )
    m.add_argument(
        "--max-saturated-px",
        type=int,
        default=None,
        help="reject a target with more pixels at the saturation level than this (a camera whose pixels "
        "bloom); default: targets clipped by an overexposure are measured, and counted in the output",
    )
    m.add_argument(
        "--defects",
        default=None,
        help="defects.json of the camera's sensor (posecell calibrate defects): its pixels are patched first",
    )
    m.add_argument("images", nargs="+", metavar="IMAGE", help="PNG, TIFF or PGM, 8 or 16 bit")
    m.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.core.results import Failure, Reason
    from service.pipeline.measure import FrameMeasurer, MeasureSettings
    from service.store import formats

    camera_data = formats.read_json(args.camera)
    camera = formats.camera_from_json(camera_data, str(args.camera))
    field = formats.read_field(args.field)
    # the options by the service's [processing] names; None (not given): the defaults, set in one place
    settings = MeasureSettings.from_options(
        code_family=args.code_family,
        min_contrast_dn=args.min_contrast_dn,
        min_area_px=args.min_area_px,
        max_area_px=args.max_area_px,
        sigma_px=args.sigma_px,
        max_sigma0_px=args.max_sigma0_px,
        codes_enough=args.codes_enough,
        bit_depth=args.bit_depth,
        centre=args.centre,
        max_saturated_px=args.max_saturated_px,
        correct_eccentricity=not args.no_eccentricity,
    )
    if warning := formats.centre_mismatch(formats.calibrated_centre(camera_data), settings.detect.centre):
        print_err(f"posecell measure: warning: {warning}")
    defects = None if args.defects is None else formats.read_defects(args.defects)
    try:
        measurer = FrameMeasurer(camera, field, settings, defects, frames_owned=True)  # each image read for it
    except ValueError as e:
        raise CliError(f"{args.defects}: {e}") from None
    failed = 0
    for path in args.images:
        try:
            image = formats.read_image(path)
        except formats.FormatError as e:
            # one unreadable file is one failed image, not the end of the run
            out = Failure(Reason.bad_image, str(e)).to_dict()
        else:
            outcome = measurer.measure(image)
            out = outcome.result.to_dict()
            out["timings_ms"] = {k: round(v, 3) for k, v in outcome.timings_ms.items()}
            if (b := outcome.brightness) is not None and b.n_measured:
                out["blur_px"] = round(b.blur_px, 2)
            if b is not None and b.n_saturated:
                out["targets_saturated"] = b.n_saturated
                print_err(f"posecell measure: {path}: {b.saturation_note}")
            if b is not None and b.focus_note:
                print_err(f"posecell measure: {path}: {b.focus_note}")
        out = {"image": str(path), **out}
        failed += not out["ok"]
        print_json(out)
        if not out["ok"]:
            print_err(f"posecell measure: {path}: {out['message']}")
    return EXIT_FAILED if failed == len(args.images) else 0
