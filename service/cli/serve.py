"""``posecell serve``: the measurement service, its cameras, robot, processing worker and HTTP API.

The API layer (FastAPI, uvicorn, the drivers) is imported only when the verb runs: the CLI is the
composition root that may start it, and ``posecell --help`` should not pay for it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.common import Subparsers


def add_parser(subparsers: Subparsers) -> None:
    sv = subparsers.add_parser(
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
    sv.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Serve until interrupted; the exit code is the service's."""
    from api.serve import run_serve

    return run_serve(args.config, args.host, args.port, args.state_dir)
