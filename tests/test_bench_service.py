"""``posecell bench service``: the service measured end to end from a client (real child process)."""

from __future__ import annotations

import json

import orjson
import pytest

from service.bench import service as bench_service


def test_the_probe_reads_exposure_and_seq_without_parsing_the_message():
    data = json.dumps(
        {"ok": True, "seq": 1234, "t_exposure_unix_ns": 1_764_000_000_123_456_789, "targets": []}
    ).encode()
    assert bench_service._int_after(data, b'"seq":') == 1234
    assert bench_service._int_after(data.replace(b" ", b""), b'"t_exposure_unix_ns":') == 1_764_000_000_123_456_789
    assert bench_service._int_after(data, b'"missing":') is None
    assert bench_service._int_after(b'{"seq":-3}', b'"seq":') == -3


def test_a_messages_latency_is_split_into_stages_that_add_up_to_it():
    timings = {"windows": 0.4, "child": 0.8, "measure": 1.3, "flange": 0.1, "processing": 1.5, "latency": 1.9}
    data = orjson.dumps({"ok": True, "seq": 7, "t_exposure_unix_ns": 1_000_000, "timings_ms": timings, "x": {"y": 1}})
    assert orjson.loads(bench_service._timings(data)) == timings
    assert bench_service._timings(b'{"ok":false}') == b"{}"
    arrival_ns = 1_000_000 + 2_600_000  # 2.6 ms after the exposure
    stages = bench_service.stage_ms(arrival_ns, 1_000_000, timings)
    assert stages == pytest.approx((0.4, 0.5, 0.8, 0.2, 0.7))  # begun 0.4 ms after the exposure, ...
    assert sum(stages) == pytest.approx(2.6)
    assert len(stages) == len(bench_service.STAGES)
    assert bench_service.stage_ms(arrival_ns, 1_000_000, {"latency": 1.0}) is None  # measured in-process


@pytest.mark.slow  # starts the service and renders the replay frames
def test_a_row_of_the_service_benchmark_is_measured_from_the_messages():
    # the two others subscribe pose-only (targets=false), the probe takes whole messages
    row = bench_service.measure(rate_hz=100, n_clients=3, seconds=3.0, warmup_s=1.0, pose_only=True)
    assert row["pose_only"] is True and row["clients"] == 3
    assert 20 < row["results_per_s"] <= 110  # a loaded 2-core machine still keeps a good part of 100 Hz
    assert 0.0 <= row["lost_fraction"] < 0.8
    assert 0.0 < row["ws_p50_ms"] <= row["ws_p99_ms"] <= row["ws_max_ms"] < 5000.0
    assert row["commit_p99_ms"] > 0.0 and row["cpu_ms_per_frame"] > 0.0
    host = row["host"]  # the host watched over the clients' window (service/bench/stalls.py)
    assert host is not None and 2.5 < host.seconds < 10.0 and 0.0 <= host.p99_ms <= host.max_ms
    # the replay plays back and forth: no jump of the arm for the ROI tracking to lose (a wrap
    # every 100 frames cost two full frames, 2 % of them, and was the p99)
    assert row["full_frames"] == 0
    stages = row["stages_ms"]
    assert len(stages) == len(bench_service.STAGES)
    assert all(0.0 <= p50 <= p99 < 5000.0 for p50, p99 in stages[1:])  # the first may be < 0 by clock jitter
    # the stages' medians come to about the median exposure -> WebSocket time
    assert 0.3 * row["ws_p50_ms"] < sum(p50 for p50, _ in stages) < 3.0 * row["ws_p50_ms"]


def test_the_client_mixes_are_numbers_with_p_for_pose_only_others():
    assert bench_service.parse_clients("1, 50,50p") == ((1, False), (50, False), (50, True))
    with pytest.raises(ValueError):
        bench_service.parse_clients("many")


def test_the_lean_load_clients_read_every_message_and_answer_pings_over_a_real_websocket():
    import asyncio
    import threading

    from websockets.asyncio.server import serve

    from service.bench.ws_load import read_streams

    sizes = [0, 5, 125, 126, 300, 65_535, 65_536, 200_000] * 3  # 7-, 16- and 64-bit lengths
    pongs: list[float] = []
    ready, port = threading.Event(), []

    async def handler(ws):
        for n in sizes[:10]:
            await ws.send(b"x" * n)
        pongs.append(await asyncio.wait_for(await ws.ping(b"are-you-there"), 5.0))  # the pong came back
        for n in sizes[10:]:
            await ws.send("é" * (n // 2))  # text frames too
        await asyncio.sleep(0.5)

    async def main():
        async with serve(handler, "127.0.0.1", 0, max_size=None, ping_interval=None) as server:
            port.append(server.sockets[0].getsockname()[1])
            ready.set()
            await asyncio.sleep(4.0)

    t = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    t.start()
    assert ready.wait(5.0)
    assert read_streams(f"127.0.0.1:{port[0]}", "/ws", 3, 1.5) == 3 * len(sizes)
    assert len(pongs) == 3
    t.join(5.0)


@pytest.mark.parametrize("centre", [None, "centroid", "edge"])
def test_the_benchmarks_service_measures_with_the_centres_asked_for(tmp_path, centre):
    from service.settings import load_settings

    config = tmp_path / "bench.toml"
    config.write_text(bench_service._config(500.0, centre))
    settings = load_settings(config)
    assert settings.processing.centre == (centre or "edge")
    assert settings.cameras[0].driver == "replay" and settings.cameras[0].frame_rate_hz == 500.0
