"""The running service measures each camera in a child process: said in ``/health``; a killed child
costs a frame with a sentence and the stream goes on; ``measure_in = "thread"`` measures in-process."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from websockets.sync.client import connect

pytestmark = pytest.mark.slow  # a live server with the simulated cell


def _measurement(live):
    h = live.wait_for(
        lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="a running cell"
    )
    return h["processing"]["measurement"]["cam0"]


def test_health_names_the_child_that_measures_the_camera(live):
    m = _measurement(live)
    assert m["in"] == "process" and m["pid"] not in (None, os.getpid())
    with open(f"/proc/{m['pid']}/status") as f:  # a live process of this machine, ours
        assert int(next(line for line in f if line.startswith("PPid:")).split()[1]) > 0


def test_a_killed_measurement_child_costs_a_frame_with_a_sentence_then_poses_go_on(live):
    m = _measurement(live)
    with connect(f"{live.ws_url}/ws/poses?camera=cam0&targets=false&token={live.token}") as ws:
        ws.recv(timeout=10)
        os.kill(m["pid"], signal.SIGKILL)
        failed, ok_after, deadline = None, 0, time.monotonic() + 30
        while ok_after < 5 and time.monotonic() < deadline:
            r = json.loads(ws.recv(timeout=10))
            if failed is None and not r["ok"]:
                failed = r
            elif failed is not None and r["ok"]:
                ok_after += 1
    assert failed is not None, "no failed frame after the child was killed"
    assert failed["reason"] == "bad_image" and "measurement process of camera cam0 died" in failed["message"]
    assert ok_after == 5, "poses did not resume after the child was replaced"
    m2 = live.wait_for(lambda h: h["processing"]["measurement"]["cam0"]["restarts"] >= 1, what="a restart")
    assert m2["processing"]["measurement"]["cam0"]["pid"] not in (None, m["pid"])
    assert m2["status"] == "ok"
    with live.client() as c:
        metrics = c.get("/metrics").text
    line = next(
        x for x in metrics.splitlines() if x.startswith('posecell_measure_process_restarts_total{camera="cam0"}')
    )
    assert float(line.rsplit(" ", 1)[1]) >= 1


def test_measure_in_thread_is_applied_at_run_time_and_back(live):
    _measurement(live)
    with live.client() as c:
        for where in ("thread", "process"):
            r = c.put("/config", json={"processing": {"measure_in": where}})
            assert r.status_code == 200, r.text
            n0 = c.get("/health").json()["processing"]["ok"]
            h = live.wait_for(
                lambda h, w=where, n=n0: (
                    h["processing"]["measurement"]["cam0"]["in"] == w and h["processing"]["ok"] >= n + 5
                ),
                what=f"poses measured in a {where}",
            )
            pid = h["processing"]["measurement"]["cam0"]["pid"]
            assert (pid is None) == (where == "thread")
