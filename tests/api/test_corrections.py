"""The online correction stream ``/ws/corrections`` over a real WebSocket in the simulated cell.

The simulated arm is 1-2 mm off the controller's nominal model and its hand-eye is preloaded, so
each frame has a flange deviation; the stream must give its opposite as the offset (gain 1: each
frame's own), hold beyond the bound, hold ``stale`` within its watchdog when the camera goes, and
refuse a client without the token.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from service.core.measurement import Measurement
from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server

TOKEN = "corrections-token"


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("state-corrections")),
        server__port=free_port(),
        server__token=TOKEN,
        cameras=[{"frame_rate_hz": 20.0}],
    )
    yield from run_server(settings)


def _ready(cell: LiveServer) -> None:
    cell.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="the cell")


def _stream(cell: LiveServer, query: str = "", token: str | None = TOKEN):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return connect(f"{cell.ws_url}/ws/corrections{query}", additional_headers=headers, open_timeout=10)


def test_each_frame_gives_its_deviation_undone_and_a_fault_or_a_silence_holds(cell: LiveServer) -> None:
    _ready(cell)
    results: dict[int, Measurement] = {}
    unsubscribe = cell.worker.subscribe(lambda m: results.setdefault(m.seq, m) if m.seq is not None else None)
    try:
        with _stream(cell, "?gain=1&watchdog_ms=300") as ws:
            messages = [json.loads(ws.recv(timeout=5)) for _ in range(20)]
    finally:
        unsubscribe()
    applied = [m for m in messages if m["state"] == "apply"]
    assert len(applied) >= 15, messages[:3]
    for msg in applied:
        m = results[msg["seq"]]  # the frame it came from, as the worker published it
        assert msg["t_exposure_unix_ns"] == m.t_unix_ns
        np.testing.assert_allclose(msg["offset_mm"], -np.asarray(m.flange.deviation.vector_mm), atol=1e-4)
        np.testing.assert_allclose(msg["deviation_mm"], m.flange.deviation.vector_mm, atol=1e-4)
    assert 0.3 < np.median([np.linalg.norm(m["offset_mm"]) for m in applied]) < 5.0  # the arm's errors

    # a bound below the arm's own error: every frame is a fault, and nothing is applied
    with _stream(cell, "?max_mm=0.05") as ws:
        held = [json.loads(ws.recv(timeout=5)) for _ in range(5)]
    assert all(m["state"] == "hold" and m["reason"] == "beyond_bound" for m in held), held
    assert all(m["offset_mm"] == [0.0, 0.0, 0.0] for m in held) and "beyond the bound" in held[0]["message"]

    # the camera goes: the watchdog holds within its time although no frame comes
    with _stream(cell, "?watchdog_ms=200") as ws:
        while json.loads(ws.recv(timeout=5))["state"] != "apply":
            pass
        with cell.client() as c:
            assert c.post("/sim/faults", json={"device": "camera", "action": "unplug"}).status_code == 200
        t_unplug = time.monotonic()
        try:
            while (msg := json.loads(ws.recv(timeout=5)))["state"] == "apply":
                pass
            waited_s = time.monotonic() - t_unplug
        finally:
            with cell.client() as c:
                assert c.post("/sim/faults", json={"device": "camera", "action": "plug"}).status_code == 200
    assert msg["reason"] == "stale" and msg["seq"] is None and waited_s < 1.0, (msg, waited_s)
    _ready(cell)


def test_a_client_without_the_token_or_for_an_unknown_camera_is_refused(cell: LiveServer) -> None:
    for query, token in (("", None), ("", "wrong"), ("?camera=nope", TOKEN)):
        with _stream(cell, query, token) as ws, pytest.raises(ConnectionClosed) as e:
            ws.recv(timeout=5)
        assert e.value.rcvd is not None and e.value.rcvd.code == 1008, (query, token)
        assert ("Bearer" if query == "" else "no camera 'nope'") in e.value.rcvd.reason
