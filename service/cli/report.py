"""``posecell report circle|iso9283|table1``: the robot's accuracy from recorded poses (DESIGN section 5).

One JSON object on stdout (the figures), and ``report.json``, ``report.md``, the plots (SVG and PNG) and
``report.html`` in ``-o DIR``; the
CSV formats and the analyses are in :mod:`service.workflows.reports` and :mod:`service.core.accuracy`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.common import CliError, Subparsers, print_err, print_json, solving


def add_parser(subparsers: Subparsers) -> None:
    rp = subparsers.add_parser(
        "report", help="the robot's accuracy: ISO 230-4 circle, ISO 9283 poses, the paper's Table 1"
    )
    kinds = rp.add_subparsers(dest="what", metavar="WHAT")
    kinds.required = True
    circle = kinds.add_parser(
        "circle",
        help="ISO 230-4 circular test: G (cw, ccw, bidirectional), H, F, mean radial deviation",
        description="CSV columns in time order: t_s, direction (cw or ccw), x_mm, y_mm, z_mm; optional a_deg, "
        "b_deg, c_deg (KUKA A, B, C: the orientation deviation along the path) and x_cmd_mm, y_cmd_mm, "
        "z_cmd_mm (the robot's reported path).",
    )
    circle.add_argument("--radius-mm", required=True, type=float, help="the nominal radius, mm")
    circle.add_argument("--centre-mm", help="the nominal centre X,Y,Z mm (for the centre offset)")
    iso = kinds.add_parser(
        "iso9283",
        help="ISO 9283 pose accuracy and repeatability (AP, RP, vAP) per pose",
        description="CSV columns: pose, cycle, x_cmd_mm, y_cmd_mm, z_cmd_mm, a_cmd_deg, b_cmd_deg, c_cmd_deg, "
        "x_mm, y_mm, z_mm, a_deg, b_deg, c_deg (KUKA A, B, C), optional direction (of approach).",
    )
    t1 = kinds.add_parser(
        "table1",
        help="the paper's Table 1: positions visited forward then in reverse order, deviations with σ",
        description="CSV columns in visit order: [position,] x_mm, y_mm, z_mm, a_deg, b_deg, c_deg (KUKA A, B, C) "
        "[, sigma_x_mm, sigma_y_mm, sigma_z_mm, sigma_a_deg, sigma_b_deg, sigma_c_deg]; without position the "
        "rows are positions 1..K then K..1.",
    )
    sim = kinds.add_parser(
        "sim",
        help="run an accuracy test in the simulated cell (or a running service) and write its report",
        description="Starts `posecell serve` (the simulated cell) in a child process, or uses --url, runs the "
        "test over HTTP (POST /tests/KIND: the arm runs the program, the camera measures), and writes the "
        "report as the other verbs do, plus test.json: the test's record, in the simulation with the same "
        "analysis of the arm's true poses (details.truth).",
    )
    sim.add_argument("test", choices=("circle", "iso9283", "table1"), help="which test")
    sim.add_argument(
        "--params",
        default="{}",
        help='the test\'s parameters as JSON, e.g. \'{"laps": 2, "speed_mm_s": 75}\' (GET /docs: POST /tests/KIND)',
    )
    sim.add_argument("--url", help="a running service (e.g. http://127.0.0.1:8000) instead of a new simulated cell")
    sim.add_argument("--token", default="", help="its API token (POSECELL_SERVER__TOKEN) with --url")
    sim.add_argument("-o", "--out", required=True, type=Path, help="folder for the report and test.json")
    sim.set_defaults(func=run_sim, kind="sim")
    for p, kind in ((circle, "circle"), (iso, "iso9283"), (t1, "table1")):
        p.add_argument("--poses", required=True, type=Path, help="the recorded poses (CSV)")
        p.add_argument(
            "-o",
            "--out",
            required=True,
            type=Path,
            help="folder for report.json, report.md, the figures (SVG, PNG) and report.html",
        )
        p.set_defaults(func=run, kind=kind)


def run(args: argparse.Namespace) -> int:
    from service.workflows.reports import circle_report, iso9283_report, table1_report, write_report

    with solving(f"report {args.kind}"):
        if args.kind == "circle":
            report = circle_report(args.poses, args.radius_mm, _centre(args.centre_mm))
        elif args.kind == "iso9283":
            report = iso9283_report(args.poses)
        else:
            report = table1_report(args.poses)
    for path in write_report(args.out, args.kind, report):
        print_err(f"posecell report {args.kind}: wrote {path}")
    print_json(report)
    return 0


def run_sim(args: argparse.Namespace) -> int:
    import json
    import tempfile

    from service.workflows.reports import write_report
    from service.workflows.sim_tests import SimTestError, run_test

    try:
        params = json.loads(args.params)
    except ValueError as e:
        raise CliError(f"--params must be a JSON object: {e}") from None
    if not isinstance(params, dict):
        raise CliError("--params must be a JSON object, e.g. '{\"laps\": 2}'")

    def progress(fraction: float, sentence: str) -> None:
        print_err(f"posecell report sim {args.test}: {100 * fraction:3.0f} % {sentence}")

    try:
        if args.url:
            report, row = run_test(args.url.rstrip("/"), args.token, args.test, params, progress)
        else:
            from service.bench.child import serve_child, wait_ready

            with tempfile.TemporaryDirectory() as state, serve_child(Path(state)) as served:
                print_err(f"posecell report sim {args.test}: starting the simulated cell ({served.url})")
                wait_ready(served.address, timeout_s=300.0)
                report, row = run_test(served.url, served.token, args.test, params, progress)
    except SimTestError as e:
        raise CliError(str(e)) from None
    paths = write_report(args.out, args.test, report)
    (args.out / "test.json").write_text(json.dumps(row, indent=1) + "\n")
    for path in (*paths, args.out / "test.json"):
        print_err(f"posecell report sim {args.test}: wrote {path}")
    print_json({"report": {k: v for k, v in report.items() if k not in ("points", "profile", "attained")}, **row})
    return 0


def _centre(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise CliError(f"--centre-mm takes X,Y,Z in mm, e.g. 1200,0,800, not {text!r}")
    return values
