"""The WebSocket fan-out writes each message's frame once, straight to the sockets that can take it:
every client still gets every message of its variant, in order; a compressed connection takes the
ASGI path."""

from __future__ import annotations

import asyncio
import json
import struct
import threading

import numpy as np
import pytest
from websockets.sync.client import connect

from api.ws import Hub, ws_frame
from service.core.measurement import Measurement
from service.core.results import PoseResult, TargetTable
from service.settings import load_settings
from tests.api.conftest import free_port, run_server


def test_a_frame_is_an_unmasked_final_text_frame_with_the_length_as_rfc_6455_says():
    for n, head in ((5, b"\x81\x05"), (125, b"\x81\x7d"), (200, b"\x81\x7e" + struct.pack("!H", 200))):
        assert ws_frame("x" * n) == head + b"x" * n
    big = ws_frame("é" * 40_000)  # 80 000 bytes of UTF-8: the 64-bit length
    assert big[:2] == b"\x81\x7f" and struct.unpack("!Q", big[2:10])[0] == 80_000 and len(big) == 80_010


def test_a_client_without_targets_that_connects_while_a_result_is_on_its_way_gets_it_without_them():
    """The worker encodes a result's variants in its thread; the loop sends it a moment later. A
    client that connected in between must still get its variant (it once got the full text)."""
    table = TargetTable(("C1", "C2"), np.zeros((2, 2)), np.zeros((2, 2)), np.ones(2, bool), np.ones(2, bool))
    result = PoseResult(np.eye(4), np.full(3, 0.01), np.full(3, 0.001), 0.05, 0.05, table)

    async def scenario():
        hub = Hub()
        hub.bind(asyncio.get_running_loop())
        full = hub.add(None, None)
        hub.publish_threadsafe(Measurement("cam0", result, 1, 1, seq=1))  # only full clients yet
        lite = hub.add(None, None, targets=False)  # connects before the loop runs the publication
        await asyncio.sleep(0.01)
        return json.loads(full.queue.get_nowait()), json.loads(lite.queue.get_nowait())

    to_full, to_lite = asyncio.run(scenario())
    assert [t["id"] for t in to_full["targets"]] == ["C1", "C2"]
    assert "targets" not in to_lite and to_lite["seq"] == to_full["seq"] == 1


def _read(url: str, n: int, out: list[dict], compression: str | None = "deflate") -> None:
    with connect(url, compression=compression) as ws:
        ws.recv(timeout=30)  # the newest result at connection
        out.extend(json.loads(ws.recv(timeout=30)) for _ in range(n))


def _stream(live, clients: list[tuple[bool, str | None]], n: int = 40) -> list[list[dict]]:
    outs: list[list[dict]] = [[] for _ in clients]
    threads = [
        threading.Thread(
            target=_read,
            args=(f"{live.ws_url}/ws/poses?camera=cam0&targets={str(t).lower()}&token={live.token}", n, out, comp),
        )
        for (t, comp), out in zip(clients, outs)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    return outs


@pytest.mark.slow  # a live server with the simulated cell
def test_every_client_gets_every_message_of_its_variant_in_order_written_once_for_all(live):
    live.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180, what="a running cell")
    with live.client() as c:
        before = c.get("/health").json()["websocket"]["sent_direct"]
    variants = [True, True, True, False, False]
    outs = _stream(live, [(t, None) for t in variants])
    for with_targets, out in zip(variants, outs):
        assert len(out) == 40
        seqs = [m["seq"] for m in out]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # in order, none twice
        assert all(("targets" in m) == with_targets for m in out if m["ok"])
    # the clients read together: they saw the same frames (the stream at 15 Hz, no client behind)
    common = set.intersection(*({m["seq"] for m in out} for out in outs))
    assert len(common) >= 30
    by_seq = [{m["seq"]: m for m in out} for out in outs]
    s = min(common)
    assert by_seq[0][s] == by_seq[1][s]  # the same bytes for everyone: the same document
    assert {k: v for k, v in by_seq[0][s].items() if k != "targets"} == by_seq[3][s]
    with live.client() as c:
        after = c.get("/health").json()["websocket"]["sent_direct"]
    assert after - before >= 0.9 * 5 * 40  # written straight to the sockets, not through the ASGI sends


@pytest.mark.slow
def test_a_compressed_connection_takes_the_asgi_path_and_gets_every_message(tmp_path):
    settings = load_settings(
        None,
        state_dir=str(tmp_path),
        server__port=free_port(),
        server__token="test-token",
        server__ws_compression=True,
        cameras=[{"frame_rate_hz": 15.0}],
    )
    for live in run_server(settings):
        live.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180, what="a cell")
        (out,) = _stream(live, [(True, "deflate")], n=20)
        seqs = [m["seq"] for m in out]
        assert len(out) == 20 and seqs == sorted(seqs) and all("targets" in m for m in out if m["ok"])
        with live.client() as c:
            assert c.get("/health").json()["websocket"]["sent_direct"] == 0
