"""``posecell bench``: the speed and accuracy benchmarks of DESIGN section 7, printed as markdown
tables (the sections are in :mod:`service.bench`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.common import Subparsers


def add_parser(subparsers: Subparsers) -> None:
    b = subparsers.add_parser(
        "bench",
        help="speed and accuracy benchmarks (DESIGN section 7)",
        description="Runs the benchmark sections and prints their tables (markdown).",
    )
    b.add_argument(
        "sections",
        nargs="*",
        default=[],
        help="sections to run (default: all but ab): accuracy, speed, faults, service, host, real, independent; "
        "ab (with --against): this checkout's frame times against another revision's, head to head",
    )
    b.add_argument(
        "--frames",
        type=int,
        default=120,
        help="rendered frames for the speed section; ROI frames a round for the host section",
    )
    b.add_argument(
        "--condition-frames",
        type=int,
        default=30,
        help="frames per row of the speed section's condition matrix (0: leave it out)",
    )
    b.add_argument(
        "--sheet-frames",
        type=int,
        default=5,
        help="frames per row of the independent section (the printed sheet imaged by cairo and OpenCV)",
    )
    b.add_argument(
        "--tracked-frames",
        type=_tracked_frames,
        default=None,
        help="frames of each tracked sequence of the independent section (default: 6 x --sheet-frames)",
    )
    b.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials for the accuracy tables")
    b.add_argument("--seed", type=int, default=1)
    b.add_argument("--rounds", type=int, default=5, help="repetitions of each fault for the faults section")
    b.add_argument("--rates", default="100,250,500,1000", help="camera frame rates, Hz, for the service section")
    b.add_argument(
        "--clients",
        default="1,50,50p",
        help="numbers of WebSocket clients for the service section (50p: the others than the probe pose-only)",
    )
    b.add_argument("--seconds", type=float, default=10.0, help="measured seconds per row of the service section")
    b.add_argument(
        "--centre",
        choices=["edge", "centroid"],
        default=None,
        help="the service section: the targets' centres as the service measures them "
        "([processing] centre; default: the service's, edge)",
    )
    b.add_argument(
        "--data",
        type=Path,
        default=None,
        help="the real section's data set, MicMac's Circ-Code-Target panel "
        "(default: ../shared/data/micmac-circ-code-target)",
    )
    b.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="the real section's camera.json of the panel's lens "
        "(default: posecell calibrates it from the images first)",
    )
    b.add_argument(
        "--against",
        default=None,
        help="the ab section: a git revision (its tree kept in ~/.cache/posecell/bench-ab; its kernels "
        "compile on the first run, ~2 min) or a directory holding a service package",
    )
    b.set_defaults(func=run)


def _tracked_frames(text: str) -> int:
    n = int(text)
    if n < 2:
        raise argparse.ArgumentTypeError(
            f"{n}: a tracked sequence needs 2 frames or more (the first is measured in full)"
        )
    return n


def run(args: argparse.Namespace) -> int:
    """The sections read their options from ``args`` themselves; an unknown section exits 2."""
    from service.bench.main import run_bench

    return run_bench(args)
