"""``posecell simulate``: render a simulated data set with its ground truth (the work is in
:mod:`service.workflows.simulate`)."""

from __future__ import annotations

import argparse

from service.cli.common import Subparsers, print_err


def add_parser(subparsers: Subparsers) -> None:
    sim = subparsers.add_parser(
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
    sim.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.sim.render import RenderSettings
    from service.store import formats
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
    print_err(f"posecell simulate: {args.frames} frames, camera.json, field.json and truth.jsonl in {out}")
    return 0
