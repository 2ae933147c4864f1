"""``posecell serve``: the HTTP service under uvicorn, configured from TOML + environment."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from service.settings import SettingsError, load_settings


def run_serve(config: Path | None, host: str | None, port: int | None, state_dir: Path | None) -> int:
    try:
        settings = load_settings(config, server__host=host, server__port=port,
                                 state_dir=str(state_dir) if state_dir else None)
    except SettingsError as e:
        print(f"posecell serve: {e}", file=sys.stderr)
        return 2
    import uvicorn  # the service's own dependency; the other verbs need not import it

    from api.app import create_app

    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    where = "the simulated cell" if settings.uses_sim else "the configured devices"
    print(f"posecell serve: {where} on http://{settings.server.host}:{settings.server.port} "
          f"(API docs at /docs, state in {settings.resolved_state_dir()})", file=sys.stderr)
    app = create_app(settings)
    try:
        uvicorn.run(app, host=settings.server.host, port=settings.server.port, lifespan="on",
                    log_level=settings.log_level, ws_ping_interval=20.0)
    except OSError as e:  # port in use, no permission
        print(f"posecell serve: cannot listen on {settings.server.host}:{settings.server.port}: {e}", file=sys.stderr)
        return 1
    return 0
