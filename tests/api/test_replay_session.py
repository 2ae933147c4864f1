"""A recorded session replayed through the service: the same frames meet the same robot poses.

The simulated cell is recorded over HTTP while a WebSocket client keeps every live result; a second
service then plays the recording with the ``replay`` camera (``timing = "recorded"``) and the
``replay`` robot. Each replayed frame's reported flange and deviation are those of the live result
of the same exposure.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.replay_clock import clock_of
from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server

pytestmark = pytest.mark.slow


class Collector:
    """Every result a WebSocket client receives (pose only), read by a thread."""

    def __init__(self, ws_url: str) -> None:
        self.results: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._stack = contextlib.ExitStack()
        self._ws = self._stack.enter_context(connect(f"{ws_url}/ws/poses?targets=false", open_timeout=10))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.results.append(json.loads(self._ws.recv(timeout=0.5)))
            except TimeoutError:
                continue
            except Exception:  # closed
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._stack.close()


def wait_ended(client: Any, rec_id: str) -> dict[str, Any]:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        summary: dict[str, Any] = client.get(f"/recordings/{rec_id}").json()
        if summary["state"] != "recording":
            return summary
        time.sleep(0.1)
    raise AssertionError("the recording did not end")


@pytest.fixture(scope="module")
def recorded(live: LiveServer) -> Iterator[tuple[Path, dict[int, dict[str, Any]]]]:
    live.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=120, what="the cell")
    collector = Collector(live.ws_url)
    try:
        with live.client() as c:
            rec_id = c.post("/recordings", json={"max_frames": 12}).json()["id"]
            summary = wait_ended(c, rec_id)
        time.sleep(0.5)  # the last results reach the client
    finally:
        collector.close()
    assert summary["state"] == "complete" and summary["cameras"]["cam0"]["written"] == 12
    by_exposure = {r["t_exposure_host_ns"]: r for r in collector.results if r.get("t_exposure_host_ns")}
    yield Path(summary["folder"]), by_exposure


def test_a_replayed_session_gives_each_frame_the_flange_and_deviation_it_had_live(recorded, live, tmp_path):
    folder, live_results = recorded
    stated = json.loads((folder / "recording.json").read_text())["settings"]  # the delays the pairing used live
    with live.client() as c:  # the cell's calibrations, as a user would carry them to the analysis machine
        calibrations = {kind: c.get(f"/calibration/{kind}").json() for kind in ("camera", "field", "handeye")}
    t_recorded = [int(line.split(",")[1]) for line in (folder / "cam0" / "timestamps.csv").read_text().split()[1:]]
    live_t = np.array(sorted(live_results))
    # the live results of the recorded frames (exposed a few ms before they arrived)
    assert sum(np.any((t - 50_000_000 < live_t) & (live_t < t)) for t in t_recorded) >= 10
    settings = load_settings(
        None,
        state_dir=str(tmp_path / "replay-state"),
        server__port=free_port(),
        server__token="replay-token",
        cameras=[
            {
                "name": "cam0",
                "driver": "replay",
                "frame_rate_hz": 15.0,
                "transport_latency_s": stated["camera_transport_latency_s"]["cam0"],
                "options": {"source": str(folder / "cam0"), "timing": "recorded"},
            }
        ],
        robot={
            "driver": "replay",
            "options": {"source": str(folder)},
            "transport_latency_s": stated["robot_transport_latency_s"],
        },
    )
    servers = run_server(settings)
    server = next(servers)
    try:
        with server.client() as c:
            for kind, data in calibrations.items():
                assert c.put(f"/calibration/{kind}", json=data).status_code == 200, kind
        server.wait_for(lambda h: h["processing"]["ok"] >= 20, timeout_s=120, what="replayed results")
        collector = Collector(server.ws_url)
        time.sleep(2.0)  # three passes of the 12 frames
        collector.close()
    finally:
        servers.close()
    clock = clock_of(folder)
    # the robot's speed along the recording, on its own clock (t_robot_s; the host stamps come in batches)
    robot = np.loadtxt(folder / "robot.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3, 4))
    speed_mm_s = float(np.max(np.linalg.norm(np.diff(robot[:, 1:], axis=0), axis=1) / np.diff(robot[:, 0])))
    compared, flange_mm, deviation_mm, dt_ns = 0, [], [], []
    for r in collector.results:
        if not r.get("ok") or r.get("deviation") is None:
            continue
        # the replayed exposure on the recording's clock, the pass removed: the live result of that
        # frame is the one within a millisecond (both are the service's alignment of the same stamps)
        half = clock.step_ns // 2  # an exposure comes before its frame's arrival, the clock's origin
        t_live = clock.t0_ns + (r["t_exposure_host_ns"] - clock.anchor_ns + half) % clock.span_ns - half
        k = int(np.argmin(np.abs(live_t - t_live)))
        live = live_results[int(live_t[k])]
        if abs(int(live_t[k]) - t_live) > 1_000_000 or live.get("deviation") is None:
            continue
        compared += 1
        # the controller's flange at the exposure: the same samples, interpolated at the same instant
        t_replay, t_live_flange = np.array(r["T_base_flange"])[:3, 3], np.array(live["T_base_flange"])[:3, 3]
        flange_mm.append(float(np.abs(t_replay - t_live_flange).max()))
        dt_ns.append(abs(int(live_t[k]) - t_live))
        deviation_mm.append(abs(r["deviation"]["position_mm"] - live["deviation"]["position_mm"]))
    assert compared >= 20, f"{compared} replayed results compared of {len(collector.results)}"
    flange, deviation = np.array(flange_mm), np.array(deviation_mm)
    # the controller's flange at the exposure: the same samples, interpolated at the service's estimate
    # of the same instant. The replay aligns the camera's and the robot's clocks afresh: the exposures
    # come out µs apart, the robot's stamps some 10-60 µs on a loaded host, so the flanges differ by the
    # robot's travel in that time (at most 0.1 ms in the median, 0.5 ms at worst) and no more
    assert np.median(dt_ns) < 100_000, np.median(dt_ns)
    assert np.median(flange) < speed_mm_s * 1e-4 + 0.001, (np.median(flange), speed_mm_s)
    assert np.max(flange) < speed_mm_s * 5e-4 + 0.001, (np.max(flange), speed_mm_s)
    # the same image measured again (ROI tracking or a full frame, as the replay's own tracking goes):
    # the deviation differs by the flange's difference and the measurement's
    assert np.median(deviation - flange) < 0.005 and np.max(deviation - flange) < 0.05, (deviation, flange)
