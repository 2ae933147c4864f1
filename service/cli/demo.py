"""``posecell demo``: the simulated cell measured live, one JSON line per frame (the work is in
:mod:`service.workflows.demo`)."""

from __future__ import annotations

import argparse

from service.cli.common import Subparsers


def add_parser(subparsers: Subparsers) -> None:
    dm = subparsers.add_parser(
        "demo",
        help="the simulated cell measured live (JSON lines)",
        description="Renders a camera circling above the reference plate and measures every frame live "
        "with ROI tracking; prints one JSON line per frame with the pose and its error against the truth.",
    )
    dm.add_argument("--frames", type=int, default=60, help="frames per lap")
    dm.add_argument("--laps", type=int, default=3)
    dm.add_argument("--rate-hz", type=float, default=25.0)
    dm.add_argument("--seed", type=int, default=1)
    dm.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.workflows.demo import run_demo

    return run_demo(n_frames=args.frames, rate_hz=args.rate_hz, laps=args.laps, seed=args.seed)
