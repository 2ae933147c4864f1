"""`posecell serve` as an operator starts it: a subprocess, a TOML file, environment overrides, SIGTERM."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from websockets.sync.client import connect as ws_connect

from tests.api.conftest import free_port
from tests.host_speed import allowed_gaps

ROOT = Path(__file__).resolve().parents[2]
POSECELL = Path(sys.executable).with_name("posecell")


def _wait_health(url: str, proc: subprocess.Popen, timeout_s: float = 180.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"posecell serve exited with {proc.returncode}: {proc.stderr.read()}")
        try:
            h = httpx.get(f"{url}/health", timeout=2).json()
            if h.get("status") == "ok" and h["processing"]["ok"] > 0:
                return h
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise AssertionError("posecell serve did not become healthy")


def test_serve_runs_the_simulated_cell_from_a_config_file_and_stops_cleanly(tmp_path):
    port = free_port()
    cfg = tmp_path / "posecell.toml"
    cfg.write_text((ROOT / "deploy" / "posecell.example.toml").read_text().replace("port = 8000", "port = 1"))
    env = {
        **os.environ,
        "POSECELL_SERVER__PORT": str(port),
        "POSECELL_STATE_DIR": str(tmp_path / "state"),
        "POSECELL_SERVER__TOKEN": "e2e",
    }
    proc = subprocess.Popen(
        [str(POSECELL), "serve", "--config", str(cfg)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        h = _wait_health(f"http://127.0.0.1:{port}", proc)
        assert h["cameras"]["cam0"]["state"] == "ok"
        # the simulated cell at its configured 20 Hz from its first frame: the camera boots with
        # its renderer and streams once the measurement is ready, so no frame is skipped (the first
        # full-frame measurements may still take longer than a period on a busy host: a drop or two)
        while (cam := httpx.get(f"http://127.0.0.1:{port}/status", timeout=5).json()["cameras"]["cam0"])["frames"] < 40:
            time.sleep(0.2)
        # a gap is a frame the simulated camera could not render within its period (tests/host_speed.py)
        allowed = allowed_gaps(cam["frames"])
        assert cam["seq_gaps"] <= allowed and cam["fps"] > 19.0, (cam, allowed)
        r = httpx.post(f"http://127.0.0.1:{port}/measure", json={}, headers={"Authorization": "Bearer e2e"}, timeout=10)
        assert r.status_code == 200 and r.json()["ok"] is True
        # the client offers permessage-deflate (the websockets library does by default); the
        # service declines it unless [server] ws_compression is on: compressing costs CPU per client
        with ws_connect(f"ws://127.0.0.1:{port}/ws/poses") as ws:
            assert "permessage-deflate" in (ws.request.headers.get("Sec-WebSocket-Extensions") or "")
            assert ws.response.headers.get("Sec-WebSocket-Extensions") is None
            assert json.loads(ws.recv(timeout=10))["camera"] == "cam0"
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    # uvicorn shuts down gracefully, then re-raises SIGTERM; systemd counts that as a clean stop
    assert proc.returncode in (0, -signal.SIGTERM), err
    assert "Application shutdown complete" in err
    db = tmp_path / "state" / "measurements.sqlite"
    assert db.exists() and (tmp_path / "state" / "calibration").is_dir()


def test_serve_refuses_a_bad_configuration_with_one_sentence(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[server]\nport = 'eighty'\n")
    r = subprocess.run([str(POSECELL), "serve", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "server.port" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_unit_verifies_and_is_hardened(tmp_path):
    unit = tmp_path / "posecell.service"
    unit.write_text(
        (ROOT / "deploy" / "posecell.service").read_text().replace("/opt/posecell/.venv/bin/posecell", str(POSECELL))
    )
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", str(unit)], capture_output=True, text=True, timeout=60
    )
    exposure = float(r.stdout.split("Overall exposure level for posecell.service:")[1].split()[0])
    assert exposure < 4.5  # "OK" on systemd's scale (lower is safer)


def test_websocket_compression_is_an_option_passed_to_uvicorn():
    from api.serve import uvicorn_config
    from service.settings import Settings

    assert uvicorn_config(object(), Settings()).ws_per_message_deflate is False
    on = Settings.model_validate({"server": {"ws_compression": True}})
    assert uvicorn_config(object(), on).ws_per_message_deflate is True
