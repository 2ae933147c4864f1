"""``posecell calibrate``: the calibration verbs.

Here: ``handeye`` (T_flange_camera and T_base_field from pose pairs), ``robot`` (the arm's kinematic
errors from measured flange positions) and ``handeye-session`` (the guided hand-eye calibration of a
running service). The bundle adjustments ``camera`` and ``rig`` are in :mod:`service.cli.calibrate_bundle`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli import calibrate_bundle
from service.cli.common import EXIT_FAILED, CliError, Subparsers, print_err, print_json, solving


def add_parser(subparsers: Subparsers) -> None:
    cal = subparsers.add_parser("calibrate", help="calibration workflows").add_subparsers(dest="what", metavar="WHAT")
    cal.required = True
    _add_handeye(cal)
    _add_robot(cal)
    _add_handeye_session(cal)
    _add_defects(cal)
    calibrate_bundle.add_parsers(cal)  # camera, rig: listed after these in the help, as they always were


def _add_handeye(cal: Subparsers) -> None:
    he = cal.add_parser(
        "handeye",
        help="hand-eye (T_flange_camera) and robot-world (T_base_field) calibration",
        description="Solves T_base_flange_j @ X = Z @ T_field_camera_j for X = T_flange_camera and "
        "Z = T_base_field (Tsai-Lenz, then a joint least-squares refinement).",
    )
    he.add_argument("--samples", required=True, help="JSON list of {'T_base_flange': 4x4, 'T_field_camera': 4x4} in mm")
    he.add_argument("-o", "--output", help="also write the result to this JSON file")
    he.set_defaults(func=run_handeye)


def _add_robot(cal: Subparsers) -> None:
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
    rb.add_argument(
        "--parameterisation",
        choices=["hayati", "dh"],
        default="hayati",
        help="hayati: Hayati's beta in place of d on near-parallel links (default); dh: classic DH errors only",
    )
    rb.add_argument("-o", "--output", type=Path, help="write the corrected model (JSON)")
    rb.set_defaults(func=run_robot)


def _add_handeye_session(cal: Subparsers) -> None:
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
    hs.set_defaults(func=run_handeye_session)


def _add_defects(cal: Subparsers) -> None:
    df = cal.add_parser(
        "defects",
        help="the sensor's defect pixels: hot ones from dark frames, dead ones from flat frames",
        description="Finds the pixels that stand above their 3 x 3 neighbourhood in most of the frames (hot): "
        "take them with the ring light off or the lens capped, at the working exposure and gain (or from "
        "several views: targets move, defects do not); with --flat, also the pixels that lie below it in "
        "frames of an evenly lit field (dead): a white card or a diffuser before the lens under the ring "
        "light, well below full scale. The map written is patched into every frame before it is measured "
        "(posecell measure --defects, [[cameras]] defects).",
    )
    df.add_argument("images", nargs="*", metavar="IMAGE", help="dark frames (or folders of them), at least 5")
    df.add_argument(
        "--flat", nargs="+", metavar="FLAT", default=[], help="flat frames (or folders of them), at least 5"
    )
    df.add_argument("-o", "--output", required=True, type=Path, help="defects.json to write")
    df.add_argument(
        "--min-fraction", type=float, default=None, help="of the frames a pixel must stand out in (default 0.8)"
    )
    df.add_argument(
        "--k-sigma", type=float, default=None, help="how far above (below) its neighbours, in noise sigmas (default 8)"
    )
    df.add_argument("--min-dn", type=float, default=None, help="hot: and at least this many 8-bit DN (default 12)")
    df.add_argument(
        "--min-drop", type=float, default=None, help="dead: and at least this share of the level below (default 0.3)"
    )
    df.add_argument(
        "--bit-depth", type=int, default=None, help="significant bits of 16-bit frames (e.g. 12), as for measure"
    )
    df.set_defaults(func=run_defects)


def run_defects(args: argparse.Namespace) -> int:
    """Find the defects; prints what was found (JSON) and writes the map."""
    from service.core.targets import defects
    from service.store import formats
    from service.workflows.calibrate_camera import image_paths

    if not args.images and not args.flat:
        raise CliError("give dark frames (IMAGE ...), flat frames (--flat FLAT ...) or both")
    full_dn = None if args.bit_depth is None else float(2**args.bit_depth - 1)
    common = {"k_sigma": args.k_sigma, "min_fraction": args.min_fraction}
    hot = dead = None
    try:
        if args.images:
            frames = [formats.read_image(p) for p in image_paths(args.images)]
            options = {k: v for k, v in {**common, "min_dn": args.min_dn}.items() if v is not None}
            hot = defects.find_defects(frames, full_dn=full_dn, **options)
        if args.flat:
            flats = [formats.read_image(p) for p in image_paths(args.flat)]
            options = {k: v for k, v in {**common, "min_drop": args.min_drop}.items() if v is not None}
            dead = defects.find_dead_pixels(flats, full_dn=full_dn, **options)
    except ValueError as e:
        raise CliError(str(e)) from None
    found = [search.defects for search in (hot, dead) if search is not None]
    m = found[0] if len(found) == 1 else found[0].merged(found[1])  # one sensor: hot and dead pixels alike
    # an existing map at the output keeps its pixels of the kind not searched now (flat frames alone
    # keep its hot pixels, dark frames alone its dead ones): mapping one kind never loses the other
    kept = 0
    if args.output.exists() and (hot is None or dead is None):
        try:
            before = formats.read_defects(args.output)
        except (OSError, ValueError) as e:
            raise CliError(f"{args.output} is there but not a defect map ({e}): not overwritten") from None
        if (before.width, before.height) == (m.width, m.height):
            other = before.of_kind(dead=hot is not None)
            m, kept = other.merged(m), len(other)
    record: dict[str, object] = {}
    if hot is not None:
        record.update(frames=hot.n_frames, threshold_dn=float(hot.threshold_dn.max()))
    if dead is not None:
        record.update(flat_frames=dead.n_frames, flat_threshold_dn=float(dead.threshold_dn.max()))
    formats.write_defects(args.output, m, **record)
    share = (len(m) - m.n_dead) / (m.width * m.height)
    out: dict[str, object] = {
        "ok": True,
        "defects": len(m),
        "hot": len(m) - m.n_dead,
        "dead": m.n_dead,
        "kept": kept,
        "share": share,
    }
    if hot is not None:
        out.update(
            frames=hot.n_frames,
            threshold_dn=[float(hot.threshold_dn.min()), float(hot.threshold_dn.max())],
            stood_out_sometimes=hot.sometimes,
        )
    if dead is not None:
        out.update(flat_frames=dead.n_frames, flat_stood_out_sometimes=dead.sometimes, unjudged=dead.unjudged)
    print_json({**out, "output": str(args.output)})
    if share > defects.SUSPECT_SHARE:
        print_err(
            f"posecell calibrate defects: warning: {share:.2%} of the pixels are hot: frames of one view "
            "count its small targets as defects; take them with the ring light off, or from several views"
        )
    if dead is not None and dead.unjudged:
        print_err(
            f"posecell calibrate defects: warning: {dead.unjudged} pixels were not judged dead or good: their "
            "neighbourhood was not lit in enough of the flat frames (light the whole field evenly)"
        )
    return 0


def run_handeye(args: argparse.Namespace) -> int:
    """Solve X and Z from the samples file; prints the result JSON (and writes it with -o), then any warnings."""
    from service.core.calib.handeye import calibrate_handeye
    from service.core.geometry.frames import check_T
    from service.store import formats

    T_base_flange, T_field_camera = formats.read_handeye_samples(args.samples)
    # a non-rigid matrix is a typo in the user's file: name the sample rather than let the solver fail on it
    for name, stack in (("T_base_flange", T_base_flange), ("T_field_camera", T_field_camera)):
        for k, T in enumerate(stack):
            try:
                check_T(T, f"sample #{k} {name}", atol=1e-4)
            except ValueError as e:
                raise CliError(f"{args.samples}: {e}") from None
    with solving("calibrate handeye"):
        result = calibrate_handeye(T_base_flange, T_field_camera)
    out = {"ok": True, **result.to_dict()}
    if args.output:
        formats.write_json_atomic(args.output, out)
    print_json(out)
    for w in result.warnings:
        print_err(f"posecell calibrate handeye: warning: {w}")
    return 0


def run_robot(args: argparse.Namespace) -> int:
    """Identify the arm's errors; prints the corrected model JSON (and writes it with -o)."""
    from service.store import formats
    from service.workflows.calibrate_robot import run_robot_calibration

    with solving("calibrate robot"):
        out = run_robot_calibration(args.robot, args.samples, args.test, args.tool_mm, args.parameterisation)
    if args.output:
        formats.write_json_atomic(args.output, out)
    print_json(out)
    return 0


def run_handeye_session(args: argparse.Namespace) -> int:
    """One step of the service's guided session over HTTP; prints the service's answer."""
    from service.workflows.handeye_client import ClientError, default_token, run

    try:
        out = run(args.action, args.url, args.token or default_token(), args.poses, args.index, args.apply)
    except ClientError as e:
        # the service refused the step or could not be reached: its sentence, and the step failed (1)
        print_err(f"posecell calibrate handeye-session: {e}")
        return EXIT_FAILED
    print_json(out)
    return 0
