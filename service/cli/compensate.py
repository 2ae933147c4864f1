"""``posecell compensate``: compensated commands for targets, from a corrected robot model.

``posecell compensate --model m.json --targets TARGETS.csv -o COMMANDS.csv [--format csv|urscript]``;
the files are described in :mod:`service.workflows.compensate`. A summary JSON line goes to stdout.
A target out of reach or too far from its seed fails the verb with exit 2 and a sentence naming it,
and nothing is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.common import CliError, Subparsers, print_json


def add_parser(subparsers: Subparsers) -> None:
    cp = subparsers.add_parser(
        "compensate",
        help="commands that bring the real arm (the corrected model) to target flange poses",
        description="Per target flange pose (x_mm, y_mm, z_mm, rx, ry, rz: UR rotation vector, base frame; "
        "optional seed_joint_1..6 in deg), the joints joint_1..6 (deg) at which the corrected model reaches it "
        "and the Cartesian pose x_cmd_mm..rz_cmd to program in the nominal controller, with the predicted "
        "correction; or a URScript movej program (--format urscript).",
    )
    cp.add_argument("--model", required=True, type=Path, help="the corrected model (m.json of calibrate robot)")
    cp.add_argument("--targets", required=True, type=Path, help="TARGETS.csv")
    cp.add_argument("-o", "--output", required=True, type=Path, help="COMMANDS.csv, or the URScript program")
    cp.add_argument("--format", choices=["csv", "urscript"], default="csv", help="default: %(default)s")
    cp.add_argument(
        "--max-seed-distance-deg",
        type=float,
        default=30.0,
        help="refuse a target whose joints are further than this from its given seed (default: %(default)s)",
    )
    cp.add_argument("--a", type=float, default=1.4, help="URScript movej acceleration, rad/s^2 (default: %(default)s)")
    cp.add_argument("--v", type=float, default=1.05, help="URScript movej speed, rad/s (default: %(default)s)")
    cp.set_defaults(func=run_compensate)


def run_compensate(args: argparse.Namespace) -> int:
    """Read the model and targets, compensate every target or refuse, write the output atomically."""
    from service.core.results import SolveError
    from service.store.robot_model import read_robot_model
    from service.workflows.compensate import commands_csv, commands_urscript, compensate, targets_from_csv

    if not args.max_seed_distance_deg > 0 or not (args.a > 0 and args.v > 0):
        raise CliError("--max-seed-distance-deg, --a and --v must be positive")
    model = read_robot_model(args.model)
    try:
        text = args.targets.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise CliError(f"{args.targets}: cannot be read ({e})") from None
    T, seeds = targets_from_csv(text, str(args.targets))
    try:
        rows = compensate(model, T, seeds, args.max_seed_distance_deg)
    except SolveError as e:
        # an unreachable target is the user's input, as a malformed one: exit 2, the rows named
        raise CliError(f"{args.targets}: {e.message}") from None
    if args.format == "urscript":
        out = commands_urscript(rows, model, args.model.name, args.a, args.v)
    else:
        out = commands_csv(rows)
    _write(args.output, out)
    corr = [r["correction_mm"] for r in rows]
    print_json(
        {
            "ok": True,
            "robot": model.robot,
            "parameterisation": model.parameterisation,
            "n_targets": len(rows),
            "correction_mm": {"mean": round(sum(corr) / len(corr), 4), "max": round(max(corr), 4)},
            "output": str(args.output),
            "format": args.format,
        }
    )
    return 0


def _write(path: Path, text: str) -> None:
    """Through a temporary file and a rename, so a crash never leaves half a program."""
    import os
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
