"""``posecell serve``: the HTTP service under uvicorn, configured from TOML + environment.

:func:`uvicorn_config` is the one place where the ``[server]`` settings become
uvicorn's options (timeouts, limits, WebSocket pings); the tests' live server
uses it too, so what is tested is what runs.
"""

from __future__ import annotations

import logging
import resource
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.settings import Settings, SettingsError, load_settings

if TYPE_CHECKING:
    import uvicorn

log = logging.getLogger(__name__)


def uvicorn_config(app: Any, settings: Settings, **overrides: Any) -> uvicorn.Config:
    """uvicorn's configuration for ``app`` from ``settings.server``; ``overrides`` win (tests: log_level)."""
    import uvicorn  # the service's own dependency; the other verbs need not import it

    s = settings.server
    try:
        from api.http_protocol import ConnectionLimits, guarded_protocol
    except ImportError:  # no httptools (not CPython): h11, with its header limit but no header timeout
        log.warning("httptools is not installed: no header or body timeouts, only keep-alive")
        http: Any = "h11"
    else:
        http = guarded_protocol(
            ConnectionLimits(
                timeout_header_s=s.timeout_header_s,
                timeout_body_s=s.timeout_body_s,
                max_header_bytes=s.max_header_bytes,
                limit_concurrency=s.limit_concurrency,
            )
        )
    options: dict[str, Any] = {
        "host": s.host,
        "port": s.port,
        "lifespan": "on",  # a failed start exits non-zero instead of serving a broken app
        "log_level": settings.log_level,
        "http": http,
        "timeout_keep_alive": s.timeout_keep_alive_s,
        "timeout_graceful_shutdown": s.timeout_graceful_shutdown_s,
        "limit_concurrency": s.limit_concurrency,
        "backlog": s.backlog,
        "h11_max_incomplete_event_size": s.max_header_bytes,
        "ws_ping_interval": s.ws_ping_interval_s,
        "ws_ping_timeout": s.ws_ping_timeout_s,
        "ws_max_size": s.ws_max_message_bytes,
        "ws": "websockets-sansio",  # the protocol api.ws.FrameWriter writes to directly
        "ws_per_message_deflate": s.ws_compression,
        **overrides,
    }
    return uvicorn.Config(app, **options)


def raise_open_file_limit() -> tuple[int, int]:
    """Raise the soft limit on open files to the hard one; the (soft, hard) now in force.

    The soft limit is 1024 by default, for select(); asyncio uses epoll, and each
    connection is a file descriptor. The systemd unit sets both (LimitNOFILE).
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError):  # an infinite hard limit, or a container that refuses
            pass
    return soft, hard


def run_serve(config: Path | None, host: str | None, port: int | None, state_dir: Path | None) -> int:
    try:
        settings = load_settings(
            config, server__host=host, server__port=port, state_dir=str(state_dir) if state_dir else None
        )
    except SettingsError as e:
        print(f"posecell serve: {e}", file=sys.stderr)
        return 2
    import uvicorn

    from api.app import create_app

    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    s = settings.server
    open_files, _ = raise_open_file_limit()
    if open_files < s.limit_concurrency + 256:
        log.warning(
            "only %d open files allowed: fewer than server.limit_concurrency (%d) + 256; raise LimitNOFILE",
            open_files,
            s.limit_concurrency,
        )
    where = "the simulated cell" if settings.uses_sim else "the configured devices"
    print(
        f"posecell serve: {where} on http://{s.host}:{s.port} "
        f"(API docs at /docs, state in {settings.resolved_state_dir()})",
        file=sys.stderr,
    )
    server = uvicorn.Server(uvicorn_config(create_app(settings), settings))
    try:
        server.run()
    except KeyboardInterrupt:  # Ctrl-C: uvicorn shut down gracefully, then re-raised SIGINT
        pass
    except OSError as e:  # port in use, no permission
        print(f"posecell serve: cannot listen on {s.host}:{s.port}: {e}", file=sys.stderr)
        return 1
    return 0 if server.started else 3  # 3: uvicorn's "startup failure" (the lifespan failed)
