"""`posecell serve` under a flood of idle sockets, started with the open-file limit of an ordinary session.

A unit without ``LimitNOFILE`` gives the service the soft limit 1024; ~1 100 idle sockets
from one client then exhausted its file descriptors and nothing could connect any more.
The service now raises its soft limit to the hard one at start (the unit sets 8192) and
closes sockets that send no request within ``timeout_header_s``.
"""

from __future__ import annotations

import contextlib
import os
import resource
import selectors
import signal
import socket
import subprocess
import threading
import time

import httpx
import pytest

from tests.api.conftest import free_port
from tests.e2e.test_serve import POSECELL, _wait_health

N_IDLE = 1100
HEADER_TIMEOUT_S = 3.0


@contextlib.contextmanager
def _open_files(n: int):
    """This process may open n files for the test's duration (within the hard limit)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < n:
        pytest.skip(f"the hard open-file limit ({hard}) is below the {n} this test needs")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, n), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def _session_limit() -> None:  # in the child, before exec: the soft limit of a login session
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard))


def test_a_thousand_idle_sockets_neither_block_the_api_nor_stay_open(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {
        **os.environ,
        "POSECELL_SERVER__PORT": str(port),
        "POSECELL_STATE_DIR": str(tmp_path / "state"),
        "POSECELL_SERVER__TOKEN": "e2e",
        "POSECELL_SERVER__TIMEOUT_HEADER_S": str(HEADER_TIMEOUT_S),
    }
    with _open_files(N_IDLE + 512):
        proc = subprocess.Popen(
            [str(POSECELL), "serve"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_session_limit,
        )
        idle: list[socket.socket] = []
        try:
            _wait_health(url, proc)
            log: list[str] = []  # keep reading the log: a full pipe would stall the service, not the test
            threading.Thread(target=lambda: log.extend(proc.stderr), daemon=True).start()  # type: ignore[arg-type]
            t_open = time.monotonic()
            for _ in range(N_IDLE):
                idle.append(socket.create_connection(("127.0.0.1", port), timeout=5))
            time.sleep(0.5)  # let the service accept them all
            t0 = time.monotonic()
            r = httpx.get(f"{url}/health", timeout=5)
            assert r.status_code == 200 and time.monotonic() - t0 < 1.0
            # every idle socket is closed by the service, about timeout_header_s after it connected
            with selectors.DefaultSelector() as sel:
                for s in idle:
                    s.setblocking(False)
                    sel.register(s, selectors.EVENT_READ)
                open_ = len(idle)
                deadline = t_open + HEADER_TIMEOUT_S + 5.0
                while open_ and time.monotonic() < deadline:
                    for key, _ in sel.select(timeout=0.5):
                        with contextlib.suppress(ConnectionResetError):
                            assert key.fileobj.recv(1024) == b""  # EOF, not an answer  # type: ignore[union-attr]
                        sel.unregister(key.fileobj)
                        open_ -= 1
            closed_after_s = time.monotonic() - t_open
            assert open_ == 0, f"{open_} of {N_IDLE} idle sockets still open after {closed_after_s:.1f} s"
            assert closed_after_s > HEADER_TIMEOUT_S * 0.8
            assert httpx.get(f"{url}/health", timeout=5).status_code == 200
        finally:
            for s in idle:
                s.close()
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
