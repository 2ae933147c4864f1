"""A real server for API tests: uvicorn on a free loopback port in a thread, the simulated cell behind it.

Tests talk to it over real HTTP (httpx) and real WebSockets (websockets), and may
reach into ``server.app.state.worker`` to inject faults (unplug the simulated
camera or robot) the way a technician would.
"""

from __future__ import annotations

import functools
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn

from api.app import create_app
from api.serve import uvicorn_config
from service.pipeline.measure import FrameMeasurer
from service.settings import Settings, load_settings
from service.sim import scene


@functools.lru_cache(maxsize=1)
def kernels_compiled() -> None:
    """Compile (or load from numba's cache) every kernel once per test process, before a server's
    clock starts: on a fresh, busy CI machine the first compile takes minutes, which is not what the
    servers' timeouts are there to measure."""
    FrameMeasurer(scene.reference_camera(), scene.reference_field())


# A session's plan runs in the solver process, which the first session starts (a fresh interpreter):
# ~10 s on a slow 2-core host, beyond the clients' 10 s default
PLAN_TIMEOUT_S = 60.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class LiveServer:
    app: Any
    url: str
    ws_url: str
    token: str
    settings: Settings

    @property
    def worker(self) -> Any:
        return self.app.state.worker

    def client(self, auth: bool = True) -> httpx.Client:
        headers = {"Authorization": f"Bearer {self.token}"} if auth else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=10.0)

    def wait_for(self, predicate: Any, timeout_s: float = 30.0, what: str = "condition") -> Any:
        deadline = time.monotonic() + timeout_s
        with self.client() as c:
            while time.monotonic() < deadline:
                h = c.get("/health").json()
                if predicate(h):
                    return h
                time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {what}; last health: {h}")


def live_settings(state_dir: Path, **overrides: Any) -> Settings:
    """The simulated cell's settings for a test server: state in ``state_dir``, a free loopback port, a
    token; ``overrides`` as ``load_settings`` takes them (``cameras=[...]``, ``sim__program=...``)."""
    return load_settings(
        None, state_dir=str(state_dir), server__port=free_port(), server__token="test-token", **overrides
    )


def run_server(settings: Settings) -> Iterator[LiveServer]:
    kernels_compiled()
    app = create_app(settings)
    # the service's own uvicorn options (timeouts, limits), on loopback
    server = uvicorn.Server(uvicorn_config(app, settings, host="127.0.0.1", log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the test server did not start")
        time.sleep(0.05)
    url = f"http://127.0.0.1:{settings.server.port}"
    try:
        yield LiveServer(app, url, url.replace("http", "ws"), app.state.token, settings)
    finally:
        server.should_exit = True
        thread.join(timeout=20)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    state: Path = tmp_path_factory.mktemp("state")
    settings = load_settings(
        None,
        state_dir=str(state),
        server__port=free_port(),
        server__token="test-token",
        cameras=[{"frame_rate_hz": 15.0}],
    )
    yield from run_server(settings)
