"""``posecell calibrate camera`` and ``posecell calibrate rig``: the two bundle adjustments.

``camera`` is the self-calibrating bundle adjustment of one camera (camera.json, optionally the surveyed
field); ``rig`` the relative orientation of rigidly mounted cameras (rig.json). Both measure images of a
target field (or take given observations) and share the options of the adjustment and of the detector;
the work is in :mod:`service.workflows.calibrate_camera` and :mod:`service.workflows.calibrate_rig`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from service.cli.common import CliError, Subparsers, print_err, print_json, solving


def add_parsers(cal: Subparsers) -> None:
    """``camera`` and ``rig`` under ``posecell calibrate``."""
    _add_camera(cal)
    _add_rig(cal)


def _add_bundle_options(q: argparse.ArgumentParser) -> None:
    """The adjustment's and the detector's options, the same for ``camera`` and ``rig``."""
    q.add_argument(
        "--sigma-px",
        type=float,
        default=0.1,
        help="a-priori precision of an image coordinate, px: weighs images against scale bars "
        "and weighted control (default 0.1); sigma0 is reported in px regardless",
    )
    q.add_argument(
        "--scale-bar",
        action="append",
        metavar="A,B,MM[,SIGMA_MM]",
        help="a known distance between targets A and B (repeatable; sigma default 0.01 mm)",
    )
    q.add_argument("--no-reject", action="store_true", help="keep every observation (no gross-error rejection)")
    q.add_argument(
        "--code-family",
        choices=["posecell12", "aicon14"],
        default="posecell12",
        help="ring code of the coded targets in the images (as for measure)",
    )
    q.add_argument("--min-contrast-dn", type=float, default=None, help="as for measure")
    q.add_argument("--min-area-px", type=int, default=None, help="as for measure")
    q.add_argument("--max-area-px", type=int, default=None, help="as for measure")
    q.add_argument("--bit-depth", type=int, choices=range(8, 17), default=None, metavar="8-16", help="as for measure")
    q.add_argument("--centre", choices=["centroid", "edge"], default=None, help="as for measure")
    q.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")


def _add_camera(cal: Subparsers) -> None:
    cc = cal.add_parser(
        "camera",
        help="self-calibrating bundle adjustment: camera.json (and the surveyed field)",
        description="Estimates the camera's Brown/Fraser interior orientation (c, x0, y0, K1-K3, P1, P2, B1, B2), "
        "every image's pose and the targets' coordinates from images of a target field (or from given "
        "observations), with sigma, correlations and rejected observations. Datum: the nominal field with "
        "inner constraints (its scale, or scale bars), or control points. Take 8 or more convergent views "
        "(tilted 20-45 deg) from all sides, half of them rolled by 90 degrees.",
    )
    cc.add_argument("--field", required=True, help="field.json, field.csv or an AICON point list .txt (nominal, mm)")
    cc.add_argument("images", nargs="*", metavar="IMAGE", help="images (or folders of images) of the field")
    cc.add_argument("--observations", help="OBS.json: {'images': [{'name': .., 'points': [{'id': .., 'uv': [u, v]}]}]}")
    cc.add_argument("-o", "--output", required=True, help="camera.json to write")
    cc.add_argument("--field-out", help="also write the surveyed field.json (with sigma_mm per target)")
    cc.add_argument("--observations-out", help="also write the measured observations (OBS.json)")
    cc.add_argument("--camera", help="start camera.json (default: --c-mm and --pixel-size-mm)")
    cc.add_argument("--c-mm", type=float, help="nominal principal distance, mm (without --camera)")
    cc.add_argument("--pixel-size-mm", type=float, help="pixel size, mm (without --camera)")
    cc.add_argument("--image-size", help="WIDTHxHEIGHT px (observations without --camera)")
    cc.add_argument("--fix", help="parameters to keep at the start camera's values, e.g. K3,B1,B2")
    cc.add_argument("--control", help="ids of control points that fix the datum (default: inner constraints)")
    cc.add_argument(
        "--control-sigma-mm",
        type=float,
        default=0.0,
        help="standard deviation of the control points, mm (default 0: fixed)",
    )
    cc.add_argument(
        "--residuals",
        choices=["pixel", "ideal"],
        default="pixel",
        help="minimize pixel residuals (default) or ideal-coordinate residuals (DBAT/PhotoModeler form)",
    )
    cc.add_argument(
        "--passes",
        type=int,
        default=2,
        help="measure the images again with the calibrated camera and recalibrate (default 2 passes)",
    )
    _add_bundle_options(cc)
    cc.set_defaults(func=run_camera)


def _add_rig(cal: Subparsers) -> None:
    cr = cal.add_parser(
        "rig",
        help="relative orientation of rigidly mounted cameras: rig.json",
        description="Calibrates the poses of cameras 1..K-1 in camera 0's frame (T_master_camera, for forward "
        "intersection) from simultaneous images of a target field: a bundle adjustment with the rig constraint. "
        "Images: one folder per camera, paired by file name, else by the frame number in the names (--pair-by), "
        "or listed in --pairs; an image without a partner or an ambiguous pair is refused. sigma: max(formal, "
        "leave-one-epoch-out jackknife), both in rig.json.",
    )
    cr.add_argument("--field", required=True, help="field.json, field.csv or an AICON point list .txt (mm)")
    cr.add_argument(
        "--camera", nargs="+", required=True, metavar="CAMERA_JSON", help="camera.json of each camera, master first"
    )
    cr.add_argument("--images", nargs="+", metavar="DIR", help="one folder of images per camera, same order")
    cr.add_argument("--observations", help="OBS.json whose images carry 'camera' (index) and 'epoch'")
    cr.add_argument(
        "--pairs",
        metavar="PAIRS_CSV",
        help="instead of --images: one row per epoch, one image path per camera (relative to the file)",
    )
    cr.add_argument(
        "--pair-by",
        choices=["auto", "name", "frame", "time"],
        default="auto",
        help="pair --images by file name, frame number in the name, or time (a timestamps.csv "
        "'name,t_ns' or 'name,t_s' in each folder); auto: name, else frame number",
    )
    cr.add_argument(
        "--time-tolerance-s",
        type=float,
        default=None,
        help="largest exposure-time difference of a pair for --pair-by time (default 0.005)",
    )
    cr.add_argument(
        "--drop-unpaired",
        action="store_true",
        help="leave out images without a partner (said in the warnings) instead of refusing",
    )
    cr.add_argument("-o", "--output", required=True, help="rig.json to write")
    cr.add_argument("--free-interior", help="interior parameters to refine too, e.g. c,x0,y0 (default none)")
    cr.add_argument(
        "--survey-field",
        action="store_true",
        help="adjust the targets too (inner constraints on the nominal field) instead of fixing them",
    )
    _add_bundle_options(cr)
    cr.set_defaults(func=run_rig)


def run_camera(args: argparse.Namespace) -> int:
    """Calibrate one camera; writes camera.json (and what --field-out, --observations-out ask for)."""
    from service.workflows.calibrate_camera import camera_options, run_camera_calibration, summary

    return _calibrate(
        "camera", lambda: run_camera_calibration(args.field, **camera_options(args)), lambda r: summary(r, args.output)
    )


def run_rig(args: argparse.Namespace) -> int:
    """Calibrate the rig's relative orientation; writes rig.json."""
    from service.workflows.calibrate_rig import rig_options, rig_summary, run_rig_calibration

    return _calibrate(
        "rig",
        lambda: run_rig_calibration(args.field, args.camera, **rig_options(args)),
        lambda r: rig_summary(r, args.output),
    )


def _calibrate(verb: str, run: Callable[[], Any], summary: Callable[[Any], Any]) -> int:
    """Run a bundle adjustment and print its summary JSON, then its warnings.

    The workflow says what is wrong with the options, images or observations by a ValueError (a
    FormatError among them): an input error, exit 2. A degenerate network is a SolveError: exit 1
    with the Failure JSON.
    """
    try:
        with solving(f"calibrate {verb}"):
            result = run()
    except ValueError as e:
        raise CliError(str(e)) from None
    print_json(summary(result))
    for w in result.warnings:
        print_err(f"posecell calibrate {verb}: warning: {w}")
    return 0
