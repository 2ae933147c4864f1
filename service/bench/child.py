"""``posecell serve`` in a child process on a free loopback port, as an integrator runs it (the benches
that measure the running service from the outside)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

TOKEN = "bench"


@dataclass(frozen=True)
class Served:
    address: str  # host:port
    token: str
    pid: int

    @property
    def url(self) -> str:
        return f"http://{self.address}"


@contextmanager
def serve_child(state_dir: Path, config: Path | None = None) -> Iterator[Served]:
    """The service (the simulated cell without ``config``) until the block ends; then terminated."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    env = {**os.environ, "POSECELL_SERVER__TOKEN": TOKEN, "POSECELL_LOG_LEVEL": "warning"}
    cmd = [sys.executable, "-m", "service.cli.main", "serve", "--port", str(port), "--state-dir", str(state_dir)]
    if config is not None:
        cmd += ["--config", str(config)]
    child = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL)
    try:
        yield Served(f"127.0.0.1:{port}", TOKEN, child.pid)
    finally:
        child.terminate()
        try:
            child.wait(timeout=20)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait(timeout=5)


def health(address: str) -> dict[str, Any]:
    """``GET /health`` of the service at ``address`` (host:port)."""
    h: dict[str, Any] = httpx.get(f"http://{address}/health", timeout=5.0).json()
    return h


def wait_ready(address: str, timeout_s: float) -> None:
    """Until the service at ``address`` has measured a pose (the numba kernels loaded, the cell running)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            h = health(address)
            if h["processing"]["ok"] > 0 and h["status"] in ("ok", "degraded"):
                return
        except (httpx.TransportError, KeyError, ValueError):
            pass
        time.sleep(0.2)
    raise TimeoutError(f"the service at {address} gave no pose within {timeout_s:.0f} s")
