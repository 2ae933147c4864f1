"""``posecell resect``: the camera pose from given image points of known field targets (space resection).

Prints one pose JSON line (DESIGN section 4); a resection that fails prints its Failure JSON instead
and exits 1.
"""

from __future__ import annotations

import argparse

from service.cli.common import CliError, Subparsers, print_json, solving


def add_parser(subparsers: Subparsers) -> None:
    r = subparsers.add_parser(
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
    r.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.pipeline.measure import resect_observations
    from service.store import formats

    camera = formats.read_camera(args.camera)
    field = formats.read_field(args.field)
    ids, uv = formats.read_observations(args.points)
    # caught here, not in the solver: the user gets the file and the ids to fix, not a solver message
    unknown = [t for t in ids if t not in field.index]
    if unknown:
        raise CliError(f"{args.points}: target ids not in the field {args.field}: {', '.join(unknown[:10])}")
    with solving("resect"):
        result = resect_observations(camera, field, ids, uv, sigma_px=args.sigma_px)
    print_json(result.to_dict())
    return 0
