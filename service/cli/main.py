"""The ``posecell`` console script: thin verbs over the engine (DESIGN section 5).

Bad input never shows a traceback: it prints one sentence on stderr and exits
non-zero (2 for a usage or file problem, 1 for a measurement that failed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from service.core.geometry.frames import check_T
from service.core.results import Failure, Reason, SolveError
from service.store import formats

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


class CliError(Exception):
    """A problem the user can fix; the message is shown as it is."""


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# -- verbs -------------------------------------------------------------------


def cmd_resect(args: argparse.Namespace) -> int:
    from service.pipeline.measure import resect_observations

    camera = formats.read_camera(args.camera)
    field = formats.read_field(args.field)
    ids, uv = formats.read_observations(args.points)
    unknown = [t for t in ids if t not in field.index]
    if unknown:
        raise CliError(f"{args.points}: target ids not in the field {args.field}: {', '.join(unknown[:10])}")
    try:
        result = resect_observations(camera, field, ids, uv, sigma_px=args.sigma_px)
    except SolveError as e:
        _print_json(Failure.from_error(e).to_dict())
        print(f"posecell resect: {e.message}", file=sys.stderr)
        return EXIT_FAILED
    _print_json(result.to_dict())
    return 0


def cmd_calibrate_handeye(args: argparse.Namespace) -> int:
    from service.core.calib.handeye import calibrate_handeye

    T_base_flange, T_field_camera = formats.read_handeye_samples(args.samples)
    for name, stack in (("T_base_flange", T_base_flange), ("T_field_camera", T_field_camera)):
        for k, T in enumerate(stack):
            try:
                check_T(T, f"sample #{k} {name}", atol=1e-4)
            except ValueError as e:
                raise CliError(f"{args.samples}: {e}") from None
    try:
        result = calibrate_handeye(T_base_flange, T_field_camera)
    except SolveError as e:
        _print_json(Failure.from_error(e).to_dict())
        print(f"posecell calibrate handeye: {e.message}", file=sys.stderr)
        return EXIT_FAILED
    out = {"ok": True, **result.to_dict()}
    if args.output:
        formats.write_json_atomic(args.output, out)
    _print_json(out)
    for w in result.warnings:
        print(f"posecell calibrate handeye: warning: {w}", file=sys.stderr)
    return 0


def _run_calibration(verb: str, run: Callable[[], Any], summary: Callable[[Any], Any]) -> int:
    """A calibration verb: input errors exit 2, a degenerate network exits 1 with ok:false JSON."""
    try:
        result = run()
    except ValueError as e:
        raise CliError(str(e)) from None
    except SolveError as e:
        _print_json(Failure.from_error(e).to_dict())
        print(f"posecell calibrate {verb}: {e.message}", file=sys.stderr)
        return EXIT_FAILED
    _print_json(summary(result))
    for w in result.warnings:
        print(f"posecell calibrate {verb}: warning: {w}", file=sys.stderr)
    return 0


def cmd_calibrate_camera(args: argparse.Namespace) -> int:
    from service.workflows.calibrate_camera import camera_options, run_camera_calibration, summary

    return _run_calibration(
        "camera", lambda: run_camera_calibration(args.field, **camera_options(args)), lambda r: summary(r, args.output)
    )


def cmd_calibrate_rig(args: argparse.Namespace) -> int:
    from service.workflows.calibrate_camera import rig_options, rig_summary, run_rig_calibration

    return _run_calibration(
        "rig",
        lambda: run_rig_calibration(args.field, args.camera, **rig_options(args)),
        lambda r: rig_summary(r, args.output),
    )


def cmd_calibrate_robot(args: argparse.Namespace) -> int:
    from service.workflows.calibrate_robot import run_robot_calibration

    try:
        out = run_robot_calibration(args.robot, args.samples, args.test, args.tool_mm)
    except SolveError as e:
        _print_json(Failure.from_error(e).to_dict())
        print(f"posecell calibrate robot: {e.message}", file=sys.stderr)
        return EXIT_FAILED
    if args.output:
        formats.write_json_atomic(args.output, out)
    _print_json(out)
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
    from service.core.targets.codes import FAMILIES
    from service.core.targets.detect import DetectSettings
    from service.pipeline.measure import FrameMeasurer, MeasureSettings

    camera = formats.read_camera(args.camera)
    field = formats.read_field(args.field)
    detect = DetectSettings(
        **{
            k: v
            for k, v in (
                ("min_contrast_dn", args.min_contrast_dn),
                ("min_area_px", args.min_area_px),
                ("max_area_px", args.max_area_px),
            )
            if v is not None
        }
    )
    settings = MeasureSettings(
        sigma_px=args.sigma_px,
        correct_eccentricity=not args.no_eccentricity,
        detect=detect,
        code_family=FAMILIES[args.code_family],
    )
    if args.max_sigma0_px is not None:
        settings = dataclasses.replace(settings, max_sigma0_px=args.max_sigma0_px)
    measurer = FrameMeasurer(camera, field, settings)
    failed = 0
    for path in args.images:
        try:
            image = formats.read_image(path)
        except formats.FormatError as e:
            out = Failure(Reason.bad_image, str(e)).to_dict()
        else:
            outcome = measurer.measure(image)
            out = outcome.result.to_dict()
            out["timings_ms"] = {k: round(v, 3) for k, v in outcome.timings_ms.items()}
        out = {"image": str(path), **out}
        failed += not out["ok"]
        _print_json(out)
        if not out["ok"]:
            print(f"posecell measure: {path}: {out['message']}", file=sys.stderr)
    return EXIT_FAILED if failed == len(args.images) else 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from service.sim.render import RenderSettings
    from service.workflows.simulate import write_dataset

    settings = RenderSettings(
        bit_depth=args.bit_depth,
        hot_spot_dn=args.hot_spot_dn,
        read_noise_dn=args.read_noise_dn,
        blur_sigma_px=args.blur_px,
    )
    out = write_dataset(
        args.output,
        args.frames,
        path=args.path,
        seed=args.seed,
        settings=settings,
        distance_mm=args.distance_mm,
        camera=formats.read_camera(args.camera) if args.camera else None,
        field=formats.read_field(args.field) if args.field else None,
    )
    print(f"posecell simulate: {args.frames} frames, camera.json, field.json and truth.jsonl in {out}", file=sys.stderr)
    return 0


def cmd_targets_sheet(args: argparse.Namespace) -> int:
    from pathlib import Path

    from service.workflows.targets_sheet import SheetOptions, field_json_of_sheet, make_sheet

    try:
        options = SheetOptions(
            width_mm=args.width_mm,
            height_mm=args.height_mm,
            n_coded=args.coded,
            n_uncoded=args.uncoded,
            coded_diameter_mm=args.coded_diameter_mm,
            uncoded_diameter_mm=args.uncoded_diameter_mm,
            margin_mm=args.margin_mm,
            clearance_mm=args.clearance_mm,
            first_code=args.first_code,
            title=args.title,
            name=args.name,
            seed=args.seed,
            ruler_mm=args.ruler_mm,
            labels=not args.no_labels,
        )
        svg, field = make_sheet(options)
    except ValueError as e:
        raise CliError(str(e)) from None
    svg_path = Path(args.svg)
    svg_path.parent.mkdir(parents=True, exist_ok=True)
    svg_path.write_text(svg, encoding="utf-8")
    formats.write_json_atomic(args.field, field_json_of_sheet(field, options))
    n_coded = int(field.is_coded.sum())
    print(
        f"posecell targets sheet: {options.width_mm:g} x {options.height_mm:g} mm, {n_coded} coded + "
        f"{len(field) - n_coded} uncoded targets -> {args.svg}, {args.field}",
        file=sys.stderr,
    )
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from service.workflows.demo import run_demo

    return run_demo(n_frames=args.frames, rate_hz=args.rate_hz, laps=args.laps, seed=args.seed)


def cmd_handeye_session(args: argparse.Namespace) -> int:
    from service.workflows.handeye_client import ClientError, default_token, run

    try:
        out = run(args.action, args.url, args.token or default_token(), args.poses, args.index, args.apply)
    except ClientError as e:
        print(f"posecell calibrate handeye-session: {e}", file=sys.stderr)
        return EXIT_FAILED
    _print_json(out)
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from api.serve import run_serve

    return run_serve(args.config, args.host, args.port, args.state_dir)


def cmd_bench(args: argparse.Namespace) -> int:
    from service.bench.main import run_bench

    return run_bench(args)


# -- parser ------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="posecell",
        description="Real-time photogrammetric robot pose measurement (see README.md).",
    )
    sub = p.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True

    sv = sub.add_parser(
        "serve",
        help="run the measurement service (REST + WebSocket API)",
        description="Runs the measurement service: cameras, robot, processing worker and the HTTP API "
        "(docs at /docs). With no --config it runs the simulated cell on 127.0.0.1:8000. Every "
        "setting can also come from the environment, e.g. POSECELL_SERVER__PORT=8080.",
    )
    sv.add_argument("--config", type=Path, help="TOML configuration (see deploy/posecell.example.toml)")
    sv.add_argument("--host", help="address to bind (default from the config: 127.0.0.1)")
    sv.add_argument("--port", type=int, help="TCP port (default from the config: 8000)")
    sv.add_argument("--state-dir", type=Path, help="measurements database, calibrations and API token")
    sv.set_defaults(func=cmd_serve)

    r = sub.add_parser(
        "resect",
        help="camera pose from given image points (space resection)",
        description="Space resection from image points [{'id':..,'uv':[u,v]}] of known field targets; "
        "prints one pose JSON line (DESIGN section 4).",
    )
    r.add_argument("--camera", required=True, help="camera.json (Brown/Fraser model)")
    r.add_argument("--field", required=True, help="field.json or field.csv (target coordinates, mm)")
    r.add_argument("--points", required=True, help="observations JSON: [{'id': ..., 'uv': [u, v]}, ...]")
    r.add_argument(
        "--sigma-px",
        type=float,
        default=None,
        help="a-priori image precision in px; default: scale the covariance by the a-posteriori sigma0",
    )
    r.set_defaults(func=cmd_resect)

    cal = sub.add_parser("calibrate", help="calibration workflows").add_subparsers(dest="what", metavar="WHAT")
    cal.required = True
    he = cal.add_parser(
        "handeye",
        help="hand-eye (T_flange_camera) and robot-world (T_base_field) calibration",
        description="Solves T_base_flange_j @ X = Z @ T_field_camera_j for X = T_flange_camera and "
        "Z = T_base_field (Tsai-Lenz, then a joint least-squares refinement).",
    )
    he.add_argument("--samples", required=True, help="JSON list of {'T_base_flange': 4x4, 'T_field_camera': 4x4} in mm")
    he.add_argument("-o", "--output", help="also write the result to this JSON file")
    he.set_defaults(func=cmd_calibrate_handeye)

    rb = cal.add_parser(
        "robot",
        help="correct the robot model from measured flange positions",
        description="Identifies the arm's kinematic errors (DH rows, base placement, the measured point on the "
        "flange) from a CSV of joint angles joint_1..joint_6 (deg) and measured positions (x_mm, y_mm, z_mm, or "
        "the laser-tracker form x_t..z_t + x_dif..z_dif), with sigma and the combinations that cannot be "
        "separated; --test reports the error on poses that took no part.",
    )
    rb.add_argument("--robot", required=True, choices=["ur5", "ur10e", "kr15"], help="the nominal model")
    rb.add_argument("--samples", required=True, type=Path, help="calibration poses (CSV)")
    rb.add_argument("--test", type=Path, help="test poses (CSV), reported before/after")
    rb.add_argument(
        "--tool-mm",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="the measured point on the flange, when the CSV has no commanded positions",
    )
    rb.add_argument("-o", "--output", type=Path, help="write the corrected model (JSON)")
    rb.set_defaults(func=cmd_calibrate_robot)

    hs = cal.add_parser(
        "handeye-session",
        help="the guided hand-eye calibration of a running service",
        description="Drives the service's guided hand-eye calibration: start (propose robot poses around the "
        "field), move K (simulated cell only), sample (record at the robot's resting pose), status, solve "
        "[--apply], export (samples for --samples). The token comes from --token, $POSECELL_TOKEN or the "
        "service's api-token file.",
    )
    hs.add_argument("action", choices=["start", "move", "sample", "status", "solve", "export"])
    hs.add_argument("index", nargs="?", type=int, help="proposal index for 'move'")
    hs.add_argument("--url", default="http://127.0.0.1:8000", help="the service (default: %(default)s)")
    hs.add_argument("--token", help="bearer token for the service")
    hs.add_argument("--poses", type=int, default=12, help="proposed poses for 'start' (default: %(default)s)")
    hs.add_argument("--apply", action="store_true", help="with 'solve': store and use the result")
    hs.set_defaults(func=cmd_handeye_session)

    def calibration_options(q: argparse.ArgumentParser) -> None:
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
        q.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")

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
    calibration_options(cc)
    cc.set_defaults(func=cmd_calibrate_camera)

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
    calibration_options(cr)
    cr.set_defaults(func=cmd_calibrate_rig)

    m = sub.add_parser(
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
    m.add_argument("images", nargs="+", metavar="IMAGE", help="PNG, TIFF or PGM, 8 or 16 bit")
    m.set_defaults(func=cmd_measure)

    sim = sub.add_parser(
        "simulate",
        help="render a simulated data set with ground truth",
        description="Renders IR target images of a field (default: the reference plate) seen by a camera "
        "(default: the reference camera) with blur and noise, plus camera.json, field.json and truth.jsonl.",
    )
    sim.add_argument("-o", "--output", required=True, help="output folder")
    sim.add_argument("--frames", type=int, default=10)
    sim.add_argument("--path", choices=["random", "circle"], default="random")
    sim.add_argument("--seed", type=int, default=1)
    sim.add_argument("--distance-mm", type=float, default=1000.0)
    sim.add_argument("--camera", help="camera.json (default: the reference camera)")
    sim.add_argument("--field", help="field.json (default: the reference plate)")
    sim.add_argument("--bit-depth", type=int, default=8, choices=[8, 12, 16])
    sim.add_argument("--hot-spot-dn", type=float, default=0.0)
    sim.add_argument("--read-noise-dn", type=float, default=1.2)
    sim.add_argument("--blur-px", type=float, default=0.6)
    sim.set_defaults(func=cmd_simulate)

    from service.workflows.targets_sheet import SheetOptions

    sheet = SheetOptions()  # the CLI's defaults are the library's, so the two cannot drift
    tg = sub.add_parser("targets", help="target sheets").add_subparsers(dest="what", metavar="WHAT")
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
    sh.add_argument("--width-mm", type=float, default=sheet.width_mm)
    sh.add_argument("--height-mm", type=float, default=sheet.height_mm)
    sh.add_argument("--coded", type=int, default=sheet.n_coded, help="number of coded targets")
    sh.add_argument("--uncoded", type=int, default=sheet.n_uncoded, help="number of uncoded targets")
    sh.add_argument("--coded-diameter-mm", type=float, default=sheet.coded_diameter_mm)
    sh.add_argument("--uncoded-diameter-mm", type=float, default=sheet.uncoded_diameter_mm)
    sh.add_argument("--margin-mm", type=float, default=sheet.margin_mm)
    sh.add_argument("--clearance-mm", type=float, default=sheet.clearance_mm)
    sh.add_argument("--first-code", type=int, default=sheet.first_code)
    sh.add_argument("--title", default=sheet.title)
    sh.add_argument("--name", default=sheet.name, help="the field's name")
    sh.add_argument("--seed", type=int, default=None, help="jitter the uncoded grid with this seed")
    sh.add_argument("--ruler-mm", type=float, default=None, help="length of the drawn scale bar")
    sh.add_argument("--no-labels", action="store_true", help="do not print target ids")
    sh.set_defaults(func=cmd_targets_sheet)

    dm = sub.add_parser(
        "demo",
        help="the simulated cell measured live (JSON lines)",
        description="Renders a camera circling above the reference plate and measures every frame live "
        "with ROI tracking; prints one JSON line per frame with the pose and its error against the truth.",
    )
    dm.add_argument("--frames", type=int, default=60, help="frames per lap")
    dm.add_argument("--laps", type=int, default=3)
    dm.add_argument("--rate-hz", type=float, default=25.0)
    dm.add_argument("--seed", type=int, default=1)
    dm.set_defaults(func=cmd_demo)

    b = sub.add_parser(
        "bench",
        help="speed and accuracy benchmarks (DESIGN section 7)",
        description="Runs the benchmark sections and prints their tables (markdown).",
    )
    b.add_argument(
        "sections",
        nargs="*",
        default=[],
        help="sections to run (default: all): accuracy, speed, faults",
    )
    b.add_argument("--frames", type=int, default=120, help="rendered frames for the speed section")
    b.add_argument(
        "--condition-frames",
        type=int,
        default=30,
        help="frames per row of the speed section's condition matrix (0: leave it out)",
    )
    b.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials for the accuracy tables")
    b.add_argument("--seed", type=int, default=1)
    b.add_argument("--rounds", type=int, default=5, help="repetitions of each fault for the faults section")
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    prog = f"posecell {args.verb}"
    try:
        return func(args)
    except (formats.FormatError, CliError) as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SolveError as e:
        print(f"{prog}: {e.message}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
