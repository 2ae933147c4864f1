"""``posecell serve`` in a child process on a free loopback port, as an integrator runs it (the benches
that measure the running service from the outside)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

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
